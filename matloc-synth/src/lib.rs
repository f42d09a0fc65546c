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
//! [`oracle`] implements the matcher's `ViewRenderer` over the world's exact geometry with an
//! analytic feature field, for tests and studies that need exact ground truth.
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
//! - Everything derives from the seed through counter-based hashing (the world uses no `rand` generator), so
//!   output is bit-identical across thread counts.

mod config;
mod error;
pub mod flight;
mod geometry;
mod noise;
pub mod oracle;
pub mod points;
mod raycast;
mod render;
mod rng;
mod survey;
mod texture;
mod world;
mod write;

#[cfg(test)]
mod tests;

pub use config::{PRESET_NAMES, SynthConfig};
pub use error::SynthError;
pub use flight::{SecondFlight, synthesize_second_flight};
pub use raycast::Hit;
pub use render::{RenderOptions, Rendered};
pub use survey::{SurveyConfig, SurveyGeometry, SurveyPlan, plan_survey, survey_geometry};
pub use world::{Material, World, WorldConfig};
pub use write::{Progress, SynthOutput, generate, synthesize, synthesize_with};
