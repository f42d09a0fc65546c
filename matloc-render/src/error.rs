use std::path::PathBuf;

use matloc_nerf_field::FieldError;

/// Errors of the renderer and trainer.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// The field rejected a query.
    #[error(transparent)]
    Field(#[from] FieldError),
    /// Two buffers that must agree in length do not.
    #[error("length mismatch for {what}: expected {expected}, got {actual}")]
    LengthMismatch {
        /// Which buffer.
        what: &'static str,
        /// Required length.
        expected: usize,
        /// Given length.
        actual: usize,
    },
    /// A ray has a bad origin, direction or range.
    #[error("ray {index} is invalid: {reason}")]
    InvalidRay {
        /// Index of the ray.
        index: usize,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// A grid or a batch of rays does not fit in memory.
    #[error("{0}")]
    Limit(#[from] matloc_core::limits::LimitError),
    /// A configuration value is out of range.
    #[error("invalid render/train config: {field}: {reason}")]
    InvalidConfig {
        /// Offending field.
        field: &'static str,
        /// Why.
        reason: String,
    },
    /// Training produced a NaN/inf loss; the weights were left as they were before the step.
    #[error("non-finite loss {loss} at step {step}; weights left at the previous step")]
    NonFiniteLoss {
        /// Step at which it happened.
        step: u64,
        /// The loss value.
        loss: f32,
    },
    /// The training set is empty.
    #[error("no training rays")]
    EmptyTrainingSet,
    /// A pixel of a [`crate::PixelSet::List`] is not finite.
    #[error("pixel {index} of the list is not finite")]
    InvalidPixel {
        /// Index in the list.
        index: usize,
    },
    /// The camera intrinsics are invalid.
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
    /// The pose has non-finite entries.
    #[error("cam_from_world has non-finite entries")]
    InvalidPose,
    /// Reading or writing a model file failed.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// A model's JSON could not be (de)serialised.
    #[error("model JSON error in {path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// Underlying error.
        source: serde_json::Error,
    },
    /// A safetensors file is malformed or truncated, or lacks a tensor or metadata entry.
    #[error("bad model file {path}: {message}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Two configurations that must agree do not (the model's JSON vs the config stored with
    /// its weights, or a resumed run's config vs its checkpoint's).
    #[error("config mismatch in {path}: {differences}")]
    ConfigMismatch {
        /// The model file or directory.
        path: PathBuf,
        /// The top-level fields that differ, e.g. `field.log2_table_size: 19 vs 16`.
        differences: String,
    },
    /// Training hit a non-finite loss; the checkpoint on disk (if any) is the last good one.
    #[error(
        "training diverged: non-finite loss {loss} at step {step}; last good checkpoint in {dir}: {}",
        last_checkpoint.map_or("none".to_string(), |s| format!("step {s}"))
    )]
    Diverged {
        /// Step at which it happened.
        step: u64,
        /// The loss value.
        loss: f32,
        /// The model directory.
        dir: PathBuf,
        /// Step of the last checkpoint written there, if any.
        last_checkpoint: Option<u64>,
    },
    /// Loading a dataset or its images failed.
    #[error("dataset: {0}")]
    Data(String),
}
