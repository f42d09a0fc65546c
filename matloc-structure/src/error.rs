//! Errors of the structure store and the structure localizer.

use std::path::PathBuf;

/// What can go wrong reading a structure file or localizing against it.
#[derive(Debug, thiserror::Error)]
pub enum StructureError {
    /// The structure file is not what [`crate::StructureMap::to_bytes`] writes.
    #[error("{path}: {reason}")]
    Format {
        /// The file (empty when parsing bytes of no file).
        path: PathBuf,
        /// What is wrong, naming the tensor or field.
        reason: String,
    },
    /// The query image does not have the camera's size.
    #[error("query image is {image:?} (w, h, channels) but its camera is {camera:?}")]
    QueryShape {
        /// Image width, height, channels.
        image: (usize, usize, usize),
        /// Camera width, height.
        camera: (u32, u32),
    },
}
