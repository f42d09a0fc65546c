//! The procedural synthetic aerial world: the embedded default dataset of matloc-nerf.
//!
//! A [`World`] is generated deterministically from a `u64` seed (world frame: x east, y north,
//! z up, metres): gently rolling terrain with grass, soil, roads with markings and sidewalks,
//! buildings with window-gridded brick/plaster/concrete facades and tiled, metal or gravel roofs,
//! rubble piles and trees. [`World::render`] ray-casts RGB (Lambertian sun + sky light, hard
//! shadows, prefiltered textures, edge anti-aliasing) and z-depth at any [`matloc_core::Camera`]
//! and `cam_from_world` pose; [`World::raycast`] answers single ray queries.
//!
//! [`plan_survey`] lays out a drone mapping flight (lawnmower lines with forward/side overlap
//! from the camera footprint, oblique pitch, two headings) plus held-out query views, and
//! [`synthesize`] renders everything into a nerfstudio dataset on disk.
//!
//! Presets ([`SynthConfig::preset`]): `tiny` (CI), `small` (demo), `rubble`, `building`.
//!
//! Design notes:
//! - Lighting is Lambertian with a fixed sun and a hemispherical sky term, so a surface point
//!   has the same colour from every view (what a NeRF can learn). Texture detail finer than the
//!   pixel footprint is prefiltered analytically (noise octaves fade out, stripes and windows are
//!   box-filtered); only silhouettes, creases and shadow edges get extra jittered rays.
//! - Depth is the z-depth of the pixel-centre ray, never averaged across an edge, so lifting a
//!   depth pixel with [`matloc_core::Camera::unproject`] lands exactly on a surface.
//! - The terrain is a triangulated height grid (two triangles per cell) traced with a two-level
//!   DDA over min/max blocks; objects are convex polyhedra (boxes, roofs, rubble chunks) and
//!   ellipsoids (tree crowns) in a binned-SAH BVH. Beyond the grid the ground is the flat plane
//!   the terrain apron fades into, so oblique views never see sky.
//! - Everything derives from the seed through counter-based hashing (no `rand` dependency), so
//!   output is bit-identical across thread counts.

mod presets;
mod raycast;
mod render;
mod rng;
mod survey;
mod texture;
mod world;
mod write;

#[cfg(test)]
mod tests;

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use thiserror::Error;

pub use presets::PRESET_NAMES;
pub use raycast::Hit;
pub use render::{RenderOptions, Rendered};
pub use survey::{SurveyConfig, SurveyGeometry, SurveyPlan, plan_survey, survey_geometry};
pub use world::{Material, World, WorldConfig};
pub use write::{Progress, generate, synthesize};

/// Errors of the synthetic-world generator.
#[derive(Debug, Error)]
pub enum SynthError {
    /// The preset name is not one of [`PRESET_NAMES`].
    #[error("unknown synthetic preset {name:?}; valid presets: {valid}")]
    UnknownPreset {
        /// The name asked for.
        name: String,
        /// Comma-separated valid names.
        valid: String,
    },
    /// A configuration value is out of range.
    #[error("invalid synthetic config field `{field}`: {reason}")]
    InvalidConfig {
        /// Dotted field path, e.g. `survey.pitch_deg`.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// The survey plan placed a camera inside or under scene geometry.
    #[error(
        "survey camera {index} at {position:?} is inside or below scene geometry; raise survey.altitude_m"
    )]
    CameraInsideScene {
        /// Index of the planned view.
        index: usize,
        /// Its world position.
        position: [f64; 3],
    },
    /// Writing an output file failed.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// Writing an image or depth file failed.
    #[error(transparent)]
    Image(Box<crate::images::ImageLoadError>),
    /// Writing `transforms.json` failed.
    #[error(transparent)]
    Dataset(Box<crate::nerfstudio::NerfstudioError>),
}

/// Everything that defines a synthetic dataset: scene, capture and rendering.
///
/// `Default` is the `small` preset with seed 0. Deserialising a partial file fills the missing
/// fields from `Default`, so a preset tweak is a few lines of JSON/TOML.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SynthConfig {
    /// Preset name recorded in the dataset metadata.
    pub preset: String,
    /// Seed of the world and of the survey jitter.
    pub seed: u64,
    /// Scene content.
    pub world: WorldConfig,
    /// Drone capture plan.
    pub survey: SurveyConfig,
    /// Renderer settings.
    pub render: RenderOptions,
}

impl Default for SynthConfig {
    fn default() -> Self {
        presets::small()
    }
}

impl SynthConfig {
    /// The configuration of a named preset (`tiny`, `small`, `rubble`, `building`), seed 0.
    pub fn preset(name: &str) -> Result<SynthConfig, SynthError> {
        presets::by_name(name).ok_or_else(|| SynthError::UnknownPreset {
            name: name.to_string(),
            valid: PRESET_NAMES.join(", "),
        })
    }

    /// The same configuration with another seed.
    pub fn with_seed(mut self, seed: u64) -> Self {
        self.seed = seed;
        self
    }

    /// Checks every field; generation calls this first.
    pub fn validate(&self) -> Result<(), SynthError> {
        self.world.validate()?;
        self.survey.validate()?;
        if self.render.edge_samples > 8 {
            return Err(SynthError::InvalidConfig {
                field: "render.edge_samples",
                reason: format!("must be at most 8, got {}", self.render.edge_samples),
            });
        }
        for (field, v) in [
            ("render.sun_strength", self.render.sun_strength),
            ("render.exposure", self.render.exposure),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(SynthError::InvalidConfig {
                    field,
                    reason: format!("must be a non-negative number, got {v}"),
                });
            }
        }
        Ok(())
    }
}
