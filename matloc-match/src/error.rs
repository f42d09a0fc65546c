//! Typed errors of the matchers.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Which side of a match problem an error refers to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Side {
    /// The query image's feature map.
    Query,
    /// The rendered map features.
    Map,
}

impl std::fmt::Display for Side {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Side::Query => "query",
            Side::Map => "map",
        })
    }
}

/// Why a match could not be computed.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum MatchError {
    /// Query and map features have different dimensionality.
    #[error("feature dimension mismatch: query has {query} dims, map has {map}")]
    DimensionMismatch {
        /// Query feature dims.
        query: usize,
        /// Map feature dims.
        map: usize,
    },
    /// One side has no (valid) features.
    #[error("no {side} features to match")]
    Empty {
        /// The empty side.
        side: Side,
    },
    /// A feature value is NaN or infinite.
    #[error("non-finite {side} feature at index {index}, dim {dim}")]
    NonFinite {
        /// Side of the offending feature.
        side: Side,
        /// Index of the feature vector (cell index for the query, point index for the map).
        index: usize,
        /// Dimension holding the non-finite value.
        dim: usize,
    },
    /// A selected dimension does not exist.
    #[error("selected dimension {dim} out of range for {dims}-d features")]
    DimOutOfRange {
        /// The selected dim.
        dim: usize,
        /// Feature dims available.
        dims: usize,
    },
    /// The dimension selection is empty or has repeated dims.
    #[error("invalid dimension selection: {0}")]
    InvalidSelection(String),
    /// Buffers whose lengths disagree with their declared shape.
    #[error("shape error: {0}")]
    Shape(String),
    /// Configuration values out of range.
    #[error("invalid matcher config: {0}")]
    InvalidConfig(String),
}
