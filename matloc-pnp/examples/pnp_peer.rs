//! Peer comparison, Rust side: writes seeded correspondence sets to `<out>/cases.json`, solves
//! them with `LoRansacPnp` (single thread, best of 3 timings per case) and writes timings and errors to `<out>/ours.json`.
//! `bench/pnp/compare.py` then runs PoseLib and OpenCV on the same sets.
//!
//! Usage: `cargo run --release -p matloc-pnp --example pnp_peer -- <out-dir> [cases] [threshold_px]`

use std::time::Instant;

use matloc_pnp::synthetic::{aerial_pose, make_scene, pose_errors, random_camera, random_pose};
use matloc_pnp::{
    LoRansacPnp, PnpInput, PnpOptions, PoseSolver, RansacOptions, RefineOptions, RobustLoss,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};

/// (name, matches, outlier ratio, planar aerial scene)
const SETTINGS: &[(&str, usize, f64, bool)] = &[
    ("general n=200 out=50%", 200, 0.5, false),
    ("general n=1000 out=80%", 1000, 0.8, false),
    ("general n=2000 out=90%", 2000, 0.9, false),
    ("planar n=500 out=0%", 500, 0.0, true),
    ("planar n=1000 out=50%", 1000, 0.5, true),
    ("planar n=1000 out=80%", 1000, 0.8, true),
];

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let out_dir =
        std::path::PathBuf::from(args.get(1).map(String::as_str).unwrap_or("bench/pnp/out"));
    let cases: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(50);
    let threshold_px: f64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(2.0);
    std::fs::create_dir_all(&out_dir).expect("create output directory");

    let options = PnpOptions {
        ransac: RansacOptions {
            max_error_px: threshold_px,
            ..RansacOptions::default()
        },
        refine: RefineOptions {
            loss: RobustLoss::Cauchy {
                scale_px: threshold_px,
            },
            ..RefineOptions::default()
        },
        ..PnpOptions::default()
    };
    let solver = LoRansacPnp::new(options);

    let mut settings_json = Vec::new();
    let mut ours_json = Vec::new();
    for (k, &(name, n, outlier_ratio, planar)) in SETTINGS.iter().enumerate() {
        let mut rng = ChaCha8Rng::seed_from_u64(1000 + k as u64);
        let mut cases_json = Vec::new();
        let mut results = Vec::new();
        for _ in 0..cases {
            let camera = random_camera(&mut rng, false);
            let gt = if planar {
                aerial_pose(&mut rng)
            } else {
                random_pose(&mut rng)
            };
            let scene = make_scene(&mut rng, camera, gt, n, outlier_ratio, 1.0, planar);
            let r = gt.rotation.to_rotation_matrix().into_inner();
            cases_json.push(json!({
                "camera": {"width": camera.width, "height": camera.height,
                           "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy},
                "gt_R": (0..3).map(|i| (0..3).map(|j| r[(i, j)]).collect::<Vec<_>>()).collect::<Vec<_>>(),
                "gt_t": gt.translation.vector.as_slice(),
                "pixels": scene.pixels.iter().map(|p| [p.x, p.y]).collect::<Vec<_>>(),
                "points": scene.points_world.iter().map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>(),
            }));
            let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
            // Best of 3 identical solves: the machine is shared, and the minimum is the least
            // disturbed measurement (compare.py does the same for PoseLib).
            let mut seconds = f64::INFINITY;
            let mut result = None;
            for _ in 0..3 {
                let mut solve_rng = ChaCha8Rng::seed_from_u64(7);
                let start = Instant::now();
                let r = solver.solve(&input, &mut solve_rng);
                seconds = seconds.min(start.elapsed().as_secs_f64());
                result = Some(r);
            }
            let result = result.expect("three solves ran");
            let (t_err, r_err, iterations) = match &result {
                Ok(res) => {
                    let (t, r) = pose_errors(&res.cam_from_world, &gt);
                    (t, r, res.stats.iterations)
                }
                Err(_) => (f64::INFINITY, f64::INFINITY, 0),
            };
            results.push(json!({"time_s": seconds, "t_err_m": finite_or_null(t_err),
                                "r_err_deg": finite_or_null(r_err), "iterations": iterations}));
        }
        eprintln!("{name}: {cases} cases written and solved");
        settings_json.push(json!({"name": name, "n": n, "outlier_ratio": outlier_ratio,
                                  "planar": planar, "cases": cases_json}));
        ours_json.push(json!({"name": name, "results": results}));
    }
    let cases_doc =
        json!({"threshold_px": threshold_px, "noise_px": 1.0, "settings": settings_json});
    let ours_doc = json!({"solver": "matloc-pnp LoRansacPnp", "settings": ours_json});
    std::fs::write(out_dir.join("cases.json"), cases_doc.to_string()).expect("write cases.json");
    std::fs::write(out_dir.join("ours.json"), ours_doc.to_string()).expect("write ours.json");
}

fn finite_or_null(v: f64) -> Value {
    if v.is_finite() { json!(v) } else { Value::Null }
}
