//! Tiled MNN tables vs the materialised faer GEMM baseline, 4800 × 4800 (an 80 × 60 query
//! against 80 × 60 rendered features) at the feature widths of the paper's Table 3; and the
//! whole matcher, global vs windowed.

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use matloc_core::FeatureMap;
use matloc_match::kernel::{nn_tables_faer, nn_tables_tiled};
use matloc_match::{
    Matcher, MnnConfig, MnnMatcher, QueryFeatures, QueryGrid, RenderedPoints, mnn_prepared,
};
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

/// The whole matcher on an 80 × 60 query against an 80 × 60 render at 47 and 5 dims (all
/// dims, and the paper's N_s = 5): global MNN vs the image-space window the localizer uses
/// (0.2 × 320 px = 64 px).
fn bench_window(c: &mut Criterion) {
    let (cols, rows) = (80usize, 60usize);
    for d in [47usize, 5] {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let q = unit_rows(&mut rng, cols * rows, d);
        let m = unit_rows(&mut rng, cols * rows, d);
        let query = QueryFeatures::new(FeatureMap::from_vec(cols, rows, d, q).unwrap(), 4.0);
        let points: Vec<[f64; 3]> = (0..cols * rows).map(|i| [i as f64, 0.0, 1.0]).collect();
        let map = RenderedPoints::all_valid(d, m, points)
            .unwrap()
            .with_grid(cols, rows)
            .unwrap()
            .with_pixel_grid(QueryGrid::with_stride(4.0))
            .unwrap();
        let mut g = c.benchmark_group(format!("mnn_matcher_80x60_d{d}"));
        g.sample_size(10);
        for (name, window_px) in [
            ("global", None),
            ("window_16px", Some(16.0)),
            ("window_32px", Some(32.0)),
            ("window_64px", Some(64.0)),
        ] {
            let matcher = MnnMatcher::new(MnnConfig {
                window_px,
                ..Default::default()
            });
            g.bench_function(name, |bch| {
                bch.iter(|| black_box(matcher.match_features(&query, &map, None).unwrap()))
            });
        }
        g.finish();
    }
}

criterion_group!(benches, bench, bench_window);
criterion_main!(benches);
