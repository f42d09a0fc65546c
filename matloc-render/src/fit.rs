//! Dataset-level training and evaluation: random rays from every training image, periodic
//! atomic checkpoints with resume, and test-view metrics (PSNR, SSIM, depth error).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use matloc_core::{Camera, Image};
use matloc_data::images::{load_frame_depth, load_frame_image};
use matloc_data::{Dataset, Split};
use matloc_nerf_field::NerfactoField;
use nalgebra::{Isometry3, Point2};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use safetensors::SafeTensors;

use crate::error::RenderError;
use crate::model::{
    CONFIG_FILE, ModelConfig, NerfModel, config_differences, read, read_tensor, serialize_tensors,
    write_atomic,
};
use crate::rays::RayBatch;
use crate::train::{OptimizerState, StepStats, Trainer};
use crate::view::{PixelSet, RenderRequest, render_view};

/// File name of the optimiser state inside a model directory (present in checkpoints).
pub const OPTIMIZER_FILE: &str = "optimizer.safetensors";

/// Origin, direction, image index and colour of one sampled ray.
type SampledRay = ([f32; 3], [f32; 3], u32, [f32; 3]);

struct TrainImage {
    camera: Camera,
    world_from_cam: Isometry3<f64>,
    rgb: Vec<u8>,
}

/// The pixels of a dataset's training images, for drawing random rays.
///
/// Colours are kept as 8 bits (what the PNGs hold); rays are built per batch from the camera
/// model, so a 220-image 320×240 set costs ~50 MB rather than ~0.8 GB of precomputed rays.
pub struct TrainImages {
    images: Vec<TrainImage>,
    /// Prefix sums of pixel counts (`images.len() + 1` entries).
    offsets: Vec<usize>,
    near_m: f32,
    far_m: f32,
    clip: Option<([f32; 3], [f32; 3])>,
}

impl TrainImages {
    /// Loads the images of `split` (their order gives the appearance index), downscaled by an
    /// integer factor (1 = full size); rays get `config`'s range and box clipping.
    pub fn load(
        dataset: &Dataset,
        split: Split,
        downscale: u32,
        config: &ModelConfig,
    ) -> Result<Self, RenderError> {
        let (near_m, far_m, clip) = (config.near_m, config.far_m, config.clip_box());
        let frames: Vec<_> = dataset.split(split).collect();
        let images = frames
            .par_iter()
            .map(|f| {
                let (img, camera) = load_frame_image(dataset, f, downscale)
                    .map_err(|e| RenderError::Data(e.to_string()))?;
                Ok(TrainImage {
                    camera,
                    world_from_cam: f.cam_from_world.inverse(),
                    rgb: img
                        .data()
                        .iter()
                        .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                        .collect(),
                })
            })
            .collect::<Result<Vec<_>, RenderError>>()?;
        if images.is_empty() {
            return Err(RenderError::EmptyTrainingSet);
        }
        let mut offsets = vec![0];
        for im in &images {
            offsets.push(offsets.last().copied().unwrap_or(0) + im.rgb.len() / 3);
        }
        Ok(Self {
            images,
            offsets,
            near_m,
            far_m,
            clip,
        })
    }

    /// Number of images.
    pub fn num_images(&self) -> usize {
        self.images.len()
    }

    /// Number of pixels over all images.
    pub fn num_pixels(&self) -> usize {
        self.offsets.last().copied().unwrap_or(0)
    }

    /// `n` rays through uniformly random pixels of all images (with the image index as
    /// appearance index) and their target colours.
    pub fn sample<R: Rng>(&self, n: usize, rng: &mut R) -> (RayBatch, Vec<f32>) {
        let total = self.num_pixels();
        let picks: Vec<usize> = (0..n).map(|_| rng.random_range(0..total)).collect();
        let per: Vec<SampledRay> = picks
            .par_iter()
            .with_min_len(256)
            .map(|&g| {
                let i = self.offsets.partition_point(|&o| o <= g) - 1;
                let im = &self.images[i];
                let p = g - self.offsets[i];
                let w = im.camera.width as usize;
                let px = Point2::new((p % w) as f64 + 0.5, (p / w) as f64 + 0.5);
                let b = im
                    .camera
                    .unproject(px)
                    .filter(|b| b.iter().all(|v| v.is_finite()))
                    .unwrap_or_else(nalgebra::Vector3::z);
                let d = im.world_from_cam.rotation * b;
                let d = d / d.norm();
                let c = im.world_from_cam.translation.vector;
                let rgb = [0, 1, 2].map(|k| im.rgb[3 * p + k] as f32 / 255.0);
                (
                    [c.x as f32, c.y as f32, c.z as f32],
                    [d.x as f32, d.y as f32, d.z as f32],
                    i as u32,
                    rgb,
                )
            })
            .collect();
        let mut rays = RayBatch {
            origins: Vec::with_capacity(n),
            directions: Vec::with_capacity(n),
            near: vec![self.near_m; n],
            far: vec![self.far_m; n],
            appearance: Some(Vec::with_capacity(n)),
        };
        let mut rgb = Vec::with_capacity(3 * n);
        for (o, d, a, c) in per {
            rays.origins.push(o);
            rays.directions.push(d);
            if let Some(v) = rays.appearance.as_mut() {
                v.push(a);
            }
            rgb.extend(c);
        }
        if let Some((lo, hi)) = self.clip {
            rays.clip_to_box(lo, hi);
        }
        (rays, rgb)
    }
}

/// A model config for a dataset: scene box from the dataset's bounds metadata (synthetic
/// worlds) or, failing that, from the camera centres; one appearance embedding per training
/// image; learning-rate decay over [`LR_HORIZON_FACTOR`] × `steps` steps; median depth at
/// render time.
pub fn config_for_dataset(dataset: &Dataset, steps: u64) -> ModelConfig {
    let centres: Vec<[f64; 3]> = dataset
        .frames
        .iter()
        .map(|f| f.center().coords.into())
        .collect();
    let (min, max) = match (dataset.metadata.bounds_min, dataset.metadata.bounds_max) {
        (Some(a), Some(b)) if (0..3).all(|k| b[k] > a[k]) => (a, b),
        _ => {
            // Cameras look into the scene: a box around their centres, grown by their spread.
            let mut a = [f64::INFINITY; 3];
            let mut b = [f64::NEG_INFINITY; 3];
            for c in &centres {
                for k in 0..3 {
                    a[k] = a[k].min(c[k]);
                    b[k] = b[k].max(c[k]);
                }
            }
            let spread = (0..3).map(|k| b[k] - a[k]).fold(1.0f64, f64::max);
            (a.map(|v| v - 0.5 * spread), b.map(|v| v + 0.5 * spread))
        }
    };
    let mid: [f64; 3] = [0, 1, 2].map(|k| 0.5 * (min[k] + max[k]));
    let mut dists: Vec<f64> = centres
        .iter()
        .map(|c| (0..3).map(|k| (c[k] - mid[k]).powi(2)).sum::<f64>().sqrt())
        .collect();
    dists.sort_by(f64::total_cmp);
    let view = dists.get(dists.len() / 2).copied().unwrap_or(1.0).max(1e-3);
    let num_train = dataset.split(Split::Train).count();
    let mut cfg = ModelConfig::for_scene(
        min.map(|v| v as f32),
        max.map(|v| v as f32),
        view as f32,
        num_train,
    );
    cfg.train.schedule.max_steps = steps.saturating_mul(LR_HORIZON_FACTOR);
    cfg
}

/// The learning rate decays from 1e-2 towards 1e-4 over this many times the run's step
/// count, so a run ends at `1e-2 · 0.01^(1/5)` ≈ 4e-3 (nerfacto decays over 200 k steps and
/// trains 30 k: it ends at 5e-3). Decaying the full 100× within a short CPU run froze the
/// field before surfaces formed: on `small`, 300 steps, test PSNR 21.3 → 24.1 dB and median
/// depth error 11.5 % → 4.5 % with this horizon (docs/BENCHMARKS.md).
pub const LR_HORIZON_FACTOR: u64 = 5;

/// Settings of [`train_on_dataset`] that do not change the model.
#[derive(Clone, Debug)]
pub struct FitOptions {
    /// Train until the model has this many steps (counting steps of a resumed checkpoint).
    pub steps: u64,
    /// Steps between checkpoints written to the output directory (0 = only at the end).
    pub checkpoint_every: u64,
    /// Integer image downscale (1 = full size).
    pub downscale: u32,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            steps: 5000,
            checkpoint_every: 500,
            downscale: 1,
        }
    }
}

/// Progress of [`train_on_dataset`], reported after every step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitProgress {
    /// The step just taken.
    pub stats: StepStats,
    /// Target step count.
    pub total_steps: u64,
    /// Step the run started (or resumed) from.
    pub start_step: u64,
    /// Seconds since this run started.
    pub elapsed_s: f64,
    /// Estimated seconds to the target from this run's mean step time.
    pub eta_s: f64,
    /// Training rays per second in this run.
    pub rays_per_s: f64,
    /// Step of the last checkpoint written, if any.
    pub last_checkpoint: Option<u64>,
}

/// Whether `dir` holds a model or checkpoint ([`NerfModel::save`] layout).
pub fn has_checkpoint(dir: &Path) -> bool {
    dir.join(CONFIG_FILE).is_file()
}

/// Writes the model and the optimiser state of `trainer` to `dir` (optimiser first, so a
/// crash in between leaves a model whose optimiser file is one checkpoint ahead; resume
/// detects that by the step number and restarts the moments).
pub fn save_checkpoint(
    dir: &Path,
    trainer: &Trainer,
    config: &ModelConfig,
) -> Result<NerfModel, RenderError> {
    std::fs::create_dir_all(dir).map_err(|source| RenderError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let opt = trainer.optimizer();
    let (m, v) = opt.moments();
    let mut tensors: Vec<(String, Vec<usize>, &[f32])> = Vec::new();
    for (i, (mi, vi)) in m.iter().zip(v).enumerate() {
        tensors.push((format!("adam.m.{i}"), vec![mi.len()], mi));
        tensors.push((format!("adam.v.{i}"), vec![vi.len()], vi));
    }
    let mut meta = HashMap::new();
    meta.insert("step".to_string(), trainer.step().to_string());
    meta.insert("adam_steps".to_string(), opt.steps().to_string());
    meta.insert("groups".to_string(), m.len().to_string());
    let opt_path = dir.join(OPTIMIZER_FILE);
    let bytes = serialize_tensors(&tensors, meta, &opt_path)?;
    write_atomic(&opt_path, &bytes)?;
    let grid = trainer
        .grid
        .clone()
        .ok_or_else(|| RenderError::InvalidConfig {
            field: "train.sampler",
            reason: "a saved model needs the occupancy sampler's grid".into(),
        })?;
    let model = NerfModel::from_parts(
        config.clone(),
        trainer.field.clone(),
        grid,
        trainer.background(),
        trainer.step(),
    )?;
    model.save(dir)?;
    Ok(model)
}

fn load_optimizer(dir: &Path, step: u64) -> Result<Option<OptimizerState>, RenderError> {
    let path = dir.join(OPTIMIZER_FILE);
    if !path.is_file() {
        return Ok(None);
    }
    let bytes = read(&path)?;
    let corrupt = |message: String| RenderError::Corrupt {
        path: path.clone(),
        message,
    };
    let st = SafeTensors::deserialize(&bytes).map_err(|e| corrupt(e.to_string()))?;
    let (_, meta) = SafeTensors::read_metadata(&bytes).map_err(|e| corrupt(e.to_string()))?;
    let meta = meta.metadata().clone().unwrap_or_default();
    let num = |k: &str| -> Result<u64, RenderError> {
        meta.get(k)
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| corrupt(format!("metadata {k:?} missing or not a number")))
    };
    if num("step")? != step {
        return Ok(None);
    }
    let groups = num("groups")? as usize;
    let mut m = Vec::with_capacity(groups);
    let mut v = Vec::with_capacity(groups);
    for i in 0..groups {
        for (name, out) in [("m", &mut m), ("v", &mut v)] {
            let key = format!("adam.{name}.{i}");
            let len = st
                .tensor(&key)
                .map_err(|_| corrupt(format!("tensor {key:?} missing")))?
                .shape()
                .iter()
                .product::<usize>();
            out.push(read_tensor(&st, &key, &[len], &path)?);
        }
    }
    Ok(Some((num("adam_steps")?, m, v)))
}

/// Trains a model on the training split of `dataset`, writing checkpoints to `out_dir`.
///
/// If `out_dir` already holds a checkpoint, training resumes from it; its config must equal
/// `config` ([`RenderError::ConfigMismatch`] lists the differences otherwise). A non-finite
/// loss stops training with [`RenderError::Diverged`]; the last checkpoint on disk is left
/// untouched. The final model is saved to `out_dir` and returned.
pub fn train_on_dataset(
    dataset: &Dataset,
    config: &ModelConfig,
    out_dir: &Path,
    opts: &FitOptions,
    mut progress: impl FnMut(&FitProgress),
) -> Result<NerfModel, RenderError> {
    config.validate()?;
    let data = TrainImages::load(dataset, Split::Train, opts.downscale, config)?;
    if data.num_images() != config.field.num_images {
        return Err(RenderError::InvalidConfig {
            field: "field.num_images",
            reason: format!(
                "{} appearance embeddings for {} training images",
                config.field.num_images,
                data.num_images()
            ),
        });
    }
    let mut trainer;
    if has_checkpoint(out_dir) {
        let model = NerfModel::load(out_dir)?;
        let diff = config_differences(config, model.config());
        if !diff.is_empty() {
            return Err(RenderError::ConfigMismatch {
                path: out_dir.to_path_buf(),
                differences: format!("requested vs checkpoint: {diff}"),
            });
        }
        let (_, field, grid, bg, step) = model.into_parts();
        trainer = Trainer::new(field, config.train.clone())?;
        let optim = load_optimizer(out_dir, step)?;
        trainer.resume(step, bg, Some(grid), optim)?;
    } else {
        let field = NerfactoField::new(config.field.clone())?;
        trainer = Trainer::new(field, config.train.clone())?;
    }
    let start_step = trainer.step();
    let start = Instant::now();
    let mut rng = ChaCha8Rng::seed_from_u64(config.train.seed ^ (start_step << 20) ^ 0x5eed);
    let mut last_checkpoint = (start_step > 0).then_some(start_step);
    let batch = config.train.batch_rays;
    while trainer.step() < opts.steps {
        let (rays, rgb) = data.sample(batch, &mut rng);
        let stats = match trainer.train_step(&rays, &rgb) {
            Ok(s) => s,
            Err(RenderError::NonFiniteLoss { step, loss }) => {
                return Err(RenderError::Diverged {
                    step,
                    loss,
                    dir: out_dir.to_path_buf(),
                    last_checkpoint,
                });
            }
            Err(e) => return Err(e),
        };
        let done = trainer.step();
        if opts.checkpoint_every > 0
            && done.is_multiple_of(opts.checkpoint_every)
            && done < opts.steps
        {
            save_checkpoint(out_dir, &trainer, config)?;
            last_checkpoint = Some(done);
        }
        let elapsed = start.elapsed().as_secs_f64();
        let run = (done - start_step) as f64;
        progress(&FitProgress {
            stats,
            total_steps: opts.steps,
            start_step,
            elapsed_s: elapsed,
            eta_s: elapsed / run.max(1.0) * (opts.steps - done) as f64,
            rays_per_s: run * batch as f64 / elapsed.max(1e-9),
            last_checkpoint,
        });
    }
    save_checkpoint(out_dir, &trainer, config)
}

/// Metrics of one rendered test view.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewMetrics {
    /// Image file of the view.
    pub image: PathBuf,
    /// PSNR (dB) of the rendered RGB against the image.
    pub psnr: f64,
    /// SSIM of the rendered RGB against the image.
    pub ssim: f64,
    /// Median of `|rendered − GT| / GT` z-depth over pixels with GT depth; `None` without
    /// a depth map.
    pub median_depth_rel_error: Option<f64>,
    /// Seconds to render RGB + depth for the view.
    pub render_s: f64,
}

/// Test-set metrics ([`evaluate`]).
#[derive(Clone, Debug, PartialEq)]
pub struct EvalReport {
    /// One entry per evaluated view.
    pub views: Vec<ViewMetrics>,
    /// Mean PSNR (dB).
    pub mean_psnr: f64,
    /// Mean SSIM.
    pub mean_ssim: f64,
    /// Median relative z-depth error over the pixels of all views with GT depth.
    pub median_depth_rel_error: Option<f64>,
}

/// A rendered test view with its ground truth, as [`evaluate`] sees it.
pub struct EvalView {
    /// The ground-truth image.
    pub image: Image<f32>,
    /// The camera (fitted to the loaded image size).
    pub camera: Camera,
    /// The rendered view (RGB + depth, plus any requested features).
    pub rendered: crate::view::RenderedView,
}

/// Renders every frame of `split` at its pose (fallback appearance) and measures PSNR, SSIM
/// and depth error; `visit` sees each view (e.g. to write images). `dims` are extra feature
/// dims to render for `visit`.
pub fn evaluate(
    model: &NerfModel,
    dataset: &Dataset,
    split: Split,
    downscale: u32,
    dims: &[usize],
    mut visit: impl FnMut(usize, &EvalView) -> Result<(), RenderError>,
) -> Result<EvalReport, RenderError> {
    let mut views = Vec::new();
    let mut all_rel = Vec::new();
    for (i, frame) in dataset.split(split).enumerate() {
        let (image, camera) = load_frame_image(dataset, frame, downscale)
            .map_err(|e| RenderError::Data(e.to_string()))?;
        let t = Instant::now();
        let rendered = render_view(
            model,
            &camera,
            &frame.cam_from_world,
            &PixelSet::Full,
            &RenderRequest {
                rgb: true,
                dims: dims.to_vec(),
                appearance: None,
            },
        )?;
        let render_s = t.elapsed().as_secs_f64();
        let rgb = rendered.rgb_image().ok_or(RenderError::EmptyTrainingSet)?;
        let psnr = matloc_core::metrics::psnr(&rgb, &image)
            .map_err(|e| RenderError::Data(e.to_string()))?;
        let ssim = matloc_core::metrics::ssim(&rgb, &image)
            .map_err(|e| RenderError::Data(e.to_string()))?;
        let gt = load_frame_depth(dataset, frame, downscale)
            .map_err(|e| RenderError::Data(e.to_string()))?;
        let median_depth_rel_error = match gt {
            Some(gt) if gt.width() == rgb.width() && gt.height() == rgb.height() => {
                let rel: Vec<f64> = gt
                    .data()
                    .iter()
                    .zip(&rendered.z_depth)
                    .filter(|(g, _)| **g > 0.0 && g.is_finite())
                    .map(|(&g, &r)| ((r - g).abs() / g) as f64)
                    .collect();
                all_rel.extend_from_slice(&rel);
                matloc_core::metrics::median(&rel)
            }
            _ => None,
        };
        let view = EvalView {
            image,
            camera,
            rendered,
        };
        visit(i, &view)?;
        views.push(ViewMetrics {
            image: dataset.image_path(frame),
            psnr,
            ssim,
            median_depth_rel_error,
            render_s,
        });
    }
    let n = views.len().max(1) as f64;
    Ok(EvalReport {
        mean_psnr: views.iter().map(|v| v.psnr).sum::<f64>() / n,
        mean_ssim: views.iter().map(|v| v.ssim).sum::<f64>() / n,
        median_depth_rel_error: matloc_core::metrics::median(&all_rel),
        views,
    })
}
