//! Runs one field phase a fixed number of times, for `perf stat -e cycles:u` on a shared
//! machine (user cycles are robust to time slicing where wall-clock benches are not).
//!
//! Usage: `fieldprof <phase> <iterations>`, phase ∈ hash_fwd, hash_bwd, geo_fwd, geo_bwd,
//! col_fwd, col_bwd, train_fwd, train_bwd, infer47, adam. Batch: 4096 rays × 48 samples.

use matloc_nerf_field::{Adam, FeatureField, FieldConfig, NerfactoField, contract_to_unit};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let phase = args.get(1).map_or("train_fwd", String::as_str).to_string();
    let iters: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(3);
    let n = 4096 * 48;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut pts = Vec::with_capacity(n);
    let mut dirs = Vec::with_capacity(n);
    for _ in 0..4096 {
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
        }
    }
    let app: Vec<u32> = (0..n).map(|i| (i / 48 % 100) as u32).collect();
    let f = NerfactoField::new(FieldConfig {
        num_images: 100,
        ..FieldConfig::default()
    })
    .expect("field");
    let unit: Vec<[f32; 3]> = pts
        .iter()
        .map(|p| contract_to_unit(&f.config().scene_box, *p))
        .collect();
    let mut enc = vec![0f32; n * 32];
    f.grid.encode(&unit, &mut enc);
    let cache = f.forward_train(&pts, &dirs, &app).expect("fwd");
    let mut grads = f.zero_grads();
    let dd = vec![1e-3f32; n];
    let dr = vec![1e-3f32; 3 * n];
    let c0 = cpu_ticks();
    let t0 = std::time::Instant::now();
    for _ in 0..iters {
        match phase.as_str() {
            "hash_fwd" => f.grid.encode(&unit, &mut enc),
            "hash_bwd" => f.grid.backward(&unit, &enc, &mut grads.table),
            "geo_fwd" => {
                let mut h = vec![0f32; n * 64];
                let mut o = vec![0f32; n * 16];
                f.geo[0].forward::<64>(&enc, &mut h, true);
                f.geo[1].forward::<16>(&h, &mut o, false);
            }
            "geo_bwd" => {
                let h = vec![0.5f32; n * 64];
                let dy = vec![1e-3f32; n * 16];
                let mut dh = vec![0f32; n * 64];
                let mut dx = vec![0f32; n * 32];
                f.geo[1].backward(&h, &dy, Some(&mut dh), &mut grads.geo[1]);
                f.geo[0].backward(&enc, &dh, Some(&mut dx), &mut grads.geo[0]);
            }
            "train_fwd" => {
                std::hint::black_box(f.forward_train(&pts, &dirs, &app).expect("fwd"));
            }
            "train_bwd" => f.backward(&cache, &dd, &dr, &mut grads).expect("bwd"),
            "infer47" => {
                let all: Vec<usize> = (0..47).collect();
                let mut d = vec![0f32; n];
                let mut fe = vec![0f32; n * 47];
                f.density_and_features(&pts, &all, &mut d, &mut fe)
                    .expect("infer");
            }
            "adam" => {
                let mut fm = f.clone();
                let mut adam = Adam::new(Default::default(), &fm.param_sizes());
                let mut p = fm.param_slices_mut();
                let mut g = grads.slices_mut();
                adam.step(1e-3, &mut p, &mut g);
            }
            other => panic!("unknown phase {other}"),
        }
    }
    let cpu_ms = (cpu_ticks() - c0) as f64 * 10.0 / iters as f64;
    eprintln!(
        "{phase}: {:.1} ms/iter wall, {cpu_ms:.1} ms/iter CPU ({n} points, {:.0} k points per CPU-s)",
        t0.elapsed().as_secs_f64() * 1e3 / iters as f64,
        n as f64 / cpu_ms
    );
}

/// User + system CPU time of the process in clock ticks (1/100 s on Linux).
fn cpu_ticks() -> u64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = s.rsplit_once(')').map_or("", |x| x.1);
    let f: Vec<&str> = after.split_whitespace().collect();
    // Fields after the command name: state is index 0, utime 11, stime 12.
    let p = |i: usize| f.get(i).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
    p(11) + p(12)
}
