//! Field throughput: hash grid, MLPs and the full forward+backward at 4096 rays × 48 samples.
//!
//! The machine is shared and has 2 cores: numbers are noisy; compare runs made back to back.

use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use matloc_nerf_field::{FeatureField, FieldConfig, NerfactoField, SceneBox};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

const N: usize = 4096 * 48;

fn inputs() -> (Vec<[f32; 3]>, Vec<[f32; 3]>, Vec<u32>) {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    // Points along rays (48 consecutive samples per ray) as the trainer produces them.
    let mut pts = Vec::with_capacity(N);
    let mut dirs = Vec::with_capacity(N);
    let mut app = Vec::with_capacity(N);
    for r in 0..4096 {
        let o: [f32; 3] = [
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            1.5,
        ];
        let d = [
            rng.random_range(-0.3f32..0.3),
            rng.random_range(-0.3f32..0.3),
            -1.0,
        ];
        let l = (d[0] * d[0] + d[1] * d[1] + 1.0f32).sqrt();
        let d = [d[0] / l, d[1] / l, d[2] / l];
        for k in 0..48 {
            let t = 0.5 + 2.5 * k as f32 / 48.0;
            pts.push([o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]);
            dirs.push(d);
            app.push((r % 100) as u32);
        }
    }
    (pts, dirs, app)
}

fn field() -> NerfactoField {
    NerfactoField::new(FieldConfig {
        scene_box: SceneBox {
            min: [-1.0; 3],
            max: [1.0; 3],
        },
        num_images: 100,
        ..FieldConfig::default()
    })
    .expect("field")
}

fn bench(c: &mut Criterion) {
    let f = field();
    let (pts, dirs, app) = inputs();
    let mut g = c.benchmark_group("field");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(8))
        .warm_up_time(Duration::from_secs(1))
        .throughput(Throughput::Elements(N as u64));

    let unit: Vec<[f32; 3]> = pts
        .iter()
        .map(|p| matloc_nerf_field::contract_to_unit(&f.config().scene_box, *p))
        .collect();
    let mut enc = vec![0f32; N * 32];
    g.bench_function("hash_encode_fwd", |b| {
        b.iter(|| f.grid.encode(black_box(&unit), &mut enc))
    });
    let d_enc: Vec<f32> = (0..N * 32).map(|i| ((i % 7) as f32 - 3.0) * 1e-3).collect();
    let mut grad = vec![0f32; f.grid.table.len()];
    g.bench_function("hash_encode_bwd", |b| {
        b.iter(|| f.grid.backward(black_box(&unit), &d_enc, &mut grad))
    });

    // MLPs run on chunks of 128 points (as inside the field), chunks in parallel.
    const K: usize = 128;
    let mut h = vec![0f32; N * 64];
    let mut out = vec![0f32; N * 16];
    g.bench_function("geo_mlp_fwd", |b| {
        b.iter(|| {
            enc.par_chunks(K * 32)
                .zip(h.par_chunks_mut(K * 64))
                .zip(out.par_chunks_mut(K * 16))
                .for_each(|((e, h), o)| {
                    f.geo[0].forward::<64>(black_box(e), h, true);
                    f.geo[1].forward::<16>(h, o, false);
                })
        })
    });
    let dy: Vec<f32> = (0..N * 16).map(|i| ((i % 5) as f32 - 2.0) * 1e-3).collect();
    let wt = [f.geo[0].transposed(), f.geo[1].transposed()];
    g.bench_function("geo_mlp_bwd", |b| {
        b.iter(|| {
            h.par_chunks(K * 64)
                .zip(dy.par_chunks(K * 16))
                .zip(enc.par_chunks(K * 32))
                .fold(
                    || {
                        (
                            f.geo[0].zero_grad(),
                            f.geo[1].zero_grad(),
                            vec![0f32; K * 64],
                            vec![0f32; K * 32],
                        )
                    },
                    |(mut g0, mut g1, mut dh, mut dx), ((h, dy), e)| {
                        let m = dy.len() / 16;
                        f.geo[1].backward_with(
                            h,
                            black_box(dy),
                            Some(&mut dh[..m * 64]),
                            &wt[1],
                            &mut g1,
                        );
                        f.geo[0].backward_with(
                            e,
                            &dh[..m * 64],
                            Some(&mut dx[..m * 32]),
                            &wt[0],
                            &mut g0,
                        );
                        (g0, g1, dh, dx)
                    },
                )
                .count()
        })
    });

    let mut dens = vec![0f32; N];
    let mut feats = vec![0f32; N * 47];
    let all: Vec<usize> = (0..47).collect();
    g.bench_function("density_features47_infer", |b| {
        b.iter(|| {
            f.density_and_features(black_box(&pts), &all, &mut dens, &mut feats)
                .expect("infer")
        })
    });

    let mut grads = f.zero_grads();
    let d_density = vec![1e-3f32; N];
    let d_rgb = vec![1e-3f32; N * 3];
    g.bench_function("train_fwd", |b| {
        b.iter(|| f.forward_train(black_box(&pts), &dirs, &app).expect("fwd"))
    });
    let cache = f.forward_train(&pts, &dirs, &app).expect("fwd");
    g.bench_function("train_bwd", |b| {
        b.iter(|| {
            f.backward(black_box(&cache), &d_density, &d_rgb, &mut grads)
                .expect("bwd")
        })
    });
    g.bench_function("train_fwd_bwd", |b| {
        b.iter(|| {
            let c = f.forward_train(black_box(&pts), &dirs, &app).expect("fwd");
            f.backward(&c, &d_density, &d_rgb, &mut grads).expect("bwd");
        })
    });
    let mut fm = f.clone();
    let mut adam = matloc_nerf_field::Adam::new(Default::default(), &fm.param_sizes());
    g.throughput(Throughput::Elements(fm.num_params() as u64));
    g.bench_function("adam_step_params", |b| {
        b.iter(|| {
            let mut p = fm.param_slices_mut();
            let mut gs = grads.slices_mut();
            adam.step(1e-3, &mut p, &mut gs);
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
