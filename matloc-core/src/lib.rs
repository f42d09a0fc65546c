//! Plain types shared by every matloc-nerf crate: camera models, frame-named poses,
//! image and dense feature-map buffers, and the error metrics used in evaluation.
//!
//! Conventions (see ARCHITECTURE.md):
//! - Poses are `cam_from_world` (world → camera) rigid transforms with OpenCV camera axes
//!   (x right, y down, z forward). Conversions to nerfstudio/OpenGL, COLMAP and Mega-NeRF
//!   conventions live in [`pose`].
//! - Continuous pixel coordinates put the centre of pixel `(col, row)` at `(col + 0.5, row + 0.5)`
//!   (the COLMAP / nerfstudio convention), so the image spans `[0, W] × [0, H]`.
//! - Geometry is `f64`; images and features are `f32`.

#[cfg(feature = "burn")]
pub mod backend;
pub mod camera;
pub mod fsutil;
pub mod hash;
pub mod image;
pub mod limits;
pub mod metrics;
pub mod pose;
pub mod shadow;
pub mod subset;

pub use camera::{Camera, CameraError, Distortion, ImplausibleCamera};
pub use image::{FeatureMap, Image, ImageError};
pub use pose::{Pose, PoseError};
