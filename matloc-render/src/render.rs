use matloc_nerf_field::{F_MLP_DIMS, FEATURE_DIM, FeatureField, FieldError};
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

/// Rays rendered by one parallel work item. Each item marches, queries the field and
/// composites its rays on its own, so a render has no serial phase between rounds; small
/// enough that a 4800-ray view spreads over both cores, large enough that one field call
/// (`RAY_CHUNK × samples_per_round` points) fills the MLP's 256-point chunks.
const RAY_CHUNK: usize = 32;

struct RayState {
    step: usize,
    trans: f32,
    done: bool,
}

/// One chunk's output rows.
struct ChunkOut<'a> {
    rgb: &'a mut [f32],
    depth: &'a mut [f32],
    accumulation: &'a mut [f32],
    features: &'a mut [f32],
    median: &'a mut [f32],
}

/// What every chunk shares.
struct Shared<'a> {
    field: &'a dyn FeatureField,
    rays: &'a RayBatch,
    grid: Option<&'a OccupancyGrid>,
    opts: &'a RenderOptions,
    /// Dims evaluated: the requested ones, then f_mlp if RGB needs it.
    eval_dims: &'a [usize],
    /// Positions of the f_mlp dims in `eval_dims` (RGB only).
    fmlp_pos: &'a [usize],
}

/// Renders depth, accumulation, the chosen feature dims and optionally RGB for every ray.
///
/// Rays are marched in rounds of `samples_per_round` occupied samples; after each round a
/// ray whose transmittance fell below `min_transmittance` stops, so the field is queried
/// mostly near the first surface. Rays are independent: the result does not depend on how
/// they are split over threads.
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
    let nc = if opts.rgb { 3 } else { 0 };
    let mut out = RenderedRays {
        rgb: vec![0.0; nc * n],
        depth: vec![0.0; n],
        accumulation: vec![0.0; n],
        features: vec![0.0; n * nd],
        num_dims: nd,
        median: vec![0.0; n],
    };
    let shared = Shared {
        field,
        rays,
        grid,
        opts,
        eval_dims: &eval_dims,
        fmlp_pos: &fmlp_pos,
    };
    // `chunks_mut(0)` panics: empty outputs still need one (empty) slice per chunk.
    fn chunks(v: &mut [f32], per_ray: usize, n: usize) -> Vec<&mut [f32]> {
        if per_ray == 0 {
            (0..n.div_ceil(RAY_CHUNK)).map(|_| &mut [][..]).collect()
        } else {
            v.chunks_mut(RAY_CHUNK * per_ray).collect()
        }
    }
    let items: Vec<(usize, ChunkOut<'_>)> = chunks(&mut out.rgb, nc, n)
        .into_iter()
        .zip(out.depth.chunks_mut(RAY_CHUNK))
        .zip(out.accumulation.chunks_mut(RAY_CHUNK))
        .zip(chunks(&mut out.features, nd, n))
        .zip(out.median.chunks_mut(RAY_CHUNK))
        .enumerate()
        .map(|(c, ((((rgb, depth), accumulation), features), median))| {
            (
                c * RAY_CHUNK,
                ChunkOut {
                    rgb,
                    depth,
                    accumulation,
                    features,
                    median,
                },
            )
        })
        .collect();
    // `tile_rays` bounds the rays in flight (and so the scratch memory) at once.
    let per_tile = opts.tile_rays.div_ceil(RAY_CHUNK).max(1);
    let mut items = items;
    while !items.is_empty() {
        let rest = items.split_off(per_tile.min(items.len()));
        items
            .into_par_iter()
            .map(|(r0, o)| render_chunk(&shared, r0, o))
            .collect::<Result<(), RenderError>>()?;
        items = rest;
    }
    Ok(out)
}

/// Renders rays `r0..r0 + out.depth.len()` into `out`.
fn render_chunk(sh: &Shared<'_>, r0: usize, out: ChunkOut<'_>) -> Result<(), RenderError> {
    let opts = sh.opts;
    let (nd, ne) = (opts.dims.len(), sh.eval_dims.len());
    let m = out.depth.len();
    let mut state: Vec<RayState> = (0..m)
        .map(|_| RayState {
            step: 0,
            trans: 1.0,
            done: false,
        })
        .collect();
    // Scratch reused across rounds: intervals of the live rays, ray-major.
    let mut ivs: Vec<(f32, f32)> = Vec::with_capacity(m * opts.samples_per_round);
    // (ray in chunk, first interval, interval count, next step)
    let mut live: Vec<(usize, usize, usize, usize)> = Vec::with_capacity(m);
    let mut pts: Vec<[f32; 3]> = Vec::new();
    let (mut sigma, mut feats, mut weights) = (Vec::new(), Vec::new(), Vec::new());
    loop {
        ivs.clear();
        live.clear();
        for (j, s) in state.iter().enumerate() {
            if s.done {
                continue;
            }
            let first = ivs.len();
            let next = march_from(
                sh.rays,
                r0 + j,
                sh.grid,
                &opts.march,
                s.step,
                opts.samples_per_round,
                &mut ivs,
            );
            live.push((j, first, ivs.len() - first, next));
        }
        if live.is_empty() {
            break;
        }
        pts.clear();
        for &(j, first, count, _) in &live {
            for &(a, b) in &ivs[first..first + count] {
                pts.push(sh.rays.at(r0 + j, 0.5 * (a + b)));
            }
        }
        let ns = pts.len();
        sigma.clear();
        sigma.resize(ns, 0f32);
        feats.clear();
        feats.resize(ns * ne, 0f32);
        if ns > 0 {
            sh.field
                .density_and_features(&pts, sh.eval_dims, &mut sigma, &mut feats)?;
        }
        weights.clear();
        weights.resize(ns, 0f32);
        for &(j, first, count, next) in &live {
            let s = &mut state[j];
            if count == 0 {
                s.done = true;
                continue;
            }
            for (q, &(a, b)) in ivs[first..first + count].iter().enumerate() {
                let k = first + q;
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
                    out.median[j] = a + ((2.0 * s.trans).ln() / sigma[k].max(1e-30)).min(b - a);
                }
                s.trans *= 1.0 - al;
                out.accumulation[j] += w;
                out.depth[j] += w * 0.5 * (a + b);
                let f = &feats[k * ne..k * ne + nd];
                for (o, &v) in out.features[j * nd..(j + 1) * nd].iter_mut().zip(f) {
                    *o += w * v;
                }
            }
            s.step = next;
            if s.trans < opts.min_transmittance || next >= total_steps(&opts.march) {
                s.done = true;
            }
        }
        if opts.rgb && ns > 0 {
            // Colour only where it is visible.
            let mut fm = Vec::new();
            let mut cd = Vec::new();
            let mut ks = Vec::new();
            for &(j, first, count, _) in &live {
                for k in first..first + count {
                    if weights[k] >= COLOUR_MIN_WEIGHT {
                        ks.push((k, j));
                        fm.extend(sh.fmlp_pos.iter().map(|&p| feats[k * ne + p]));
                        cd.push(sh.rays.directions[r0 + j]);
                    }
                }
            }
            if !ks.is_empty() {
                let mut rgb = vec![0f32; 3 * ks.len()];
                sh.field.colour(&fm, &cd, opts.appearance, &mut rgb)?;
                for (q, &(k, j)) in ks.iter().enumerate() {
                    for ch in 0..3 {
                        out.rgb[3 * j + ch] += weights[k] * rgb[3 * q + ch];
                    }
                }
            }
        }
    }
    if opts.rgb {
        for (j, s) in state.iter().enumerate() {
            for ch in 0..3 {
                out.rgb[3 * j + ch] += s.trans * opts.background[ch];
            }
        }
    }
    Ok(())
}

fn total_steps(cfg: &MarchConfig) -> usize {
    cfg.steps
}

/// Appends up to `k` occupied intervals of ray `r`, starting at step `from`, to `out`;
/// returns the next step to continue from.
fn march_from(
    rays: &RayBatch,
    r: usize,
    grid: Option<&OccupancyGrid>,
    cfg: &MarchConfig,
    from: usize,
    k: usize,
    out: &mut Vec<(f32, f32)>,
) -> usize {
    let s0 = cfg.spacing.to_s(rays.near[r]);
    let s1 = cfg.spacing.to_s(rays.far[r]);
    let ds = (s1 - s0) / cfg.steps as f32;
    let mut i = from;
    let mut taken = 0;
    // The end of step i is the start of step i + 1 (unless clamped to s1): one `to_t` per step.
    let mut a = cfg.spacing.to_t(s0 + ds * i as f32);
    while i < cfg.steps && taken < k {
        let x = s0 + ds * (i + 1) as f32;
        let next_a = cfg.spacing.to_t(x);
        let b = if x > s1 { cfg.spacing.to_t(s1) } else { next_a };
        i += 1;
        let iv = (a, b);
        a = next_a;
        if let Some(g) = grid
            && !g.is_occupied_world(rays.at(r, 0.5 * (iv.0 + iv.1)))
        {
            continue;
        }
        out.push(iv);
        taken += 1;
    }
    i
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
