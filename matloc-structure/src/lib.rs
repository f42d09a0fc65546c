//! Structure-based localization against a map's own training images.
//!
//! The map side ([`store`]): keypoints of the training images, matched between neighbours
//! and triangulated with the known poses, every keypoint that observes a point kept with its
//! binary and gradient-histogram descriptors ([`StructureMap`]). The query side
//! ([`localize()`]): the query's keypoints are matched (gradient descriptors by default,
//! [`QueryDescriptor`]) to the images nearest a start pose (a place hypothesis), P3P LO-RANSAC and
//! Levenberg–Marquardt solve the pose, a second solve starts from the images nearest the
//! estimate, and a pose is accepted when its consensus is a-contrario significant; then each
//! inlier's query pixel is aligned to the patches of its point's observations ([`align`]) and
//! the pose solved again. The map keeps every training image's gray values at the detection
//! size for that (about 77 KB per 320×240 image).
//!
//! Real photos of the map are sharper than any render and carry the scene's true texture, so
//! matching against them gives sub-pixel correspondences where a render-based method gets
//! blur; the cost is the stored descriptors (~172 bytes per observation).

pub mod align;
pub mod error;
pub mod localize;
pub mod rendered;
pub mod store;

pub use align::AlignOptions;
pub use error::StructureError;
pub use localize::{
    QueryDescriptor, StartReport, StructureOptions, StructureResult, localize,
    localize_with_references, render_agreement,
};
pub use matloc_keypoints::DescriptorKind;
pub use rendered::{ReferenceRenderer, RenderedOptions, RenderedReference};
pub use store::{
    ImageAppearance, ReprojectionStats, STRUCTURE_FORMAT, StructureImage, StructureMap,
};
