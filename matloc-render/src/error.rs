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
}
