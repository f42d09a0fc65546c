use matloc_nerf_field::{F_MLP_DIM, F_MLP_DIMS, FEATURE_DIM, FeatureField, FieldError};
use rayon::prelude::*;

use crate::error::RenderError;
use crate::occupancy::OccupancyGrid;
use crate::rays::RayBatch;
use crate::sampler::{MarchConfig, march_ray};
use crate::volume::RenderedRays;

/// Inference rendering settings.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOptions {
    /// Sample placement (with an occupancy grid, only occupied steps are evaluated).
    pub march: MarchConfig,
    /// Feature dims to render (any subset of `0..47`, any order); may be empty.
    pub dims: Vec<usize>,
    /// Whether to render RGB (runs the colour MLP on the visible samples).
    pub rgb: bool,
    /// Appearance embedding for colour; `None` = the field's fallback.
    pub appearance: Option<u32>,
    /// Colour seen where the ray is not fully absorbed.
    pub background: [f32; 3],
    /// A ray stops once its transmittance falls below this (early ray termination).
    pub min_transmittance: f32,
    /// Occupied samples evaluated per ray and round; rays are re-marched from where they
    /// stopped, so fewer samples are wasted behind surfaces.
    pub samples_per_round: usize,
    /// Rays processed together (bounds memory: ~`tile_rays × samples_per_round × 60` floats).
    pub tile_rays: usize,
    /// Density (1/m) below which a sample contributes nothing (render-time fog filter);
    /// 0 = every sample counts.
    pub min_density: f32,
}

/// Samples whose blending weight is below this get no colour evaluation (their colour
/// changes a pixel by less than this).
const COLOUR_MIN_WEIGHT: f32 = 1e-5;

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            march: MarchConfig::default(),
            dims: (0..FEATURE_DIM).collect(),
            rgb: false,
            appearance: None,
            background: [0.0; 3],
            min_transmittance: 1e-4,
            samples_per_round: 16,
            tile_rays: 16_384,
            min_density: 0.0,
        }
    }
}

/// One live ray's work in a round: its index in the tile, its new intervals, the next step.
type RoundItem = (usize, Vec<(f32, f32)>, usize);

struct RayState {
    step: usize,
    trans: f32,
    done: bool,
}

/// Renders depth, accumulation, the chosen feature dims and optionally RGB for every ray.
///
/// Rays are marched in rounds of `samples_per_round` occupied samples; after each round a
/// ray whose transmittance fell below `min_transmittance` stops, so the field is queried
/// mostly near the first surface.
pub fn render_rays(
    field: &dyn FeatureField,
    rays: &RayBatch,
    grid: Option<&OccupancyGrid>,
    opts: &RenderOptions,
) -> Result<RenderedRays, RenderError> {
    rays.validate()?;
    if let Some(&d) = opts.dims.iter().find(|&&d| d >= FEATURE_DIM) {
        return Err(FieldError::DimOutOfRange {
            dim: d,
            available: FEATURE_DIM,
        }
        .into());
    }
    if opts.samples_per_round == 0 || opts.tile_rays == 0 {
        return Err(RenderError::InvalidConfig {
            field: "samples_per_round/tile_rays",
            reason: "must be positive".into(),
        });
    }
    let n = rays.len();
    let nd = opts.dims.len();
    // Dims evaluated: the requested ones, then f_mlp if RGB needs it.
    let mut eval_dims = opts.dims.clone();
    let fmlp_pos: Vec<usize> = if opts.rgb {
        F_MLP_DIMS
            .map(|d| {
                eval_dims.iter().position(|&e| e == d).unwrap_or_else(|| {
                    eval_dims.push(d);
                    eval_dims.len() - 1
                })
            })
            .collect()
    } else {
        Vec::new()
    };
    let ne = eval_dims.len();
    let mut out = RenderedRays {
        rgb: vec![0.0; if opts.rgb { 3 * n } else { 0 }],
        depth: vec![0.0; n],
        accumulation: vec![0.0; n],
        features: vec![0.0; n * nd],
        num_dims: nd,
        median: vec![0.0; n],
    };
    for tile_start in (0..n).step_by(opts.tile_rays) {
        let tile_end = (tile_start + opts.tile_rays).min(n);
        let mut state: Vec<RayState> = (tile_start..tile_end)
            .map(|_| RayState {
                step: 0,
                trans: 1.0,
                done: false,
            })
            .collect();
        loop {
            // March every live ray to its next `samples_per_round` occupied samples.
            let batch: Vec<RoundItem> = state
                .par_iter()
                .enumerate()
                .filter(|(_, s)| !s.done)
                .map(|(j, s)| {
                    let r = tile_start + j;
                    let (iv, next) =
                        march_from(rays, r, grid, &opts.march, s.step, opts.samples_per_round);
                    (j, iv, next)
                })
                .collect();
            if batch.is_empty() {
                break;
            }
            let mut pts = Vec::new();
            for (j, iv, _) in &batch {
                let r = tile_start + j;
                for &(a, b) in iv {
                    pts.push(rays.at(r, 0.5 * (a + b)));
                }
            }
            let ns = pts.len();
            let mut sigma = vec![0f32; ns];
            let mut feats = vec![0f32; ns * ne];
            if ns > 0 {
                field.density_and_features(&pts, &eval_dims, &mut sigma, &mut feats)?;
            }
            // Composite this round (sequential per ray; cheap next to the field queries).
            let mut weights = vec![0f32; ns];
            let mut k0 = 0;
            for (j, iv, next) in &batch {
                let r = tile_start + j;
                let s = &mut state[*j];
                if iv.is_empty() {
                    s.done = true;
                    continue;
                }
                for (q, &(a, b)) in iv.iter().enumerate() {
                    let k = k0 + q;
                    if s.trans < opts.min_transmittance {
                        break;
                    }
                    if sigma[k] < opts.min_density {
                        continue;
                    }
                    let al = 1.0 - (-sigma[k] * (b - a)).exp();
                    let w = s.trans * al;
                    weights[k] = w;
                    if s.trans > 0.5 && s.trans * (1.0 - al) <= 0.5 {
                        // T(x) = T0·exp(−σx) reaches 0.5 at x = ln(2·T0)/σ.
                        out.median[r] = a + ((2.0 * s.trans).ln() / sigma[k].max(1e-30)).min(b - a);
                    }
                    s.trans *= 1.0 - al;
                    out.accumulation[r] += w;
                    out.depth[r] += w * 0.5 * (a + b);
                    for jd in 0..nd {
                        out.features[r * nd + jd] += w * feats[k * ne + jd];
                    }
                }
                k0 += iv.len();
                s.step = *next;
                if s.trans < opts.min_transmittance || *next >= total_steps(&opts.march) {
                    s.done = true;
                }
            }
            if opts.rgb && ns > 0 {
                // Colour only where it is visible.
                let (mut ks, mut rs) = (Vec::new(), Vec::new());
                let mut k0 = 0;
                for (j, iv, _) in &batch {
                    for k in k0..k0 + iv.len() {
                        if weights[k] >= COLOUR_MIN_WEIGHT {
                            ks.push(k);
                            rs.push(tile_start + j);
                        }
                    }
                    k0 += iv.len();
                }
                if !ks.is_empty() {
                    let mut fm = Vec::with_capacity(ks.len() * F_MLP_DIM);
                    let mut cd = Vec::with_capacity(ks.len());
                    for (&k, &r) in ks.iter().zip(&rs) {
                        fm.extend(fmlp_pos.iter().map(|&p| feats[k * ne + p]));
                        cd.push(rays.directions[r]);
                    }
                    let mut rgb = vec![0f32; 3 * ks.len()];
                    field.colour(&fm, &cd, opts.appearance, &mut rgb)?;
                    for (q, (&k, &r)) in ks.iter().zip(&rs).enumerate() {
                        for ch in 0..3 {
                            out.rgb[3 * r + ch] += weights[k] * rgb[3 * q + ch];
                        }
                    }
                }
            }
        }
        if opts.rgb {
            for (j, s) in state.iter().enumerate() {
                let r = tile_start + j;
                for ch in 0..3 {
                    out.rgb[3 * r + ch] += s.trans * opts.background[ch];
                }
            }
        }
    }
    Ok(out)
}

fn total_steps(cfg: &MarchConfig) -> usize {
    cfg.steps
}

/// Up to `k` occupied intervals of ray `r` starting at step `from`; returns them and the
/// next step to continue from.
fn march_from(
    rays: &RayBatch,
    r: usize,
    grid: Option<&OccupancyGrid>,
    cfg: &MarchConfig,
    from: usize,
    k: usize,
) -> (Vec<(f32, f32)>, usize) {
    let s0 = cfg.spacing.to_s(rays.near[r]);
    let s1 = cfg.spacing.to_s(rays.far[r]);
    let ds = (s1 - s0) / cfg.steps as f32;
    let mut out = Vec::with_capacity(k);
    let mut i = from;
    while i < cfg.steps && out.len() < k {
        let a = cfg.spacing.to_t(s0 + ds * i as f32);
        let b = cfg.spacing.to_t((s0 + ds * (i + 1) as f32).min(s1));
        i += 1;
        if let Some(g) = grid
            && !g.is_occupied_world(rays.at(r, 0.5 * (a + b)))
        {
            continue;
        }
        out.push((a, b));
    }
    (out, i)
}

/// Renders all rays with the single-pass sampler (no rounds): used to check the round-based
/// renderer and for callers that want every sample's weight.
pub fn render_rays_single_pass(
    field: &dyn FeatureField,
    rays: &RayBatch,
    grid: Option<&OccupancyGrid>,
    march: &MarchConfig,
    dims: &[usize],
) -> Result<RenderedRays, RenderError> {
    rays.validate()?;
    let per_ray: Vec<Vec<(f32, f32)>> = (0..rays.len())
        .into_par_iter()
        .map(|r| march_ray(rays, r, grid, march, 0.0))
        .collect();
    let samples = crate::rays::RaySamples::from_per_ray(per_ray);
    let (pts, _, _) = samples.points(rays);
    let mut sigma = vec![0f32; pts.len()];
    let mut feats = vec![0f32; pts.len() * dims.len()];
    field.density_and_features(&pts, dims, &mut sigma, &mut feats)?;
    crate::volume::volume_render(
        &samples,
        &crate::volume::SampleValues {
            sigma: &sigma,
            rgb: &[],
            features: &feats,
            num_dims: dims.len(),
        },
        [0.0; 3],
    )
}
