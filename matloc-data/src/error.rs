//! The crate-level error of format detection ([`crate::summary::read_dataset`]): one enum
//! that wraps each format's own error, so callers that accept any dataset match on one type.

use std::path::PathBuf;

use thiserror::Error;

use crate::colmap::ColmapError;
use crate::images::ImageLoadError;
use crate::meganerf::MegaNerfError;
use crate::nerfstudio::NerfstudioError;
use crate::ply::PlyError;

/// Errors raised when reading a dataset of any supported format.
#[derive(Debug, Error)]
pub enum DataError {
    /// The path does not exist.
    #[error("dataset path not found: {path}")]
    NotFound {
        /// The path given.
        path: PathBuf,
    },
    /// The path exists but holds no dataset of a supported format.
    #[error(
        "{path} is neither a nerfstudio dataset (transforms.json, transforms_{{train,val,test}}.json), \
         a Mega-NeRF dataset (coordinates.pt, train/metadata) \
         nor a COLMAP model (cameras.bin|txt in it, sparse/0, sparse or colmap/sparse/0)"
    )]
    UnknownFormat {
        /// The path given.
        path: PathBuf,
    },
    /// Reading a nerfstudio dataset failed.
    #[error(transparent)]
    Nerfstudio(#[from] NerfstudioError),
    /// Reading a COLMAP model failed.
    #[error(transparent)]
    Colmap(#[from] ColmapError),
    /// Reading a Mega-NeRF dataset failed.
    #[error(transparent)]
    MegaNerf(#[from] MegaNerfError),
    /// Reading an image or depth map failed.
    #[error(transparent)]
    Image(#[from] ImageLoadError),
    /// Reading a PLY point cloud failed.
    #[error(transparent)]
    Ply(#[from] PlyError),
}
