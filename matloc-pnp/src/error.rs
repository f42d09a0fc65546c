//! Typed errors of the pose solvers.

use matloc_core::CameraError;
use thiserror::Error;

/// Why a pose could not be estimated.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum PnpError {
    /// Fewer matches than the solver needs.
    #[error("need at least {required} 2D-3D correspondences, got {actual}")]
    InsufficientCorrespondences {
        /// Smallest number of matches the solver accepts.
        required: usize,
        /// Number of usable matches given.
        actual: usize,
    },
    /// A pixel, world point or score is NaN or infinite.
    #[error("correspondence {index}: {what} is not finite")]
    NonFiniteInput {
        /// Index of the offending correspondence.
        index: usize,
        /// Which value: `"pixel"`, `"world point"`, `"score"` or `"initial pose"`.
        what: &'static str,
    },
    /// The observation, point and score slices differ in length.
    #[error("{pixels} pixels, {points} world points and {scores:?} scores do not match")]
    LengthMismatch {
        /// Number of pixel observations.
        pixels: usize,
        /// Number of world points.
        points: usize,
        /// Number of scores, when scores were given.
        scores: Option<usize>,
    },
    /// No hypothesis reached the required number of inliers.
    #[error("best pose has {best_inliers} inliers, {required} required")]
    NoConsensus {
        /// Inlier count of the best hypothesis found (0 when none was found).
        best_inliers: usize,
        /// The `min_inliers` option.
        required: usize,
    },
    /// The configuration admits no unique pose (e.g. every point on one line, or all coincident).
    #[error("degenerate configuration: {0}")]
    Degenerate(&'static str),
    /// The camera intrinsics are invalid.
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// An option is out of range.
    #[error("invalid option `{field}`: {reason}")]
    InvalidOption {
        /// Name of the option.
        field: &'static str,
        /// What is wrong with it.
        reason: &'static str,
    },
}
