//! Robust estimation on noisy data with outliers, planar and distorted scenes, and bad input.
//!
//! Scene scale: points 20–60 m in front of cameras 640–1600 px wide with 45–80° field of view
//! (aerial scenes: ground plane seen from 30–45 m altitude, up to 25° tilt); 1 px Gaussian noise
//! per axis on the inliers; outliers pair a true world point with a uniformly random pixel.
//! Success: translation error ≤ 0.1 m and rotation error ≤ 0.1°.

mod common;

use common::{Scene, aerial_pose, make_scene, pose_errors, random_camera, random_pose};
use matloc_core::metrics::median;
use matloc_core::{Camera, Pose};
use matloc_pnp::{
    EpnpPnp, LoRansacPnp, PnpError, PnpInput, PnpOptions, PoseSolver, RansacOptions, RefineOptions,
    RobustLoss, SamplerKind, refine_pose,
};
use nalgebra::{Point2, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

struct BatchResult {
    success: f64,
    /// Success at 0.5 m / 0.5°: separates wrong poses from noise-floor misses.
    loose_success: f64,
    /// Success of the oracle: least squares on the true inliers, started at the truth.
    oracle_success: f64,
    median_t_m: f64,
    median_r_deg: f64,
    median_iterations: f64,
}

fn run_batch(
    seed: u64,
    cases: usize,
    outlier_ratio: f64,
    planar: bool,
    distorted: bool,
) -> BatchResult {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let solver = LoRansacPnp::default();
    let mut ok = 0;
    let mut loose_ok = 0;
    let mut oracle_ok = 0;
    let (mut ts, mut rs, mut its) = (Vec::new(), Vec::new(), Vec::new());
    for case in 0..cases {
        // The solver gets its own stream, so the scenes do not depend on how much it draws.
        let mut solve_rng = ChaCha8Rng::seed_from_u64(seed * 1000 + case as u64);
        let camera = random_camera(&mut rng, distorted);
        let gt = if planar {
            aerial_pose(&mut rng)
        } else {
            random_pose(&mut rng)
        };
        let n = rng.random_range(100..=2000);
        let scene = make_scene(&mut rng, camera, gt, n, outlier_ratio, 1.0, planar);
        let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
        let (inl_px, inl_pts): (Vec<_>, Vec<_>) = scene
            .pixels
            .iter()
            .zip(&scene.points_world)
            .zip(&scene.is_inlier)
            .filter(|(_, inl)| **inl)
            .map(|((a, b), _)| (*a, *b))
            .unzip();
        let oracle = refine_pose(
            &scene.camera,
            &inl_px,
            &inl_pts,
            &gt,
            &RefineOptions {
                loss: RobustLoss::Trivial,
                ..RefineOptions::default()
            },
        )
        .unwrap();
        let (ot, or) = pose_errors(&oracle.cam_from_world, &gt);
        if ot <= 0.1 && or <= 0.1 {
            oracle_ok += 1;
        }
        match solver.solve(&input, &mut solve_rng) {
            Ok(result) => {
                let (t, r) = pose_errors(&result.cam_from_world, &gt);
                if t <= 0.1 && r <= 0.1 {
                    ok += 1;
                }
                if t <= 0.5 && r <= 0.5 {
                    loose_ok += 1;
                }
                ts.push(t);
                rs.push(r);
                its.push(result.stats.iterations as f64);
            }
            Err(_) => {
                ts.push(f64::INFINITY);
                rs.push(f64::INFINITY);
            }
        }
    }
    BatchResult {
        success: ok as f64 / cases as f64,
        loose_success: loose_ok as f64 / cases as f64,
        oracle_success: oracle_ok as f64 / cases as f64,
        median_t_m: median(&ts).unwrap(),
        median_r_deg: median(&rs).unwrap(),
        median_iterations: median(&its).unwrap_or(f64::NAN),
    }
}

fn report(label: &str, r: &BatchResult) {
    println!(
        "{label}: success {:.1} % (oracle {:.1} %, at 0.5 m/0.5° {:.1} %), median t {:.4} m, median r {:.4} deg, median iterations {}",
        100.0 * r.success,
        100.0 * r.oracle_success,
        100.0 * r.loose_success,
        r.median_t_m,
        r.median_r_deg,
        r.median_iterations
    );
}

/// ≥ 99 % success up to 80 % outliers, 100–2000 matches, general 3D scenes (200 cases each).
#[test]
fn success_rate_general_scenes() {
    for (k, ratio) in [0.0, 0.5, 0.8].into_iter().enumerate() {
        let r = run_batch(100 + k as u64, 200, ratio, false, false);
        report(&format!("general, {:.0} % outliers", ratio * 100.0), &r);
        assert!(r.success >= 0.99, "success {} at {ratio}", r.success);
    }
}

/// Planar aerial scenes (all points on the ground plane). Here 0.1 m / 0.1° is at the noise
/// floor: even the oracle (least squares on the true inliers, started at the truth) misses it in
/// 1–15 % of cases, so the solver is held to within 3 points of the oracle's success rate, and
/// to ≥ 99 % at 0.5 m / 0.5° (no wrong poses).
#[test]
fn success_rate_planar_scenes() {
    for (k, ratio) in [0.0, 0.5, 0.8].into_iter().enumerate() {
        let r = run_batch(200 + k as u64, 200, ratio, true, false);
        report(&format!("planar, {:.0} % outliers", ratio * 100.0), &r);
        assert!(
            r.success >= r.oracle_success - 0.03,
            "success {} vs oracle {} at {ratio}",
            r.success,
            r.oracle_success
        );
        assert!(
            r.loose_success >= 0.99,
            "loose success {} at {ratio}",
            r.loose_success
        );
    }
}

/// Distorted lenses (OpenCV k1, k2, p1, p2): 50 % outliers.
#[test]
fn success_rate_distorted_cameras() {
    let r = run_batch(300, 100, 0.5, false, true);
    report("distorted, 50 % outliers", &r);
    assert!(r.success >= 0.99, "success {}", r.success);
}

/// 90 % outliers is reported, not held to 99 % (inliers can be as few as 10).
#[test]
fn success_rate_ninety_percent_outliers_reported() {
    let general = run_batch(400, 30, 0.9, false, false);
    report("general, 90 % outliers", &general);
    let planar = run_batch(401, 30, 0.9, true, false);
    report("planar, 90 % outliers", &planar);
    assert!(general.success >= general.oracle_success - 0.1);
    assert!(planar.success >= planar.oracle_success - 0.1);
}

fn pinhole() -> Camera {
    Camera::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0).unwrap()
}

fn small_scene(seed: u64, n: usize) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let gt = random_pose(&mut rng);
    make_scene(&mut rng, pinhole(), gt, n, 0.0, 0.0, false)
}

#[test]
fn too_few_matches_is_a_typed_error() {
    let scene = small_scene(1, 3);
    let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    assert_eq!(
        LoRansacPnp::default().solve(&input, &mut rng),
        Err(PnpError::InsufficientCorrespondences {
            required: 4,
            actual: 3
        })
    );
    let empty = PnpInput::new(&scene.camera, &[], &[]);
    assert_eq!(
        LoRansacPnp::default().solve(&empty, &mut rng),
        Err(PnpError::InsufficientCorrespondences {
            required: 4,
            actual: 0
        })
    );
}

#[test]
fn non_finite_and_mismatched_input_name_the_problem() {
    let mut scene = small_scene(2, 20);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    scene.points_world[7].y = f64::NAN;
    let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
    assert_eq!(
        LoRansacPnp::default().solve(&input, &mut rng),
        Err(PnpError::NonFiniteInput {
            index: 7,
            what: "world point"
        })
    );
    scene.points_world[7].y = 1.0;
    scene.pixels[3].x = f64::INFINITY;
    let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
    assert_eq!(
        LoRansacPnp::default().solve(&input, &mut rng),
        Err(PnpError::NonFiniteInput {
            index: 3,
            what: "pixel"
        })
    );
    let input = PnpInput::new(&scene.camera, &scene.pixels[..5], &scene.points_world);
    assert!(matches!(
        LoRansacPnp::default().solve(&input, &mut rng),
        Err(PnpError::LengthMismatch {
            pixels: 5,
            points: 20,
            scores: None
        })
    ));
}

#[test]
fn collinear_and_coincident_points_are_degenerate_not_panics() {
    let camera = pinhole();
    let gt = Pose::from_parts(
        Translation3::new(0.0, 0.0, 30.0),
        UnitQuaternion::identity(),
    );
    let line: Vec<Point3<f64>> = (0..30)
        .map(|i| Point3::new(i as f64, 0.5 * i as f64, 2.0))
        .collect();
    let pixels: Vec<Point2<f64>> = line
        .iter()
        .map(|p| camera.project_world(&gt, p).unwrap())
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let solver = LoRansacPnp::default();
    assert!(matches!(
        solver.solve(&PnpInput::new(&camera, &pixels, &line), &mut rng),
        Err(PnpError::Degenerate(_))
    ));
    let same = vec![Point3::new(1.0, 2.0, 3.0); 30];
    assert!(matches!(
        solver.solve(&PnpInput::new(&camera, &pixels, &same), &mut rng),
        Err(PnpError::Degenerate(_))
    ));
    // Nearly collinear: 1 cm off a 30 m line. Either a pose or a typed error; never a panic.
    let near: Vec<Point3<f64>> = line
        .iter()
        .enumerate()
        .map(|(i, p)| p + Vector3::new(0.0, 0.0, 0.01 * ((i * 7 % 5) as f64 - 2.0)))
        .collect();
    let near_px: Vec<Point2<f64>> = near
        .iter()
        .map(|p| camera.project_world(&gt, p).unwrap())
        .collect();
    let _ = solver.solve(&PnpInput::new(&camera, &near_px, &near), &mut rng);
    let _ = EpnpPnp::default().solve(&PnpInput::new(&camera, &near_px, &near), &mut rng);
}

#[test]
fn points_behind_the_camera_are_outliers() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let camera = random_camera(&mut rng, false);
    let gt = random_pose(&mut rng);
    let mut scene = make_scene(&mut rng, camera, gt, 200, 0.0, 0.5, false);
    // Mirror 40 points through the camera centre: same pixels, world points behind the camera.
    let centre = gt.inverse().translation.vector;
    for p in scene.points_world.iter_mut().take(40) {
        *p = Point3::from(2.0 * centre - p.coords);
    }
    let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
    let result = LoRansacPnp::default().solve(&input, &mut rng).unwrap();
    let (t, r) = pose_errors(&result.cam_from_world, &gt);
    assert!(t < 0.1 && r < 0.1, "t {t} r {r}");
    assert!(result.inliers[..40].iter().all(|&i| !i));
    assert!(result.stats.num_inliers >= 150);
}

#[test]
fn no_consensus_is_reported_not_a_pose() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let camera = random_camera(&mut rng, false);
    let gt = random_pose(&mut rng);
    let scene = make_scene(&mut rng, camera, gt, 300, 1.0, 1.0, false);
    let options = PnpOptions {
        ransac: RansacOptions {
            min_inliers: 30,
            max_iterations: 2000,
            max_error_px: 1.0,
            ..RansacOptions::default()
        },
        ..PnpOptions::default()
    };
    let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
    match LoRansacPnp::new(options).solve(&input, &mut rng) {
        Err(PnpError::NoConsensus {
            best_inliers,
            required: 30,
        }) => assert!(best_inliers < 30),
        other => panic!("expected NoConsensus, got {other:?}"),
    }
}

/// PROSAC with informative scores finds the pose in fewer samples than uniform sampling.
#[test]
fn prosac_uses_scores() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let camera = random_camera(&mut rng, false);
    let gt = random_pose(&mut rng);
    let scene = make_scene(&mut rng, camera, gt, 1000, 0.85, 1.0, false);
    // Inliers tend to score higher, with overlap (as similarity scores do).
    let scores: Vec<f64> = scene
        .is_inlier
        .iter()
        .map(|&inl| if inl { 0.6 } else { 0.4 } + rng.random_range(-0.3..0.3))
        .collect();
    let run = |sampler: SamplerKind, rng: &mut ChaCha8Rng| {
        let options = PnpOptions {
            ransac: RansacOptions {
                sampler,
                ..RansacOptions::default()
            },
            ..PnpOptions::default()
        };
        let input =
            PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world).with_scores(&scores);
        LoRansacPnp::new(options).solve(&input, rng).unwrap()
    };
    let prosac = run(SamplerKind::Prosac, &mut rng);
    let uniform = run(SamplerKind::Uniform, &mut rng);
    let (t, r) = pose_errors(&prosac.cam_from_world, &gt);
    assert!(t < 0.1 && r < 0.1);
    println!(
        "iterations: PROSAC {}, uniform {}",
        prosac.stats.iterations, uniform.stats.iterations
    );
    assert!(prosac.stats.iterations < uniform.stats.iterations);
}

/// The same seed gives the same pose; the solver works behind `dyn PoseSolver`.
#[test]
fn seeded_solves_are_reproducible_and_object_safe() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let camera = random_camera(&mut rng, true);
    let gt = aerial_pose(&mut rng);
    let scene = make_scene(&mut rng, camera, gt, 400, 0.6, 1.0, true);
    let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
    let solvers: Vec<Box<dyn PoseSolver>> = vec![Box::new(LoRansacPnp::default())];
    let a = solvers[0]
        .solve(&input, &mut ChaCha8Rng::seed_from_u64(1))
        .unwrap();
    let b = solvers[0]
        .solve(&input, &mut ChaCha8Rng::seed_from_u64(1))
        .unwrap();
    assert_eq!(a.cam_from_world, b.cam_from_world);
    assert_eq!(a.inliers, b.inliers);
    let (t, r) = pose_errors(&a.cam_from_world, &gt);
    assert!(t < 0.1 && r < 0.1, "t {t} r {r}");
    // Inlier mask agrees with the truth for all but a handful of borderline matches.
    let wrong = a
        .inliers
        .iter()
        .zip(&scene.is_inlier)
        .filter(|(x, y)| x != y)
        .count();
    assert!(wrong < 20, "{wrong} mask disagreements");
}

/// EPnP + refinement on a clean planar set (the non-minimal path used without RANSAC).
#[test]
fn epnp_solver_on_clean_noisy_planar_set() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    for _ in 0..20 {
        let camera = random_camera(&mut rng, false);
        let gt = aerial_pose(&mut rng);
        let scene = make_scene(&mut rng, camera, gt, 300, 0.0, 1.0, true);
        let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
        let result = EpnpPnp::default().solve(&input, &mut rng).unwrap();
        let (t, r) = pose_errors(&result.cam_from_world, &gt);
        assert!(t < 0.1 && r < 0.1, "t {t} r {r}");
    }
}

/// Options are plain data: a JSON file describes a run, and missing fields take defaults.
#[test]
fn options_round_trip_through_json() {
    let mut options = PnpOptions::default();
    options.ransac.max_error_px = 2.5;
    options.ransac.sampler = SamplerKind::Prosac;
    options.refine.loss = RobustLoss::Huber { scale_px: 1.5 };
    let text = serde_json::to_string(&options).unwrap();
    let back: PnpOptions = serde_json::from_str(&text).unwrap();
    assert_eq!(back, options);
    let partial: PnpOptions = serde_json::from_str(r#"{"ransac": {"max_error_px": 4.0}}"#).unwrap();
    assert_eq!(partial.ransac.max_error_px, 4.0);
    assert_eq!(
        partial.ransac.confidence,
        RansacOptions::default().confidence
    );
    assert!(partial.final_refinement);
}

/// Nearly planar ground (±0.5 m relief over a ~100 m footprint): EPnP takes its 4-control-point
/// branch on a badly conditioned spread; with the refinement the pose is still exact to noise.
#[test]
fn epnp_solver_on_nearly_planar_relief() {
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    for _ in 0..20 {
        let camera = random_camera(&mut rng, false);
        let gt = aerial_pose(&mut rng);
        let mut scene = make_scene(&mut rng, camera, gt, 300, 0.0, 0.0, true);
        for (p, px) in scene.points_world.iter_mut().zip(scene.pixels.iter_mut()) {
            p.z += rng.random_range(-0.5..0.5);
            *px = scene.camera.project_world(&gt, p).unwrap()
                + nalgebra::Vector2::new(common::gauss(&mut rng), common::gauss(&mut rng));
        }
        let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
        let result = EpnpPnp::default().solve(&input, &mut rng).unwrap();
        let (t, r) = pose_errors(&result.cam_from_world, &gt);
        assert!(t < 0.1 && r < 0.1, "t {t} r {r}");
        let ransac = LoRansacPnp::default().solve(&input, &mut rng).unwrap();
        let (t, r) = pose_errors(&ransac.cam_from_world, &gt);
        assert!(t < 0.1 && r < 0.1, "t {t} r {r}");
    }
}

/// A larger batch for the record (`cargo test -p matloc-pnp --release -- --ignored --nocapture`).
#[test]
#[ignore = "about a minute; run by hand for the report"]
fn success_rate_large_batches() {
    for (k, ratio) in [0.5, 0.8].into_iter().enumerate() {
        let r = run_batch(500 + k as u64, 1000, ratio, false, false);
        report(
            &format!("general, {:.0} % outliers, 1000 cases", ratio * 100.0),
            &r,
        );
    }
    let r = run_batch(510, 300, 0.9, false, false);
    report("general, 90 % outliers, 300 cases", &r);
}

#[test]
fn input_threshold_overrides_the_solver_option() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let gt = random_pose(&mut rng);
    // Coarse matches: 6 px noise, 30 % outliers.
    let scene = make_scene(&mut rng, pinhole(), gt, 300, 0.3, 6.0, false);
    let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
    let solver = LoRansacPnp::default();
    let tight = solver
        .solve(&input, &mut ChaCha8Rng::seed_from_u64(0))
        .map(|r| r.stats.num_inliers)
        .unwrap_or(0);
    let loose = solver
        .solve(
            &input.with_max_error_px(20.0),
            &mut ChaCha8Rng::seed_from_u64(0),
        )
        .expect("a loose threshold finds the pose");
    let true_inliers = scene.is_inlier.iter().filter(|&&b| b).count();
    // 3 px keeps a minority of 6 px-noise inliers; 20 px (> 3 sigma) keeps nearly all of them.
    assert!(tight < true_inliers / 2, "tight {tight} of {true_inliers}");
    assert!(
        loose.stats.num_inliers >= true_inliers * 95 / 100,
        "loose {} of {true_inliers}",
        loose.stats.num_inliers
    );
    let (t, r) = pose_errors(&loose.cam_from_world, &gt);
    assert!(t < 1.0 && r < 1.0, "{t} m {r} deg");
    // An invalid override is a typed error, like the option itself.
    assert!(matches!(
        solver.solve(&input.with_max_error_px(-1.0), &mut rng),
        Err(PnpError::InvalidOption { .. })
    ));
}
