//! The query encoder: a small CNN (burn, `flex` CPU backend) mapping an RGB image to a dense
//! feature map in the NeRF feature domain at the rendering grid's stride (4: a 320 × 240 image
//! gives 80 × 60 cells, cell `(c, r)` at pixel `(4c + 2, 4r + 2)` like [`matloc_match::grid_size`]).
//!
//! Trained from scratch (no pretrained weights are available here) on training images with the
//! features rendered at their true poses as targets ([`train_encoder`]). Everything is in the
//! *standardised* feature domain: targets are standardised per dim with the map's statistics
//! ([`FeatureStats`]), the network predicts standardised values, and [`QueryEncoder::encode`]
//! returns raw-domain features (`mean + std · prediction`), so the matcher applies the same
//! standardisation + L2 to both sides. Loss: `w_reg · MSE + w_nce · InfoNCE` where InfoNCE
//! contrasts each sampled cell's L2-normalised prediction against the normalised targets of the
//! other sampled cells of the same image (temperature `τ`).
//!
//! Input: the RGB image with each channel standardised by its own mean and spread
//! ([`EncoderConfig::standardize_input`]), so exposure and white balance divide out; or, as an
//! option, its two shadow-invariant channels ([`EncoderConfig::shadow_invariant`]).
//! Architecture: two stride-2 3 × 3 convolutions (3 → w/2 → w), then dilated 3 × 3 residual
//! blocks (dilations 1, 2, 4, 8 by default) for a ~70 px receptive field, then a per-cell MLP
//! head ([`EncoderConfig::head_hidden`]). Training runs end to end, then optionally trains the
//! head alone on a buffer of the frozen trunk's cell features ([`HeadPhaseConfig`]); measured in
//! docs/BENCHMARKS.md (`research/examples/encoder_study.rs`). Checkpoints are format 2
//! ([`CHECKPOINT_KEY`]); format-1 files are refused with a typed error.

mod augment;
mod input;

pub use augment::JitterConfig;
use augment::jitter;
use burn::module::Module;
use burn::nn::PaddingConfig2d;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Linear, LinearConfig};
use burn::optim::{AdamConfig, GradientsParams};
use burn::prelude::*;
use burn::store::{ModuleSnapshot, SafetensorsStore};
use burn::tensor::activation::{log_softmax, relu};
use input::input_channels;
pub use input::{local_contrast, shadow_invariant};
use matloc_core::{FeatureMap, Image};
use matloc_match::FeatureStats;
use matloc_match::RenderedView;
use rand::SeedableRng;
use rand::seq::index::sample;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Output stride of the encoder (image pixels per feature cell).
pub const ENCODER_STRIDE: u32 = 4;

/// Safetensors metadata key of the checkpoint format (2: trunk + per-cell MLP head). Format 1
/// files (key `matloc_encoder`, a 1 × 1 convolution head) are refused with
/// [`EncoderError::Format`].
pub const CHECKPOINT_KEY: &str = "matloc_encoder_v2";

/// Why the encoder could not be trained, run, saved or loaded.
#[derive(Debug, Error)]
pub enum EncoderError {
    /// The encoder predicts a different number of dims than the field provides.
    #[error("dimension mismatch: encoder has {encoder} dims, field features have {field}")]
    DimensionMismatch {
        /// Encoder output dims.
        encoder: usize,
        /// Field dims offered.
        field: usize,
    },
    /// An image is not RGB or too small, or a target grid does not fit its image.
    #[error("bad input: {0}")]
    BadInput(String),
    /// No training samples.
    #[error("no training samples")]
    NoSamples,
    /// Configuration out of range.
    #[error("invalid encoder config: {0}")]
    InvalidConfig(String),
    /// File I/O.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The checkpoint is not valid.
    #[error("{path}: invalid encoder checkpoint: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// Network shape.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EncoderConfig {
    /// Channels after the stem.
    pub width: usize,
    /// Dilations of the residual blocks at stride 4.
    pub dilations: Vec<usize>,
    /// Hidden widths of the per-cell MLP head (ReLU between layers); empty: a single linear
    /// layer from the trunk to the output dims.
    pub head_hidden: Vec<usize>,
    /// Feed the network, besides the RGB image, its local contrast: each channel's linear light
    /// divided by its 13 × 13 local mean, as a log ratio ([`local_contrast`]). Shading that is
    /// smooth over the window — a cast shadow's interior, exposure, white balance — divides
    /// out, so a query under another sun keeps its texture. Off by default: on `small` it did
    /// not help the second flight and cost same-flight accuracy (docs/DECISIONS.md, "Queries
    /// from another flight").
    #[serde(default)]
    pub local_contrast: bool,
    /// Replace the RGB channels by the two channels of the log-linear colour orthogonal to the
    /// lit-to-shadow direction ([`shadow_invariant`]): a surface moving into or out of a cast
    /// shadow (losing its sunlight, keeping the bluer sky light) keeps its value there, so
    /// shadows of another sun neither appear nor vanish in what the network sees.
    #[serde(default)]
    pub shadow_invariant: bool,
    /// Standardise each RGB channel of every image (training and query) by its own mean and
    /// spread before the network sees it: an exposure or white-balance change is a per-channel
    /// gain, which this divides out. On by default (docs/DECISIONS.md, "The encoder
    /// standardises its input"); checkpoints written without the field ran without it.
    #[serde(default = "standardize_by_default")]
    pub standardize_input: bool,
}

impl Default for EncoderConfig {
    fn default() -> Self {
        EncoderConfig {
            width: 48,
            dilations: vec![1, 2, 4, 8],
            head_hidden: vec![128, 128],
            local_contrast: false,
            shadow_invariant: false,
            standardize_input: true,
        }
    }
}

fn standardize_by_default() -> bool {
    true
}

#[derive(Module, Debug)]
struct Block {
    conv: Conv2d,
}

/// Convolutional trunk: image → `width` channels at stride 4.
#[derive(Module, Debug)]
struct Trunk {
    stem1: Conv2d,
    stem2: Conv2d,
    blocks: Vec<Block>,
}

/// Per-cell MLP on the last axis (`[..., width]` → `[..., dims]`).
#[derive(Module, Debug)]
struct Head {
    hidden: Vec<Linear>,
    out: Linear,
}

#[derive(Module, Debug)]
struct Net {
    trunk: Trunk,
    head: Head,
}

impl Trunk {
    fn new(cfg: &EncoderConfig, device: &Device) -> Self {
        let w = cfg.width;
        let conv = |cin: usize, cout: usize, k: usize, stride: usize, dil: usize| {
            let pad = dil * (k / 2);
            Conv2dConfig::new([cin, cout], [k, k])
                .with_stride([stride, stride])
                .with_dilation([dil, dil])
                .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
                .init(device)
        };
        Trunk {
            stem1: conv(input_channels(cfg), w / 2, 3, 2, 1),
            stem2: conv(w / 2, w, 3, 2, 1),
            blocks: cfg
                .dilations
                .iter()
                .map(|&d| Block {
                    conv: conv(w, w, 3, 1, d.max(1)),
                })
                .collect(),
        }
    }

    /// `[B, 3, H, W]` → `[B, width, ⌈H/4⌉, ⌈W/4⌉]`.
    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let mut h = relu(self.stem1.forward(x));
        h = relu(self.stem2.forward(h));
        for b in &self.blocks {
            h = h.clone() + relu(b.conv.forward(h));
        }
        h
    }
}

impl Head {
    fn new(cfg: &EncoderConfig, out_dims: usize, device: &Device) -> Self {
        let mut cin = cfg.width;
        let mut hidden = Vec::new();
        for &h in &cfg.head_hidden {
            hidden.push(LinearConfig::new(cin, h).init(device));
            cin = h;
        }
        Head {
            hidden,
            out: LinearConfig::new(cin, out_dims).init(device),
        }
    }

    fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let mut h = x;
        for l in &self.hidden {
            h = relu(l.forward(h));
        }
        self.out.forward(h)
    }
}

impl Net {
    fn new(cfg: &EncoderConfig, out_dims: usize, device: &Device) -> Self {
        Net {
            trunk: Trunk::new(cfg, device),
            head: Head::new(cfg, out_dims, device),
        }
    }

    /// `[B, 3, H, W]` → `[B, dims, ⌈H/4⌉, ⌈W/4⌉]`.
    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let h = self.trunk.forward(x).permute([0, 2, 3, 1]);
        self.head.forward(h).permute([0, 3, 1, 2])
    }
}

/// Training settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EncoderTrainConfig {
    /// Network shape.
    pub net: EncoderConfig,
    /// Optimiser steps.
    pub steps: usize,
    /// Images per step.
    pub batch: usize,
    /// Adam learning rate (cosine-decayed to 5 % over the run).
    pub learning_rate: f64,
    /// Weight of the regression (MSE) term.
    pub w_reg: f32,
    /// Weight of the InfoNCE term.
    pub w_nce: f32,
    /// InfoNCE temperature.
    pub temperature: f32,
    /// Cells sampled per image for InfoNCE.
    pub nce_cells: usize,
    /// Targets with less accumulation are ignored.
    pub min_accumulation: f32,
    /// Augmentation.
    pub jitter: JitterConfig,
    /// Seed of initialisation order, batches, jitter and cell sampling.
    pub seed: u64,
    /// Second phase: the head alone on a buffer of trunk features.
    pub head_phase: HeadPhaseConfig,
}

/// Second training phase (after [`EncoderTrainConfig::steps`] end-to-end steps): the trunk is
/// frozen, every training image (and `copies − 1` jittered copies) is run through it once, and
/// the per-cell MLP head is trained on random cells of that buffer, `images` images × `cells`
/// cells per step, with the same loss (InfoNCE within each image's cells). The idea of scene
/// coordinate regression's ACE (a head trained on a shuffled buffer of backbone features): a
/// head step costs a few matrix products instead of a full-image convolution pass, so it sees
/// many more cells per second.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HeadPhaseConfig {
    /// Head-only steps (0: no second phase).
    pub steps: usize,
    /// Images per step.
    pub images: usize,
    /// Cells per image per step.
    pub cells: usize,
    /// Adam learning rate (cosine-decayed to 5 % over the phase).
    pub learning_rate: f64,
    /// Buffer copies of each image (the first unjittered).
    pub copies: usize,
}

impl Default for HeadPhaseConfig {
    fn default() -> Self {
        HeadPhaseConfig {
            steps: 0,
            images: 8,
            cells: 256,
            learning_rate: 1e-3,
            copies: 1,
        }
    }
}

impl EncoderTrainConfig {
    /// Steps of both phases (what [`EncoderProgress::steps`] reports).
    pub fn total_steps(&self) -> usize {
        self.steps + self.head_phase.steps
    }
}

impl Default for EncoderTrainConfig {
    fn default() -> Self {
        EncoderTrainConfig {
            net: EncoderConfig::default(),
            steps: 300,
            batch: 2,
            learning_rate: 3e-3,
            w_reg: 1.0,
            w_nce: 0.5,
            temperature: 0.1,
            nce_cells: 256,
            min_accumulation: 0.5,
            jitter: JitterConfig::default(),
            seed: 0,
            head_phase: HeadPhaseConfig::default(),
        }
    }
}

/// One training image and the features rendered at its true pose (stride 4 grid, the dims the
/// encoder predicts in [`QueryEncoder::dims`] order).
#[derive(Clone, Debug)]
pub struct EncoderSample {
    /// RGB image, `H × W × 3`, values in `[0, 1]`.
    pub image: Image<f32>,
    /// Rendered targets.
    pub target: RenderedView,
    /// Camera and scene up of the view, when known: augmentation then casts shadows of the
    /// view's own geometry (the target's depth) under random suns.
    pub view: Option<SampleView>,
}

/// Where a training image was taken, for geometry-aware augmentation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SampleView {
    /// Intrinsics at the image's size.
    pub camera: matloc_core::Camera,
    /// The scene's up direction in camera coordinates (unit).
    pub up_cam: [f64; 3],
}

/// Reported after every step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EncoderProgress {
    /// Steps done (both phases).
    pub step: usize,
    /// Total steps ([`EncoderTrainConfig::total_steps`]).
    pub steps: usize,
    /// Total loss of the step.
    pub loss: f32,
    /// Regression term.
    pub mse: f32,
    /// InfoNCE term.
    pub nce: f32,
}

/// A trained query encoder (inference on the plain `flex` device).
#[derive(Debug)]
pub struct QueryEncoder {
    config: EncoderConfig,
    dims: Vec<usize>,
    stats: FeatureStats,
    net: Net,
}

fn image_tensor(
    images: &[Image<f32>],
    cfg: &EncoderConfig,
    device: &Device,
) -> Result<Tensor<4>, EncoderError> {
    let (w, h, _) = images[0].shape();
    let c = input_channels(cfg);
    let mut data = Vec::with_capacity(images.len() * c * h * w);
    for img in images {
        if img.shape().0 != w || img.shape().1 != h {
            return Err(EncoderError::BadInput("images of different sizes".into()));
        }
        data.extend(input::planes(img, cfg)?);
    }
    Ok(Tensor::<4>::from_data(
        TensorData::new(data, [images.len(), c, h, w]),
        device,
    ))
}

/// Crops the network output to the rendering grid (`⌊H/4⌋ × ⌊W/4⌋`).
fn crop(out: Tensor<4>, rows: usize, cols: usize) -> Tensor<4> {
    let [b, d, _, _] = out.dims();
    out.slice([0..b, 0..d, 0..rows, 0..cols])
}

impl QueryEncoder {
    /// Field dims the encoder predicts, in output channel order.
    pub fn dims(&self) -> &[usize] {
        &self.dims
    }

    /// Standardisation statistics (one entry per predicted dim).
    pub fn stats(&self) -> &FeatureStats {
        &self.stats
    }

    /// Network shape.
    pub fn config(&self) -> &EncoderConfig {
        &self.config
    }

    /// Checks that the encoder predicts exactly `field_dims` (e.g. the map's selected dims).
    pub fn check_dims(&self, field_dims: &[usize]) -> Result<(), EncoderError> {
        if self.dims != field_dims {
            return Err(EncoderError::DimensionMismatch {
                encoder: self.dims.len(),
                field: field_dims.len(),
            });
        }
        Ok(())
    }

    /// Raw-domain feature map (`⌊H/4⌋ × ⌊W/4⌋ × dims`) of an RGB image.
    pub fn encode(&self, image: &Image<f32>) -> Result<FeatureMap, EncoderError> {
        let device = Device::flex();
        let x = image_tensor(std::slice::from_ref(image), &self.config, &device)?;
        let (rows, cols) = (
            image.height() / ENCODER_STRIDE as usize,
            image.width() / ENCODER_STRIDE as usize,
        );
        let out = crop(self.net.forward(x), rows, cols);
        let d = self.dims.len();
        let v: Vec<f32> = out
            .into_data()
            .try_into_vec()
            .map_err(|e| EncoderError::BadInput(format!("{e:?}")))?;
        let mut map = FeatureMap::new(cols, rows, d);
        let buf = map.data_mut();
        for k in 0..d {
            let (m, s) = (self.stats.mean[k], self.stats.std[k]);
            for i in 0..rows * cols {
                buf[i * d + k] = m + s * v[k * rows * cols + i];
            }
        }
        Ok(map)
    }

    fn to_bytes(&self) -> Result<Vec<u8>, String> {
        let meta = serde_json::to_string(&(&self.config, &self.dims, &self.stats))
            .map_err(|e| e.to_string())?;
        let mut store = SafetensorsStore::from_bytes(None).metadata(CHECKPOINT_KEY, meta);
        self.net
            .save_into(&mut store)
            .map_err(|e| format!("{e:?}"))?;
        store.get_bytes().map_err(|e| format!("{e:?}"))
    }

    /// Writes weights (safetensors) with the shape, dims and statistics as metadata, atomically.
    pub fn save(&self, path: &Path) -> Result<(), EncoderError> {
        let bytes = self.to_bytes().map_err(|reason| EncoderError::Format {
            path: path.to_path_buf(),
            reason,
        })?;
        matloc_core::fsutil::write_atomic(path, &bytes).map_err(|source| EncoderError::Io {
            path: path.to_path_buf(),
            source,
        })
    }

    /// Reads a checkpoint written by [`QueryEncoder::save`].
    pub fn load(path: &Path) -> Result<Self, EncoderError> {
        let bytes = std::fs::read(path).map_err(|source| EncoderError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let bad = |reason: String| EncoderError::Format {
            path: path.to_path_buf(),
            reason,
        };
        let (_, meta) =
            safetensors::SafeTensors::read_metadata(&bytes).map_err(|e| bad(e.to_string()))?;
        let entries = meta.metadata().as_ref();
        let json = match entries.and_then(|m| m.get(CHECKPOINT_KEY)) {
            Some(j) => j,
            None if entries.is_some_and(|m| m.contains_key("matloc_encoder")) => {
                return Err(bad(
                    "format 1 (convolutional head, before format 2's MLP head): retrain the encoder"
                        .into(),
                ));
            }
            None => return Err(bad(format!("no {CHECKPOINT_KEY} metadata"))),
        };
        let meta: serde_json::Value = serde_json::from_str(json).map_err(|e| bad(e.to_string()))?;
        // Encoders trained before input standardisation existed fed the raw image.
        let legacy_input = meta[0].get("standardize_input").is_none();
        let (mut config, dims, stats): (EncoderConfig, Vec<usize>, FeatureStats) =
            serde_json::from_value(meta).map_err(|e| bad(e.to_string()))?;
        if legacy_input {
            config.standardize_input = false;
        }
        if stats.mean.len() != dims.len() || stats.std.len() != dims.len() || dims.is_empty() {
            return Err(bad("statistics do not match the dims".into()));
        }
        let device = Device::flex();
        let mut net = Net::new(&config, dims.len(), &device);
        let mut store = SafetensorsStore::from_bytes(Some(bytes));
        net.load_from(&mut store)
            .map_err(|e| bad(format!("{e:?}")))?;
        Ok(QueryEncoder {
            config,
            dims,
            stats,
            net: net.valid(),
        })
    }
}

/// Trains an encoder predicting field `dims` (the target views hold exactly these dims, in this
/// order) with standardisation `stats` (one entry per dim, from the map's rendered features).
pub fn train_encoder(
    samples: &[EncoderSample],
    dims: Vec<usize>,
    stats: FeatureStats,
    cfg: &EncoderTrainConfig,
    progress: &mut dyn FnMut(&EncoderProgress),
) -> Result<QueryEncoder, EncoderError> {
    if samples.is_empty() {
        return Err(EncoderError::NoSamples);
    }
    let d = dims.len();
    if d == 0 || stats.mean.len() != d || stats.std.len() != d {
        return Err(EncoderError::InvalidConfig(format!(
            "{d} dims with {} / {} statistics",
            stats.mean.len(),
            stats.std.len()
        )));
    }
    if cfg.batch == 0
        || cfg.net.width < 2
        || cfg.temperature.is_nan()
        || cfg.temperature <= 0.0
        || cfg.steps == 0
    {
        return Err(EncoderError::InvalidConfig(
            "batch, steps, width and temperature must be positive".into(),
        ));
    }
    cfg.jitter.validate().map_err(EncoderError::InvalidConfig)?;
    let (w, h, _) = samples[0].image.shape();
    let (cols, rows) = (w / ENCODER_STRIDE as usize, h / ENCODER_STRIDE as usize);
    for s in samples {
        if s.target.dims != d {
            return Err(EncoderError::DimensionMismatch {
                encoder: d,
                field: s.target.dims,
            });
        }
        if s.image.shape() != (w, h, 3) || s.target.cols != cols || s.target.rows != rows {
            return Err(EncoderError::BadInput(format!(
                "every sample needs a {w} x {h} RGB image and a {cols} x {rows} target grid"
            )));
        }
    }
    let cells = rows * cols;
    // Standardised, channel-major targets and validity masks, prepared once.
    let targets: Vec<(Vec<f32>, Vec<f32>, Vec<usize>)> = samples
        .iter()
        .map(|s| {
            let mut t = vec![0.0f32; d * cells];
            let mut mask = vec![0.0f32; cells];
            let mut valid = Vec::new();
            for i in 0..cells {
                if s.target.has_surface(i, cfg.min_accumulation) {
                    mask[i] = 1.0;
                    valid.push(i);
                    for k in 0..d {
                        let sd = stats.std[k];
                        let v = s.target.features[i * d + k];
                        t[k * cells + i] = if sd > 1e-12 {
                            (v - stats.mean[k]) / sd
                        } else {
                            0.0
                        };
                    }
                }
            }
            (t, mask, valid)
        })
        .collect();
    let device = Device::flex().autodiff();
    // Weight initialisation draws from the backend's generator: seeded, so that the same
    // samples and config train the same encoder (a map built by block jobs equals one built
    // in one process), under the process-wide lock so a concurrent training cannot draw in
    // between.
    let mut net =
        matloc_core::backend::seeded_module(&device, cfg.seed, || Net::new(&cfg.net, d, &device));
    let mut optim = AdamConfig::new().init();
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let bsz = cfg.batch.min(samples.len());
    for step in 0..cfg.steps {
        let picks = sample(&mut rng, samples.len(), bsz).into_vec();
        let imgs: Vec<Image<f32>> = picks
            .iter()
            .map(|&p| jitter(&samples[p], &cfg.jitter, &mut rng))
            .collect();
        let x = image_tensor(&imgs, &cfg.net, &device)?;
        let mut tdata = Vec::with_capacity(bsz * d * cells);
        let mut mdata = Vec::with_capacity(bsz * cells);
        for &p in &picks {
            tdata.extend_from_slice(&targets[p].0);
            mdata.extend_from_slice(&targets[p].1);
        }
        let target = Tensor::<4>::from_data(TensorData::new(tdata, [bsz, d, rows, cols]), &device);
        let mask = Tensor::<4>::from_data(TensorData::new(mdata, [bsz, 1, rows, cols]), &device);
        let pred = crop(net.forward(x), rows, cols);
        let n_valid: f32 = picks.iter().map(|&p| targets[p].2.len() as f32).sum();
        let diff = (pred.clone() - target.clone()) * mask;
        let mse = diff
            .square()
            .sum()
            .div_scalar((n_valid * d as f32).max(1.0));
        let mut loss = mse.clone().mul_scalar(cfg.w_reg);
        let mut nce_total = 0.0f32;
        if cfg.w_nce > 0.0 {
            let mut nce_terms = Vec::new();
            for (b, &p) in picks.iter().enumerate() {
                let valid = &targets[p].2;
                let k = cfg.nce_cells.min(valid.len());
                if k < 2 {
                    continue;
                }
                let idx: Vec<i64> = sample(&mut rng, valid.len(), k)
                    .into_iter()
                    .map(|j| valid[j] as i64)
                    .collect();
                let idx_t = Tensor::<1, Int>::from_data(TensorData::new(idx, [k]), &device);
                let flat = |t: &Tensor<4>| {
                    t.clone()
                        .slice([b..b + 1, 0..d, 0..rows, 0..cols])
                        .reshape([d, cells])
                        .swap_dims(0, 1)
                        .select(0, idx_t.clone())
                        .reshape([1, k, d])
                };
                nce_terms.push(info_nce(
                    flat(&pred),
                    flat(&target),
                    cfg.temperature,
                    &device,
                ));
            }
            if !nce_terms.is_empty() {
                let n = nce_terms.len() as f32;
                let nce = Tensor::cat(nce_terms, 0).sum().div_scalar(n);
                nce_total = nce.clone().into_scalar_f32();
                loss = loss + nce.mul_scalar(cfg.w_nce);
            }
        }
        let mse_v = mse.into_scalar_f32();
        let loss_v = loss.clone().into_scalar_f32();
        let grads = GradientsParams::from_grads(loss.backward(), &net);
        let t = step as f64 / cfg.steps.max(1) as f64;
        let lr = cosine_lr(cfg.learning_rate, t);
        net = optim.step(lr, net, grads);
        progress(&EncoderProgress {
            step: step + 1,
            steps: cfg.total_steps(),
            loss: loss_v,
            mse: mse_v,
            nce: nce_total,
        });
    }
    if cfg.head_phase.steps > 0 {
        let head = train_head(
            &net.trunk.valid(),
            net.head,
            samples,
            &targets,
            (rows, cols, d),
            cfg,
            &mut rng,
            progress,
        )?;
        net = Net {
            trunk: net.trunk,
            head,
        };
    }
    Ok(QueryEncoder {
        config: cfg.net.clone(),
        dims,
        stats,
        net: net.valid(),
    })
}

/// Learning rate at fraction `t` of a phase: cosine decay from `base` to 5 % of it.
fn cosine_lr(base: f64, t: f64) -> f64 {
    base * (0.05 + 0.95 * 0.5 * (1.0 + (std::f64::consts::PI * t).cos()))
}

/// InfoNCE of `[G, K, D]` predictions against targets: within each of the `G` groups, cell
/// `i`'s prediction must pick target `i` among the group's `K` (cosine similarity over
/// `temperature`); mean over all `G · K` cells, as a `[1]` tensor.
fn info_nce(pred: Tensor<3>, target: Tensor<3>, temperature: f32, device: &Device) -> Tensor<1> {
    let [g, k, _] = pred.dims();
    let norm = |t: Tensor<3>| {
        let n = t.clone().square().sum_dim(2).sqrt().add_scalar(1e-6);
        t / n
    };
    let logits = norm(pred)
        .matmul(norm(target).swap_dims(1, 2))
        .div_scalar(temperature);
    let eye = Tensor::<2>::eye(k, device).reshape([1, k, k]);
    (log_softmax(logits, 2) * eye)
        .sum()
        .div_scalar(-((g * k) as f32))
        .reshape([1])
}

/// Per-image buffer of the second phase: row-major trunk features and standardised targets of
/// the valid cells.
struct CellBuffer {
    features: Vec<f32>,
    targets: Vec<f32>,
    n: usize,
}

/// The second phase (see [`HeadPhaseConfig`]); `targets` are the prepared channel-major
/// standardised targets and valid cells of `samples`.
#[allow(clippy::too_many_arguments)]
fn train_head(
    trunk: &Trunk,
    mut head: Head,
    samples: &[EncoderSample],
    targets: &[(Vec<f32>, Vec<f32>, Vec<usize>)],
    (rows, cols, d): (usize, usize, usize),
    cfg: &EncoderTrainConfig,
    rng: &mut ChaCha8Rng,
    progress: &mut dyn FnMut(&EncoderProgress),
) -> Result<Head, EncoderError> {
    let hc = &cfg.head_phase;
    if hc.images == 0 || hc.cells < 2 || hc.copies == 0 {
        return Err(EncoderError::InvalidConfig(
            "head phase needs images >= 1, cells >= 2, copies >= 1".into(),
        ));
    }
    let plain = Device::flex();
    let width = cfg.net.width;
    let cells = rows * cols;
    let mut buffers = Vec::with_capacity(samples.len() * hc.copies);
    for copy in 0..hc.copies {
        for chunk in (0..samples.len()).collect::<Vec<_>>().chunks(4) {
            let imgs: Vec<Image<f32>> = chunk
                .iter()
                .map(|&p| {
                    if copy == 0 {
                        samples[p].image.clone()
                    } else {
                        jitter(&samples[p], &cfg.jitter, rng)
                    }
                })
                .collect();
            let x = image_tensor(&imgs, &cfg.net, &plain)?;
            let f = crop(trunk.forward(x), rows, cols);
            let v: Vec<f32> = f
                .into_data()
                .try_into_vec()
                .map_err(|e| EncoderError::BadInput(format!("{e:?}")))?;
            for (b, &p) in chunk.iter().enumerate() {
                let (t, _, valid) = &targets[p];
                let base = b * width * cells;
                let mut features = Vec::with_capacity(valid.len() * width);
                let mut tgt = Vec::with_capacity(valid.len() * d);
                for &i in valid {
                    features.extend((0..width).map(|k| v[base + k * cells + i]));
                    tgt.extend((0..d).map(|k| t[k * cells + i]));
                }
                buffers.push(CellBuffer {
                    features,
                    targets: tgt,
                    n: valid.len(),
                });
            }
        }
    }
    buffers.retain(|b| b.n >= 2);
    if buffers.is_empty() {
        return Err(EncoderError::NoSamples);
    }
    let device = Device::flex().autodiff();
    let mut optim = AdamConfig::new().init();
    let g = hc.images.min(buffers.len());
    for step in 0..hc.steps {
        let picks = sample(rng, buffers.len(), g).into_vec();
        let k = picks
            .iter()
            .map(|&p| buffers[p].n)
            .min()
            .unwrap_or(0)
            .min(hc.cells);
        let mut x = Vec::with_capacity(g * k * width);
        let mut y = Vec::with_capacity(g * k * d);
        for &p in &picks {
            let b = &buffers[p];
            for i in sample(rng, b.n, k) {
                x.extend_from_slice(&b.features[i * width..(i + 1) * width]);
                y.extend_from_slice(&b.targets[i * d..(i + 1) * d]);
            }
        }
        let x = Tensor::<3>::from_data(TensorData::new(x, [g, k, width]), &device);
        let y = Tensor::<3>::from_data(TensorData::new(y, [g, k, d]), &device);
        let pred = head.forward(x);
        let mse = (pred.clone() - y.clone()).square().mean().reshape([1]);
        let mut loss = mse.clone().mul_scalar(cfg.w_reg);
        let mut nce_v = 0.0;
        if cfg.w_nce > 0.0 {
            let nce = info_nce(pred, y, cfg.temperature, &device);
            nce_v = nce.clone().into_scalar_f32();
            loss = loss + nce.mul_scalar(cfg.w_nce);
        }
        let mse_v = mse.into_scalar_f32();
        let loss_v = loss.clone().into_scalar_f32();
        let grads = GradientsParams::from_grads(loss.backward(), &head);
        let t = step as f64 / hc.steps as f64;
        let lr = cosine_lr(hc.learning_rate, t);
        head = optim.step(lr, head, grads);
        progress(&EncoderProgress {
            step: cfg.steps + step + 1,
            steps: cfg.total_steps(),
            loss: loss_v,
            mse: mse_v,
            nce: nce_v,
        });
    }
    Ok(head)
}

trait ScalarF32 {
    fn into_scalar_f32(self) -> f32;
}

impl ScalarF32 for Tensor<1> {
    fn into_scalar_f32(self) -> f32 {
        self.into_data()
            .try_into_vec::<f32>()
            .ok()
            .and_then(|v| v.first().copied())
            .unwrap_or(f32::NAN)
    }
}
