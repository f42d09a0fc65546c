//! Volume rendering forward and backward over [`RaySamples`].
//!
//! With `τ_k = σ_k δ_k`, `T_k = exp(−Σ_{j<k} τ_j)`, `w_k = T_k (1 − e^{−τ_k})`:
//! RGB `= Σ w_k c_k + (1 − Σ w_k)·bg`, depth `U = Σ w_k t_k` (t at the interval midpoint,
//! distance along the unit ray), accumulation `A = Σ w_k`, features `F = Σ w_k f_k`.
//! The backward uses `∂Y/∂τ_k = T_{k+1} y_k − Σ_{j>k} w_j y_j − bg·T_N`.

use rayon::prelude::*;

use crate::error::RenderError;
use crate::rays::RaySamples;

/// Per-ray rendered quantities.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RenderedRays {
    /// RGB (`n × 3`), background composited; empty if not rendered.
    pub rgb: Vec<f32>,
    /// Expected distance along the ray `Σ w t` (metres; not divided by accumulation).
    pub depth: Vec<f32>,
    /// Accumulated opacity `Σ w`.
    pub accumulation: Vec<f32>,
    /// Rendered features (`n × num_dims`, point-major); empty if none.
    pub features: Vec<f32>,
    /// Feature dims per ray in `features`.
    pub num_dims: usize,
    /// Median distance: where the transmittance falls to 0.5 (exact for piecewise-constant
    /// density), 0 where it never does; filled by [`crate::render_rays`] only (empty
    /// elsewhere).
    pub median: Vec<f32>,
}

impl RenderedRays {
    /// Depth divided by accumulation (the depth of the visible surface); `None` where the
    /// ray hit (almost) nothing.
    pub fn normalized_depth(&self, i: usize) -> Option<f32> {
        let a = self.accumulation[i];
        (a > 1e-3).then(|| self.depth[i] / a)
    }

    /// z-depth (along the camera's forward axis) of ray `i` from its distance depth.
    pub fn z_depth(&self, i: usize, direction: [f32; 3], forward: [f32; 3]) -> f32 {
        z_from_distance(self.depth[i], direction, forward)
    }
}

/// Converts a distance along a unit ray to depth along the camera's unit forward axis.
/// Linear, so it also converts the gradient: `∂L/∂U = (d·f) ∂L/∂z`.
#[inline]
pub fn z_from_distance(distance: f32, direction: [f32; 3], forward: [f32; 3]) -> f32 {
    distance * (direction[0] * forward[0] + direction[1] * forward[1] + direction[2] * forward[2])
}

/// Blending weights of every sample and the final transmittance of every ray.
pub fn compute_weights(samples: &RaySamples, sigma: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let mut w = vec![0f32; samples.len()];
    let mut t_end = vec![1f32; samples.num_rays()];
    for r in 0..samples.num_rays() {
        let mut t = 1f32;
        for k in samples.range(r) {
            let a = 1.0 - (-sigma[k] * (samples.t_end[k] - samples.t_start[k])).exp();
            w[k] = t * a;
            t *= 1.0 - a;
        }
        t_end[r] = t;
    }
    (w, t_end)
}

/// Per-sample inputs of a render: density and optionally colours and features.
#[derive(Clone, Copy, Debug)]
pub struct SampleValues<'a> {
    /// Density per sample.
    pub sigma: &'a [f32],
    /// Colour per sample (`n × 3`), or empty.
    pub rgb: &'a [f32],
    /// Features per sample (`n × num_dims`), or empty.
    pub features: &'a [f32],
    /// Width of `features` rows.
    pub num_dims: usize,
}

impl SampleValues<'_> {
    fn check(&self, n: usize) -> Result<(), RenderError> {
        let chk = |what, expected: usize, actual: usize| {
            if expected == actual {
                Ok(())
            } else {
                Err(RenderError::LengthMismatch {
                    what,
                    expected,
                    actual,
                })
            }
        };
        chk("sigma", n, self.sigma.len())?;
        if !self.rgb.is_empty() {
            chk("rgb", 3 * n, self.rgb.len())?;
        }
        if !self.features.is_empty() {
            chk("features", n * self.num_dims, self.features.len())?;
        }
        Ok(())
    }
}

/// Rays per parallel work item.
const RAY_GROUP: usize = 64;

/// Renders every ray (parallel over groups of rays).
pub fn volume_render(
    samples: &RaySamples,
    v: &SampleValues<'_>,
    background: [f32; 3],
) -> Result<RenderedRays, RenderError> {
    v.check(samples.len())?;
    let n = samples.num_rays();
    let nd = if v.features.is_empty() { 0 } else { v.num_dims };
    let has_rgb = !v.rgb.is_empty();
    let mut out = RenderedRays {
        rgb: vec![0.0; if has_rgb { 3 * n } else { 0 }],
        depth: vec![0.0; n],
        accumulation: vec![0.0; n],
        features: vec![0.0; n * nd],
        num_dims: nd,
        median: Vec::new(),
    };
    let rgb_chunks: Vec<&mut [f32]> = if has_rgb {
        out.rgb.chunks_mut(3 * RAY_GROUP).collect()
    } else {
        (0..n.div_ceil(RAY_GROUP)).map(|_| &mut [][..]).collect()
    };
    let feat_chunks: Vec<&mut [f32]> = if nd > 0 {
        out.features.chunks_mut(nd * RAY_GROUP).collect()
    } else {
        (0..n.div_ceil(RAY_GROUP)).map(|_| &mut [][..]).collect()
    };
    out.depth
        .par_chunks_mut(RAY_GROUP)
        .zip(out.accumulation.par_chunks_mut(RAY_GROUP))
        .zip(rgb_chunks.into_par_iter())
        .zip(feat_chunks.into_par_iter())
        .enumerate()
        .for_each(|(g, (((depth, acc), rgb), feat))| {
            for (j, r) in (g * RAY_GROUP..(g * RAY_GROUP + depth.len())).enumerate() {
                let mut t = 1f32;
                let mut c = [0f32; 3];
                let (mut d, mut a) = (0f32, 0f32);
                for k in samples.range(r) {
                    let al = 1.0 - (-v.sigma[k] * (samples.t_end[k] - samples.t_start[k])).exp();
                    let w = t * al;
                    t *= 1.0 - al;
                    a += w;
                    d += w * samples.t_mid(k);
                    if has_rgb {
                        for ch in 0..3 {
                            c[ch] += w * v.rgb[3 * k + ch];
                        }
                    }
                    if nd > 0 {
                        let f = &mut feat[j * nd..(j + 1) * nd];
                        for (o, x) in f.iter_mut().zip(&v.features[k * nd..(k + 1) * nd]) {
                            *o += w * x;
                        }
                    }
                }
                depth[j] = d;
                acc[j] = a;
                if has_rgb {
                    for ch in 0..3 {
                        rgb[3 * j + ch] = c[ch] + t * background[ch];
                    }
                }
            }
        });
    Ok(out)
}

/// Incoming gradients of a loss w.r.t. rendered quantities; empty slices mean zero.
#[derive(Clone, Copy, Debug, Default)]
pub struct RenderGradients<'a> {
    /// `∂L/∂rgb` (`n_rays × 3`).
    pub rgb: &'a [f32],
    /// `∂L/∂depth` (distance depth).
    pub depth: &'a [f32],
    /// `∂L/∂accumulation`.
    pub accumulation: &'a [f32],
    /// `∂L/∂features` (`n_rays × num_dims`).
    pub features: &'a [f32],
}

/// Gradients w.r.t. the per-sample inputs (and the background colour).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SampleGradients {
    /// `∂L/∂σ` per sample.
    pub sigma: Vec<f32>,
    /// `∂L/∂c` per sample (`n × 3`); empty if no RGB gradient came in.
    pub rgb: Vec<f32>,
    /// `∂L/∂f` per sample (`n × num_dims`); empty if no feature gradient came in.
    pub features: Vec<f32>,
    /// `∂L/∂background`.
    pub background: [f32; 3],
}

/// Backward of [`volume_render`].
pub fn volume_render_backward(
    samples: &RaySamples,
    v: &SampleValues<'_>,
    background: [f32; 3],
    g: &RenderGradients<'_>,
) -> Result<SampleGradients, RenderError> {
    v.check(samples.len())?;
    let n = samples.num_rays();
    let ns = samples.len();
    let nd = v.num_dims;
    let use_rgb = !g.rgb.is_empty() && !v.rgb.is_empty();
    let use_feat = !g.features.is_empty() && !v.features.is_empty() && nd > 0;
    for (what, buf, width, used) in [
        ("d_rgb", g.rgb, 3, !g.rgb.is_empty()),
        ("d_depth", g.depth, 1, !g.depth.is_empty()),
        (
            "d_accumulation",
            g.accumulation,
            1,
            !g.accumulation.is_empty(),
        ),
        ("d_features", g.features, nd, !g.features.is_empty()),
    ] {
        if used && buf.len() != n * width {
            return Err(RenderError::LengthMismatch {
                what,
                expected: n * width,
                actual: buf.len(),
            });
        }
    }
    let mut out = SampleGradients {
        sigma: vec![0.0; ns],
        rgb: vec![0.0; if use_rgb { 3 * ns } else { 0 }],
        features: vec![0.0; if use_feat { nd * ns } else { 0 }],
        background: [0.0; 3],
    };
    // Split the per-sample outputs at ray-group boundaries so groups can run in parallel.
    let groups = n.div_ceil(RAY_GROUP);
    let mut sig_parts = Vec::with_capacity(groups);
    let mut rgb_parts = Vec::with_capacity(groups);
    let mut feat_parts = Vec::with_capacity(groups);
    {
        let (mut s_rest, mut c_rest, mut f_rest) =
            (&mut out.sigma[..], &mut out.rgb[..], &mut out.features[..]);
        for gi in 0..groups {
            let a = samples.offsets[gi * RAY_GROUP];
            let b = samples.offsets[((gi + 1) * RAY_GROUP).min(n)];
            let m = b - a;
            let (s, sr) = s_rest.split_at_mut(m);
            s_rest = sr;
            sig_parts.push(s);
            let (c, cr) = c_rest.split_at_mut(if use_rgb { 3 * m } else { 0 });
            c_rest = cr;
            rgb_parts.push(c);
            let (f, fr) = f_rest.split_at_mut(if use_feat { nd * m } else { 0 });
            f_rest = fr;
            feat_parts.push(f);
        }
    }
    let bg_grads: Vec<[f32; 3]> = sig_parts
        .into_par_iter()
        .zip(rgb_parts)
        .zip(feat_parts)
        .enumerate()
        .map(|(gi, ((ds, dc), df))| {
            let mut d_bg = [0f32; 3];
            let base = samples.offsets[gi * RAY_GROUP];
            let mut w = Vec::new();
            let mut trans = Vec::new();
            for r in gi * RAY_GROUP..((gi + 1) * RAY_GROUP).min(n) {
                let rg = samples.range(r);
                w.clear();
                trans.clear();
                let mut t = 1f32;
                for k in rg.clone() {
                    let al = 1.0 - (-v.sigma[k] * (samples.t_end[k] - samples.t_start[k])).exp();
                    w.push(t * al);
                    t *= 1.0 - al;
                    trans.push(t); // T_{k+1}
                }
                let t_final = t;
                let g_rgb = if use_rgb {
                    [g.rgb[3 * r], g.rgb[3 * r + 1], g.rgb[3 * r + 2]]
                } else {
                    [0.0; 3]
                };
                let g_d = if g.depth.is_empty() { 0.0 } else { g.depth[r] };
                let g_a = if g.accumulation.is_empty() {
                    0.0
                } else {
                    g.accumulation[r]
                };
                let g_f = if use_feat {
                    &g.features[r * nd..(r + 1) * nd]
                } else {
                    &[][..]
                };
                let bg_term = t_final
                    * (g_rgb[0] * background[0]
                        + g_rgb[1] * background[1]
                        + g_rgb[2] * background[2]);
                for ch in 0..3 {
                    d_bg[ch] += g_rgb[ch] * t_final;
                }
                // Suffix sums Σ_{j>k} w_j y_j, contracted with the incoming gradient.
                let mut suffix = 0f32;
                for (j, k) in rg.clone().enumerate().rev() {
                    let local = k - base;
                    let t_next = trans[j];
                    let delta = samples.t_end[k] - samples.t_start[k];
                    let mut y_dot_g = g_d * samples.t_mid(k) + g_a;
                    if use_rgb {
                        for ch in 0..3 {
                            y_dot_g += g_rgb[ch] * v.rgb[3 * k + ch];
                            dc[3 * local + ch] = g_rgb[ch] * w[j];
                        }
                    }
                    if use_feat {
                        let f = &v.features[k * nd..(k + 1) * nd];
                        for (gf, x) in g_f.iter().zip(f) {
                            y_dot_g += gf * x;
                        }
                        for (o, gf) in df[local * nd..(local + 1) * nd].iter_mut().zip(g_f) {
                            *o = gf * w[j];
                        }
                    }
                    let d_tau = t_next * y_dot_g - suffix - bg_term;
                    ds[local] = d_tau * delta;
                    suffix += w[j] * y_dot_g;
                }
            }
            d_bg
        })
        .collect();
    for b in bg_grads {
        for ch in 0..3 {
            out.background[ch] += b[ch];
        }
    }
    Ok(out)
}

/// mip-NeRF 360's distortion loss of every ray and its gradient w.r.t. σ.
///
/// `L = Σ_ij w_i w_j |m_i − m_j| + ⅓ Σ_i w_i² (s1_i − s0_i)` with `m` the interval midpoints
/// in the normalised coordinates `s0`/`s1` (per sample, ascending along each ray, e.g. the
/// sampler's spacing mapped to `[0,1]`). It pulls each ray's weight into one compact
/// interval, which suppresses fog and floaters that few-view training otherwise keeps.
/// Evaluated in O(n) per ray with prefix sums.
pub fn distortion_loss(
    samples: &RaySamples,
    sigma: &[f32],
    s0: &[f32],
    s1: &[f32],
) -> Result<(Vec<f32>, Vec<f32>), RenderError> {
    let ns = samples.len();
    for (what, len) in [("sigma", sigma.len()), ("s0", s0.len()), ("s1", s1.len())] {
        if len != ns {
            return Err(RenderError::LengthMismatch {
                what,
                expected: ns,
                actual: len,
            });
        }
    }
    let n = samples.num_rays();
    let per_ray: Vec<(f32, Vec<f32>)> = (0..n)
        .into_par_iter()
        .with_min_len(64)
        .map(|r| {
            let rg = samples.range(r);
            let m = rg.len();
            let mut w = Vec::with_capacity(m);
            let mut trans = Vec::with_capacity(m);
            let mut t = 1f32;
            for k in rg.clone() {
                let al = 1.0 - (-sigma[k] * (samples.t_end[k] - samples.t_start[k])).exp();
                w.push(t * al);
                t *= 1.0 - al;
                trans.push(t);
            }
            let mid: Vec<f32> = rg.clone().map(|k| 0.5 * (s0[k] + s1[k])).collect();
            let del: Vec<f32> = rg.clone().map(|k| s1[k] - s0[k]).collect();
            let (a_tot, b_tot): (f32, f32) = w
                .iter()
                .zip(&mid)
                .fold((0.0, 0.0), |(a, b), (wi, mi)| (a + wi, b + wi * mi));
            let mut a = 0f32;
            let mut b = 0f32;
            let mut loss = 0f32;
            let mut g = vec![0f32; m];
            for i in 0..m {
                // Σ_j w_j |m_i − m_j| split into j < i and j > i.
                let after_a = a_tot - a - w[i];
                let after_b = b_tot - b - w[i] * mid[i];
                let s = mid[i] * a - b + after_b - mid[i] * after_a;
                loss += w[i] * s + w[i] * w[i] * del[i] / 3.0;
                g[i] = 2.0 * s + 2.0 / 3.0 * w[i] * del[i];
                a += w[i];
                b += w[i] * mid[i];
            }
            // ∂L/∂τ_k = T_{k+1} g_k − Σ_{j>k} w_j g_j.
            let mut d_sigma = vec![0f32; m];
            let mut suffix = 0f32;
            for (j, k) in rg.enumerate().rev() {
                d_sigma[j] = (trans[j] * g[j] - suffix) * (samples.t_end[k] - samples.t_start[k]);
                suffix += w[j] * g[j];
            }
            (loss, d_sigma)
        })
        .collect();
    let mut losses = Vec::with_capacity(n);
    let mut d = Vec::with_capacity(ns);
    for (l, g) in per_ray {
        losses.push(l);
        d.extend(g);
    }
    Ok((losses, d))
}
