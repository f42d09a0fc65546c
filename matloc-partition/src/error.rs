//! Typed errors of the partition crate.

use std::path::PathBuf;

use thiserror::Error;

/// Everything that can go wrong while sampling, partitioning or reading a partition.
#[derive(Debug, Error)]
pub enum PartitionError {
    /// More blocks were asked for than there are poses to fill them.
    #[error("cannot split {poses} poses into {blocks} blocks")]
    TooFewPoses {
        /// Poses given.
        poses: usize,
        /// Blocks required.
        blocks: usize,
    },
    /// A pose has a NaN or infinite component.
    #[error("pose {index} is not finite")]
    NonFinitePose {
        /// Position of the pose in the input.
        index: usize,
    },
    /// A pose has no sample points (it sees only sky, or its depth map is empty).
    #[error("pose {index} has no sample points")]
    EmptySamples {
        /// Position of the pose in the input.
        index: usize,
    },
    /// A sample point has a NaN or infinite coordinate.
    #[error("pose {index} has a non-finite sample point")]
    NonFiniteSample {
        /// Position of the pose in the input.
        index: usize,
    },
    /// A frame that must be sampled from depth has no depth map.
    #[error("frame {index} has no depth map; the partition needs depth (or a surface source)")]
    MissingDepth {
        /// Frame index in the dataset.
        index: usize,
    },
    /// Loading a depth map failed.
    #[error("loading the depth map of frame {index}: {message}")]
    Depth {
        /// Frame index in the dataset.
        index: usize,
        /// The loader's message.
        message: String,
    },
    /// The sample points asked for do not fit in memory.
    #[error("{0}")]
    Limit(#[from] matloc_core::limits::LimitError),
    /// A configuration value is out of range.
    #[error("invalid partition setting `{field}`: {reason}")]
    InvalidConfig {
        /// The setting.
        field: &'static str,
        /// Why it is rejected.
        reason: String,
    },
    /// The partition's data are inconsistent (e.g. a hand-edited file).
    #[error("inconsistent partition: {0}")]
    Inconsistent(String),
    /// Reading or writing a partition file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A partition file is not valid JSON of the expected shape.
    #[error("{path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The parse error.
        source: serde_json::Error,
    },
    /// A partition file was written by an incompatible version.
    #[error("partition format version {found} is not supported (expected {expected})")]
    UnsupportedVersion {
        /// Version in the file.
        found: u32,
        /// Version this build reads.
        expected: u32,
    },
}
