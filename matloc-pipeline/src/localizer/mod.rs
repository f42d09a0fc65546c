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
use matloc_match::ViewRenderer;
use matloc_match::featuremetric::refine_pose;
use matloc_match::localize::{render_map_points, solve_pose_within};
use matloc_match::{Matcher, QueryFeatures};
use matloc_place::{PlaceHypothesis, PlacePredictor};
use matloc_pnp::PoseSolver;
use matloc_pnp::significance::{chance_inlier_probability, log10_nfa};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::error::PipelineError;

pub mod confidence;
pub mod options;

use confidence::Evidence;
use options::LocalizeOptions;

/// Encodes a query image into the NeRF feature domain (all the dims the map may select from).
pub trait QueryFeatureEncoder: Send + Sync {
    /// Field dims of the output channels, in channel order.
    fn dims(&self) -> &[usize];
    /// Image pixels per output cell (the rendering grid's stride).
    fn stride(&self) -> u32;
    /// Feature map of an RGB image (`⌊H/stride⌋ × ⌊W/stride⌋ × dims`).
    fn encode(&self, image: &Image<f32>) -> Result<matloc_core::FeatureMap, PipelineError>;
    /// Per-dim statistics of the features the encoder was trained to predict (one entry per
    /// output channel), which the matcher standardises both sides with; `None` when it has
    /// none (the matcher then only L2-normalises).
    fn stats(&self) -> Option<&matloc_match::FeatureStats>;
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
    /// The pose the hypothesis' passes reached within the correction limits, accepted or
    /// not (`None` when no pass solved one): where a later stage may start from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_cam_from_world: Option<Pose>,
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
        )?;
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
                log10_nfa: log10_nfa(
                    matches.len(),
                    r.stats.num_inliers,
                    self.solver.minimal_sample(),
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
        let (image, camera) = options::query_at_working_size(image, camera, self.options.max_side);
        let (image, camera) = (image.as_ref(), &camera);
        let mut clock = StageClock(Vec::new());
        let mut rng = ChaCha8Rng::seed_from_u64(self.options.seed);

        let t = Instant::now();
        let hypotheses = self
            .place
            .predict(image, camera, self.options.top_k.max(1))?;
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
                refined_cam_from_world: None,
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
                    Err(PipelineError::ViewRender(e)) => {
                        report.failure = Some(e.to_string());
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
                report.refined_cam_from_world = Some(pose);
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
            tracing::debug!(
                hypothesis = index,
                group = report.group,
                block = report.block,
                passes = report.passes,
                matches = report.matches,
                inliers = report.inliers,
                confidence = report.confidence,
                accepted = ok,
                failure = report.failure.as_deref().unwrap_or(""),
                "place hypothesis tried"
            );
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
        tracing::debug!(
            localized = cam_from_world.is_some(),
            confidence,
            inliers,
            hypotheses = reports.len(),
            seconds = start.elapsed().as_secs_f64(),
            "query done"
        );
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

/// A place predictor that returns fixed hypotheses (calibration, and evaluating every method
/// from the same coarse poses).
pub struct FixedPlace(pub Vec<PlaceHypothesis>);

impl PlacePredictor for FixedPlace {
    fn predict(
        &self,
        _image: &Image<f32>,
        _camera: &Camera,
        k: usize,
    ) -> Result<Vec<PlaceHypothesis>, matloc_place::PlaceError> {
        Ok(self.0.iter().take(k).cloned().collect())
    }
}
