//! Typed errors of the place crate.

use std::path::PathBuf;

use thiserror::Error;

/// Everything that can go wrong while grouping poses, training, predicting or storing a model.
#[derive(Debug, Error)]
pub enum PlaceError {
    /// There are too few poses for the groups asked for.
    #[error("{poses} poses are too few for {groups} group(s) of at least {min_group_size} poses")]
    TooFewPoses {
        /// Poses given.
        poses: usize,
        /// Groups needed.
        groups: usize,
        /// Smallest group size allowed.
        min_group_size: usize,
    },
    /// A pose has a NaN or infinite component.
    #[error("pose {index} is not finite")]
    NonFinitePose {
        /// Position of the pose in the input.
        index: usize,
    },
    /// An image has no pixels, or not three channels.
    #[error("image {index} is empty or not RGB ({width}x{height}x{channels})")]
    EmptyImage {
        /// Position of the image in the input (0 for a single query).
        index: usize,
        /// Width in pixels.
        width: usize,
        /// Height in pixels.
        height: usize,
        /// Channels.
        channels: usize,
    },
    /// An image has NaN or infinite values.
    #[error("image {index} has non-finite pixel values")]
    NonFiniteImage {
        /// Position of the image in the input.
        index: usize,
    },
    /// Inputs that must have the same length do not.
    #[error("{what}: {a} vs {b}")]
    LengthMismatch {
        /// What is being compared.
        what: &'static str,
        /// First length.
        a: usize,
        /// Second length.
        b: usize,
    },
    /// A label refers to a group that does not exist.
    #[error("label {label} of sample {index} is not below the group count {groups}")]
    BadLabel {
        /// Sample.
        index: usize,
        /// Its label.
        label: usize,
        /// Number of groups.
        groups: usize,
    },
    /// A configuration value is out of range.
    #[error("invalid place setting `{field}`: {reason}")]
    InvalidConfig {
        /// The setting.
        field: &'static str,
        /// Why it is rejected.
        reason: String,
    },
    /// Training diverged (the loss became non-finite).
    #[error("training diverged at epoch {epoch} (loss {loss})")]
    Diverged {
        /// Epoch.
        epoch: usize,
        /// The loss value.
        loss: f32,
    },
    /// Reading or writing a model file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A model's JSON file is not valid.
    #[error("{path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The parse error.
        source: serde_json::Error,
    },
    /// The weights file does not fit the model described by the JSON file.
    #[error("{path}: {message}")]
    Weights {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A model file was written by an incompatible version.
    #[error("place model format version {found} is not supported (expected {expected})")]
    UnsupportedVersion {
        /// Version in the file.
        found: u32,
        /// Version this build reads.
        expected: u32,
    },
}
