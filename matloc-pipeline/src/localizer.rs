//! The MatLoc localizer: place recognition → render selected features at the coarse pose →
//! encode the query → mutual-nearest-neighbour matches → PnP, composed from the stage traits
//! so any stage can be swapped.
//!
//! Beyond the paper's single pass:
//! - **top-k fallback**: when the best place hypothesis does not give a confident pose, the next
//!   ones are tried (up to [`LocalizeOptions::top_k`]);
//! - **iterative refinement**: after a pose within the correction limits (confident or not), the
//!   map is re-rendered at the estimate and matched again until the pose moves less than the
//!   convergence thresholds
//!   (up to [`LocalizeOptions::max_passes`] passes in all);
//! - **feature-metric refinement**: after each pass's PnP the pose is refined against every
//!   rendered point's feature, not only the mutual matches
//!   ([`LocalizeOptions::featuremetric`]);
//! - **calibrated confidence and refusal**: every attempt is scored by the
//!   [`ConfidenceModel`]; below its threshold the query is reported as not localized instead
//!   of returning a wrong pose; under it, a pass whose PnP consensus chance could produce
//!   (a-contrario test, [`LocalizeOptions::max_log10_nfa`]) scores 0 whatever the model says.

use std::time::Instant;

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::{Camera, Image, Pose};
use matloc_match::featuremetric::{FeatureMetricConfig, refine_pose};
use matloc_match::gt::ViewRenderer;
use matloc_match::localize::{LocalizeError, render_map_points, solve_pose_within};
use matloc_match::{Matcher, QueryFeatures};
use matloc_place::PlacePredictor;
use matloc_pnp::PoseSolver;
use matloc_pnp::significance::{chance_inlier_probability, log10_nfa};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::confidence::{ConfidenceModel, Evidence};
use crate::error::PipelineError;

/// Encodes a query image into the NeRF feature domain (all the dims the map may select from).
pub trait QueryFeatureEncoder: Send + Sync {
    /// Field dims of the output channels, in channel order.
    fn dims(&self) -> &[usize];
    /// Image pixels per output cell (the rendering grid's stride).
    fn stride(&self) -> u32;
    /// Feature map of an RGB image (`⌊H/stride⌋ × ⌊W/stride⌋ × dims`).
    fn encode(&self, image: &Image<f32>) -> Result<matloc_core::FeatureMap, PipelineError>;
}

/// One sub-NeRF block as the localizer sees it: its renderer, the query encoder into its
/// feature space, its matcher and the dims selected for its region.
///
/// Each sub-NeRF has its own hash grid, so its intermediate features live in their own space:
/// the encoder (and the matcher's feature statistics) belong to the block, not to the map.
pub struct LocalizerBlock<'a> {
    /// Renders features + depth of the block.
    pub renderer: &'a dyn ViewRenderer,
    /// Query image → this block's feature domain.
    pub encoder: &'a dyn QueryFeatureEncoder,
    /// 2D–3D matcher (with this block's feature normalisation).
    pub matcher: &'a dyn Matcher,
    /// Field dims rendered in this block's region (a subset of the encoder's dims): the
    /// matcher's feature space, and what feature-metric refinement aligns.
    pub dims: Vec<usize>,
    /// The dims among `dims` that matching uses (`None`: all of `dims`). Matching on the few
    /// selected dims while refining on all of them keeps the paper's cheap matching without
    /// giving up the refinement's accuracy.
    pub match_dims: Option<Vec<usize>>,
}

/// Localizer settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LocalizeOptions {
    /// Place hypotheses to try, best first.
    pub top_k: usize,
    /// Render/match passes per hypothesis (1 = the paper's single pass). Default 2: on the
    /// `small` demo map a third pass changed neither accuracy (accepted median 1.03 m with 2
    /// passes, 1.08 m with 3) nor refusals and cost 0.04 s per query (0.231 → 0.273 s, idle).
    pub max_passes: usize,
    /// Stop refining when the pose moves less than this (metres) ...
    pub converge_translation_m: f64,
    /// ... and less than this (degrees).
    pub converge_rotation_deg: f64,
    /// Rendered cells with less accumulated opacity are not matched.
    pub min_accumulation: f32,
    /// A solved pose farther than this from its hypothesis' coarse pose (metres) is rejected:
    /// a place hypothesis is coarse, but not that wrong, and PnP on a wrong place can find a
    /// self-consistent pose far away (measured on the synthetic world: a camera flipped by
    /// 180° and moved 80 m, with 196 inliers).
    pub max_correction_m: f64,
    /// The same bound on the rotation, degrees.
    pub max_correction_deg: f64,
    /// Confidence model and refusal threshold.
    pub confidence: ConfidenceModel,
    /// Seed of the PnP sampler (per query, so results do not depend on query order).
    pub seed: u64,
    /// Matching window: a query cell and a rendered cell are candidates only when their
    /// pixels are within this fraction of the image width (0 = global mutual nearest
    /// neighbours, as in the paper). The render is made at the coarse pose, a few metres off,
    /// so the true match is near; the window keeps PnP from the self-consistent far-away poses
    /// that global matches of a weak encoder support. Default 0.2 (64 px at 320 px, 16 cells).
    /// Same maps recalibrated, global → 0.2: `small` demo-8 refusals 26.7 → 3.3 %, recall at
    /// 1 m 63 → 80 %; demo-9 median 0.401 m / 0.514° → 0.319 m / 0.370°; demo-7 0.393 / 0.454
    /// → 0.331 / 0.352; `rubble` 0.217 / 0.237 → 0.187 / 0.204, refusals 12.5 → 7.5 %; no
    /// false accept (0.1 and 0.15 gave one on `rubble`). Used by maps loaded through
    /// [`crate::stages::LoadedBlocks`].
    pub window_fraction: f64,
    /// PnP inlier threshold of a hypothesis' first pass, in query cells (the encoder's stride,
    /// so it scales with the query resolution). Learned-encoder matches are often a cell or
    /// two off (tiny preset, encoder all 47 dims from the true pose: 17 % of MNN matches within
    /// 2 px, 44 % within 8 px = 2 cells); one step from 3 m / 5° starts reaches 1 m / 5° in
    /// 3/30 test views at 0.75 cells (3 px), 9/30 at 1.5–2.5 cells.
    pub first_pass_threshold_cells: f64,
    /// The same for the refinement passes (rendered at the previous estimate).
    pub refine_threshold_cells: f64,
    /// Feature-metric refinement after each pass's PnP (`None`: off): the pose is moved so
    /// that the query feature map agrees with every rendered point's feature, not only the
    /// mutual matches ([`matloc_match::featuremetric`]). The first pass starts it from the PnP
    /// pose, later passes from the pose the map was rendered at (PnP still runs there, for the
    /// confidence). Tiny preset, learned encoder, 30 starts at 3 m / 5°: PnP alone median
    /// 1.58 m (8/30 within 1 m); + refinement 0.71 m (23/30); re-rendered at that pose and
    /// refined again 0.48 m (22/30), vs 0.62 m when the second round starts from its PnP pose.
    pub featuremetric: Option<FeatureMetricConfig>,
    /// Steps of the ray-marching grid of every render through a map loaded by
    /// [`crate::stages::LoadedBlocks`] (0 = each model's own setting, 256 for survey scenes).
    /// The baseline methods render through the same models, so they get the same setting.
    /// Default 128: the steps span each ray's box-clipped range (tens of metres), so 256 is
    /// finer than the rendered cells need, and samples per ray scale with the steps (37.9 at
    /// 256, 19.1 at 128 on `small`). Measured on the session-7 maps (recalibrated, 2 passes):
    /// `small` 0.408 m / 0.323 s per query at 256, 0.367 m / 0.218 s at 128, 0.370 m / 0.199 s
    /// at 96, 0.859 m / 0.186 s at 64; `rubble` 0.211 m / 0.298 s at 256, 0.199 m / 0.205 s at
    /// 128, 0.199 m / 0.175 s at 96.
    pub render_steps: usize,
    /// Hypotheses after the first with a place score below this are not tried (they are
    /// sorted by score, so the rest are skipped too). A refused query otherwise pays for
    /// every hypothesis: on the sixth `small` demo map 8 refused queries took 0.43 s each
    /// against 0.16 s for an accepted one, and 7 of 58 hypotheses scored below 0.01. No
    /// hypothesis after the first that was accepted on four maps scored below 0.02.
    pub min_place_score: f32,
    /// A pass's PnP consensus must be beyond chance: its a-contrario number of false alarms
    /// ([`matloc_pnp::significance`], wrong matches uniform over the image or over the
    /// matching window when there is one, the PnP inlier radius) must be below
    /// `10^max_log10_nfa`, or the pass scores 0 whatever the calibrated confidence says (its
    /// pose still seeds the next pass; `+∞` turns the test off). The confidence is fitted on a few
    /// dozen calibration attempts; on a CI-sized map with 3 correct ones among 24 it accepted
    /// 9–10 inliers of ~25 matches, which chance reaches (log10 NFA ≈ 0). On the `small` and
    /// `rubble` calibration sets 1 of 46 correct attempts each is above 0 (7 of 95 and 11 of
    /// 212 inliers), and 11–14 of ~50 wrong ones are below it: the test is a floor under the
    /// calibrated confidence, not a replacement.
    pub max_log10_nfa: f64,
    /// A pass whose pose is rotated more than this from its hypothesis' coarse pose
    /// (degrees) scores 0, but still seeds the next pass (a first pass from a coarse pose
    /// metres off can be tilted wrongly and still lead the second to the right pose). Maps
    /// set it by calibration ([`crate::stages::CalibrationConfig::rotation_bound_margin`]):
    /// wrong poses that PnP and the confidence accept slide along the near-nadir
    /// tilt/shift ambiguity, away from the coarse attitude. Default 180 (off).
    pub max_accept_rotation_deg: f64,
    /// With a selection smaller than the encoder's dims, render every encoded dim and refine
    /// feature-metrically on all of them, matching still on the selection only (maps loaded
    /// through [`crate::stages::LoadedBlocks`]; `false`: render and refine on the selection).
    /// Default `true` (no effect on maps that match on all 47 dims, the build's default): over
    /// seven maps (Table 3, `matloc match eval --map`, docs/BENCHMARKS.md session 15) refining
    /// on all dims after matching on 5 selected ones lowered the median in 11 of 14
    /// map/selector pairs (render-F1 and GT-pair greedy N_s = 5), significantly in 3 (up to
    /// −0.18 m), never significantly raised it, and leaves it indistinguishable from matching
    /// on all 47; matching on the 5 alone is significantly worse than 47 dims on `rubble`.
    pub refine_on_all_dims: bool,
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
        }
    }
}

/// What happened with one place hypothesis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HypothesisReport {
    /// Pose group.
    pub group: usize,
    /// Place score.
    pub score: f32,
    /// Block rendered.
    pub block: usize,
    /// Coarse pose of the group.
    pub coarse_cam_from_world: Pose,
    /// Matches of the last pass.
    pub matches: usize,
    /// PnP inliers of the last pass.
    pub inliers: usize,
    /// Confidence of the last pass.
    pub confidence: f64,
    /// Passes run.
    pub passes: usize,
    /// Whether this hypothesis gave the accepted pose.
    pub accepted: bool,
    /// Why it failed, when it did before PnP produced a pose.
    pub failure: Option<String>,
    /// Feature-metric alignment contrast of the last pass (0 when refinement is off or failed;
    /// see [`matloc_match::featuremetric::FeatureMetricOutcome::contrast`]).
    #[serde(default)]
    pub alignment: f64,
    /// Base-10 log of the a-contrario number of false alarms of the last pass's PnP consensus
    /// (`None` when PnP gave no pose or the consensus was no larger than a minimal sample).
    #[serde(default)]
    pub log10_nfa: Option<f64>,
}

/// The result of localizing one query.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Localization {
    /// The pose, or `None` when refused ("not localized").
    pub cam_from_world: Option<Pose>,
    /// Confidence of the returned (or best refused) attempt.
    pub confidence: f64,
    /// PnP inliers of the returned attempt.
    pub inliers: usize,
    /// Hypotheses tried, in order.
    pub hypotheses: Vec<HypothesisReport>,
    /// Seconds per stage, summed over hypotheses and passes
    /// (`place`, `encode`, `render`, `match`, `pnp`, `refine`).
    pub stage_seconds: Vec<(String, f64)>,
    /// End-to-end seconds.
    pub total_seconds: f64,
}

/// The MatLoc localizer over the five stage interfaces.
pub struct Localizer<'a> {
    /// Coarse poses: top-k pose groups with the block serving each.
    pub place: &'a dyn PlacePredictor,
    /// Sub-NeRF blocks, indexed by block id.
    pub blocks: Vec<LocalizerBlock<'a>>,
    /// Pose solver.
    pub solver: &'a dyn PoseSolver,
    /// Settings.
    pub options: LocalizeOptions,
}

struct StageClock(Vec<(String, f64)>);

impl StageClock {
    fn add(&mut self, name: &str, t: Instant) {
        let s = t.elapsed().as_secs_f64();
        if let Some(e) = self.0.iter_mut().find(|(n, _)| n == name) {
            e.1 += s;
        } else {
            self.0.push((name.to_string(), s));
        }
    }
}

/// Result of one render → match → PnP pass.
struct Pass {
    pose: Option<Pose>,
    matches: usize,
    inliers: usize,
    evidence: Evidence,
    /// See [`HypothesisReport::log10_nfa`] (`+∞` when not measured).
    log10_nfa: f64,
}

/// Positions of field dims `dims` in the list `within` (an encoder's output channels, a
/// block's rendered dims); a dim it lacks is [`PipelineError::DimsNotEncoded`].
pub(crate) fn positions_of(dims: &[usize], within: &[usize]) -> Result<Vec<usize>, PipelineError> {
    dims.iter()
        .map(|d| {
            within
                .iter()
                .position(|e| e == d)
                .ok_or(PipelineError::DimsNotEncoded { dim: *d })
        })
        .collect()
}

impl Localizer<'_> {
    /// Channel indices of `dims` in the encoder's output.
    fn channels_of(block: &LocalizerBlock<'_>) -> Result<Vec<usize>, PipelineError> {
        positions_of(&block.dims, block.encoder.dims())
    }

    fn pass(
        &self,
        block: &LocalizerBlock<'_>,
        query: &QueryFeatures,
        camera: &Camera,
        cam_from_world: &Pose,
        threshold_cells: f64,
        refine_from_render: bool,
        rng: &mut ChaCha8Rng,
        clock: &mut StageClock,
    ) -> Result<Pass, PipelineError> {
        let t = Instant::now();
        let points = render_map_points(
            block.renderer,
            camera,
            cam_from_world,
            block.encoder.stride(),
            &block.dims,
            self.options.min_accumulation,
        )
        .map_err(localize_err)?;
        clock.add("render", t);
        let t = Instant::now();
        let selection = match &block.match_dims {
            Some(m) => Some(positions_of(m, &block.dims)?),
            None => None,
        };
        let matches = match block
            .matcher
            .match_features(query, &points, selection.as_deref())
        {
            Ok(m) => m,
            Err(matloc_match::MatchError::Empty { .. }) => Vec::new(),
            Err(e) => return Err(PipelineError::Match(e)),
        };
        clock.add("match", t);
        let t = Instant::now();
        let threshold_px = threshold_cells * block.encoder.stride() as f64;
        let solved = solve_pose_within(&matches, camera, self.solver, Some(threshold_px), rng);
        clock.add("pnp", t);
        let refined = match (&solved, &self.options.featuremetric) {
            (Ok(r), Some(cfg)) => {
                let t = Instant::now();
                let init = if refine_from_render {
                    cam_from_world
                } else {
                    &r.cam_from_world
                };
                let (stats, l2) = block.matcher.feature_space();
                // Too few rendered points in view is not an error of the query: keep PnP's pose.
                let out = refine_pose(query, &points, camera, init, None, stats, l2, cfg).ok();
                clock.add("refine", t);
                out.map(|o| (o.cam_from_world, o.contrast))
            }
            _ => None,
        };
        let alignment = refined.as_ref().map_or(0.0, |r| r.1);
        let refined = refined.map(|r| r.0);
        Ok(match solved {
            Ok(r) => Pass {
                pose: Some(refined.unwrap_or(r.cam_from_world)),
                matches: matches.len(),
                inliers: r.stats.num_inliers,
                // P3P samples three matches.
                log10_nfa: log10_nfa(
                    matches.len(),
                    r.stats.num_inliers,
                    3,
                    chance_inlier_probability(
                        threshold_px,
                        camera.width,
                        camera.height,
                        block.matcher.window_px(),
                    ),
                ),
                evidence: Evidence {
                    inliers: r.stats.num_inliers,
                    inlier_ratio: r.stats.inlier_ratio,
                    matches: matches.len(),
                    alignment,
                },
            },
            Err(_) => Pass {
                pose: None,
                matches: matches.len(),
                inliers: 0,
                log10_nfa: f64::INFINITY,
                evidence: Evidence {
                    inliers: 0,
                    inlier_ratio: 0.0,
                    matches: matches.len(),
                    alignment: 0.0,
                },
            },
        })
    }

    /// Localizes one query image taken with `camera` (any resolution the camera describes;
    /// lens distortion is handled by the renderer and the solver).
    pub fn localize(
        &self,
        image: &Image<f32>,
        camera: &Camera,
    ) -> Result<Localization, PipelineError> {
        let start = Instant::now();
        let (w, h, c) = image.shape();
        if w != camera.width as usize || h != camera.height as usize || c != 3 {
            return Err(PipelineError::QueryShape {
                image: (w, h, c),
                camera: (camera.width, camera.height),
            });
        }
        let mut clock = StageClock(Vec::new());
        let mut rng = ChaCha8Rng::seed_from_u64(self.options.seed);

        let t = Instant::now();
        let hypotheses = self
            .place
            .predict(image, camera, self.options.top_k.max(1))
            .map_err(|e| PipelineError::Place(e.to_string()))?;
        clock.add("place", t);

        // Encoded query per block, computed when a hypothesis first needs that block.
        let mut encoded: Vec<Option<matloc_core::FeatureMap>> = vec![None; self.blocks.len()];

        let mut reports = Vec::new();
        let mut best: Option<(f64, usize, Pose)> = None;
        let mut accepted = None;
        for (index, hyp) in hypotheses.iter().enumerate() {
            if index > 0 && hyp.score < self.options.min_place_score {
                break;
            }
            let block_id = hyp.block.unwrap_or(0);
            let mut report = HypothesisReport {
                group: hyp.group,
                score: hyp.score,
                block: block_id,
                coarse_cam_from_world: hyp.cam_from_world,
                matches: 0,
                inliers: 0,
                confidence: 0.0,
                passes: 0,
                accepted: false,
                failure: None,
                alignment: 0.0,
                log10_nfa: None,
            };
            let Some(block) = self.blocks.get(block_id) else {
                report.failure = Some(format!("no block {block_id} in the map"));
                reports.push(report);
                continue;
            };
            let channels = Self::channels_of(block)?;
            if encoded[block_id].is_none() {
                let t = Instant::now();
                encoded[block_id] = Some(block.encoder.encode(image)?);
                clock.add("encode", t);
            }
            let map = encoded[block_id]
                .as_ref()
                .ok_or(PipelineError::Internal("query not encoded"))?;
            let query = QueryFeatures::new(
                map.select_channels(&channels),
                block.encoder.stride() as f64,
            );
            let mut pose = hyp.cam_from_world;
            let mut confidence = 0.0;
            for pass_index in 0..self.options.max_passes.max(1) {
                let threshold_cells = if pass_index == 0 {
                    self.options.first_pass_threshold_cells
                } else {
                    self.options.refine_threshold_cells
                };
                let pass = match self.pass(
                    block,
                    &query,
                    camera,
                    &pose,
                    threshold_cells,
                    pass_index > 0,
                    &mut rng,
                    &mut clock,
                ) {
                    Ok(p) => p,
                    Err(PipelineError::RenderFailure(e)) => {
                        report.failure = Some(e);
                        break;
                    }
                    Err(e) => return Err(e),
                };
                report.passes = pass_index + 1;
                report.matches = pass.matches;
                report.inliers = pass.inliers;
                report.alignment = pass.evidence.alignment;
                report.log10_nfa = pass.log10_nfa.is_finite().then_some(pass.log10_nfa);
                let new_pose = pass.pose.filter(|p| {
                    translation_error_m(p, &hyp.cam_from_world) <= self.options.max_correction_m
                        && rotation_error_deg(p, &hyp.cam_from_world)
                            <= self.options.max_correction_deg
                });
                let Some(new_pose) = new_pose else {
                    if pass_index == 0 {
                        report.failure = Some(match pass.pose {
                            Some(_) => "pose too far from the coarse pose".to_string(),
                            None => format!("no pose from {} matches", pass.matches),
                        });
                    }
                    break;
                };
                // A consensus chance could produce scores 0, but its pose still seeds the next
                // pass: from a coarse pose metres off, the first render gives few matches.
                let c = if pass.log10_nfa <= self.options.max_log10_nfa
                    && rotation_error_deg(&new_pose, &hyp.cam_from_world)
                        <= self.options.max_accept_rotation_deg
                {
                    self.options.confidence.confidence(&pass.evidence)
                } else {
                    0.0
                };
                let threshold = self.options.confidence.accept_threshold;
                // A refinement pass that loses the evidence keeps the earlier pose. (Comparing
                // raw confidences would stop on noise once they saturate near 1.) A weak first
                // pass still gets its refinement passes: the render at a coarse pose metres off
                // gives few matches, the render at the estimate many more.
                if pass_index > 0 && c < threshold && c <= confidence {
                    break;
                }
                confidence = c;
                report.confidence = c;
                let moved_t = translation_error_m(&new_pose, &pose);
                let moved_r = rotation_error_deg(&new_pose, &pose);
                pose = new_pose;
                if best.as_ref().is_none_or(|b| c > b.0) {
                    best = Some((c, pass.inliers, pose));
                }
                if pass_index > 0
                    && moved_t < self.options.converge_translation_m
                    && moved_r < self.options.converge_rotation_deg
                {
                    break;
                }
            }
            let ok = report.passes > 0
                && report.failure.is_none()
                && confidence >= self.options.confidence.accept_threshold;
            report.accepted = ok;
            reports.push(report);
            if ok {
                accepted = Some((confidence, reports.last().map_or(0, |r| r.inliers), pose));
                break;
            }
        }
        let (cam_from_world, confidence, inliers) = match (accepted, best) {
            (Some((c, n, p)), _) => (Some(p), c, n),
            (None, Some((c, n, _))) => (None, c, n),
            (None, None) => (None, 0.0, 0),
        };
        Ok(Localization {
            cam_from_world,
            confidence,
            inliers,
            hypotheses: reports,
            stage_seconds: clock.0,
            total_seconds: start.elapsed().as_secs_f64(),
        })
    }
}

fn localize_err(e: LocalizeError) -> PipelineError {
    match e {
        LocalizeError::Render(r) => PipelineError::RenderFailure(r.to_string()),
        LocalizeError::Match(m) => PipelineError::Match(m),
    }
}
