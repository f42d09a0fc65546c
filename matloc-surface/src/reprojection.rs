//! Reprojection residuals of a camera `(R, c)` (its `cam_from_world` rotation and centre: a
//! point `X` is `R (X − c)` in the camera) with their Jacobians, the Huber weights both bundle
//! adjustments use, and the structure-only adjustment of one point ([`refine_point`]). A
//! residual is the difference of the point's pinhole projection and the observed pixel
//! undistorted through the camera's lens, in pixels (`fx`, `fy`).

use matloc_core::Camera;
use matloc_core::pose::{Pose, camera_center};
use nalgebra::{Matrix3, Point2, Point3, Rotation3, Vector2, Vector3};

/// Per image: the rotation and centre being adjusted.
#[derive(Clone, Copy)]
pub(crate) struct Cam {
    pub(crate) r: Rotation3<f64>,
    pub(crate) c: Vector3<f64>,
}

/// An observation undistorted: normalised image coordinates and the focal lengths.
#[derive(Clone, Copy)]
pub(crate) struct Obs {
    pub(crate) image: usize,
    pub(crate) point: usize,
    pub(crate) target: Vector2<f64>,
    pub(crate) focal: Vector2<f64>,
}

/// A residual (pixels) with its Jacobians w.r.t. the camera's `(δθ, δc)` and the point's `δX`.
pub(crate) type Linearised = (
    Vector2<f64>,
    nalgebra::Matrix2x6<f64>,
    nalgebra::Matrix2x3<f64>,
);

/// The residual of `o` and its Jacobians (`None` behind the camera).
pub(crate) fn residual(cam: &Cam, x: &Vector3<f64>, o: &Obs) -> Option<Linearised> {
    let p = cam.r * (x - cam.c);
    if p.z <= 1e-9 {
        return None;
    }
    let iz = 1.0 / p.z;
    let r = Vector2::new(
        o.focal.x * (p.x * iz - o.target.x),
        o.focal.y * (p.y * iz - o.target.y),
    );
    // d r / d p.
    let dr = nalgebra::Matrix2x3::new(
        o.focal.x * iz,
        0.0,
        -o.focal.x * p.x * iz * iz,
        0.0,
        o.focal.y * iz,
        -o.focal.y * p.y * iz * iz,
    );
    // d p / d δθ = −[p]×, d p / d δc = −R, d p / d δX = R.
    let rm = cam.r.matrix();
    let mut jcam = nalgebra::Matrix2x6::zeros();
    jcam.fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(dr * (-p.cross_matrix())));
    jcam.fixed_view_mut::<2, 3>(0, 3).copy_from(&(dr * (-rm)));
    Some((r, jcam, dr * rm))
}

/// Huber weight of a residual of norm `n`.
pub(crate) fn huber_weight(n: f64, delta: f64) -> f64 {
    if n <= delta { 1.0 } else { delta / n }
}

/// Huber cost of a residual of norm `n` (½ n² inside).
pub(crate) fn huber_cost(n: f64, delta: f64) -> f64 {
    if n <= delta {
        0.5 * n * n
    } else {
        delta * (n - 0.5 * delta)
    }
}

/// One fixed camera's observation of a point, for [`refine_point`].
#[derive(Clone, Copy, Debug)]
pub struct PointView<'a> {
    /// The image's camera (the pixel's frame).
    pub camera: &'a Camera,
    /// Its `cam_from_world`, held fixed.
    pub cam_from_world: &'a Pose,
    /// Where the image sees the point, continuous pixel coordinates.
    pub pixel: Point2<f64>,
}

/// Structure-only bundle adjustment of one point: the cameras fixed, the point moved to
/// minimise the Huber cost of its reprojection errors (Levenberg–Marquardt on its three
/// coordinates, at most `iterations` steps) — what a triangulation from rays (least squares
/// on distances to the rays, which weighs far cameras more) leaves to be done. `None` when a
/// pixel does not undistort or the start is behind a camera; otherwise the refined point
/// (the start itself when no step lowers the cost).
pub fn refine_point(
    views: &[PointView<'_>],
    start: Point3<f64>,
    huber_px: f64,
    iterations: usize,
) -> Option<Point3<f64>> {
    let mut cams = Vec::with_capacity(views.len());
    let mut obs = Vec::with_capacity(views.len());
    for (k, v) in views.iter().enumerate() {
        let b = v.camera.unproject(v.pixel)?;
        let target = Vector2::new(b.x / b.z, b.y / b.z);
        if !(target.x.is_finite() && target.y.is_finite()) {
            return None;
        }
        cams.push(Cam {
            r: v.cam_from_world.rotation.to_rotation_matrix(),
            c: camera_center(v.cam_from_world).coords,
        });
        obs.push(Obs {
            image: k,
            point: 0,
            target,
            focal: Vector2::new(v.camera.fx, v.camera.fy),
        });
    }
    let cost = |x: &Vector3<f64>| -> Option<f64> {
        obs.iter().try_fold(0.0, |acc, o| {
            residual(&cams[o.image], x, o).map(|(r, _, _)| acc + huber_cost(r.norm(), huber_px))
        })
    };
    let mut x = start.coords;
    let mut current = cost(&x)?;
    let mut lambda = 1e-3;
    for _ in 0..iterations {
        let (mut h, mut g) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros());
        for o in &obs {
            let (r, _, jp) = residual(&cams[o.image], &x, o)?;
            let w = huber_weight(r.norm(), huber_px);
            h += w * jp.transpose() * jp;
            g += w * jp.transpose() * r;
        }
        let mut improved = false;
        while lambda < 1e8 {
            let mut damped = h;
            for d in 0..3 {
                damped[(d, d)] += lambda * h[(d, d)].max(1e-12);
            }
            let Some(step) = damped.lu().solve(&(-g)) else {
                lambda *= 10.0;
                continue;
            };
            let y = x + step;
            if let Some(c) = cost(&y)
                && c < current
            {
                let gain = current - c;
                x = y;
                current = c;
                lambda = (lambda * 0.1).max(1e-9);
                improved = gain > 1e-12 * (1.0 + current);
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    Some(Point3::from(x))
}
