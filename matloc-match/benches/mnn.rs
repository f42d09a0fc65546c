//! Tiled MNN tables vs the materialised faer GEMM baseline, 4800 × 4800 (an 80 × 60 query
//! against 80 × 60 rendered features) at the feature widths of the paper's Table 3.

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use matloc_match::kernel::{nn_tables_faer, nn_tables_tiled};
use matloc_match::{MnnConfig, mnn_prepared};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;

fn unit_rows(rng: &mut ChaCha8Rng, n: usize, d: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..n * d).map(|_| rng.random_range(-1.0f32..1.0)).collect();
    for row in v.chunks_exact_mut(d) {
        let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
        row.iter_mut().for_each(|x| *x /= norm);
    }
    v
}

fn bench(c: &mut Criterion) {
    let n = 4800;
    let mut g = c.benchmark_group("mnn_4800x4800");
    g.sample_size(10);
    for d in [5usize, 10, 15, 32, 47] {
        let mut rng = ChaCha8Rng::seed_from_u64(d as u64);
        let a = unit_rows(&mut rng, n, d);
        let b = unit_rows(&mut rng, n, d);
        g.bench_with_input(BenchmarkId::new("tiled", d), &d, |bch, &d| {
            bch.iter(|| black_box(nn_tables_tiled(&a, n, &b, n, d, false)))
        });
        g.bench_with_input(BenchmarkId::new("tiled_second", d), &d, |bch, &d| {
            bch.iter(|| black_box(nn_tables_tiled(&a, n, &b, n, d, true)))
        });
        g.bench_with_input(BenchmarkId::new("tiled_mnn_ratio", d), &d, |bch, &d| {
            let cfg = MnnConfig {
                ratio: Some(0.9),
                ..Default::default()
            };
            bch.iter(|| black_box(mnn_prepared(&a, &b, d, &cfg)))
        });
        g.bench_with_input(BenchmarkId::new("faer_materialised", d), &d, |bch, &d| {
            bch.iter(|| black_box(nn_tables_faer(&a, n, &b, n, d)))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
