//! Dataset formats: the in-memory dataset, its readers and writers, image and depth loading.
//!
//! - [`dataset`]: the in-memory [`Dataset`] every reader produces (frames with intrinsics,
//!   `cam_from_world` pose, image and optional depth path, split).
//! - [`nerfstudio`]: read/write nerfstudio `transforms.json`.
//! - [`colmap`]: read COLMAP sparse models (text and binary).
//! - [`images`]: load RGB images and depth maps, rescaling intrinsics to the loaded size.
//! - [`summary`]: [`read_dataset`] for any supported layout, and a validation summary.
//! - [`error`]: [`DataError`], what any reader can fail with.

pub mod colmap;
pub mod dataset;
pub mod error;
pub mod images;
pub mod nerfstudio;
pub mod summary;

pub use dataset::{Dataset, Frame, Split};
pub use error::DataError;
pub use summary::read_dataset;
