//! Synthetic 2D–3D correspondence sets with ground truth, for tests, benchmarks and demos.
//!
//! Scale: points 20–60 m in front of the camera (an aerial view from a few tens of metres),
//! cameras of 640–1600 px width with 45–80° horizontal field of view, so 1 px of image noise is
//! 2–7 cm of lateral error at the points.

use matloc_core::{Camera, Distortion, Pose};
use nalgebra::{Point2, Point3, Translation3, UnitQuaternion, Vector2, Vector3};
use rand::{Rng, RngCore};

/// One generated problem with its ground truth.
#[derive(Clone, Debug)]
pub struct Scene {
    /// The camera that observed the points.
    pub camera: Camera,
    /// Ground-truth pose.
    pub cam_from_world: Pose,
    /// Observed pixels (noisy for inliers, random for outliers).
    pub pixels: Vec<Point2<f64>>,
    /// World points.
    pub points_world: Vec<Point3<f64>>,
    /// Whether each match is a true (noisy) correspondence.
    pub is_inlier: Vec<bool>,
}

/// Standard normal sample (Box–Muller; keeps the tests free of extra dependencies).
pub fn gauss(rng: &mut dyn RngCore) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// A pinhole (or mildly distorted) camera of realistic size and field of view.
pub fn random_camera(rng: &mut dyn RngCore, distorted: bool) -> Camera {
    let width = rng.random_range(640..1600u32);
    let height = width * 3 / 4;
    let hfov_deg: f64 = rng.random_range(45.0..80.0);
    let f = 0.5 * width as f64 / (0.5 * hfov_deg.to_radians()).tan();
    let distortion = if distorted {
        Distortion {
            k1: rng.random_range(-0.2..0.1),
            k2: rng.random_range(-0.03..0.03),
            p1: rng.random_range(-0.001..0.001),
            p2: rng.random_range(-0.001..0.001),
            k3: 0.0,
        }
    } else {
        Distortion::NONE
    };
    Camera::opencv(
        width,
        height,
        f * rng.random_range(0.99..1.01),
        f,
        0.5 * width as f64 + rng.random_range(-10.0..10.0),
        0.5 * height as f64 + rng.random_range(-10.0..10.0),
        distortion,
    )
    .unwrap()
}

/// A random `cam_from_world`: any orientation, camera centre within ±200 m of the origin.
pub fn random_pose(rng: &mut dyn RngCore) -> Pose {
    let axis = Vector3::new(gauss(rng), gauss(rng), gauss(rng));
    let angle = rng.random_range(0.0..std::f64::consts::PI);
    let rotation = UnitQuaternion::from_scaled_axis(axis.normalize() * angle);
    let centre = Vector3::new(
        rng.random_range(-200.0..200.0),
        rng.random_range(-200.0..200.0),
        rng.random_range(-50.0..50.0),
    );
    // t = −R c
    Pose::from_parts(Translation3::from(-(rotation * centre)), rotation)
}

/// A looking-down aerial pose over the ground plane z = 0: altitude 30–45 m, tilt up to 25°.
pub fn aerial_pose(rng: &mut dyn RngCore) -> Pose {
    let yaw = rng.random_range(0.0..std::f64::consts::TAU);
    let tilt = rng.random_range(0.0..25f64).to_radians();
    let tilt_axis = rng.random_range(0.0..std::f64::consts::TAU);
    // Camera z (forward) = world −z, tilted.
    let down = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, yaw);
    let tilt = UnitQuaternion::from_scaled_axis(
        Vector3::new(tilt_axis.cos(), tilt_axis.sin(), 0.0) * tilt,
    );
    let world_from_cam_rot = tilt * down;
    let centre = Vector3::new(
        rng.random_range(-300.0..300.0),
        rng.random_range(-300.0..300.0),
        rng.random_range(30.0..45.0),
    );
    let rotation = world_from_cam_rot.inverse();
    Pose::from_parts(Translation3::from(-(rotation * centre)), rotation)
}

/// A random pixel well inside the image.
fn random_pixel(rng: &mut dyn RngCore, camera: &Camera) -> Point2<f64> {
    Point2::new(
        rng.random_range(0.02..0.98) * camera.width as f64,
        rng.random_range(0.02..0.98) * camera.height as f64,
    )
}

/// A random pixel and the world point seen there: at depth 20–60 m, or on the plane z = 0 when
/// `planar` (falling back to depth sampling if the plane is rarely in view).
fn random_visible_point(
    rng: &mut dyn RngCore,
    camera: &Camera,
    cam_from_world: &Pose,
    planar: bool,
) -> (Point2<f64>, Point3<f64>) {
    let mut attempts = 0;
    loop {
        attempts += 1;
        let planar = planar && attempts < 1000;
        let px = random_pixel(rng, camera);
        let Some(bearing) = camera.unproject(px) else {
            continue;
        };
        let world_from_cam = cam_from_world.inverse();
        if planar {
            let o = world_from_cam.translation.vector;
            let d = world_from_cam.rotation * bearing;
            if d.z.abs() < 1e-6 {
                continue;
            }
            let s = -o.z / d.z;
            let depth = s * bearing.z;
            if s > 0.0 && (15.0..80.0).contains(&depth) {
                return (px, Point3::from(o + s * d));
            }
        } else {
            let depth = rng.random_range(20.0..60.0);
            let p_cam = bearing * (depth / bearing.z);
            return (px, world_from_cam * Point3::from(p_cam));
        }
    }
}

/// Matches seen by `camera` at `cam_from_world`, outliers first, with Gaussian pixel noise (σ = `noise_px` per axis) and a fraction of wrong matches
/// (a true world point paired with a uniformly random pixel).
pub fn make_scene(
    rng: &mut dyn RngCore,
    camera: Camera,
    cam_from_world: Pose,
    n: usize,
    outlier_ratio: f64,
    noise_px: f64,
    planar: bool,
) -> Scene {
    let num_outliers = (n as f64 * outlier_ratio).round() as usize;
    let mut pixels = Vec::with_capacity(n);
    let mut points_world = Vec::with_capacity(n);
    let mut is_inlier = Vec::with_capacity(n);
    for i in 0..n {
        let (clean, p) = random_visible_point(rng, &camera, &cam_from_world, planar);
        let inlier = i >= num_outliers;
        let px = if inlier {
            clean + Vector2::new(gauss(rng), gauss(rng)) * noise_px
        } else {
            random_pixel(rng, &camera)
        };
        pixels.push(px);
        points_world.push(p);
        is_inlier.push(inlier);
    }
    Scene {
        camera,
        cam_from_world,
        pixels,
        points_world,
        is_inlier,
    }
}

/// (translation error m, rotation error deg).
pub fn pose_errors(est: &Pose, gt: &Pose) -> (f64, f64) {
    (
        matloc_core::metrics::translation_error_m(est, gt),
        matloc_core::metrics::rotation_error_deg(est, gt),
    )
}
