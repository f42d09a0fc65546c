//! Structure-based localization against a map's own training images.
//!
//! The map side ([`store`]): keypoints of the training images, matched between neighbours
//! and triangulated with the known poses, every keypoint that observes a point kept with its
//! descriptor ([`StructureMap`]). The query side ([`localize()`]): the query's keypoints are
//! matched to the images nearest a start pose (a place hypothesis), P3P LO-RANSAC and
//! Levenberg–Marquardt solve the pose, a second solve starts from the images nearest the
//! estimate, and a pose is accepted when its consensus is a-contrario significant.
//!
//! Real photos of the map are sharper than any render and carry the scene's true texture, so
//! matching against them gives sub-pixel correspondences where a render-based method gets
//! blur; the cost is the stored descriptors (~44 bytes per observation).

pub mod error;
pub mod localize;
pub mod store;

pub use error::StructureError;
pub use localize::{StartReport, StructureOptions, StructureResult, localize};
pub use store::{STRUCTURE_FORMAT, StructureImage, StructureMap};
