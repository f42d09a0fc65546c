//! Sampling, volume rendering and training for a [`matloc_nerf_field::FeatureField`].
//!
//! Rendering functions are pure: they take rays (origins + unit directions, in world metres)
//! and a field, and return per-ray RGB, depth (distance along the ray; see
//! [`volume::z_from_distance`] for z-depth), accumulation and any subset of the 47 feature
//! dims. Cameras live elsewhere; callers turn pixels into rays.
//!
//! Samplers: stratified samples on a linear-then-disparity spacing grid ([`Spacing`]), an
//! instant-ngp-style occupancy grid over the contracted cube for empty-space skipping
//! ([`OccupancyGrid`]), and one inverse-CDF importance stage ([`importance_resample`]). The
//! trainer picks one via [`SamplerKind`].

mod error;
mod occupancy;
mod rays;
mod render;
mod sampler;
mod train;
pub mod volume;

pub use error::RenderError;
pub use occupancy::{OccupancyConfig, OccupancyGrid};
pub use rays::{RayBatch, RaySamples};
pub use render::{RenderOptions, render_rays, render_rays_single_pass};
pub use sampler::{MarchConfig, Spacing, importance_resample, march_ray, sample_rays};
pub use train::{Background, Progress, SamplerKind, StepStats, TrainConfig, Trainer};
pub use volume::{
    RenderGradients, RenderedRays, SampleGradients, SampleValues, compute_weights, distortion_loss,
    volume_render, volume_render_backward,
};
