//! Dataset formats: the in-memory dataset, its readers and writers, image and depth loading.
//!
//! - [`dataset`]: the in-memory [`Dataset`] every reader produces (frames with intrinsics,
//!   `cam_from_world` pose, image and optional depth path, split).
//! - [`nerfstudio`]: read/write nerfstudio `transforms.json`.
//! - [`colmap`]: read COLMAP sparse models (text and binary).
//! - [`ply`], [`points`]: a dataset's sparse point cloud (COLMAP `points3D` with tracks, or a
//!   PLY file) as [`points::SparsePoints`].
//! - [`meganerf`]: read/write the Mega-NeRF / Mill-19 layout (`coordinates.pt`, per-image
//!   metadata `.pt` files), undoing its normalisation; [`torch_pt`]: the `.pt` files themselves.
//! - [`split`]: [`split::SplitRule`], a test split for data that has none.
//! - [`images`]: load RGB images and depth maps, rescaling intrinsics to the loaded size.
//! - [`query`]: query input: intrinsics as requests and hloc query lists state them, query
//!   images decoded and brought to the map's resolution, query lists and paths.
//! - [`summary`]: [`read_dataset`] for any supported layout, and a validation summary.
//! - [`error`]: [`DataError`], what any reader can fail with.

pub mod colmap;
pub mod dataset;
pub mod error;
pub mod images;
pub mod meganerf;
pub mod nerfstudio;
pub mod ply;
pub mod points;
pub mod query;
pub mod split;
pub mod summary;
pub mod torch_pt;

pub use dataset::{Dataset, Frame, PointSource, Split};
pub use error::DataError;
pub use summary::read_dataset;
