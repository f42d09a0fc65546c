//! An ORB-like keypoint pipeline, written for the "rendered RGB + keypoints" localization
//! baseline: render RGB at the coarse pose, match keypoints against the query, lift with the
//! rendered depth, solve PnP.
//!
//! - [`detect_and_describe`]: a scale pyramid (factor 1.2), FAST-9 corners ranked by the Harris
//!   response with 3×3 non-maximum suppression and a per-cell cap so keypoints spread over the
//!   image, orientation by the intensity centroid, and a 256-bit rotated BRIEF descriptor on a
//!   Gaussian-smoothed image (a fixed, seeded test pattern inside a disk of radius 15, so any
//!   rotation stays inside the patch).
//! - [`match_descriptors`]: brute-force Hamming distances, mutual nearest neighbours, Lowe's
//!   ratio test and a distance cap.
//!
//! Coordinates follow `matloc-core`: the centre of pixel `(col, row)` is `(col + 0.5, row + 0.5)`.

mod detect;
mod gray;
mod matching;

pub use detect::{Descriptor, Keypoint, KeypointConfig, detect_and_describe};
pub use gray::GrayImage;
pub use matching::{KeypointMatch, MatchConfig, hamming, match_descriptors};
