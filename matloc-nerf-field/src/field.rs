use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::activation::{sigmoid, trunc_exp, trunc_exp_grad};
use crate::config::{AppearanceFallback, FieldConfig};
use crate::contraction::contract_to_unit;
use crate::error::FieldError;
use crate::feature::{F_MLP_DIM, F_POS_DIM, FEATURE_DIM, FeatureField};
use crate::hashgrid::HashGrid;
use crate::mlp::{Linear, LinearGrad};
use crate::sh::{SH_DIM, sh_encode};

/// Hidden width of both MLPs.
pub(crate) const HIDDEN: usize = 64;
/// Geometry MLP output width: density + f_mlp.
pub(crate) const GEO_OUT: usize = 1 + F_MLP_DIM;
/// Points per work item of the fused MLP kernels: activations of a chunk (~100 KB) stay in L2.
const MLP_CHUNK: usize = 128;
/// Marks "no appearance index" in per-point appearance arrays.
const NO_APPEARANCE: u32 = u32::MAX;

/// The nerfacto-like field: hash grid → geometry MLP → (density, f_mlp); colour MLP.
#[derive(Clone, Debug)]
pub struct NerfactoField {
    config: FieldConfig,
    /// Hash-grid encoding (f_pos).
    pub grid: HashGrid,
    /// Geometry MLP: 32 → 64 (ReLU) → 16.
    pub geo: [Linear; 2],
    /// Colour MLP: (16 + 15 + A) → 64 (ReLU) → 64 (ReLU) → 3 (sigmoid).
    pub col: [Linear; 3],
    /// Appearance embeddings, `num_images × appearance_dim`.
    pub appearance: Vec<f32>,
}

/// Gradients of every parameter of a [`NerfactoField`], same shapes.
#[derive(Clone, Debug)]
pub struct FieldGrads {
    /// `∂L/∂table`.
    pub table: Vec<f32>,
    /// Geometry MLP layers.
    pub geo: [LinearGrad; 2],
    /// Colour MLP layers.
    pub col: [LinearGrad; 3],
    /// Appearance embeddings.
    pub appearance: Vec<f32>,
}

impl FieldGrads {
    /// Parameter groups in the order of [`NerfactoField::param_slices_mut`].
    pub fn slices_mut(&mut self) -> Vec<&mut [f32]> {
        let mut v: Vec<&mut [f32]> = vec![&mut self.table];
        for l in self.geo.iter_mut().chain(self.col.iter_mut()) {
            v.push(&mut l.w);
            v.push(&mut l.b);
        }
        v.push(&mut self.appearance);
        v
    }

    /// Sets every gradient to zero.
    pub fn zero(&mut self) {
        for s in self.slices_mut() {
            s.fill(0.0);
        }
    }
}

/// Activations saved by [`NerfactoField::forward_train`] for the backward pass.
#[derive(Clone, Debug, Default)]
pub struct TrainCache {
    unit: Vec<[f32; 3]>,
    app: Vec<u32>,
    enc: Vec<f32>,
    geo_h: Vec<f32>,
    geo_out: Vec<f32>,
    col_in: Vec<f32>,
    h1: Vec<f32>,
    h2: Vec<f32>,
    rgb: Vec<f32>,
    density: Vec<f32>,
    /// Scratch of the hash-grid passes and `∂L/∂f_pos`, kept so that a cache reused across
    /// steps ([`NerfactoField::forward_train_into`], [`NerfactoField::backward_reusing`])
    /// does not allocate (and page-fault) ~300 MB of fresh memory every step.
    scratch_lvl: Vec<f32>,
    scratch_d_enc: Vec<f32>,
}

impl TrainCache {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.density.len()
    }
    /// Whether the batch was empty.
    pub fn is_empty(&self) -> bool {
        self.density.is_empty()
    }
    /// Density per point.
    pub fn density(&self) -> &[f32] {
        &self.density
    }
    /// RGB per point (`n × 3`).
    pub fn rgb(&self) -> &[f32] {
        &self.rgb
    }
    /// Hash-grid inputs in `[0,1]³` (after contraction).
    pub fn unit_points(&self) -> &[[f32; 3]] {
        &self.unit
    }
    /// The 47-d features of point `i` (f_pos then f_mlp).
    pub fn features(&self, i: usize) -> [f32; FEATURE_DIM] {
        let mut f = [0f32; FEATURE_DIM];
        f[..F_POS_DIM].copy_from_slice(&self.enc[i * F_POS_DIM..(i + 1) * F_POS_DIM]);
        f[F_POS_DIM..].copy_from_slice(&self.geo_out[i * GEO_OUT + 1..(i + 1) * GEO_OUT]);
        f
    }
}

/// Mutable per-chunk views of a [`TrainCache`] so chunks can be filled in parallel.
struct ChunkMut<'a> {
    dirs: &'a [[f32; 3]],
    app: &'a [u32],
    enc: &'a mut [f32],
    geo_h: &'a mut [f32],
    geo_out: &'a mut [f32],
    col_in: &'a mut [f32],
    h1: &'a mut [f32],
    h2: &'a mut [f32],
    rgb: &'a mut [f32],
    density: &'a mut [f32],
}

/// Per-thread accumulator of MLP/appearance gradients plus scratch for the backward pass.
struct BwdAcc {
    geo: [LinearGrad; 2],
    col: [LinearGrad; 3],
    app: Vec<f32>,
    d_h2: Vec<f32>,
    d_h1: Vec<f32>,
    d_col_in: Vec<f32>,
    d_geo_out: Vec<f32>,
    d_geo_h: Vec<f32>,
}

impl NerfactoField {
    /// A freshly initialised field (deterministic from `config.seed`).
    pub fn new(config: FieldConfig) -> Result<Self, FieldError> {
        config.validate()?;
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        let grid = HashGrid::new(
            config.log2_table_size,
            config.base_resolution,
            config.max_resolution,
            &mut rng,
        );
        let relu_gain = std::f32::consts::SQRT_2;
        let geo = [
            Linear::new(F_POS_DIM, HIDDEN, relu_gain, &mut rng),
            Linear::new(HIDDEN, GEO_OUT, 1.0, &mut rng),
        ];
        let col = [
            Linear::new(config.colour_input_dim(), HIDDEN, relu_gain, &mut rng),
            Linear::new(HIDDEN, HIDDEN, relu_gain, &mut rng),
            Linear::new(HIDDEN, 3, 1.0, &mut rng),
        ];
        // nerfstudio initialises embeddings N(0,1); a smaller spread keeps the colour MLP's
        // first steps dominated by geometry features.
        let appearance = (0..config.num_images * config.appearance_dim)
            .map(|_| rand::Rng::random_range(&mut rng, -0.1f32..0.1))
            .collect();
        Ok(Self {
            config,
            grid,
            geo,
            col,
            appearance,
        })
    }

    pub(crate) fn from_parts(
        config: FieldConfig,
        grid: HashGrid,
        geo: [Linear; 2],
        col: [Linear; 3],
        appearance: Vec<f32>,
    ) -> Self {
        Self {
            config,
            grid,
            geo,
            col,
            appearance,
        }
    }

    /// Density unit conversion (1/m per unit of `trunc_exp(raw)`): `2 / mean box extent`.
    ///
    /// The network's density lives in the box-normalised frame (box = `[-1,1]³`), as in
    /// nerfstudio where scenes are rescaled to unit size; converting here keeps the initial
    /// optical depth across the box ≈ 1 whatever the scene's size in metres, so a 500 m
    /// aerial scene does not start out opaque.
    pub fn density_scale(&self) -> f32 {
        self.config.scene_box.density_scale()
    }

    /// The configuration the field was built with.
    pub fn config(&self) -> &FieldConfig {
        &self.config
    }

    /// Zero gradients shaped like this field.
    pub fn zero_grads(&self) -> FieldGrads {
        FieldGrads {
            table: vec![0.0; self.grid.table.len()],
            geo: [self.geo[0].zero_grad(), self.geo[1].zero_grad()],
            col: [
                self.col[0].zero_grad(),
                self.col[1].zero_grad(),
                self.col[2].zero_grad(),
            ],
            appearance: vec![0.0; self.appearance.len()],
        }
    }

    /// Parameter groups: table, then (w, b) of geo0, geo1, col0, col1, col2, then appearance.
    pub fn param_slices_mut(&mut self) -> Vec<&mut [f32]> {
        let mut v: Vec<&mut [f32]> = vec![&mut self.grid.table];
        for l in self.geo.iter_mut().chain(self.col.iter_mut()) {
            v.push(&mut l.w);
            v.push(&mut l.b);
        }
        v.push(&mut self.appearance);
        v
    }

    /// Sizes of the parameter groups of [`Self::param_slices_mut`].
    pub fn param_sizes(&self) -> Vec<usize> {
        let mut v = vec![self.grid.table.len()];
        for l in self.geo.iter().chain(self.col.iter()) {
            v.push(l.w.len());
            v.push(l.b.len());
        }
        v.push(self.appearance.len());
        v
    }

    /// Total number of parameters.
    pub fn num_params(&self) -> usize {
        self.param_sizes().iter().sum()
    }

    /// The embedding used for `appearance`, or the fallback.
    fn embedding(&self, appearance: Option<u32>) -> Result<Vec<f32>, FieldError> {
        let a = self.config.appearance_dim;
        let n = self.config.num_images;
        match appearance {
            Some(i) if (i as usize) < n => {
                Ok(self.appearance[i as usize * a..(i as usize + 1) * a].to_vec())
            }
            Some(i) => Err(FieldError::AppearanceOutOfRange { index: i, count: n }),
            None => Ok(self.fallback_embedding()),
        }
    }

    fn fallback_embedding(&self) -> Vec<f32> {
        let a = self.config.appearance_dim;
        let n = self.config.num_images;
        let mut e = vec![0f32; a];
        if self.config.appearance_fallback == AppearanceFallback::Mean && n > 0 {
            for row in self.appearance.chunks_exact(a) {
                for (x, y) in e.iter_mut().zip(row) {
                    *x += y / n as f32;
                }
            }
        }
        e
    }

    /// Forward pass for training: density and RGB of each sample, with saved activations.
    ///
    /// `appearance` is either empty (fallback embedding for every point) or one image index
    /// per point.
    pub fn forward_train(
        &self,
        points: &[[f32; 3]],
        dirs: &[[f32; 3]],
        appearance: &[u32],
    ) -> Result<TrainCache, FieldError> {
        let mut c = TrainCache::default();
        self.forward_train_into(points, dirs, appearance, &mut c)?;
        Ok(c)
    }

    /// [`Self::forward_train`] into an existing cache, reusing its buffers (a training loop
    /// keeps one cache across steps).
    pub fn forward_train_into(
        &self,
        points: &[[f32; 3]],
        dirs: &[[f32; 3]],
        appearance: &[u32],
        c: &mut TrainCache,
    ) -> Result<(), FieldError> {
        let n = points.len();
        check_len("dirs", n, dirs.len())?;
        if !appearance.is_empty() {
            check_len("appearance", n, appearance.len())?;
            if let Some(&bad) = appearance
                .iter()
                .find(|&&i| i as usize >= self.config.num_images)
            {
                return Err(FieldError::AppearanceOutOfRange {
                    index: bad,
                    count: self.config.num_images,
                });
            }
        }
        let ci = self.config.colour_input_dim();
        let sb = self.config.scene_box;
        let mut unit = std::mem::take(&mut c.unit);
        unit.clear();
        unit.par_extend(points.par_iter().map(|p| contract_to_unit(&sb, *p)));
        let mut app = std::mem::take(&mut c.app);
        app.clear();
        if appearance.is_empty() {
            app.resize(n, NO_APPEARANCE);
        } else {
            app.extend_from_slice(appearance);
        }
        // Every element of these is overwritten below, so stale values need no clearing;
        // `resize` only zero-fills growth.
        c.enc.resize(n * F_POS_DIM, 0.0);
        c.geo_h.resize(n * HIDDEN, 0.0);
        c.geo_out.resize(n * GEO_OUT, 0.0);
        c.col_in.resize(n * ci, 0.0);
        c.h1.resize(n * HIDDEN, 0.0);
        c.h2.resize(n * HIDDEN, 0.0);
        c.rgb.resize(n * 3, 0.0);
        c.density.resize(n, 0.0);
        let fallback = self.fallback_embedding();
        self.grid
            .encode_with_scratch(&unit, &mut c.enc, &mut c.scratch_lvl);
        {
            let chunks = Self::split_chunks(c, &unit, dirs, &app, ci);
            chunks
                .into_par_iter()
                .for_each(|ch| self.forward_chunk(ch, ci, &fallback));
        }
        c.unit = unit;
        c.app = app;
        Ok(())
    }

    fn split_chunks<'a>(
        c: &'a mut TrainCache,
        unit: &'a [[f32; 3]],
        dirs: &'a [[f32; 3]],
        app: &'a [u32],
        ci: usize,
    ) -> Vec<ChunkMut<'a>> {
        let k = MLP_CHUNK;
        let mut out = Vec::with_capacity(unit.len().div_ceil(k));
        let mut enc = c.enc.chunks_mut(k * F_POS_DIM);
        let mut geo_h = c.geo_h.chunks_mut(k * HIDDEN);
        let mut geo_out = c.geo_out.chunks_mut(k * GEO_OUT);
        let mut col_in = c.col_in.chunks_mut(k * ci.max(1));
        let mut h1 = c.h1.chunks_mut(k * HIDDEN);
        let mut h2 = c.h2.chunks_mut(k * HIDDEN);
        let mut rgb = c.rgb.chunks_mut(k * 3);
        let mut density = c.density.chunks_mut(k);
        for ((_, d), a) in unit.chunks(k).zip(dirs.chunks(k)).zip(app.chunks(k)) {
            // All iterators have exactly as many chunks as `unit`, so these never run dry.
            let (
                Some(enc),
                Some(geo_h),
                Some(geo_out),
                Some(col_in),
                Some(h1),
                Some(h2),
                Some(rgb),
                Some(density),
            ) = (
                enc.next(),
                geo_h.next(),
                geo_out.next(),
                col_in.next(),
                h1.next(),
                h2.next(),
                rgb.next(),
                density.next(),
            )
            else {
                break;
            };
            out.push(ChunkMut {
                dirs: d,
                app: a,
                enc,
                geo_h,
                geo_out,
                col_in,
                h1,
                h2,
                rgb,
                density,
            });
        }
        out
    }

    fn forward_chunk(&self, ch: ChunkMut<'_>, ci: usize, fallback: &[f32]) {
        let a_dim = self.config.appearance_dim;
        let scale = self.density_scale();
        self.geo[0].forward::<HIDDEN>(ch.enc, ch.geo_h, true);
        self.geo[1].forward::<GEO_OUT>(ch.geo_h, ch.geo_out, false);
        for (i, row) in ch.col_in.chunks_exact_mut(ci).enumerate() {
            row[..SH_DIM].copy_from_slice(&sh_encode(ch.dirs[i]));
            row[SH_DIM..SH_DIM + F_MLP_DIM]
                .copy_from_slice(&ch.geo_out[i * GEO_OUT + 1..(i + 1) * GEO_OUT]);
            let emb = match ch.app[i] {
                NO_APPEARANCE => fallback,
                j => &self.appearance[j as usize * a_dim..(j as usize + 1) * a_dim],
            };
            row[SH_DIM + F_MLP_DIM..].copy_from_slice(emb);
            ch.density[i] = scale * trunc_exp(ch.geo_out[i * GEO_OUT]);
        }
        self.col[0].forward::<HIDDEN>(ch.col_in, ch.h1, true);
        self.col[1].forward::<HIDDEN>(ch.h1, ch.h2, true);
        self.col[2].forward::<3>(ch.h2, ch.rgb, false);
        for v in ch.rgb.iter_mut() {
            *v = sigmoid(*v);
        }
    }

    /// Backward pass: accumulates parameter gradients into `grads` given `∂L/∂density`
    /// (`n`) and `∂L/∂rgb` (`n × 3`) for the points of `cache`.
    pub fn backward(
        &self,
        cache: &TrainCache,
        d_density: &[f32],
        d_rgb: &[f32],
        grads: &mut FieldGrads,
    ) -> Result<(), FieldError> {
        self.backward_impl(
            cache,
            d_density,
            d_rgb,
            grads,
            &mut Vec::new(),
            &mut Vec::new(),
        )
    }

    /// [`Self::backward`] using (and keeping) the cache's scratch buffers.
    pub fn backward_reusing(
        &self,
        cache: &mut TrainCache,
        d_density: &[f32],
        d_rgb: &[f32],
        grads: &mut FieldGrads,
    ) -> Result<(), FieldError> {
        let mut d_enc = std::mem::take(&mut cache.scratch_d_enc);
        let mut d_lvl = std::mem::take(&mut cache.scratch_lvl);
        let r = self.backward_impl(cache, d_density, d_rgb, grads, &mut d_enc, &mut d_lvl);
        cache.scratch_d_enc = d_enc;
        cache.scratch_lvl = d_lvl;
        r
    }

    fn backward_impl(
        &self,
        cache: &TrainCache,
        d_density: &[f32],
        d_rgb: &[f32],
        grads: &mut FieldGrads,
        d_enc: &mut Vec<f32>,
        d_lvl: &mut Vec<f32>,
    ) -> Result<(), FieldError> {
        let n = cache.len();
        check_len("d_density", n, d_density.len())?;
        check_len("d_rgb", 3 * n, d_rgb.len())?;
        let ci = self.config.colour_input_dim();
        let a_dim = self.config.appearance_dim;
        let scale = self.density_scale();
        let k = MLP_CHUNK;
        // Fully overwritten by the geometry MLP's input gradient, so not cleared.
        d_enc.resize(n * F_POS_DIM, 0.0);
        let wt_geo = [self.geo[0].transposed(), self.geo[1].transposed()];
        let wt_col = [
            self.col[0].transposed(),
            self.col[1].transposed(),
            self.col[2].transposed(),
        ];
        let new_acc = || BwdAcc {
            geo: [self.geo[0].zero_grad(), self.geo[1].zero_grad()],
            col: [
                self.col[0].zero_grad(),
                self.col[1].zero_grad(),
                self.col[2].zero_grad(),
            ],
            app: vec![0.0; self.appearance.len()],
            d_h2: vec![0.0; k * HIDDEN],
            d_h1: vec![0.0; k * HIDDEN],
            d_col_in: vec![0.0; k * ci],
            d_geo_out: vec![0.0; k * GEO_OUT],
            d_geo_h: vec![0.0; k * HIDDEN],
        };
        let acc = d_enc
            .par_chunks_mut(k * F_POS_DIM)
            .enumerate()
            .fold(new_acc, |mut acc, (ci_idx, d_enc_chunk)| {
                let s = ci_idx * k;
                let e = (s + k).min(n);
                let m = e - s;
                // Through the sigmoid.
                let mut d_z3 = [0f32; MLP_CHUNK * 3];
                for i in 0..3 * m {
                    let r = cache.rgb[3 * s + i];
                    d_z3[i] = d_rgb[3 * s + i] * r * (1.0 - r);
                }
                let h2 = &cache.h2[s * HIDDEN..e * HIDDEN];
                let h1 = &cache.h1[s * HIDDEN..e * HIDDEN];
                let col_in = &cache.col_in[s * ci..e * ci];
                let d_h2 = &mut acc.d_h2[..m * HIDDEN];
                self.col[2].backward_with(
                    h2,
                    &d_z3[..3 * m],
                    Some(d_h2),
                    &wt_col[2],
                    &mut acc.col[2],
                );
                relu_mask(h2, d_h2);
                let d_h1 = &mut acc.d_h1[..m * HIDDEN];
                self.col[1].backward_with(h1, d_h2, Some(d_h1), &wt_col[1], &mut acc.col[1]);
                relu_mask(h1, d_h1);
                let d_col_in = &mut acc.d_col_in[..m * ci];
                self.col[0].backward_with(
                    col_in,
                    d_h1,
                    Some(d_col_in),
                    &wt_col[0],
                    &mut acc.col[0],
                );
                let d_geo_out = &mut acc.d_geo_out[..m * GEO_OUT];
                for i in 0..m {
                    let raw = cache.geo_out[(s + i) * GEO_OUT];
                    d_geo_out[i * GEO_OUT] = d_density[s + i] * scale * trunc_exp_grad(raw);
                    d_geo_out[i * GEO_OUT + 1..(i + 1) * GEO_OUT]
                        .copy_from_slice(&d_col_in[i * ci + SH_DIM..i * ci + SH_DIM + F_MLP_DIM]);
                    let j = cache.app[s + i];
                    if j != NO_APPEARANCE && a_dim > 0 {
                        let g = &mut acc.app[j as usize * a_dim..(j as usize + 1) * a_dim];
                        for (gv, dv) in g
                            .iter_mut()
                            .zip(&d_col_in[i * ci + SH_DIM + F_MLP_DIM..(i + 1) * ci])
                        {
                            *gv += dv;
                        }
                    }
                }
                let geo_h = &cache.geo_h[s * HIDDEN..e * HIDDEN];
                let d_geo_h = &mut acc.d_geo_h[..m * HIDDEN];
                self.geo[1].backward_with(
                    geo_h,
                    d_geo_out,
                    Some(d_geo_h),
                    &wt_geo[1],
                    &mut acc.geo[1],
                );
                relu_mask(geo_h, d_geo_h);
                let enc = &cache.enc[s * F_POS_DIM..e * F_POS_DIM];
                self.geo[0].backward_with(
                    enc,
                    d_geo_h,
                    Some(d_enc_chunk),
                    &wt_geo[0],
                    &mut acc.geo[0],
                );
                acc
            })
            .map(|a| (a.geo, a.col, a.app))
            .reduce_with(|mut a, b| {
                for (x, y) in a.0.iter_mut().zip(&b.0) {
                    x.add(y);
                }
                for (x, y) in a.1.iter_mut().zip(&b.1) {
                    x.add(y);
                }
                for (x, y) in a.2.iter_mut().zip(&b.2) {
                    *x += y;
                }
                a
            });
        if let Some((geo, col, app)) = acc {
            for (x, y) in grads.geo.iter_mut().zip(&geo) {
                x.add(y);
            }
            for (x, y) in grads.col.iter_mut().zip(&col) {
                x.add(y);
            }
            for (x, y) in grads.appearance.iter_mut().zip(&app) {
                *x += y;
            }
        }
        self.grid
            .backward_with_scratch(&cache.unit, d_enc, &mut grads.table, d_lvl);
        Ok(())
    }
}

fn relu_mask(h: &[f32], d: &mut [f32]) {
    // A select rather than a conditional store, so the loop vectorises.
    for (dv, hv) in d.iter_mut().zip(h) {
        *dv = if *hv <= 0.0 { 0.0 } else { *dv };
    }
}

fn check_len(what: &'static str, expected: usize, actual: usize) -> Result<(), FieldError> {
    if expected == actual {
        Ok(())
    } else {
        Err(FieldError::LengthMismatch {
            what,
            expected,
            actual,
        })
    }
}

/// Points per inference work item.
const INFER_CHUNK: usize = 256;

impl FeatureField for NerfactoField {
    fn density_and_features(
        &self,
        points: &[[f32; 3]],
        dims: &[usize],
        density: &mut [f32],
        features: &mut [f32],
    ) -> Result<(), FieldError> {
        let n = points.len();
        check_len("density", n, density.len())?;
        check_len("features", n * dims.len(), features.len())?;
        if let Some(&d) = dims.iter().find(|&&d| d >= FEATURE_DIM) {
            return Err(FieldError::DimOutOfRange {
                dim: d,
                available: FEATURE_DIM,
            });
        }
        let nd = dims.len();
        let k = INFER_CHUNK;
        let scale = self.density_scale();
        let sb = self.config.scene_box;
        let unit: Vec<[f32; 3]> = points
            .par_iter()
            .map(|p| contract_to_unit(&sb, *p))
            .collect();
        let mut enc = vec![0f32; n * F_POS_DIM];
        self.grid.encode(&unit, &mut enc);
        // An empty `features` still needs one (empty) chunk per point chunk to zip with.
        let feat_chunks: Vec<&mut [f32]> = if nd == 0 {
            (0..n.div_ceil(k)).map(|_| &mut [][..]).collect()
        } else {
            features.chunks_mut(k * nd).collect()
        };
        enc.par_chunks(k * F_POS_DIM)
            .zip(density.par_chunks_mut(k))
            .zip(feat_chunks.into_par_iter())
            .for_each_init(
                || (vec![0f32; k * HIDDEN], vec![0f32; k * GEO_OUT]),
                |(h, out), ((enc, dens), feat)| {
                    let m = dens.len();
                    self.geo[0].forward::<HIDDEN>(enc, &mut h[..m * HIDDEN], true);
                    self.geo[1].forward::<GEO_OUT>(
                        &h[..m * HIDDEN],
                        &mut out[..m * GEO_OUT],
                        false,
                    );
                    for i in 0..m {
                        dens[i] = scale * trunc_exp(out[i * GEO_OUT]);
                        for (j, &d) in dims.iter().enumerate() {
                            feat[i * nd + j] = if d < F_POS_DIM {
                                enc[i * F_POS_DIM + d]
                            } else {
                                out[i * GEO_OUT + 1 + (d - F_POS_DIM)]
                            };
                        }
                    }
                },
            );
        Ok(())
    }

    fn colour(
        &self,
        f_mlp: &[f32],
        directions: &[[f32; 3]],
        appearance: Option<u32>,
        rgb: &mut [f32],
    ) -> Result<(), FieldError> {
        let n = directions.len();
        check_len("f_mlp", n * F_MLP_DIM, f_mlp.len())?;
        check_len("rgb", n * 3, rgb.len())?;
        let emb = self.embedding(appearance)?;
        let ci = self.config.colour_input_dim();
        let k = INFER_CHUNK;
        directions
            .par_chunks(k)
            .zip(f_mlp.par_chunks(k * F_MLP_DIM))
            .zip(rgb.par_chunks_mut(k * 3))
            .for_each_init(
                || {
                    (
                        vec![0f32; k * ci],
                        vec![0f32; k * HIDDEN],
                        vec![0f32; k * HIDDEN],
                    )
                },
                |(xin, h1, h2), ((dirs, f), out)| {
                    let m = dirs.len();
                    for (i, row) in xin.chunks_exact_mut(ci).take(m).enumerate() {
                        row[..SH_DIM].copy_from_slice(&sh_encode(dirs[i]));
                        row[SH_DIM..SH_DIM + F_MLP_DIM]
                            .copy_from_slice(&f[i * F_MLP_DIM..(i + 1) * F_MLP_DIM]);
                        row[SH_DIM + F_MLP_DIM..].copy_from_slice(&emb);
                    }
                    self.col[0].forward::<HIDDEN>(&xin[..m * ci], &mut h1[..m * HIDDEN], true);
                    self.col[1].forward::<HIDDEN>(&h1[..m * HIDDEN], &mut h2[..m * HIDDEN], true);
                    self.col[2].forward::<3>(&h2[..m * HIDDEN], out, false);
                    for v in out.iter_mut() {
                        *v = sigmoid(*v);
                    }
                },
            );
        Ok(())
    }
}

impl NerfactoField {
    /// `∂L/∂x_world` for each point given `∂L/∂density` and `∂L/∂f_pos` (`n × 32`, may be
    /// empty): chains through the geometry MLP, the hash grid and the contraction. Intended
    /// for pose refinement; finite differences are used for the contraction Jacobian.
    pub fn density_input_gradient(
        &self,
        points: &[[f32; 3]],
        d_density: &[f32],
    ) -> Result<Vec<[f32; 3]>, FieldError> {
        let n = points.len();
        check_len("d_density", n, d_density.len())?;
        let sb = self.config.scene_box;
        let unit: Vec<[f32; 3]> = points.iter().map(|p| contract_to_unit(&sb, *p)).collect();
        let mut enc = vec![0f32; n * F_POS_DIM];
        self.grid.encode(&unit, &mut enc);
        let mut h = vec![0f32; n * HIDDEN];
        let mut out = vec![0f32; n * GEO_OUT];
        self.geo[0].forward::<HIDDEN>(&enc, &mut h, true);
        self.geo[1].forward::<GEO_OUT>(&h, &mut out, false);
        let mut d_out = vec![0f32; n * GEO_OUT];
        for i in 0..n {
            d_out[i * GEO_OUT] =
                d_density[i] * self.density_scale() * trunc_exp_grad(out[i * GEO_OUT]);
        }
        let mut d_h = vec![0f32; n * HIDDEN];
        let mut scratch1 = self.geo[1].zero_grad();
        self.geo[1].backward(&h, &d_out, Some(&mut d_h), &mut scratch1);
        relu_mask(&h, &mut d_h);
        let mut d_enc = vec![0f32; n * F_POS_DIM];
        let mut scratch0 = self.geo[0].zero_grad();
        self.geo[0].backward(&enc, &d_h, Some(&mut d_enc), &mut scratch0);
        let d_unit = self.grid.input_gradient(&unit, &d_enc);
        // Chain through the (piecewise smooth) contraction with a central-difference Jacobian.
        Ok(points
            .iter()
            .zip(&d_unit)
            .map(|(p, du)| {
                let mut g = [0f32; 3];
                for a in 0..3 {
                    let eps = 1e-3 * (sb.max[a] - sb.min[a]);
                    let mut pp = *p;
                    let mut pm = *p;
                    pp[a] += eps;
                    pm[a] -= eps;
                    let up = contract_to_unit(&sb, pp);
                    let um = contract_to_unit(&sb, pm);
                    g[a] = (0..3).map(|b| du[b] * (up[b] - um[b]) / (2.0 * eps)).sum();
                }
                g
            })
            .collect())
    }
}
