//! Rigid poses named by their frames, and conversions at the format edges.
//!
//! The internal representation is always `cam_from_world` (world → camera) with OpenCV camera
//! axes: x right, y down, z forward. Other conventions appear only in the conversion functions:
//!
//! | source | stores | camera axes |
//! |---|---|---|
//! | nerfstudio / OpenGL `transform_matrix` | camera-to-world 4×4 | x right, y up, z back |
//! | COLMAP `images.txt` | world-to-camera, quaternion (w, x, y, z) + t | OpenCV |
//! | Mega-NeRF `camera_in_drb` | camera-to-world 3×4 | x down, y right, z back |
//!
//! World coordinates are passed through unchanged; only the camera axes are re-expressed.
//! Mega-NeRF's metadata files store `camera_in_drb` with its columns reordered to
//! `[right, −down, back]`, i.e. OpenGL camera axes (see `matloc_data::meganerf`).

use nalgebra::{
    Isometry3, Matrix3, Matrix3x4, Matrix4, Point3, Quaternion, Rotation3, Translation3,
    UnitQuaternion, Vector3,
};
use thiserror::Error;

/// A rigid transform. Always name variables by frames: `cam_from_world`, `world_from_cam`.
pub type Pose = Isometry3<f64>;

/// Largest Frobenius norm of `RᵀR − I` accepted as a rotation (exported files round to ~1e-6;
/// anything beyond this carries scale or shear and is rejected rather than silently fixed).
pub const RIGIDITY_TOLERANCE: f64 = 1e-3;

/// Errors raised when a matrix or quaternion is not a valid rigid transform.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum PoseError {
    /// An entry is NaN or infinite.
    #[error("pose entry ({row}, {col}) is not finite ({value})")]
    NonFinite {
        /// Row of the entry.
        row: usize,
        /// Column of the entry.
        col: usize,
        /// Its value.
        value: f64,
    },
    /// The rotation block is not orthonormal with determinant +1.
    #[error(
        "rotation is not rigid: |RᵀR − I| = {orthogonality_error:.3e}, det = {determinant:.6} (tolerance {RIGIDITY_TOLERANCE:e})"
    )]
    NotRigid {
        /// Frobenius norm of `RᵀR − I`.
        orthogonality_error: f64,
        /// Determinant of the rotation block.
        determinant: f64,
    },
    /// The last row of a homogeneous 4×4 matrix is not `[0 0 0 1]`.
    #[error("last row of the 4x4 pose is {row:?}, expected [0, 0, 0, 1]")]
    BadHomogeneousRow {
        /// The row found.
        row: [f64; 4],
    },
    /// A quaternion with (near) zero norm.
    #[error("quaternion norm {norm} is too far from 1")]
    BadQuaternion {
        /// Its norm.
        norm: f64,
    },
}

/// Camera axes of nerfstudio/OpenGL (x right, y up, z back) expressed in OpenCV camera axes.
fn opencv_from_opengl_axes() -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
}

/// Camera axes of Mega-NeRF (x down, y right, z back) expressed in OpenCV camera axes.
fn opencv_from_drb_axes() -> Matrix3<f64> {
    Matrix3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0)
}

/// Checks that `r` is a rotation within [`RIGIDITY_TOLERANCE`] and returns the nearest one.
pub fn rotation_from_matrix(r: &Matrix3<f64>) -> Result<UnitQuaternion<f64>, PoseError> {
    for row in 0..3 {
        for col in 0..3 {
            let value = r[(row, col)];
            if !value.is_finite() {
                return Err(PoseError::NonFinite { row, col, value });
            }
        }
    }
    let orthogonality_error = (r.transpose() * r - Matrix3::identity()).norm();
    let determinant = r.determinant();
    if orthogonality_error > RIGIDITY_TOLERANCE || determinant <= 0.0 {
        return Err(PoseError::NotRigid {
            orthogonality_error,
            determinant,
        });
    }
    // Nearest rotation by SVD (R = U Vᵀ). nalgebra's iterative `from_matrix` starts from the
    // identity and can stall near 180° rotations, which axis flips produce routinely.
    let svd = r.svd(true, true);
    let (u, v_t) = (svd.u.expect("requested"), svd.v_t.expect("requested"));
    let nearest = u * v_t;
    Ok(UnitQuaternion::from_rotation_matrix(
        &Rotation3::from_matrix_unchecked(nearest),
    ))
}

fn check_translation(t: &Vector3<f64>, col: usize) -> Result<(), PoseError> {
    for row in 0..3 {
        if !t[row].is_finite() {
            return Err(PoseError::NonFinite {
                row,
                col,
                value: t[row],
            });
        }
    }
    Ok(())
}

/// `cam_from_world` from a camera-to-world rotation in some camera-axis convention.
fn cam_from_world_from_c2w(
    rot_world_from_axes: &Matrix3<f64>,
    centre: &Vector3<f64>,
    opencv_from_axes: &Matrix3<f64>,
) -> Result<Pose, PoseError> {
    check_translation(centre, 3)?;
    let rot_world_from_axes = rotation_from_matrix(rot_world_from_axes)?;
    // world_from_cv = world_from_axes * axes_from_cv; axes_from_cv = opencv_from_axesᵀ.
    let axes_from_cv = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
        opencv_from_axes.transpose(),
    ));
    let rot = rot_world_from_axes * axes_from_cv;
    let world_from_cam = Isometry3::from_parts(Translation3::from(*centre), rot);
    Ok(world_from_cam.inverse())
}

/// `cam_from_world` from a nerfstudio / OpenGL camera-to-world `transform_matrix`.
pub fn cam_from_world_from_opengl(c2w: &Matrix4<f64>) -> Result<Pose, PoseError> {
    let last = [c2w[(3, 0)], c2w[(3, 1)], c2w[(3, 2)], c2w[(3, 3)]];
    for (col, &value) in last.iter().enumerate() {
        if !value.is_finite() {
            return Err(PoseError::NonFinite { row: 3, col, value });
        }
    }
    if (last[0].abs() + last[1].abs() + last[2].abs() + (last[3] - 1.0).abs()) > 1e-6 {
        return Err(PoseError::BadHomogeneousRow { row: last });
    }
    let r: Matrix3<f64> = c2w.fixed_view::<3, 3>(0, 0).into_owned();
    let t: Vector3<f64> = c2w.fixed_view::<3, 1>(0, 3).into_owned();
    cam_from_world_from_c2w(&r, &t, &opencv_from_opengl_axes())
}

/// nerfstudio / OpenGL camera-to-world 4×4 of a `cam_from_world` pose.
pub fn opengl_from_cam_from_world(cam_from_world: &Pose) -> Matrix4<f64> {
    let world_from_cam = cam_from_world.inverse();
    let r = world_from_cam.rotation.to_rotation_matrix().into_inner() * opencv_from_opengl_axes();
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    m.fixed_view_mut::<3, 1>(0, 3)
        .copy_from(&world_from_cam.translation.vector);
    m
}

/// `cam_from_world` from a COLMAP image pose: quaternion `(qw, qx, qy, qz)` and translation.
pub fn cam_from_world_from_colmap(qvec: [f64; 4], tvec: [f64; 3]) -> Result<Pose, PoseError> {
    for (col, &value) in qvec.iter().enumerate() {
        if !value.is_finite() {
            return Err(PoseError::NonFinite { row: 0, col, value });
        }
    }
    let t = Vector3::from(tvec);
    check_translation(&t, 4)?;
    let q = Quaternion::new(qvec[0], qvec[1], qvec[2], qvec[3]);
    let norm = q.norm();
    // COLMAP writes normalised quaternions with ~1e-9 rounding; accept loose rounding only.
    if (norm - 1.0).abs() > 1e-3 {
        return Err(PoseError::BadQuaternion { norm });
    }
    Ok(Isometry3::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// COLMAP `(qw, qx, qy, qz)` and translation of a `cam_from_world` pose (qw ≥ 0).
pub fn colmap_from_cam_from_world(cam_from_world: &Pose) -> ([f64; 4], [f64; 3]) {
    let q = cam_from_world.rotation.quaternion();
    let sign = if q.w < 0.0 { -1.0 } else { 1.0 };
    let t = cam_from_world.translation.vector;
    (
        [sign * q.w, sign * q.i, sign * q.j, sign * q.k],
        [t.x, t.y, t.z],
    )
}

/// `cam_from_world` from a Mega-NeRF camera-to-world 3×4 in (down, right, back) camera axes.
pub fn cam_from_world_from_mega_nerf(c2w: &Matrix3x4<f64>) -> Result<Pose, PoseError> {
    let r: Matrix3<f64> = c2w.fixed_view::<3, 3>(0, 0).into_owned();
    let t: Vector3<f64> = c2w.column(3).into_owned();
    cam_from_world_from_c2w(&r, &t, &opencv_from_drb_axes())
}

/// Mega-NeRF camera-to-world 3×4 (down, right, back axes) of a `cam_from_world` pose.
pub fn mega_nerf_from_cam_from_world(cam_from_world: &Pose) -> Matrix3x4<f64> {
    let world_from_cam = cam_from_world.inverse();
    let r = world_from_cam.rotation.to_rotation_matrix().into_inner() * opencv_from_drb_axes();
    let mut m = Matrix3x4::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    m.set_column(3, &world_from_cam.translation.vector);
    m
}

/// Camera centre in world coordinates.
pub fn camera_center(cam_from_world: &Pose) -> Point3<f64> {
    cam_from_world.inverse_transform_point(&Point3::origin())
}

/// A camera pose re-expressed in another world frame: `cam_from_other` for `cam_from_world`
/// and the transform `world_from_other` between the frames (points map as
/// `x_world = world_from_other · x_other`).
pub fn cam_from_other_world(cam_from_world: &Pose, world_from_other: &Pose) -> Pose {
    cam_from_world * world_from_other
}

/// Unit viewing direction (the camera's +z axis) in world coordinates.
pub fn viewing_direction(cam_from_world: &Pose) -> Vector3<f64> {
    cam_from_world.inverse_transform_vector(&Vector3::z())
}

/// `cam_from_world` of a camera at `eye` looking at `target`, with image "up" towards `up`.
///
/// Returns `None` when `eye == target` or the viewing direction is parallel to `up`.
pub fn look_at(eye: &Point3<f64>, target: &Point3<f64>, up: &Vector3<f64>) -> Option<Pose> {
    let forward = (target - eye).try_normalize(1e-12)?;
    // OpenCV axes are right-handed with y down: x = y × z = (−up) × forward = forward × up.
    let right = forward.cross(up).try_normalize(1e-9)?;
    let down = forward.cross(&right);
    // Rows of cam_from_world rotation are the camera axes in world coordinates.
    let r = Matrix3::from_rows(&[right.transpose(), down.transpose(), forward.transpose()]);
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let t = -(rot * eye.coords);
    Some(Isometry3::from_parts(Translation3::from(t), rot))
}

/// The pose `w` of the way from `a` to `b` (`cam_from_world`): camera centres interpolated
/// linearly, attitudes by slerp (`a`'s when they are opposite). The slerped quaternion is
/// renormalised: for nearly equal attitudes slerp divides by a small sine and leaves its norm
/// off by ~1e-10, which moves a centre 150 m out by nanometres through `t = −R c`.
pub fn interpolate(a: &Pose, b: &Pose, w: f64) -> Pose {
    let c = camera_center(a).coords.lerp(&camera_center(b).coords, w);
    let r = a
        .rotation
        .try_slerp(&b.rotation, w, 1e-9)
        .unwrap_or(a.rotation);
    let r = UnitQuaternion::new_normalize(r.into_inner());
    Isometry3::from_parts(Translation3::from(-(r * c)), r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn pose_strategy() -> impl Strategy<Value = Pose> {
        (
            prop::array::uniform3(-1.0..1.0f64),
            0.01..std::f64::consts::PI,
            prop::array::uniform3(-500.0..500.0f64),
        )
            .prop_filter_map("axis must be non-zero", |(axis, angle, t)| {
                let axis = nalgebra::Unit::try_new(Vector3::from(axis), 1e-3)?;
                Some(Isometry3::from_parts(
                    Translation3::from(Vector3::from(t)),
                    UnitQuaternion::from_axis_angle(&axis, angle),
                ))
            })
    }

    fn close(a: &Pose, b: &Pose) -> bool {
        (a.translation.vector - b.translation.vector).norm() < 1e-9
            && a.rotation.angle_to(&b.rotation) < 1e-9
    }

    fn yaw_pitch_pose(yaw: f64, pitch: f64, c: [f64; 3]) -> Pose {
        let r = UnitQuaternion::from_euler_angles(pitch, 0.0, yaw);
        Isometry3::from_parts(Translation3::from(-(r * Vector3::from(c))), r)
    }

    /// Attitudes 0.3° apart, 150 m out: an unrenormalised slerp moved this centre by 6 nm.
    #[test]
    fn interpolating_nearby_attitudes_keeps_the_centre_and_a_unit_quaternion() {
        let a = yaw_pitch_pose(0.3, 0.2, [0.0, 48.7, 107.7]);
        let b = yaw_pitch_pose(0.305, 0.2, [-3.2, 48.8, 100.0]);
        let m = interpolate(&a, &b, 0.5);
        let mid = nalgebra::center(&camera_center(&a), &camera_center(&b));
        assert!((camera_center(&m) - mid).norm() < 1e-11);
        assert!((m.rotation.into_inner().norm() - 1.0).abs() < 1e-15);
    }

    proptest! {
        #[test]
        fn interpolate_moves_centres_linearly_and_turns_evenly(
            y1 in -3.0f64..3.0, y2 in -0.5f64..0.5, p in -1.0f64..1.0,
            c1 in proptest::array::uniform3(-150.0f64..150.0),
            c2 in proptest::array::uniform3(-150.0f64..150.0),
            w in 0.0f64..1.0,
        ) {
            let (a, b) = (yaw_pitch_pose(y1, p, c1), yaw_pitch_pose(y1 + y2, p, c2));
            let m = interpolate(&a, &b, w);
            let expect = Vector3::from(c1).lerp(&Vector3::from(c2), w);
            prop_assert!((camera_center(&m).coords - expect).norm() < 1e-9);
            let (ta, tb) = (m.rotation.angle_to(&a.rotation), m.rotation.angle_to(&b.rotation));
            let total = a.rotation.angle_to(&b.rotation);
            prop_assert!((ta - w * total).abs() < 1e-9 && (tb - (1.0 - w) * total).abs() < 1e-9);
            prop_assert!((interpolate(&a, &b, 0.0).translation.vector - a.translation.vector).norm() < 1e-9);
        }

        #[test]
        fn opengl_round_trip(p in pose_strategy()) {
            let m = opengl_from_cam_from_world(&p);
            prop_assert!(close(&cam_from_world_from_opengl(&m).unwrap(), &p));
        }

        #[test]
        fn colmap_round_trip(p in pose_strategy()) {
            let (q, t) = colmap_from_cam_from_world(&p);
            prop_assert!(q[0] >= 0.0);
            prop_assert!(close(&cam_from_world_from_colmap(q, t).unwrap(), &p));
        }

        #[test]
        fn mega_nerf_round_trip(p in pose_strategy()) {
            let m = mega_nerf_from_cam_from_world(&p);
            prop_assert!(close(&cam_from_world_from_mega_nerf(&m).unwrap(), &p));
        }

        #[test]
        fn chain_opengl_colmap_mega(p in pose_strategy()) {
            let from_gl = cam_from_world_from_opengl(&opengl_from_cam_from_world(&p)).unwrap();
            let (q, t) = colmap_from_cam_from_world(&from_gl);
            let from_colmap = cam_from_world_from_colmap(q, t).unwrap();
            let from_mega = cam_from_world_from_mega_nerf(&mega_nerf_from_cam_from_world(&from_colmap)).unwrap();
            prop_assert!(close(&from_mega, &p));
            // The camera centre is the same point in every convention.
            let gl = opengl_from_cam_from_world(&p);
            let c = camera_center(&p);
            prop_assert!((Vector3::new(gl[(0,3)], gl[(1,3)], gl[(2,3)]) - c.coords).norm() < 1e-9);
        }

        #[test]
        fn another_world_sees_the_same_camera(p in pose_strategy(), t in pose_strategy(),
                                              x in prop::array::uniform3(-50.0..50.0f64)) {
            // `t` is world_from_other: a point's camera coordinates do not depend on the
            // frame its world coordinates are written in.
            let other = cam_from_other_world(&p, &t);
            let x_other = Point3::from(Vector3::from(x));
            prop_assert!((other * x_other - p * (t * x_other)).norm() < 1e-8);
            prop_assert!((t * camera_center(&other) - camera_center(&p)).norm() < 1e-8);
            prop_assert!(close(&cam_from_other_world(&other, &t.inverse()), &p));
        }

        #[test]
        fn look_at_looks_at(eye in prop::array::uniform3(-100.0..100.0f64), target in prop::array::uniform3(-100.0..100.0f64)) {
            let eye = Point3::from(Vector3::from(eye));
            let target = Point3::from(Vector3::from(target));
            if let Some(p) = look_at(&eye, &target, &Vector3::z()) {
                let t_cam = p * target;
                prop_assert!(t_cam.x.abs() < 1e-6 * (1.0 + t_cam.z) && t_cam.y.abs() < 1e-6 * (1.0 + t_cam.z));
                prop_assert!(t_cam.z > 0.0);
                prop_assert!((camera_center(&p) - eye).norm() < 1e-9);
            }
        }
    }

    #[test]
    fn look_at_keeps_image_up_towards_up() {
        // Looking north with z up: image right is east, image down is world -z.
        let p = look_at(
            &Point3::origin(),
            &Point3::new(0.0, 10.0, 0.0),
            &Vector3::z(),
        )
        .unwrap();
        assert!((p.transform_vector(&Vector3::x()) - Vector3::x()).norm() < 1e-12);
        assert!((p.inverse_transform_vector(&Vector3::x()) - Vector3::x()).norm() < 1e-12);
        assert!((p.inverse_transform_vector(&Vector3::y()) + Vector3::z()).norm() < 1e-12);
    }

    #[test]
    fn opengl_axes_are_flipped() {
        // A nerfstudio camera at the origin with identity transform looks down world -z,
        // with image up = world +y.
        let p = cam_from_world_from_opengl(&Matrix4::identity()).unwrap();
        assert!((viewing_direction(&p) - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        let up_in_cam = p.transform_vector(&Vector3::y());
        assert!((up_in_cam - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn mega_nerf_axes() {
        // Identity drb camera-to-world: camera x (down) = world x, so the OpenCV camera's
        // forward axis (= -back) is world -z and its y (down) is world +x.
        let p = cam_from_world_from_mega_nerf(&Matrix3x4::identity()).unwrap();
        assert!((viewing_direction(&p) - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        let down_world = p.inverse_transform_vector(&Vector3::y());
        assert!((down_world - Vector3::x()).norm() < 1e-12);
    }

    #[test]
    fn bad_matrices_are_rejected() {
        let mut m = Matrix4::identity();
        m[(0, 0)] = 2.0;
        assert!(matches!(
            cam_from_world_from_opengl(&m),
            Err(PoseError::NotRigid { .. })
        ));
        let mut m = Matrix4::identity();
        m[(1, 3)] = f64::NAN;
        assert!(matches!(
            cam_from_world_from_opengl(&m),
            Err(PoseError::NonFinite { row: 1, col: 3, .. })
        ));
        let mut m = Matrix4::identity();
        m[(2, 2)] = -1.0; // reflection
        assert!(matches!(
            cam_from_world_from_opengl(&m),
            Err(PoseError::NotRigid { .. })
        ));
        let mut m = Matrix4::identity();
        m[(3, 0)] = 0.5;
        assert!(matches!(
            cam_from_world_from_opengl(&m),
            Err(PoseError::BadHomogeneousRow { .. })
        ));
        assert!(matches!(
            cam_from_world_from_colmap([0.0; 4], [0.0; 3]),
            Err(PoseError::BadQuaternion { .. })
        ));
    }
}
