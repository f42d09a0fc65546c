//! Localizer settings.

use matloc_core::{Camera, Image};
use matloc_match::featuremetric::FeatureMetricConfig;
use matloc_pnp::PnpOptions;
use serde::{Deserialize, Serialize};

use crate::localizer::confidence::ConfidenceModel;

/// Localizer settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LocalizeOptions {
    /// Place hypotheses to try, best first.
    pub top_k: usize,
    /// Render/match passes per hypothesis (1 = the paper's single pass); a third pass changed
    /// nothing measurable and costs time (docs/DECISIONS.md).
    pub max_passes: usize,
    /// Stop refining when the pose moves less than this (metres) ...
    pub converge_translation_m: f64,
    /// ... and less than this (degrees).
    pub converge_rotation_deg: f64,
    /// Rendered cells with less accumulated opacity are not matched.
    pub min_accumulation: f32,
    /// A solved pose farther than this from its hypothesis' coarse pose (metres) is rejected:
    /// PnP on a wrong place can find a self-consistent pose far away.
    pub max_correction_m: f64,
    /// The same bound on the rotation, degrees.
    pub max_correction_deg: f64,
    /// Confidence model and refusal threshold (replaced by the calibrated one when a map is
    /// loaded).
    pub confidence: ConfidenceModel,
    /// Seed of the PnP sampler (per query, so results do not depend on query order).
    pub seed: u64,
    /// Matching window as a fraction of the image width: a query cell and a rendered cell are
    /// candidates only within it (0 = global mutual nearest neighbours, as the paper). The
    /// render is made at the coarse pose, so the true match is near; the window keeps PnP from
    /// far-away self-consistent poses that global matches of a weak encoder support.
    pub window_fraction: f64,
    /// PnP inlier threshold of a hypothesis' first pass, in query cells (the encoder's stride,
    /// so it scales with the resolution): learned-encoder matches are often a cell or two off.
    pub first_pass_threshold_cells: f64,
    /// The same for the refinement passes (rendered at the previous estimate).
    pub refine_threshold_cells: f64,
    /// Feature-metric refinement after each pass's PnP (`None`: off): the pose is moved so the
    /// query feature map agrees with every rendered point's feature, not only the mutual
    /// matches ([`matloc_match::featuremetric`]); later passes start it from the pose the map
    /// was rendered at.
    pub featuremetric: Option<FeatureMetricConfig>,
    /// Ray-marching steps of every render through a loaded map (0 = each model's own setting);
    /// the baselines render through the same models with the same setting.
    pub render_steps: usize,
    /// Hypotheses after the first with a place score below this are skipped (they are sorted
    /// by score): a refused query otherwise pays for every hypothesis.
    pub min_place_score: f32,
    /// A pass's PnP consensus must be beyond chance: its a-contrario number of false alarms
    /// ([`matloc_pnp::significance`]) must be below `10^max_log10_nfa`, or the pass scores 0
    /// whatever the calibrated confidence says (its pose still seeds the next pass; `+∞` turns
    /// the test off). A floor under the confidence fitted on a few dozen attempts.
    pub max_log10_nfa: f64,
    /// A pass whose pose is rotated more than this from its hypothesis' coarse pose (degrees)
    /// scores 0 but still seeds the next pass. Maps set it by calibration
    /// ([`crate::config::CalibrationConfig::rotation_bound_margin`]); 180 = off.
    pub max_accept_rotation_deg: f64,
    /// With a selection smaller than the encoder's dims: render every encoded dim and refine
    /// feature-metrically on all of them, matching on the selection only (`false`: render and
    /// refine on the selection).
    pub refine_on_all_dims: bool,
    /// Options of the pose solver (P3P in LO-RANSAC with LM refinement) of maps loaded with
    /// their own components; each pass sets the inlier threshold from the `*_threshold_cells`.
    pub pnp: PnpOptions,
    /// A query whose longer side exceeds this is first box-downscaled by the smallest integer
    /// factor that brings it within (`None`: used as given). A loaded map falls back to its
    /// working resolution, so queries at camera resolution cost what the map's views cost.
    pub max_side: Option<u32>,
}

/// `image` and `camera` reduced to at most `max_side` on the longer side (integer box
/// downscale, exact `1 / factor` intrinsics), or borrowed unchanged.
pub fn query_at_working_size<'a>(
    image: &'a Image<f32>,
    camera: &Camera,
    max_side: Option<u32>,
) -> (std::borrow::Cow<'a, Image<f32>>, Camera) {
    let f = matloc_data::images::working_factor(camera.width, camera.height, max_side);
    if f <= 1 {
        return (std::borrow::Cow::Borrowed(image), *camera);
    }
    (
        std::borrow::Cow::Owned(matloc_core::image::downscale_box(image, f)),
        matloc_data::images::box_downscaled_camera(camera, f),
    )
}

impl Default for LocalizeOptions {
    fn default() -> Self {
        Self {
            top_k: 3,
            max_passes: 2,
            converge_translation_m: 0.02,
            converge_rotation_deg: 0.05,
            min_accumulation: 0.5,
            max_correction_m: 25.0,
            max_correction_deg: 45.0,
            confidence: ConfidenceModel::default(),
            seed: 0,
            window_fraction: 0.2,
            first_pass_threshold_cells: 3.0,
            refine_threshold_cells: 3.0,
            featuremetric: Some(FeatureMetricConfig::default()),
            render_steps: 128,
            min_place_score: 0.01,
            max_log10_nfa: 0.0,
            max_accept_rotation_deg: 180.0,
            refine_on_all_dims: true,
            pnp: PnpOptions::default(),
            max_side: None,
        }
    }
}
