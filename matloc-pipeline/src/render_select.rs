//! Feature selection scored the way the localizer uses the dims (beyond the paper).
//!
//! [`matloc_select::MatchingSelector`] scores a subset by how many GT pairs find their exact
//! partner among the other pairs of a render. The localizer instead matches the encoder's whole
//! grid against the whole render inside an image window, and what it needs is matches close
//! enough to their true projection for PnP. This module scores subsets on exactly that: a
//! block's held-out views (kept out of its encoder, so their encoder features are as weak as a
//! query's), each rendered once on all dims at a perturbed pose, matched with the block's own
//! windowed matcher restricted to the candidate dims, and either counted against the true
//! projection or solved with PnP. The greedy search is [`matloc_select::GreedySearch`].

use matloc_core::Pose;
use matloc_core::metrics::translation_error_m;
use matloc_data::Dataset;
use matloc_match::gt::Perturbation;
use matloc_match::localize::{correct_matches, render_map_points, solve_pose_within};
use matloc_match::{MatchError, Matcher, QueryFeatures, RenderedPoints};
use matloc_pnp::LoRansacPnp;
use matloc_select::{GreedySearch, Selection, SelectionReport};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::build::MapConfig;
use crate::error::PipelineError;
use crate::localizer::QueryFeatureEncoder;
use crate::stages::{MapBlock, block_matcher, load_image, views_of_block};
use matloc_partition::Partition;

/// What a subset is scored by on the selection views.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum RenderScore {
    /// F1 of the windowed MNN matches: a match is correct when its 3D point projects within
    /// `tol_px` of its query pixel at the true pose; recall is over the render's valid points.
    MatchF1 {
        /// Pixel tolerance of a correct match.
        tol_px: f64,
    },
    /// One render–match–PnP pass from the perturbed pose (the localizer's first-pass inlier
    /// threshold): the mean over views of the translation error (a failed pass keeps the
    /// start, a worse pose counts as the start) relative to the start's, negated.
    SinglePass,
}

/// Settings of [`select_on_renders`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RenderSelectConfig {
    /// Greedy forward search and swap refinement.
    pub search: GreedySearch,
    /// Criterion.
    pub score: RenderScore,
    /// At most this many held-out views per block (evenly spaced; 0 = all).
    pub max_views: usize,
    /// Start poses of the views: the true pose perturbed by this.
    pub perturbation: Perturbation,
    /// Seed of the perturbations (and of RANSAC for [`RenderScore::SinglePass`]).
    pub seed: u64,
}

impl Default for RenderSelectConfig {
    fn default() -> Self {
        Self {
            search: GreedySearch {
                max_swap_rounds: 1,
                ..GreedySearch::default()
            },
            score: RenderScore::MatchF1 { tol_px: 4.0 },
            max_views: 16,
            perturbation: crate::stages::PairStageConfig::default().perturbation,
            seed: 0,
        }
    }
}

/// One held-out view as the selection scores it: the encoder's map of its image on every
/// encoded dim and the block's render at a perturbed pose on the same dims.
pub struct SelectionView {
    /// Frame index in the dataset.
    pub index: usize,
    /// Intrinsics.
    pub camera: matloc_core::Camera,
    /// True pose.
    pub truth: Pose,
    /// The perturbed pose rendered at.
    pub start: Pose,
    /// Encoder features on every encoded dim.
    pub query: QueryFeatures,
    /// Rendered points with features on every encoded dim.
    pub points: RenderedPoints,
}

/// Block `b`'s selection views: its held-out views (every `holdout_every`-th, as calibration
/// uses), encoded by `block`'s encoder and rendered by its NeRF at perturbed poses.
pub fn selection_views(
    block: &MapBlock,
    dataset: &Dataset,
    partition: &Partition,
    map_config: &MapConfig,
    b: usize,
    config: &RenderSelectConfig,
) -> Result<Vec<SelectionView>, PipelineError> {
    if b >= partition.blocks.len() {
        return Err(PipelineError::Config(format!(
            "no block {b} (the partition has {})",
            partition.blocks.len()
        )));
    }
    let holdout = map_config.calibration.holdout_every;
    let (_, held) = views_of_block(dataset, partition, b, holdout);
    if held.is_empty() {
        return Err(PipelineError::Config(format!(
            "block {b} has no held-out views to select on (calibration.holdout_every = {holdout})"
        )));
    }
    let held = crate::stages::spaced(&held, config.max_views);
    let stride = QueryFeatureEncoder::stride(&block.encoder);
    let dims = block.encoder.dims().to_vec();
    let min_acc = map_config.localize.min_accumulation;
    let mut out = Vec::with_capacity(held.len());
    for v in held {
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        rng.set_stream(((b as u64) << 32) | v.index as u64);
        let start = config.perturbation.apply(&v.cam_from_world, &mut rng);
        let (image, camera) = load_image(dataset, v.index)?;
        let encoded = block
            .encoder
            .encode(&image)
            .map_err(|e| PipelineError::Encoder(e.to_string()))?;
        let points = render_map_points(&block.renderer, &camera, &start, stride, &dims, min_acc)
            .map_err(|e| PipelineError::RenderFailure(e.to_string()))?;
        out.push(SelectionView {
            index: v.index,
            camera,
            truth: v.cam_from_world,
            start,
            query: QueryFeatures::new(encoded, stride as f64),
            points,
        });
    }
    Ok(out)
}

/// Selects `n_s` of the block's encoded dims by the greedy search over `config.score` on
/// `views` (from [`selection_views`] of the same block); `threshold_cells` is the PnP inlier
/// threshold of [`RenderScore::SinglePass`] (the map's first-pass one).
pub fn select_on_renders(
    block: &MapBlock,
    views: &[SelectionView],
    n_s: usize,
    threshold_cells: f64,
    config: &RenderSelectConfig,
) -> Result<Selection, PipelineError> {
    let encoded = block.encoder.dims().to_vec();
    if n_s == 0 || n_s > encoded.len() {
        return Err(PipelineError::Config(format!(
            "N_s = {n_s} must be in 1..={}",
            encoded.len()
        )));
    }
    if views.is_empty() {
        return Err(PipelineError::Config("no selection views".into()));
    }
    let window = Matcher::window_px(&block.matcher);
    let matcher = block_matcher(&block.encoder, &encoded, window)?;
    let solver = LoRansacPnp::default();
    let threshold_px = threshold_cells * QueryFeatureEncoder::stride(&block.encoder) as f64;
    let mut score = |positions: &[usize]| -> Result<f64, PipelineError> {
        let (mut correct, mut matched, mut valid) = (0usize, 0usize, 0usize);
        let mut rel_err = 0.0;
        for (k, v) in views.iter().enumerate() {
            let matches = match matcher.match_features(&v.query, &v.points, Some(positions)) {
                Ok(m) => m,
                Err(MatchError::Empty { .. }) => Vec::new(),
                Err(e) => return Err(PipelineError::Match(e)),
            };
            let start_err = translation_error_m(&v.start, &v.truth).max(1e-6);
            match config.score {
                RenderScore::MatchF1 { tol_px } => {
                    valid += v.points.valid().iter().filter(|&&x| x).count();
                    matched += matches.len();
                    correct += correct_matches(&matches, &v.camera, &v.truth, tol_px);
                }
                RenderScore::SinglePass => {
                    let mut rng = ChaCha8Rng::seed_from_u64(config.seed ^ 0x5e1ec7);
                    rng.set_stream(k as u64);
                    let err = solve_pose_within(
                        &matches,
                        &v.camera,
                        &solver,
                        Some(threshold_px),
                        &mut rng,
                    )
                    .map_or(start_err, |r| {
                        translation_error_m(&r.cam_from_world, &v.truth)
                    });
                    rel_err += err.min(start_err) / start_err;
                }
            }
        }
        Ok(match config.score {
            RenderScore::MatchF1 { .. } => {
                if correct == 0 {
                    0.0
                } else {
                    let p = correct as f64 / matched as f64;
                    let r = correct as f64 / valid.max(1) as f64;
                    2.0 * p * r / (p + r)
                }
            }
            RenderScore::SinglePass => -rel_err / views.len() as f64,
        })
    };
    let found = config.search.run(encoded.len(), n_s, &mut score)?;
    let mut dims: Vec<usize> = found.dims.iter().map(|&p| encoded[p]).collect();
    dims.sort_unstable();
    Ok(Selection {
        dims,
        report: SelectionReport {
            selector: "greedy on renders".into(),
            objective_name: match config.score {
                RenderScore::MatchF1 { tol_px } => {
                    format!("F1 of windowed MNN within {tol_px} px on held-out renders (maximised)")
                }
                RenderScore::SinglePass => {
                    "minus mean relative translation error of one PnP pass (maximised)".into()
                }
            },
            objective: found.score,
            per_dim_cost: found.single.iter().map(|s| -s).collect(),
            evaluations: found.evaluations,
        },
    })
}
