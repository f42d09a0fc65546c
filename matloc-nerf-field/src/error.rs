use std::path::PathBuf;

/// Errors of the field crate. Variants carry the facts needed to act on them.
#[derive(Debug, thiserror::Error)]
pub enum FieldError {
    /// A configuration value is out of its valid range.
    #[error("invalid field config: {field}: {reason}")]
    InvalidConfig {
        /// The offending config field.
        field: &'static str,
        /// Why it is invalid.
        reason: String,
    },
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
    /// A requested feature dimension does not exist.
    #[error("feature dim {dim} out of range (field has {available} dims)")]
    DimOutOfRange {
        /// Requested dimension.
        dim: usize,
        /// Number of dimensions the field has.
        available: usize,
    },
    /// An appearance (image) index beyond the embedding table.
    #[error("appearance index {index} out of range ({count} embeddings)")]
    AppearanceOutOfRange {
        /// Requested index.
        index: u32,
        /// Number of embeddings.
        count: usize,
    },
    /// Reading or writing a file failed.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The JSON config could not be (de)serialised.
    #[error("config JSON error in {path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// Underlying error.
        source: serde_json::Error,
    },
    /// The safetensors container is malformed.
    #[error("safetensors error in {path}: {message}")]
    Safetensors {
        /// The file.
        path: PathBuf,
        /// What the parser said.
        message: String,
    },
    /// A tensor the config requires is absent.
    #[error("tensor {name} missing from {path}")]
    MissingTensor {
        /// Tensor name.
        name: String,
        /// The file.
        path: PathBuf,
    },
    /// A tensor's shape or dtype does not match what the config implies.
    #[error("tensor {name}: config implies shape {expected:?}, file has {actual:?}")]
    ShapeMismatch {
        /// Tensor name.
        name: String,
        /// Shape the config implies.
        expected: Vec<usize>,
        /// Shape stored in the file.
        actual: Vec<usize>,
    },
}
