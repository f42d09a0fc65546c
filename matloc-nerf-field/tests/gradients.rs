//! Finite-difference checks of every hand-written backward pass.

use matloc_nerf_field::{
    FieldConfig, FieldGrads, HashGrid, N_LEVELS, NerfactoField, SceneBox, trunc_exp, trunc_exp_grad,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn small_config() -> FieldConfig {
    FieldConfig {
        log2_table_size: 10,
        base_resolution: 4,
        max_resolution: 64,
        scene_box: SceneBox {
            min: [-2.0, -2.0, -1.0],
            max: [2.0, 2.0, 1.0],
        },
        num_images: 3,
        appearance_dim: 4,
        seed: 7,
        ..FieldConfig::default()
    }
}

/// A field with a table large enough that the MLPs are far from linear.
fn test_field() -> NerfactoField {
    let mut f = NerfactoField::new(small_config()).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for v in &mut f.grid.table {
        *v = rng.random_range(-0.5..0.5);
    }
    for l in f.geo.iter_mut().chain(f.col.iter_mut()) {
        for b in &mut l.b {
            *b = rng.random_range(-0.1..0.1);
        }
    }
    f
}

struct Batch {
    points: Vec<[f32; 3]>,
    dirs: Vec<[f32; 3]>,
    app: Vec<u32>,
    w_density: Vec<f32>,
    w_rgb: Vec<f32>,
}

fn batch(n: usize, seed: u64) -> Batch {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let points = (0..n)
        .map(|_| {
            [
                rng.random_range(-3.0..3.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(-1.5..1.5),
            ]
        })
        .collect();
    let dirs = (0..n)
        .map(|_| {
            let d: [f32; 3] = [
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
            [d[0] / l, d[1] / l, d[2] / l]
        })
        .collect();
    Batch {
        points,
        dirs,
        app: (0..n).map(|i| (i % 3) as u32).collect(),
        w_density: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
        w_rgb: (0..3 * n).map(|_| rng.random_range(-1.0..1.0)).collect(),
    }
}

/// Loss = Σ a·log(density) + Σ b·rgb, evaluated in f64 for the finite differences.
/// log(density) = raw pre-activation, which keeps the loss well scaled.
fn loss(f: &NerfactoField, b: &Batch) -> f64 {
    let c = f.forward_train(&b.points, &b.dirs, &b.app).unwrap();
    let mut l = 0f64;
    for (d, w) in c.density().iter().zip(&b.w_density) {
        l += (*w as f64) * (*d as f64);
    }
    for (r, w) in c.rgb().iter().zip(&b.w_rgb) {
        l += (*w as f64) * (*r as f64);
    }
    l
}

fn analytic(f: &NerfactoField, b: &Batch) -> FieldGrads {
    let c = f.forward_train(&b.points, &b.dirs, &b.app).unwrap();
    let mut g = f.zero_grads();
    f.backward(&c, &b.w_density, &b.w_rgb, &mut g).unwrap();
    g
}

/// Checks `count` parameters of group `group` (largest-gradient ones plus random ones).
fn check_group(f: &NerfactoField, b: &Batch, g: &mut FieldGrads, group: usize, count: usize) {
    let grads: Vec<f32> = g.slices_mut()[group].to_vec();
    let mut idx: Vec<usize> = (0..grads.len()).collect();
    idx.sort_by(|&i, &j| grads[j].abs().total_cmp(&grads[i].abs()));
    let mut chosen: Vec<usize> = idx.iter().take(count / 2).copied().collect();
    let mut rng = ChaCha8Rng::seed_from_u64(group as u64);
    for _ in 0..count / 2 {
        chosen.push(rng.random_range(0..grads.len()));
    }
    let mut failures = Vec::new();
    for &i in &chosen {
        let eps = 1e-3f32;
        let mut fp = f.clone();
        fp.param_slices_mut()[group][i] += eps;
        let mut fm = f.clone();
        fm.param_slices_mut()[group][i] -= eps;
        let fd = (loss(&fp, b) - loss(&fm, b)) / (2.0 * eps as f64);
        let a = grads[i] as f64;
        if (a - fd).abs() > 2e-2 * a.abs().max(fd.abs()) + 2e-3 {
            failures.push((i, a, fd));
        }
    }
    // A ReLU kink crossed by ±eps can spoil a single difference; more than one is a bug.
    assert!(
        failures.len() <= 1,
        "group {group}: {} of {} mismatches: {failures:?}",
        failures.len(),
        chosen.len()
    );
}

#[test]
fn full_field_gradients_match_finite_differences() {
    // Few points: a parameter feeding every point moves many ReLU pre-activations, and each
    // kink crossed within ±eps perturbs the central difference.
    let f = test_field();
    let b = batch(8, 3);
    let mut g = analytic(&f, &b);
    let groups = f.param_sizes().len();
    assert_eq!(groups, 12);
    for group in 0..groups {
        check_group(&f, &b, &mut g, group, 16);
    }
}

#[test]
fn colour_only_loss_gradients_match() {
    // Only the colour head (incl. sigmoid) and what feeds it: density weights zero.
    let f = test_field();
    let mut b = batch(24, 5);
    b.w_density.iter_mut().for_each(|w| *w = 0.0);
    let mut g = analytic(&f, &b);
    for group in [5, 6, 7, 8, 9, 10, 11] {
        check_group(&f, &b, &mut g, group, 12);
    }
    // The appearance gradient only touches embeddings of images in the batch.
    assert!(g.appearance.iter().any(|v| *v != 0.0));
}

#[test]
fn density_only_loss_gradients_match() {
    // Geometry MLP + trunc_exp + hash grid only; the colour head must get zero gradient.
    let f = test_field();
    let mut b = batch(24, 9);
    b.w_rgb.iter_mut().for_each(|w| *w = 0.0);
    let mut g = analytic(&f, &b);
    for group in 0..5 {
        check_group(&f, &b, &mut g, group, 12);
    }
    assert!(g.col.iter().all(|l| l.w.iter().all(|v| *v == 0.0)));
}

#[test]
fn trunc_exp_gradient() {
    for &x in &[-5.0f32, -1.0, 0.0, 0.5, 3.0, 10.0] {
        let eps = 1e-3 * (1.0 + x.abs());
        let fd = (trunc_exp(x + eps) as f64 - trunc_exp(x - eps) as f64) / (2.0 * eps as f64);
        let a = trunc_exp_grad(x) as f64;
        assert!((a - fd).abs() <= 1e-3 * a.abs(), "x={x}: {a} vs {fd}");
    }
    // Beyond the clamp the gradient saturates while the value keeps growing.
    assert_eq!(trunc_exp_grad(20.0), trunc_exp_grad(15.0));
    assert!(trunc_exp(20.0) > trunc_exp(15.0));
    assert!(trunc_exp(1000.0).is_finite());
}

#[test]
fn hash_grid_table_gradient_and_interpolation() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut grid = HashGrid::new(10, 4, 64, &mut rng);
    for v in &mut grid.table {
        *v = rng.random_range(-1.0..1.0);
    }
    let pts: Vec<[f32; 3]> = (0..50)
        .map(|_| [rng.random(), rng.random(), rng.random()])
        .collect();
    let w: Vec<f32> = (0..50 * 32).map(|_| rng.random_range(-1.0..1.0)).collect();
    let enc_loss = |g: &HashGrid| -> f64 {
        let mut out = vec![0f32; pts.len() * 32];
        g.encode(&pts, &mut out);
        out.iter().zip(&w).map(|(a, b)| *a as f64 * *b as f64).sum()
    };
    let mut grad = vec![0f32; grid.table.len()];
    grid.backward(&pts, &w, &mut grad);
    // The encoding is linear in the table: differences are exact up to rounding.
    let touched: Vec<usize> = (0..grad.len()).filter(|&i| grad[i] != 0.0).collect();
    assert!(touched.len() > 100);
    for &i in touched.iter().step_by(touched.len() / 40) {
        let mut gp = grid.clone();
        gp.table[i] += 0.5;
        let mut gm = grid.clone();
        gm.table[i] -= 0.5;
        let fd = (enc_loss(&gp) - enc_loss(&gm)) / 1.0;
        assert!(
            (fd - grad[i] as f64).abs() < 1e-3 * (1.0 + fd.abs()),
            "entry {i}: {} vs {fd}",
            grad[i]
        );
    }
    // Untouched entries have exactly zero gradient.
    let mut gp = grid.clone();
    let zero = (0..grad.len()).find(|&i| grad[i] == 0.0).unwrap();
    gp.table[zero] += 1.0;
    assert!((enc_loss(&gp) - enc_loss(&grid)).abs() < 1e-9);
}

#[test]
fn hash_grid_input_gradient() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let mut grid = HashGrid::new(10, 4, 32, &mut rng);
    for v in &mut grid.table {
        *v = rng.random_range(-1.0..1.0);
    }
    let pts: Vec<[f32; 3]> = (0..20)
        .map(|_| {
            [
                rng.random_range(0.1..0.9),
                rng.random_range(0.1..0.9),
                rng.random_range(0.1..0.9),
            ]
        })
        .collect();
    let w: Vec<f32> = (0..20 * 32).map(|_| rng.random_range(-1.0..1.0)).collect();
    let g = grid.input_gradient(&pts, &w);
    let mut bad = 0;
    for (i, p) in pts.iter().enumerate() {
        for a in 0..3 {
            let eps = 1e-4f32;
            let f = |q: [f32; 3]| -> f64 {
                let mut o = vec![0f32; 32];
                grid.encode(&[q], &mut o);
                o.iter()
                    .zip(&w[i * 32..(i + 1) * 32])
                    .map(|(x, y)| *x as f64 * *y as f64)
                    .sum()
            };
            let mut pp = *p;
            pp[a] += eps;
            let mut pm = *p;
            pm[a] -= eps;
            let fd = (f(pp) - f(pm)) / (2.0 * eps as f64);
            // Piecewise-linear in p: a cell boundary inside ±eps breaks one difference.
            if (fd - g[i][a] as f64).abs() > 2e-2 * (1.0 + fd.abs()) {
                bad += 1;
            }
        }
    }
    assert!(bad <= 2, "{bad} input-gradient mismatches");
}

#[test]
fn density_input_gradient_matches() {
    let f = test_field();
    let b = batch(10, 21);
    let ones = vec![1.0f32; 10];
    let g = f.density_input_gradient(&b.points, &ones).unwrap();
    let dens = |p: [f32; 3]| -> f64 {
        let c = f.forward_train(&[p], &[[0.0, 0.0, 1.0]], &[]).unwrap();
        c.density()[0] as f64
    };
    let mut bad = 0;
    for (i, p) in b.points.iter().enumerate() {
        for a in 0..3 {
            let eps = 2e-4f32;
            let mut pp = *p;
            pp[a] += eps;
            let mut pm = *p;
            pm[a] -= eps;
            let fd = (dens(pp) - dens(pm)) / (2.0 * eps as f64);
            if (fd - g[i][a] as f64).abs() > 5e-2 * fd.abs().max(g[i][a].abs() as f64) + 1e-2 {
                bad += 1;
            }
        }
    }
    assert!(bad <= 3, "{bad} of 30 input-gradient mismatches");
}

#[test]
fn dense_and_hashed_levels_index_correctly() {
    let levels = HashGrid::layout(19, 16, 2048);
    assert_eq!(levels.len(), N_LEVELS);
    assert_eq!(levels[0].resolution, 16);
    assert_eq!(levels[N_LEVELS - 1].resolution, 2048);
    for l in &levels {
        let verts = (l.resolution as usize + 1).pow(3);
        assert_eq!(l.dense, verts <= 1 << 19);
        assert_eq!(l.size, if l.dense { verts } else { 1 << 19 });
    }
    assert!(levels[0].dense && !levels[N_LEVELS - 1].dense);
    // Dense level: every vertex gets its own entry.
    let lv = levels[0];
    let r = lv.resolution + 1;
    let mut seen = vec![false; lv.size];
    for z in 0..lv.resolution {
        for y in 0..lv.resolution {
            for x in 0..lv.resolution {
                let p = [
                    (x as f32 + 0.5) / lv.resolution as f32,
                    (y as f32 + 0.5) / lv.resolution as f32,
                    (z as f32 + 0.5) / lv.resolution as f32,
                ];
                let (idx, w) = HashGrid::corners(&lv, p);
                assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-5);
                assert_eq!(idx[0], x + r * (y + r * z));
                for i in idx {
                    seen[i as usize] = true;
                }
            }
        }
    }
    assert!(seen.iter().all(|s| *s));
    // Hashed level: index = (x·1 ⊕ y·2654435761 ⊕ z·805459861) mod T.
    let lv = levels[N_LEVELS - 1];
    let p = [0.3f32, 0.6, 0.9];
    let (idx, _) = HashGrid::corners(&lv, p);
    let s = lv.resolution as f32;
    let c = [
        (0.3 * s).floor() as u32,
        (0.6 * s).floor() as u32,
        (0.9 * s).floor() as u32,
    ];
    let expect = (c[0] ^ c[1].wrapping_mul(2_654_435_761) ^ c[2].wrapping_mul(805_459_861))
        & ((1 << 19) - 1);
    assert_eq!(idx[0], expect);
}

#[test]
fn encoding_matches_reference_trilinear() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut grid = HashGrid::new(12, 4, 128, &mut rng);
    for v in &mut grid.table {
        *v = rng.random_range(-1.0..1.0);
    }
    let p = [0.123f32, 0.777, 0.5001];
    let mut out = vec![0f32; 32];
    grid.encode(&[p], &mut out);
    for (l, lv) in grid.levels().iter().enumerate() {
        let s = lv.resolution as f64;
        let mut f = [0f64; 2];
        let base: Vec<f64> = p.iter().map(|&x| (x as f64 * s).floor()).collect();
        for dz in 0..2u32 {
            for dy in 0..2u32 {
                for dx in 0..2u32 {
                    let v = [
                        base[0] as u32 + dx,
                        base[1] as u32 + dy,
                        base[2] as u32 + dz,
                    ];
                    let r = lv.resolution + 1;
                    let e = if lv.dense {
                        v[0] + r * (v[1] + r * v[2])
                    } else {
                        matloc_nerf_field::hash_coords(v) & (lv.size as u32 - 1)
                    } as usize
                        + lv.offset;
                    let mut w = 1.0;
                    for (a, d) in [dx, dy, dz].iter().enumerate() {
                        let fr = p[a] as f64 * s - base[a];
                        w *= if *d == 1 { fr } else { 1.0 - fr };
                    }
                    f[0] += w * grid.table[2 * e] as f64;
                    f[1] += w * grid.table[2 * e + 1] as f64;
                }
            }
        }
        assert!((out[2 * l] as f64 - f[0]).abs() < 1e-4, "level {l}");
        assert!((out[2 * l + 1] as f64 - f[1]).abs() < 1e-4, "level {l}");
    }
}

/// A cache reused across batches of different sizes (grown, then shrunk) gives bit-identical
/// activations and the same gradients as fresh allocations: no stale values leak through.
#[test]
fn reused_cache_matches_fresh_pass() {
    let f = test_field();
    let mut cache = matloc_nerf_field::TrainCache::default();
    for (n, seed) in [(50, 1), (300, 2), (37, 3)] {
        let b = batch(n, seed);
        f.forward_train_into(&b.points, &b.dirs, &b.app, &mut cache)
            .unwrap();
        let fresh = f.forward_train(&b.points, &b.dirs, &b.app).unwrap();
        assert_eq!(cache.density(), fresh.density());
        assert_eq!(cache.rgb(), fresh.rgb());
        let mut g_reuse = f.zero_grads();
        f.backward_reusing(&mut cache, &b.w_density, &b.w_rgb, &mut g_reuse)
            .unwrap();
        let g_fresh = analytic(&f, &b);
        // The table gradient is summed in a fixed order; the MLP gradients are reduced over
        // rayon's (timing-dependent) split, so they agree up to rounding.
        assert_eq!(g_reuse.table, g_fresh.table);
        let mut a = g_reuse;
        let mut b = g_fresh;
        for (x, y) in a.slices_mut().into_iter().zip(b.slices_mut()) {
            for (u, v) in x.iter().zip(y.iter()) {
                assert!((u - v).abs() <= 1e-5 * (1.0 + v.abs()), "{u} vs {v}");
            }
        }
    }
}
