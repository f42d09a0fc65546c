//! Criterion benches: the P3P minimal solver, EPnP, one refinement, and full LO-RANSAC solves
//! (200 matches at 50 % outliers, 1000 matches at 80 %; 2 px threshold, 1 px noise).

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use matloc_pnp::synthetic::{make_scene, random_camera, random_pose};
use matloc_pnp::{
    LoRansacPnp, PnpInput, PnpOptions, PoseSolver, RansacOptions, RefineOptions, epnp, p3p,
    refine_pose,
};
use nalgebra::{Vector2, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn bench_minimal(c: &mut Criterion) {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let camera = random_camera(&mut rng, false);
    let gt = random_pose(&mut rng);
    let scene = make_scene(&mut rng, camera, gt, 300, 0.0, 0.0, false);
    let bearings: Vec<Vector3<f64>> = scene
        .pixels
        .iter()
        .map(|p| camera.unproject(*p).unwrap())
        .collect();
    let points: Vec<Vector3<f64>> = scene.points_world.iter().map(|p| p.coords).collect();
    let mut out = Vec::with_capacity(4);
    let mut k = 0;
    c.bench_function("p3p", |b| {
        b.iter(|| {
            k = (k + 3) % 297;
            out.clear();
            p3p(
                black_box(&[bearings[k], bearings[k + 1], bearings[k + 2]]),
                black_box(&[points[k], points[k + 1], points[k + 2]]),
                &mut out,
            );
            out.len()
        })
    });
    let normalized: Vec<Vector2<f64>> = bearings
        .iter()
        .map(|b| Vector2::new(b.x / b.z, b.y / b.z))
        .collect();
    c.bench_function("epnp_100", |b| {
        b.iter(|| epnp(black_box(&normalized[..100]), black_box(&points[..100])))
    });
    let noisy = make_scene(&mut rng, camera, gt, 300, 0.0, 1.0, false);
    c.bench_function("refine_300", |b| {
        b.iter(|| {
            refine_pose(
                &camera,
                &noisy.pixels,
                &noisy.points_world,
                black_box(&gt),
                &RefineOptions::default(),
            )
        })
    });
}

fn bench_ransac(c: &mut Criterion) {
    for sprt in [true, false] {
        let options = PnpOptions {
            ransac: RansacOptions {
                max_error_px: 2.0,
                sprt,
                ..RansacOptions::default()
            },
            ..PnpOptions::default()
        };
        let solver = LoRansacPnp::new(options);
        for (n, ratio) in [(200usize, 0.5f64), (1000, 0.8)] {
            let mut rng = ChaCha8Rng::seed_from_u64(n as u64);
            let camera = random_camera(&mut rng, false);
            let gt = random_pose(&mut rng);
            let scene = make_scene(&mut rng, camera, gt, n, ratio, 1.0, false);
            let input = PnpInput::new(&scene.camera, &scene.pixels, &scene.points_world);
            let name = format!(
                "lo_ransac_{n}_matches_{:.0}pct_outliers{}",
                ratio * 100.0,
                if sprt { "" } else { "_no_sprt" }
            );
            let mut seed = 0;
            c.bench_function(&name, |b| {
                b.iter(|| {
                    seed += 1;
                    let mut rng = ChaCha8Rng::seed_from_u64(seed);
                    solver
                        .solve(black_box(&input), &mut rng)
                        .map(|r| r.stats.num_inliers)
                })
            });
        }
    }
}

criterion_group!(benches, bench_minimal, bench_ransac);
criterion_main!(benches);
