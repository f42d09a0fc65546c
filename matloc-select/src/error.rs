//! Typed errors of the selectors.

use thiserror::Error;

/// Why a selection could not be made.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum SelectError {
    /// No ground-truth pairs.
    #[error("no ground-truth pairs")]
    EmptyPairs,
    /// The budget `N_s` is 0 or exceeds the feature dims.
    #[error("budget N_s = {n_s} must be in 1..={dims}")]
    InvalidBudget {
        /// Requested budget.
        n_s: usize,
        /// Feature dims available.
        dims: usize,
    },
    /// A feature buffer is not a whole number of `dims`-wide rows.
    #[error("{what} has {len} values, not a multiple of {dims} dims")]
    DimensionMismatch {
        /// Which buffer.
        what: String,
        /// Its length.
        len: usize,
        /// Expected row width.
        dims: usize,
    },
    /// A feature value is NaN or infinite.
    #[error("non-finite value in {what} row {index}")]
    NonFinite {
        /// Which buffer.
        what: String,
        /// Row index.
        index: usize,
    },
    /// Inconsistent shapes.
    #[error("shape error: {0}")]
    Shape(String),
    /// Configuration values out of range.
    #[error("invalid selector config: {0}")]
    InvalidConfig(String),
    /// The matcher failed while scoring a candidate selection.
    #[error("matching failed: {0}")]
    Match(#[from] matloc_match::MatchError),
}
