//! The MatLoc-NeRF pipeline as a library.
//!
//! - [`manifest`]: the map directory — a versioned JSON manifest (config, scene frame, blocks,
//!   stage records, file list with SHA-256 checksums) next to safetensors/JSON files, all
//!   written atomically, validated on load.
//! - [`localizer`]: the MatLoc [`Localizer`] over the stage traits, with top-k fallback,
//!   iterative refinement and refusal.
//! - [`build`], [`stages`]: map building stage by stage, resumable, and [`stages::LoadedMap`],
//!   a built map loaded and validated.
//! - [`baselines`]: rendered-RGB + keypoints, iNeRF and curriculum iNeRF from the same coarse
//!   poses and map as MatLoc.
//! - [`confidence`]: calibrated P(correct | inliers, inlier ratio, matches) and the refusal
//!   rule.
//! - [`render_select`]: feature selection scored by windowed matching (or a PnP pass) of
//!   held-out views against renders, as the localizer uses the dims.
//! - [`table3`]: the paper's Table 3 (feature sets × matching time, precision, pose error) on
//!   a built map.
//! - [`eval`]: per-method accuracy, refusal and timing summaries in the layout of the paper's
//!   Tables 1 and 2, and their markdown rendering.
//!
//! The command-line tool (`matloc`) only parses arguments, draws progress and plots, and calls
//! into this crate.

pub mod adapters;
pub mod baselines;
pub mod build;
pub mod confidence;
pub mod diagnostics;
mod error;
pub mod eval;
pub mod localizer;
pub mod manifest;
pub mod methods;
pub mod render_select;
pub mod stages;
pub mod table3;

pub use error::PipelineError;
pub use eval::{
    MethodSummary, QueryOutcome, RECALL_THRESHOLDS, RecallThreshold, accuracy_table, summarize,
    timing_table,
};
pub use localizer::{
    HypothesisReport, Localization, LocalizeOptions, Localizer, LocalizerBlock, QueryFeatureEncoder,
};
pub use manifest::{
    BlockEntry, FileEntry, MANIFEST_VERSION, Manifest, MapDir, MapError, StageRecord,
};
