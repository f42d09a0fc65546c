//! Sampling, volume rendering and training for a [`matloc_nerf_field::FeatureField`], and the
//! model-level API the rest of the pipeline uses.
//!
//! # Rendering a camera view (stable API)
//!
//! ```no_run
//! use matloc_render::{NerfModel, PixelSet, RenderRequest, render_view};
//! # fn demo(camera: &matloc_core::Camera, cam_from_world: &nalgebra::Isometry3<f64>)
//! #     -> Result<(), matloc_render::RenderError> {
//! let model = NerfModel::load(std::path::Path::new("maps/block0"))?;
//! let view = render_view(
//!     &model,
//!     camera,                          // intrinsics + OpenCV distortion
//!     cam_from_world,                  // world → camera, OpenCV axes
//!     &PixelSet::Grid { stride: 4 },   // 80×60 block centres of a 320×240 camera
//!     &RenderRequest { rgb: false, dims: vec![3, 10, 33, 40, 46], appearance: None },
//! )?;
//! // Per entry (row-major width × height): view.z_depth[i], view.distance[i],
//! // view.accumulation[i], view.features[i * 5 + j] = F(r) for dims[j].
//! # Ok(()) }
//! ```
//!
//! - [`PixelSet`]: the full image, a stride-`s` grid of block centres, or a pixel list.
//!   Pixels are continuous (pixel `(c, r)` has its centre at `(c + 0.5, r + 0.5)`); each is
//!   undistorted with `Camera::unproject`, and entries whose undistortion fails are marked
//!   `valid = false` and zeroed.
//! - [`RenderRequest`]: RGB on/off, any subset of the 47 feature dims (`0..32` = f_pos, the
//!   16 hash levels × 2; `32..47` = f_mlp), appearance embedding (`None` = mean).
//! - [`RenderedView`]: RGB, distance along the ray and z-depth (both normalised by the
//!   accumulation, 0 where nothing is hit), accumulation, and features `F(r) = Σ w_k f_k`
//!   (not normalised, as in the paper), with helpers to images / [`matloc_core::FeatureMap`].
//! - [`NerfModel`]: field + scene box + occupancy grid + configs ([`ModelConfig`]), saved as
//!   `model.safetensors` + `model.json` (both atomic); loading a truncated file, a file whose
//!   stored config differs from the JSON, or tensors whose shapes differ from the config is a
//!   typed [`RenderError`].
//!
//! # Training on a dataset
//!
//! [`train_on_dataset`] draws batches of random rays from all training images of a
//! [`matloc_data::Dataset`] (per-image appearance embeddings), trains with Adam and
//! exponential decay, writes atomic checkpoints (model + `optimizer.safetensors`) and resumes
//! from them; [`evaluate`] renders the test views and reports PSNR, SSIM and the median
//! relative depth error against ground-truth depth.
//!
//! # Lower level
//!
//! Rendering functions are pure: they take rays (origins + unit directions, in world metres)
//! and a field, and return per-ray RGB, depth (distance along the ray; see
//! [`volume::z_from_distance`] for z-depth), accumulation and any subset of the 47 feature
//! dims.
//!
//! Samplers: stratified samples on a linear-then-disparity spacing grid ([`Spacing`]), an
//! instant-ngp-style occupancy grid over the contracted cube for empty-space skipping
//! ([`OccupancyGrid`]), and one inverse-CDF importance stage ([`importance_resample`]). The
//! trainer picks one via [`SamplerKind`].

mod error;
mod fit;
mod model;
mod occupancy;
mod rays;
mod render;
mod sampler;
mod train;
mod view;
pub mod volume;

pub use error::RenderError;
pub use fit::{
    EvalReport, EvalView, FitOptions, FitProgress, LR_HORIZON_FACTOR, OPTIMIZER_FILE, TrainImages,
    ViewMetrics, config_for_dataset, evaluate, has_checkpoint, save_checkpoint, train_on_dataset,
};
pub use model::{
    CONFIG_FILE, DepthKind, MODEL_FORMAT, ModelConfig, NerfModel, ViewConfig, WEIGHTS_FILE,
    config_differences,
};
pub use occupancy::{OccupancyConfig, OccupancyGrid};
pub use rays::{RayBatch, RaySamples};
pub use render::{RenderOptions, render_rays, render_rays_single_pass};
pub use sampler::{MarchConfig, Spacing, importance_resample, march_ray, sample_rays};
pub use train::{
    Background, OptimizerState, Progress, SamplerKind, StepStats, TrainConfig, Trainer,
};
pub use view::{PixelSet, RenderRequest, RenderedView, camera_rays, pixel_positions, render_view};
pub use volume::{
    RenderGradients, RenderedRays, SampleGradients, SampleValues, compute_weights, distortion_loss,
    volume_render, volume_render_backward,
};
