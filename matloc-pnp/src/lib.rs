//! Camera pose from 2D–3D matches: the last stage of matloc-nerf localisation, usable on its own.
//!
//! - [`p3p()`]: Lambda Twist P3P minimal solver (up to 4 poses from 3 matches).
//! - [`epnp()`]: EPnP non-minimal solver, with the planar case (3 control points) for
//!   aerial-like scenes.
//! - [`ransac()`]: generic LO-RANSAC over an [`Estimator`] and a [`Sampler`] (uniform or
//!   PROSAC), MSAC scoring with the threshold in pixels, adaptive termination by confidence.
//! - [`refine_pose()`]: Levenberg–Marquardt on the reprojection error in pixels through the full
//!   camera model (OpenCV distortion included), with a [`RobustLoss`].
//! - [`significance`]: the a-contrario number of false alarms of a consensus (could these
//!   inliers be chance?).
//! - [`PoseSolver`]: the object-safe interface; [`LoRansacPnp`] is P3P in LO-RANSAC followed by
//!   robust refinement, [`EpnpPnp`] fits clean inlier sets.
//!
//! Conventions (as in `matloc-core`): poses are `cam_from_world` with OpenCV camera axes
//! (x right, y down, z forward); pixel centres sit at `+0.5`. Distorted pixels are undistorted
//! once up front; the minimal solver and the RANSAC residuals work on undistorted normalised
//! coordinates scaled by the focal lengths (pixels), and the final refinement measures
//! reprojection error in real pixels through the distortion model. All geometry is `f64`.
//!
//! # Example
//!
//! ```
//! use matloc_core::{Camera, Pose};
//! use matloc_pnp::{LoRansacPnp, PnpInput, PoseSolver};
//! use nalgebra::{Point3, Translation3, UnitQuaternion};
//! use rand::SeedableRng;
//!
//! let camera = Camera::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0).unwrap();
//! // Camera 40 m above a gently sloped ground, looking down (z forward = world −z).
//! let cam_from_world = Pose::from_parts(
//!     Translation3::new(1.0, -2.0, 40.0),
//!     UnitQuaternion::from_euler_angles(std::f64::consts::PI + 0.05, 0.02, 0.3),
//! );
//! let mut points_world = Vec::new();
//! let mut pixels = Vec::new();
//! for i in 0..15 {
//!     for j in 0..15 {
//!         let p = Point3::new(i as f64 * 2.0 - 14.0, j as f64 * 2.0 - 14.0, 0.05 * i as f64);
//!         let mut px = camera.project_world(&cam_from_world, &p).unwrap();
//!         if (i + j) % 3 == 0 {
//!             px.x += 57.0; // a wrong match
//!         }
//!         points_world.push(p);
//!         pixels.push(px);
//!     }
//! }
//! let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
//! let result = LoRansacPnp::default()
//!     .solve(&PnpInput::new(&camera, &pixels, &points_world), &mut rng)
//!     .unwrap();
//! let t_err = matloc_core::metrics::translation_error_m(&result.cam_from_world, &cam_from_world);
//! assert!(t_err < 1e-6);
//! assert_eq!(result.stats.num_inliers, 150);
//! ```

// `!(x > 0.0)` is deliberate throughout: it rejects NaN along with non-positive values.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod epnp;
pub mod error;
pub mod estimator;
pub mod model;
pub mod p3p;
mod poly;
pub mod ransac;
pub mod refine;
pub mod significance;
pub mod solver;
pub mod synthetic;

pub use epnp::epnp;
pub use error::PnpError;
pub use estimator::AbsolutePoseEstimator;
pub use model::PoseMatrix;
pub use p3p::p3p;
pub use ransac::{
    Estimator, ProsacSampler, RansacOptions, RansacOutput, Sampler, SamplerKind, UniformSampler,
    ransac,
};
pub use refine::{RefineOptions, RefineReport, RobustLoss, refine_pose};
pub use solver::{
    EpnpPnp, LoRansacPnp, MIN_CORRESPONDENCES, PnpInput, PnpOptions, PnpResult, PnpStats,
    PoseSolver, solve_pnp,
};
