//! Query input, shared by `matloc localize`, `matloc eval` and `matloc serve`:
//!
//! - [`camera`]: intrinsics from a COLMAP model name + parameters (hloc's query lists, a
//!   request's `camera` part), nerfstudio keys or a matloc camera; unsupported models are
//!   rejected by name.
//! - [`image`]: decoding query images from bytes with limits, fitting intrinsics to the decoded
//!   size and bringing both to the map's resolution.
//! - [`spec`]: hloc query lists, image paths with their intrinsics and ground truth, and loading
//!   a query ready to localize.

pub mod camera;
pub mod image;
pub mod spec;

pub use self::camera::{CameraSpecError, parse_camera_json};
pub use self::image::{DecodeLimits, QueryError, decode_rgb, fit_to_image, to_map_resolution};
pub use self::spec::{
    Query, QueryInputError, QuerySpec, dataset_queries, load_query, parse_query_list,
    read_intrinsics, read_query_list, specs_from_paths,
};
