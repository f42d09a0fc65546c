//! The query path shared by `matloc localize`, `matloc eval` and `matloc serve`, after the
//! input side in [`matloc_data::query`] (intrinsics, query lists, images at the map's size):
//!
//! - [`batch`]: a batch of query specs localized in order, a failing query kept as its record.
//! - [`record`]: the JSON record of one query (`matloc localize --format jsonl`, the server's
//!   response body).
//! - [`poses`]: pose files of a batch (JSON lines, hloc, TUM, COLMAP, nerfstudio) in the data's
//!   world or the original one.

pub mod batch;
pub mod poses;
pub mod record;

pub use batch::{BatchError, batch_status, error_chain, localize_batch, localize_each};
pub use poses::{
    Localized, OutputWorld, PoseFormat, PoseWriteError, QueryRecord, WorldKind, write_poses,
};
pub use record::{error_record, localization_record};
