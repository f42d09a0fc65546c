//! Views rendered where no training image looks: the structure localizer's reference when a
//! query's viewpoint is one the survey never flew.
//!
//! A pose whose consensus passes every test but that no training image looks towards (a
//! viewpoint beyond the survey) cannot be confirmed by the training images. A
//! [`ReferenceRenderer`] (the map's radiance field) draws the scene at that pose; the pose is
//! accepted when the render agrees with the query there ([`RenderedOptions::min_agreement`]).
//! Optionally, when every start is refused, the best refused poses are rendered with their
//! depth and the query's keypoints matched to the render's solve the pose again
//! ([`RenderedOptions::max_renders`]).

use matloc_core::pose::Pose;
use matloc_core::{Camera, Image};
use nalgebra::Point3;
use serde::{Deserialize, Serialize};

/// The scene drawn at a pose with the query's camera.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderedReference {
    /// Colour in `[0, 1]`, the camera's size, 3 channels.
    pub image: Image<f32>,
    /// Per pixel (row-major), the depth along the optical axis in metres; 0 where nothing
    /// was hit.
    pub z_depth: Vec<f32>,
    /// Per pixel, the accumulated opacity in `[0, 1]`.
    pub accumulation: Vec<f32>,
}

/// Renders the scene at a pose: a map's radiance field behind the structure localizer.
pub trait ReferenceRenderer: Send + Sync {
    /// The view of `camera` at `cam_from_world`; `looking_at` is a world point the view is
    /// known to see (the consensus's points), so a map of several blocks can choose the one
    /// that holds it. `None` when nothing of the map can draw it.
    fn render_reference(
        &self,
        camera: &Camera,
        cam_from_world: &Pose,
        looking_at: &Point3<f64>,
    ) -> Option<RenderedReference>;
}

/// When and how the structure localizer renders a reference.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderedOptions {
    /// Render references at all (only where a renderer is given).
    pub enabled: bool,
    /// A consensus that passes every test but whose pose no training image looks towards
    /// (within `max_view_angle_deg`) is accepted when at least this share of the textured
    /// patches of a view rendered at the pose agree with the query there (zero-mean
    /// normalised cross-correlation of 13 px squares at 0.5 or more, within 2 px; both
    /// images blurred by 1 px). Read as the structure localizer's `min_agreement` is: half of
    /// what the map shows there must be seen in the query.
    pub min_agreement: f64,
    /// Gaussian blur of the render and the query before they are compared, pixels (a
    /// radiance field renders softer than a photograph).
    pub blur_px: f32,
    /// Render pixels whose accumulated opacity is below this are neither compared nor lifted
    /// to 3D.
    pub min_accumulation: f32,
    /// When every start is refused, the refused poses with at least `min_start_inliers`
    /// inliers (at most this many, best first) are rendered, the query's keypoints matched
    /// to the render's and lifted by its depth, the pose solved, rendered again there and
    /// solved once more; 0 = off. Each costs two renders.
    pub max_renders: usize,
    /// See `max_renders`.
    pub min_start_inliers: usize,
    /// A weak accepted consensus (under the localizer's `weak_inliers`) is rendered with up
    /// to this many unconfirmed consensuses at other places (one per place, most inliers
    /// first), and the one whose view agrees most with the query is kept; 0 = off.
    pub max_rivals: usize,
    /// Inliers a pose solved from a render needs (the NFA and image coverage tests are the
    /// localizer's own).
    pub min_inliers: usize,
    /// The second solve from a render must lie within this distance of the first, metres ...
    pub agree_m: f64,
    /// ... and this angle, degrees.
    pub agree_deg: f64,
}

impl Default for RenderedOptions {
    fn default() -> Self {
        RenderedOptions {
            enabled: true,
            min_agreement: 0.5,
            blur_px: 2.0,
            min_accumulation: 0.3,
            max_renders: 0,
            min_start_inliers: 8,
            max_rivals: 3,
            min_inliers: 20,
            agree_m: 1.0,
            agree_deg: 3.0,
        }
    }
}
