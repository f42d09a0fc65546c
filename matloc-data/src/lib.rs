//! Dataset formats and the procedural synthetic aerial world.
//!
//! - [`dataset`]: the in-memory [`Dataset`] every reader produces (frames with intrinsics,
//!   `cam_from_world` pose, image and optional depth path, split).
//! - [`nerfstudio`]: read/write nerfstudio `transforms.json`.
//! - [`colmap`]: read COLMAP sparse models (text and binary).
//! - [`images`]: load RGB images and depth maps, rescaling intrinsics to the loaded size.
//! - [`synth`]: the deterministic synthetic aerial world, its renderer and survey capture.
//! - [`fsutil`]: atomic file writes (temporary file + rename).

pub mod colmap;
pub mod dataset;
pub mod error;
pub mod fsutil;
pub mod images;
pub mod nerfstudio;
pub mod summary;
pub mod synth;

pub use dataset::{Dataset, Frame, Split};
pub use error::DataError;
pub use summary::read_dataset;
