//! The scene surface a map build needs, for datasets with or without depth.
//!
//! Building a map needs to know where the surface is in every training view (the partition
//! samples rays up to it). Sources, in order of preference ([`SurfaceChoice::Auto`]): the
//! dataset's depth files; its sparse point cloud — COLMAP `points3D` with tracks (a point
//! counts in the views that observed it) or nerfstudio's PLY (a point counts where it
//! projects); otherwise points triangulated from the posed images ([`triangulate`]). Points
//! become coarse per-frame depth maps ([`densify`]), so every consumer reads a depth map.
//!
//! - [`config`] holds [`SurfaceConfig`], [`SurfaceChoice`] and [`TriangulateConfig`];
//! - [`source`] has [`plan`] (which source, without reading anything) and [`FrameSurfaces`];
//!   [`kind`] names the sources ([`SurfaceKind`]);
//! - [`densify`] and [`triangulate`] are the two algorithms;
//! - [`sunlight`] finds the cast shadows of the map's sun in the training images and lifts them
//!   ([`SunlightConfig`]);
//! - [`viewpoints`] samples virtual camera poses beyond the survey over the height field of
//!   the surface the training cameras saw ([`VirtualViewsConfig`], [`sample_viewpoints`]);
//! - [`error`] holds [`SurfaceError`].

pub mod bundle;
pub mod config;
pub mod densify;
pub mod error;
pub mod kind;
mod reprojection;
pub mod source;
pub mod sunlight;
pub mod triangulate;
pub mod viewpoints;

pub use config::{SurfaceChoice, SurfaceConfig, TriangulateConfig};
pub use error::SurfaceError;
pub use kind::SurfaceKind;
pub use source::{FrameSurfaces, SurfacePlan, plan};
pub use sunlight::SunlightConfig;
pub use triangulate::triangulate;
pub use viewpoints::{VirtualViewsConfig, sample_viewpoints};
