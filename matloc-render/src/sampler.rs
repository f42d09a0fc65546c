use rand::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::occupancy::OccupancyGrid;
use crate::rays::{RayBatch, RaySamples};

/// Spacing of samples along a ray: linear in distance up to `linear_range_m`, then linear in
/// disparity (1/t) out to `far`.
///
/// This is nerfstudio's `UniformLinDispPiecewiseSampler` spacing `g(x) = x/2` for `x < 1`,
/// `1 − 1/(2x)` beyond, with `x = t / linear_range_m`. It matches the scene contraction:
/// distances beyond the foreground box are compressed, so equal steps in `g` are roughly
/// equal steps in contracted space. Set `linear_range_m` to about the camera-to-far-edge
/// distance of the scene box; with `linear_range_m >= far` the spacing is purely linear.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Spacing {
    /// Distance (metres) at which spacing switches from linear to disparity.
    pub linear_range_m: f32,
}

impl Spacing {
    /// `g(t)`.
    #[inline]
    pub fn to_s(&self, t: f32) -> f32 {
        let x = t / self.linear_range_m;
        if x < 1.0 { 0.5 * x } else { 1.0 - 0.5 / x }
    }

    /// `g⁻¹(s)`.
    #[inline]
    pub fn to_t(&self, s: f32) -> f32 {
        let x = if s < 0.5 {
            2.0 * s
        } else {
            0.5 / (1.0 - s).max(1e-7)
        };
        x * self.linear_range_m
    }
}

/// How samples are placed along a ray.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MarchConfig {
    /// Spacing of the step grid.
    pub spacing: Spacing,
    /// Number of steps covering `[near, far]` in spacing space. Without an occupancy grid,
    /// every step is a sample (the uniform sampler).
    pub steps: usize,
    /// Most samples kept per ray (training budget); consecutive occupied steps are merged
    /// into wider intervals when a ray has more.
    pub max_samples: usize,
}

impl Default for MarchConfig {
    fn default() -> Self {
        Self {
            spacing: Spacing {
                linear_range_m: 1e9,
            },
            steps: 256,
            max_samples: 1024,
        }
    }
}

/// Step `i` of `steps` on ray `r` in spacing space with the grid shifted by `jitter ∈ [0,1)`.
#[inline]
fn step_interval(cfg: &MarchConfig, s0: f32, s1: f32, i: usize, jitter: f32) -> (f32, f32) {
    let ds = (s1 - s0) / cfg.steps as f32;
    let a = s0 + ds * (i as f32 + jitter - if jitter > 0.0 { 1.0 } else { 0.0 });
    let b = a + ds;
    (cfg.spacing.to_t(a.max(s0)), cfg.spacing.to_t(b.min(s1)))
}

/// Samples along one ray: the occupied steps (all steps without a grid), capped at
/// `max_samples` by merging runs of consecutive samples.
///
/// `jitter` (per ray, in `[0,1)`) shifts the step grid for stratified training samples; the
/// first and last intervals are clipped to `[near, far]`.
pub fn march_ray(
    rays: &RayBatch,
    r: usize,
    grid: Option<&OccupancyGrid>,
    cfg: &MarchConfig,
    jitter: f32,
) -> Vec<(f32, f32)> {
    let s0 = cfg.spacing.to_s(rays.near[r]);
    let s1 = cfg.spacing.to_s(rays.far[r]);
    let n_steps = cfg.steps + usize::from(jitter > 0.0);
    let mut out = Vec::new();
    for i in 0..n_steps {
        let (a, b) = step_interval(cfg, s0, s1, i, jitter);
        if b <= a {
            continue;
        }
        if let Some(g) = grid
            && !g.is_occupied_world(rays.at(r, 0.5 * (a + b)))
        {
            continue;
        }
        out.push((a, b));
    }
    if out.len() > cfg.max_samples && cfg.max_samples > 0 {
        // Groups of ⌊n/m⌋ or ⌈n/m⌉ consecutive intervals, so exactly `max_samples` remain
        // (fixed-size groups of ⌈n/m⌉ left 25 of 49 jittered steps at a budget of 48).
        let (n, m) = (out.len(), cfg.max_samples);
        out = (0..m)
            .map(|g| (out[g * n / m].0, out[(g + 1) * n / m - 1].1))
            .collect();
    }
    out
}

/// Samples for every ray (parallel). With `rng`, each ray's grid is jittered (training).
pub fn sample_rays<R: Rng>(
    rays: &RayBatch,
    grid: Option<&OccupancyGrid>,
    cfg: &MarchConfig,
    rng: Option<&mut R>,
) -> RaySamples {
    let jit: Vec<f32> = match rng {
        Some(rng) => (0..rays.len())
            .map(|_| rng.random_range(1e-6f32..1.0))
            .collect(),
        None => vec![0.0; rays.len()],
    };
    let per_ray: Vec<Vec<(f32, f32)>> = (0..rays.len())
        .into_par_iter()
        .with_min_len(64)
        .map(|r| march_ray(rays, r, grid, cfg, jit[r]))
        .collect();
    RaySamples::from_per_ray(per_ray)
}

/// One importance (inverse-CDF) resampling stage: `n` new intervals per ray drawn from the
/// piecewise-constant density given by `weights` over the coarse intervals.
///
/// `padding` is added to every weight so empty regions keep a little probability (nerfstudio
/// uses 0.01 for the same reason). With `rng`, the CDF is sampled at stratified random
/// positions, else at the bin centres. New intervals span between consecutive new sample
/// positions, so they tile the region where the weights are.
pub fn importance_resample<R: Rng>(
    coarse: &RaySamples,
    weights: &[f32],
    n: usize,
    padding: f32,
    mut rng: Option<&mut R>,
) -> RaySamples {
    let mut per_ray = Vec::with_capacity(coarse.num_rays());
    for r in 0..coarse.num_rays() {
        let rg = coarse.range(r);
        if rg.is_empty() || n == 0 {
            per_ray.push(Vec::new());
            continue;
        }
        let w: Vec<f32> = weights[rg.clone()]
            .iter()
            .map(|v| v.max(0.0) + padding)
            .collect();
        let total: f32 = w.iter().sum();
        let mut cdf = Vec::with_capacity(w.len() + 1);
        cdf.push(0.0f32);
        let mut acc = 0.0;
        for v in &w {
            acc += v / total;
            cdf.push(acc);
        }
        // n + 1 edges in u-space → n intervals.
        let edges_u: Vec<f32> = (0..=n)
            .map(|i| {
                let j = match rng.as_deref_mut() {
                    Some(rng) => rng.random_range(0.0f32..1.0),
                    None => 0.5,
                };
                ((i as f32 + j) / (n + 1) as f32).min(1.0)
            })
            .collect();
        let ts: Vec<f32> = edges_u
            .iter()
            .map(|&u| {
                let b = cdf.partition_point(|&c| c <= u).clamp(1, w.len());
                let (c0, c1) = (cdf[b - 1], cdf[b]);
                let k = rg.start + b - 1;
                let f = if c1 > c0 { (u - c0) / (c1 - c0) } else { 0.5 };
                coarse.t_start[k] + f.clamp(0.0, 1.0) * (coarse.t_end[k] - coarse.t_start[k])
            })
            .collect();
        per_ray.push(ts.windows(2).map(|p| (p[0], p[1].max(p[0]))).collect());
    }
    RaySamples::from_per_ray(per_ray)
}
