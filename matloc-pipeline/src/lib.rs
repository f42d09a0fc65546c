//! The MatLoc-NeRF pipeline as a library, in one-way layers (each imports only those above):
//!
//! - [`error`]: [`PipelineError`], with the stage crates' typed errors as sources.
//! - [`gt`]: ground-truth 2D–3D pairs from perturbed training poses (paper 3.1.2), the input of
//!   encoder training and feature selection.
//! - [`localizer`]: the MatLoc [`Localizer`] over the stage traits (top-k fallback, iterative
//!   refinement, calibrated confidence and refusal), its [`LocalizeOptions`] and
//!   [`localizer::confidence`].
//! - [`config`]: [`MapConfig`], everything that defines a map build.
//! - [`map`]: the map directory (manifest, checksums, file layout) and [`LoadedMap`], a built
//!   map loaded behind the stage traits.
//! - [`build`]: map building, one file per stage, resumable.
//! - [`baselines`], [`methods`]: rendered-RGB + keypoints, iNeRF and curriculum iNeRF from the
//!   same coarse poses and map as MatLoc, and one entry point for every method, which refuses
//!   a pose outside the map's [`volume`].
//! - [`query`]: the query path of `matloc localize` and `matloc serve`: a batch of queries
//!   localized in order, the JSON record of one query, pose files (JSON lines, hloc, TUM,
//!   COLMAP, nerfstudio).
//! - [`eval`]: the paper's Tables 1–4 and diagnostics.
//!
//! The command-line tool (`matloc`) only parses arguments, draws progress and plots, and calls
//! into this crate.

pub mod adapters;
pub mod baselines;
pub mod build;
pub mod config;
mod error;
pub mod eval;
pub mod gt;
pub mod localizer;
pub mod map;
pub mod methods;
pub mod query;
pub mod volume;

pub use config::MapConfig;
pub use error::PipelineError;
pub use eval::{
    MethodSummary, QueryOutcome, RECALL_THRESHOLDS, RecallThreshold, Reliability, ReliabilityBin,
    accuracy_table, reliability, reliability_table, summarize, summarize_with, timing_table,
};
pub use localizer::options::LocalizeOptions;
pub use localizer::{
    FixedPlace, HypothesisReport, Localization, Localizer, LocalizerBlock, QueryFeatureEncoder,
};
pub use map::{
    BlockEntry, FileEntry, LoadedMap, MANIFEST_VERSION, Manifest, MapDir, MapError, StageRecord,
    VirtualViewsRecord,
};
