//! Pose groups and the place predictor that gives a query image its coarse pose (paper
//! Section 3.2, Table 4).
//!
//! Training poses are grouped by two-stage K-means ([`groups`]): camera centres first, then
//! viewing directions inside every spatial cluster; each group's medoid is its coarse pose and
//! each group knows the sub-NeRF block that serves it. The place classifier ([`model`]) is a small
//! CNN (burn, `flex` CPU backend, trained from scratch) whose L2-normalised embedding is trained
//! with the ArcFace additive angular margin loss over the groups, on augmented images
//! ([`augment`]). The network sees the image's two shadow-invariant channels
//! ([`NetConfig::shadow_invariant`]), so photos under another sun, exposure or white balance
//! look like the map's. The baseline regresses translation + quaternion (PoseNet-style) on the
//! same backbone. Both sit behind [`PlacePredictor`] ([`predictor`]).

pub mod augment;
pub mod error;
pub mod groups;
pub mod model;
pub mod predictor;

pub use augment::{AugmentConfig, augment};
pub use error::PlaceError;
pub use groups::{GroupConfig, PoseGroup, PoseGroups, median_viewing_distance};
pub use model::{ArcFaceConfig, NetConfig, arcface_loss, regression_loss};
pub use predictor::{
    EpochReport, ExtraViews, MODEL_JSON, MODEL_WEIGHTS, PLACE_MODEL_VERSION, PlaceHypothesis,
    PlaceMethod, PlaceModel, PlacePredictor, TrainConfig, surface_points, view_overlap,
    view_point_from_depth,
};
