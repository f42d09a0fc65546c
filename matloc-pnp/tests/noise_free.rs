//! Property tests of the solvers on exact data and of the refinement's monotonicity.
//!
//! Scene scale: points 20–60 m in front of cameras 640–1600 px wide with 45–80° field of view,
//! camera centres within ±200 m of the world origin in any orientation (see `common`).

mod common;

use common::{aerial_pose, make_scene, pose_errors, random_camera, random_pose};
use matloc_core::{Camera, Pose};
use matloc_pnp::{PoseMatrix, RefineOptions, RobustLoss, epnp, p3p, refine_pose};
use nalgebra::{Point2, Point3, Translation3, UnitQuaternion, Vector2, Vector3};
use proptest::prelude::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn normalized(camera: &Camera, pixels: &[Point2<f64>]) -> Vec<Vector2<f64>> {
    pixels
        .iter()
        .map(|p| camera.pixel_to_normalized(*p).unwrap())
        .collect()
}

fn coords(points: &[Point3<f64>]) -> Vec<Vector3<f64>> {
    points.iter().map(|p| p.coords).collect()
}

/// Robust cost of a pose recomputed independently of the refinement code.
fn robust_cost(
    camera: &Camera,
    pixels: &[Point2<f64>],
    points: &[Point3<f64>],
    pose: &Pose,
    loss: &RobustLoss,
) -> f64 {
    pixels
        .iter()
        .zip(points)
        .map(|(px, p)| match camera.project_world(pose, p) {
            Some(proj) => loss.cost((proj - px).norm_squared()),
            None => loss.cost(1e12),
        })
        .sum()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// P3P on exact bearings: one of its solutions is the true pose to 1e-6 m / 1e-6°.
    #[test]
    fn p3p_recovers_exact_pose(seed in any::<u64>(), planar in any::<bool>()) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let camera = random_camera(&mut rng, false);
        let gt = if planar { aerial_pose(&mut rng) } else { random_pose(&mut rng) };
        let scene = make_scene(&mut rng, camera, gt, 3, 0.0, 0.0, planar);
        let bearings: Vec<Vector3<f64>> = scene.pixels.iter().map(|p| camera.unproject(*p).unwrap()).collect();
        let pts = coords(&scene.points_world);
        // Nearly collinear random triples are legitimately ill-conditioned; skip them.
        let area = (pts[1] - pts[0]).cross(&(pts[2] - pts[0])).norm();
        let longest = (pts[1] - pts[0]).norm().max((pts[2] - pts[0]).norm()).max((pts[2] - pts[1]).norm());
        prop_assume!(area > 0.05 * longest * longest);
        let mut out = Vec::new();
        p3p(&[bearings[0], bearings[1], bearings[2]], &[pts[0], pts[1], pts[2]], &mut out);
        prop_assert!(!out.is_empty() && out.len() <= 4);
        let best = out
            .iter()
            .map(|m| { let (t, r) = pose_errors(&m.to_pose(), &gt); t.max(r) })
            .fold(f64::INFINITY, f64::min);
        prop_assert!(best < 1e-6, "best of {} solutions is {best}", out.len());
    }

    /// EPnP on exact correspondences (general and planar scenes) recovers the pose to 1e-6.
    #[test]
    fn epnp_recovers_exact_pose(seed in any::<u64>(), n in 6usize..200, planar in any::<bool>()) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let camera = random_camera(&mut rng, false);
        let gt = if planar { aerial_pose(&mut rng) } else { random_pose(&mut rng) };
        let scene = make_scene(&mut rng, camera, gt, n, 0.0, 0.0, planar);
        let pose = epnp(&normalized(&camera, &scene.pixels), &coords(&scene.points_world)).expect("EPnP pose");
        let (t, r) = pose_errors(&pose.to_pose(), &gt);
        prop_assert!(t < 1e-6 && r < 1e-6, "t {t} m, r {r} deg");
    }

    /// Refinement never increases the robust cost, for every loss, from perturbed starts on
    /// noisy data with outliers and a distorted lens.
    #[test]
    fn refinement_never_increases_cost(
        seed in any::<u64>(),
        loss_kind in 0usize..4,
        scale in 0.5f64..5.0,
        perturb in 0.0f64..0.05,
    ) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let camera = random_camera(&mut rng, seed % 2 == 0);
        let gt = random_pose(&mut rng);
        let scene = make_scene(&mut rng, camera, gt, 60, 0.3, 1.0, false);
        let loss = match loss_kind {
            0 => RobustLoss::Trivial,
            1 => RobustLoss::Huber { scale_px: scale },
            2 => RobustLoss::Cauchy { scale_px: scale },
            _ => RobustLoss::Truncated { scale_px: scale },
        };
        let start = Pose::from_parts(
            Translation3::from(gt.translation.vector + Vector3::new(1.0, -2.0, 0.5) * perturb * 20.0),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.3, 0.2, -0.4) * perturb) * gt.rotation,
        );
        let options = RefineOptions { loss, ..RefineOptions::default() };
        let report = refine_pose(&camera, &scene.pixels, &scene.points_world, &start, &options).unwrap();
        prop_assert!(report.final_cost <= report.initial_cost, "{} > {}", report.final_cost, report.initial_cost);
        let before = robust_cost(&camera, &scene.pixels, &scene.points_world, &start, &loss);
        let after = robust_cost(&camera, &scene.pixels, &scene.points_world, &report.cam_from_world, &loss);
        prop_assert!(after <= before * (1.0 + 1e-9) + 1e-9, "independent cost {after} > {before}");
        prop_assert!((before - report.initial_cost).abs() <= 1e-6 * before.max(1.0));
    }
}

/// The analytic Jacobian agrees with the cost: a refinement from the exact pose on exact data
/// stays there, and from a perturbed pose returns to it (distorted camera).
#[test]
fn refinement_converges_to_exact_pose_with_distortion() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for _ in 0..20 {
        let camera = random_camera(&mut rng, true);
        let gt = random_pose(&mut rng);
        let scene = make_scene(&mut rng, camera, gt, 50, 0.0, 0.0, false);
        let start = Pose::from_parts(
            Translation3::from(gt.translation.vector + Vector3::new(0.5, -0.3, 1.0)),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.01, -0.02, 0.015)) * gt.rotation,
        );
        let options = RefineOptions {
            loss: RobustLoss::Trivial,
            ..RefineOptions::default()
        };
        let report = refine_pose(
            &camera,
            &scene.pixels,
            &scene.points_world,
            &start,
            &options,
        )
        .unwrap();
        let (t, r) = pose_errors(&report.cam_from_world, &gt);
        assert!(
            t < 1e-6 && r < 1e-6,
            "t {t} r {r} after {} iterations",
            report.iterations
        );
    }
}

/// EPnP handles a matrix-form pose round trip (sanity of the public model type).
#[test]
fn pose_matrix_round_trip() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let pose = random_pose(&mut rng);
    let back = PoseMatrix::from_pose(&pose).to_pose();
    let (t, r) = pose_errors(&back, &pose);
    assert!(t < 1e-9 && r < 1e-9);
}
