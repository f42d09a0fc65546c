//! An ORB-like keypoint pipeline with two descriptors, for the map's keypoint structure and
//! the "rendered RGB + keypoints" localization baseline.
//!
//! - [`detect_and_describe`]: a scale pyramid (factor 1.2), FAST-9 corners ranked by the Harris
//!   response with 3×3 non-maximum suppression and a per-cell cap so keypoints spread over the
//!   image, orientation by the intensity centroid, and a 256-bit rotated BRIEF descriptor on a
//!   Gaussian-smoothed image (a fixed, seeded test pattern inside a disk of radius 15, so any
//!   rotation stays inside the patch).
//! - [`detect_and_describe_gradients`]: the same keypoints with a float gradient-histogram
//!   descriptor (SIFT's 4 × 4 × 8 layout, RootSIFT normalisation, bytes).
//! - [`match_descriptors`]: brute-force distances (Hamming or Euclidean), mutual nearest
//!   neighbours, Lowe's ratio test and a distance cap.
//!
//! Coordinates follow `matloc-core`: the centre of pixel `(col, row)` is `(col + 0.5, row + 0.5)`.

mod detect;
mod gradient;
mod gray;
mod matching;

pub use detect::{Descriptor, Keypoint, KeypointConfig, detect_and_describe};
pub use gradient::{
    GradientDescriptor, GradientField, describe_gradients_at, detect_and_describe_both,
    detect_and_describe_gradients, gradient_distance_sq,
};
pub use gray::GrayImage;
pub use matching::{
    DescriptorKind, KeypointDescriptor, KeypointMatch, MatchConfig, hamming, match_descriptors,
};
