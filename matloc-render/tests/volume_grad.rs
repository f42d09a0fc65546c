//! Finite-difference checks of the volume-rendering backward, and sampler properties.

use matloc_render::{
    MarchConfig, RayBatch, RaySamples, RenderGradients, SampleValues, Spacing, importance_resample,
    march_ray, volume_render, volume_render_backward,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

struct Case {
    samples: RaySamples,
    sigma: Vec<f32>,
    rgb: Vec<f32>,
    feat: Vec<f32>,
    nd: usize,
    bg: [f32; 3],
    g_rgb: Vec<f32>,
    g_depth: Vec<f32>,
    g_acc: Vec<f32>,
    g_feat: Vec<f32>,
}

fn case() -> Case {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let counts = [5usize, 1, 0, 12, 7];
    let per_ray: Vec<Vec<(f32, f32)>> = counts
        .iter()
        .map(|&c| {
            let mut t = rng.random_range(0.1..1.0);
            (0..c)
                .map(|_| {
                    let d = rng.random_range(0.05..0.5);
                    let iv = (t, t + d);
                    t += d + rng.random_range(0.0..0.2);
                    iv
                })
                .collect()
        })
        .collect();
    let samples = RaySamples::from_per_ray(per_ray);
    let ns = samples.len();
    let nr = samples.num_rays();
    let nd = 4;
    let mut r = |n: usize, lo: f32, hi: f32| -> Vec<f32> {
        (0..n).map(|_| rng.random_range(lo..hi)).collect()
    };
    Case {
        sigma: r(ns, 0.0, 4.0),
        rgb: r(3 * ns, 0.0, 1.0),
        feat: r(nd * ns, -1.0, 1.0),
        nd,
        bg: [0.3, 0.6, 0.9],
        g_rgb: r(3 * nr, -1.0, 1.0),
        g_depth: r(nr, -1.0, 1.0),
        g_acc: r(nr, -1.0, 1.0),
        g_feat: r(nd * nr, -1.0, 1.0),
        samples,
    }
}

fn loss(c: &Case, sigma: &[f32], rgb: &[f32], feat: &[f32], bg: [f32; 3]) -> f64 {
    let v = SampleValues {
        sigma,
        rgb,
        features: feat,
        num_dims: c.nd,
    };
    let o = volume_render(&c.samples, &v, bg).unwrap();
    let dot =
        |a: &[f32], b: &[f32]| -> f64 { a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum() };
    dot(&o.rgb, &c.g_rgb)
        + dot(&o.depth, &c.g_depth)
        + dot(&o.accumulation, &c.g_acc)
        + dot(&o.features, &c.g_feat)
}

fn assert_close(what: &str, a: f32, fd: f64) {
    let a = a as f64;
    assert!(
        (a - fd).abs() <= 1e-2 * a.abs().max(fd.abs()) + 1e-3,
        "{what}: analytic {a} vs fd {fd}"
    );
}

#[test]
fn volume_render_backward_matches_finite_differences() {
    let c = case();
    let v = SampleValues {
        sigma: &c.sigma,
        rgb: &c.rgb,
        features: &c.feat,
        num_dims: c.nd,
    };
    let g = volume_render_backward(
        &c.samples,
        &v,
        c.bg,
        &RenderGradients {
            rgb: &c.g_rgb,
            depth: &c.g_depth,
            accumulation: &c.g_acc,
            features: &c.g_feat,
        },
    )
    .unwrap();
    let eps = 1e-3f32;
    for k in 0..c.sigma.len() {
        let mut p = c.sigma.clone();
        p[k] += eps;
        let mut m = c.sigma.clone();
        m[k] -= eps;
        let fd = (loss(&c, &p, &c.rgb, &c.feat, c.bg) - loss(&c, &m, &c.rgb, &c.feat, c.bg))
            / (2.0 * eps as f64);
        assert_close(&format!("sigma[{k}]"), g.sigma[k], fd);
    }
    for k in 0..c.rgb.len() {
        let mut p = c.rgb.clone();
        p[k] += eps;
        let mut m = c.rgb.clone();
        m[k] -= eps;
        let fd = (loss(&c, &c.sigma, &p, &c.feat, c.bg) - loss(&c, &c.sigma, &m, &c.feat, c.bg))
            / (2.0 * eps as f64);
        assert_close(&format!("rgb[{k}]"), g.rgb[k], fd);
    }
    for k in 0..c.feat.len() {
        let mut p = c.feat.clone();
        p[k] += eps;
        let mut m = c.feat.clone();
        m[k] -= eps;
        let fd = (loss(&c, &c.sigma, &c.rgb, &p, c.bg) - loss(&c, &c.sigma, &c.rgb, &m, c.bg))
            / (2.0 * eps as f64);
        assert_close(&format!("feat[{k}]"), g.features[k], fd);
    }
    for ch in 0..3 {
        let mut p = c.bg;
        p[ch] += eps;
        let mut m = c.bg;
        m[ch] -= eps;
        let fd = (loss(&c, &c.sigma, &c.rgb, &c.feat, p) - loss(&c, &c.sigma, &c.rgb, &c.feat, m))
            / (2.0 * eps as f64);
        assert_close(&format!("bg[{ch}]"), g.background[ch], fd);
    }
}

#[test]
fn weights_sum_to_accumulation_and_empty_rays_show_background() {
    let c = case();
    let v = SampleValues {
        sigma: &c.sigma,
        rgb: &c.rgb,
        features: &[],
        num_dims: 0,
    };
    let o = volume_render(&c.samples, &v, c.bg).unwrap();
    let (w, t_end) = matloc_render::compute_weights(&c.samples, &c.sigma);
    for r in 0..c.samples.num_rays() {
        let s: f32 = w[c.samples.range(r)].iter().sum();
        assert!((s - o.accumulation[r]).abs() < 1e-5);
        assert!((1.0 - t_end[r] - s).abs() < 1e-5);
    }
    // Ray 2 has no samples: it is the background.
    assert_eq!(&o.rgb[6..9], &c.bg);
    assert_eq!(o.accumulation[2], 0.0);
}

#[test]
fn spacing_is_monotone_and_invertible() {
    let s = Spacing {
        linear_range_m: 10.0,
    };
    let mut prev = -1.0;
    for i in 0..1000 {
        let t = i as f32 * 0.37;
        let u = s.to_s(t);
        assert!(u > prev && u < 1.0);
        prev = u;
        assert!((s.to_t(u) - t).abs() <= 1e-3 * (1.0 + t));
    }
}

#[test]
fn march_covers_near_far_without_gaps() {
    let rays = RayBatch::new(vec![[0.0; 3]], vec![[0.0, 0.0, 1.0]], 0.5, 200.0).unwrap();
    let cfg = MarchConfig {
        spacing: Spacing {
            linear_range_m: 20.0,
        },
        steps: 64,
        max_samples: 1000,
    };
    for jitter in [0.0f32, 0.3, 0.999] {
        let iv = march_ray(&rays, 0, None, &cfg, jitter);
        assert!((iv[0].0 - 0.5).abs() < 1e-4);
        assert!((iv[iv.len() - 1].1 - 200.0).abs() < 1e-2 * 200.0);
        for p in iv.windows(2) {
            assert!((p[0].1 - p[1].0).abs() < 1e-4 * p[0].1.max(1.0));
        }
    }
    // The budget merges intervals but still covers the range.
    let capped = MarchConfig {
        max_samples: 10,
        ..cfg
    };
    let iv = march_ray(&rays, 0, None, &capped, 0.0);
    assert!(iv.len() <= 10);
    assert!((iv[0].0 - 0.5).abs() < 1e-4);
}

#[test]
fn importance_samples_concentrate_where_weight_is() {
    let per_ray = vec![(0..20).map(|i| (i as f32, i as f32 + 1.0)).collect()];
    let coarse = RaySamples::from_per_ray(per_ray);
    let mut w = vec![0f32; 20];
    w[12] = 1.0;
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let fine = importance_resample(&coarse, &w, 32, 0.001, Some(&mut rng));
    assert_eq!(fine.len(), 32);
    let inside = (0..fine.len())
        .filter(|&k| (12.0..=13.0).contains(&fine.t_mid(k)))
        .count();
    assert!(inside >= 25, "{inside}");
    for k in 1..fine.len() {
        assert!(fine.t_start[k] >= fine.t_start[k - 1]);
    }
}

#[test]
fn distortion_gradient_matches_finite_differences() {
    let c = case();
    let ns = c.samples.len();
    // Normalised coordinates: any increasing map of t works for the check.
    let s0: Vec<f32> = c.samples.t_start.iter().map(|t| t / 5.0).collect();
    let s1: Vec<f32> = c.samples.t_end.iter().map(|t| t / 5.0).collect();
    let w_r: Vec<f32> = (0..c.samples.num_rays()).map(|r| 1.0 + r as f32).collect();
    let total = |sigma: &[f32]| -> f64 {
        let (l, _) = matloc_render::distortion_loss(&c.samples, sigma, &s0, &s1).unwrap();
        l.iter().zip(&w_r).map(|(a, b)| *a as f64 * *b as f64).sum()
    };
    let (_, d) = matloc_render::distortion_loss(&c.samples, &c.sigma, &s0, &s1).unwrap();
    for r in 0..c.samples.num_rays() {
        for k in c.samples.range(r) {
            let eps = 1e-3f32;
            let mut p = c.sigma.clone();
            p[k] += eps;
            let mut m = c.sigma.clone();
            m[k] -= eps;
            let fd = (total(&p) - total(&m)) / (2.0 * eps as f64);
            assert_close(&format!("dist sigma[{k}]"), d[k] * w_r[r], fd);
        }
    }
    assert_eq!(d.len(), ns);
}
