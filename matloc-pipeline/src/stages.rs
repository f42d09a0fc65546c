//! The map-build stages after the sub-NeRFs: ground-truth pairs → query encoder → feature
//! selection (each per block) → pose groups and place classifier → confidence calibration.
//!
//! Every sub-NeRF has its own hash grid, so its intermediate features live in their own space:
//! pairs, encoder, feature statistics and the selected dims are therefore per block. Every
//! `holdout_every`-th training view of a block is kept out of the pairs and the encoder (not out
//! of the NeRF, which is the map) and serves to calibrate the confidence on views the learned
//! stages have not seen.

use std::path::Path;
use std::time::Instant;

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::{Camera, FeatureMap, Image};
use matloc_data::{Dataset, Split};
use matloc_match::encoder::{
    ENCODER_STRIDE, EncoderSample, EncoderTrainConfig, HeadPhaseConfig, QueryEncoder, train_encoder,
};
use matloc_match::gt::{
    GtConfig, GtPairSet, PerturbKind, Perturbation, TrainingView, ViewRenderer, generate_pairs,
};
use matloc_match::nerf_view::NerfViewRenderer;
use matloc_match::{FeatureStats, MnnConfig, MnnMatcher};
use matloc_partition::Partition;
use matloc_place::{
    ExtraViews, GroupConfig, PlaceHypothesis, PlaceMethod, PlaceModel, PlacePredictor, PoseGroups,
    TrainConfig, view_point_from_depth,
};
use matloc_pnp::LoRansacPnp;
use matloc_render::NerfModel;
use matloc_select::{FeatureSelector, MatchingSelector, PairSet};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::build::{BuildEvent, MapConfig, block_dir};
use crate::confidence::{ConfidenceModel, Evidence};
use crate::error::PipelineError;
use crate::localizer::{LocalizeOptions, Localizer, LocalizerBlock};
use crate::manifest::MapDir;
use crate::render_select::{RenderSelectConfig, select_on_renders, selection_views};

/// Ground-truth pair generation per block.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PairStageConfig {
    /// Training views per block used for pairs (evenly spaced; held-out views excluded).
    pub views_per_block: usize,
    /// Coarse-pose error model the pairs cover (the place predictor's medoid poses are a few
    /// metres and degrees off).
    pub perturbation: Perturbation,
    /// Perturbed renders per view.
    pub perturbations_per_view: usize,
}

impl Default for PairStageConfig {
    fn default() -> Self {
        Self {
            views_per_block: 16,
            perturbation: Perturbation {
                kind: PerturbKind::UniformBall,
                translation_m: 3.0,
                rotation_deg: 5.0,
            },
            perturbations_per_view: 1,
        }
    }
}

/// Query encoder training per block.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct EncoderStageConfig {
    /// Training views per block (evenly spaced; held-out views excluded).
    pub views_per_block: usize,
    /// Network and optimiser settings.
    pub train: EncoderTrainConfig,
}

impl Default for EncoderStageConfig {
    /// 600 end-to-end steps, then 3000 head-only steps on the frozen trunk's cell buffer
    /// (docs/BENCHMARKS.md "Query encoder": on tiny, 69 s for 48 views at 160 × 120; matching
    /// precision from the true pose on all 47 dims 0.12 → 0.26 on training views, 0.12 → 0.16
    /// on test views against 300 end-to-end steps of the linear-head encoder).
    fn default() -> Self {
        Self {
            views_per_block: 128,
            train: EncoderTrainConfig {
                steps: 600,
                head_phase: HeadPhaseConfig {
                    steps: 3000,
                    ..HeadPhaseConfig::default()
                },
                ..EncoderTrainConfig::default()
            },
        }
    }
}

/// Feature selection per block.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SelectStageConfig {
    /// Dims to select (N_s); at least the field's 47 keeps every dim without running the
    /// selector.
    pub dims: usize,
    /// How dims are scored when `dims` is below the field's.
    pub selector: SelectorKind,
    /// Settings of [`SelectorKind::Renders`].
    pub renders: RenderSelectConfig,
}

/// Selector of the build's select stage.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum SelectorKind {
    /// Greedy MNN-F1 on the block's GT pairs (exact partners among the render's pairs).
    GtPairs,
    /// Greedy on held-out renders, scored as the localizer matches
    /// ([`crate::render_select`]; default: on the fifteenth `small` map N_s = 5 localizes
    /// 72/90 starts within 1 m, median 0.437 m, against 68/90 and 0.443 m on GT pairs,
    /// docs/BENCHMARKS.md).
    #[default]
    Renders,
}

impl Default for SelectStageConfig {
    /// All 47 dims: with the learned encoder, matching on every dim localizes more than any
    /// 5- to 16-dim greedy selection (tiny preset, from 3 m / 5° starts, 8 px threshold:
    /// all-47 9/30 test views, greedy-16 6/30, greedy-10 5/30, greedy-5 ≤ 3/30; matching costs
    /// 23 ms instead of 5 ms at 4800 × 4800, docs/BENCHMARKS.md). Selection remains the
    /// paper's speed lever (`dims: 5` in a map config) and what the perfect-feature Table 3
    /// measures.
    fn default() -> Self {
        Self {
            dims: 47,
            selector: SelectorKind::default(),
            renders: RenderSelectConfig::default(),
        }
    }
}

/// Pose groups and the place classifier.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PlaceStageConfig {
    /// Two-stage K-means settings.
    pub groups: GroupConfig,
    /// ArcFace classifier training.
    pub train: TrainConfig,
    /// Views rendered by the sub-NeRFs near the training views, added to the classifier's
    /// training set (the paper's optional NeRF augmentation).
    pub rendered: RenderedViewsConfig,
    /// Coarse pose of a predicted group: the member whose image embedding is nearest the
    /// query's (true) or the group medoid (false, the paper). A group spans up to the
    /// orientation threshold in viewing direction, so its medoid can be far from the query's.
    pub member_pose: bool,
    /// Weight of a group's best member similarity in its score against the class centre's
    /// (`PlaceModel::set_member_weight`). 0.5 raised co-visible top-1 coarse poses on
    /// `rubble` from 92.5 % to 100 % and top-3 on `small` by 0–10 points, but localization
    /// not at all (same median on `small`, one query fewer on `rubble`), so it is off (0).
    pub member_weight: f32,
    /// Blend temperature of a coarse pose between the nearest member and its most similar
    /// neighbour (`PlaceModel::set_member_blend`; 0 = off). Survey queries fall between two
    /// database poses: on `small` the nearest member is 5–6 m from the query, the blend at
    /// 0.25 brings the median coarse error to 1.7 m (rubble 7.5 → 2.7 m).
    pub member_blend: f32,
    /// The blend is a second hypothesis of the top group, tried only when the nearest
    /// member's fails (`PlaceModel::set_blend_as_extra`). Replacing the nearest member made
    /// localization worse (`small`: 0.44 → 0.76 m, 2 false accepts): queries that localize
    /// from 5 m can fail from 1 m. As a fallback (same maps, recalibrated), refusals fell
    /// 33 → 13 % and 20 → 3 % on two `small` maps and 15 → 7.5 % on `rubble`, medians 0.44 →
    /// 0.39 m, 0.37 → 0.36 m and 0.199 m, no false accepts (temperature 1: one on two maps).
    pub blend_as_extra: bool,
}

impl PlaceStageConfig {
    /// Applies the prediction settings (coarse pose, group scoring) to a loaded model.
    pub fn configure(&self, place: &mut PlaceModel) {
        place.set_refine_within_group(self.member_pose);
        place.set_member_weight(self.member_weight);
        place.set_member_blend(self.member_blend);
        place.set_blend_as_extra(self.blend_as_extra);
    }
}

impl Default for PlaceStageConfig {
    fn default() -> Self {
        Self {
            groups: GroupConfig::default(),
            train: TrainConfig::default(),
            rendered: RenderedViewsConfig::default(),
            member_pose: true,
            member_weight: 0.0,
            member_blend: 0.25,
            blend_as_extra: true,
        }
    }
}

/// NeRF-rendered training views for the place classifier: the survey gives ~2 images per pose
/// group, and test queries fall between survey poses.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RenderedViewsConfig {
    /// Views rendered per training view (0 = off). On two `small` maps 1–2 views raised the
    /// top-1 group accuracy from 73 % to 80–83 % (~70 s of build time per view); 4 gained
    /// nothing more (docs/BENCHMARKS.md).
    pub per_view: usize,
    /// Perturbation of the rendered poses: uniform ball of this radius, metres ...
    pub translation_m: f64,
    /// ... and a rotation of up to this angle about a uniform axis, degrees.
    pub rotation_deg: f64,
    /// Rendered width in pixels (height by the aspect ratio); 0 = twice the classifier's input
    /// width, the size its augmentation crops from.
    pub width: usize,
    /// Seed of the perturbations.
    pub seed: u64,
}

impl Default for RenderedViewsConfig {
    fn default() -> Self {
        Self {
            per_view: 1,
            translation_m: 5.0,
            rotation_deg: 10.0,
            width: 0,
            seed: 0,
        }
    }
}

/// Held-out views and confidence calibration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CalibrationConfig {
    /// Every n-th training view of a block is held out of pairs and encoder (0 = none).
    pub holdout_every: usize,
    /// At most this many held-out views are localized for calibration.
    pub max_views: usize,
    /// Place hypotheses per view, each localized on its own (wrong places give the negatives).
    pub hypotheses_per_view: usize,
    /// A pose within this translation error counts as correct, metres (default 5 m / 10°,
    /// the evaluation's loosest recall threshold: the refusal exists to avoid false accepts,
    /// and a learned-encoder pose of a metre or two is not one — the paper's own MatLoc
    /// errors are 1.7–1.8 m) ...
    pub correct_translation_m: f64,
    /// ... and within this rotation error, degrees.
    pub correct_rotation_deg: f64,
    /// Refusal threshold on the calibrated probability.
    pub accept_threshold: f64,
    /// The localizer accepts a pose only within this many times the 90th percentile of the
    /// rotation corrections (pose vs coarse pose) of correct calibration attempts
    /// ([`LocalizeOptions::max_accept_rotation_deg`]; 0 = no calibrated bound). Wrong poses
    /// that PnP and the confidence accept slide along the near-nadir tilt/shift ambiguity,
    /// away from the coarse attitude: on three `small` maps every correct pose was ≤ 4.7°
    /// from its coarse pose, the two false accepts 9.1° and 15.9°.
    pub rotation_bound_margin: f64,
    /// Lower limit of the calibrated rotation bound, degrees.
    pub min_rotation_bound_deg: f64,
}

impl Default for CalibrationConfig {
    fn default() -> Self {
        Self {
            holdout_every: 8,
            max_views: 24,
            hypotheses_per_view: 3,
            correct_translation_m: 5.0,
            correct_rotation_deg: 10.0,
            accept_threshold: 0.5,
            rotation_bound_margin: 2.5,
            min_rotation_bound_deg: 6.0,
        }
    }
}

/// What calibration saw, stored next to the fitted model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationRecord {
    /// The fitted model.
    pub model: ConfidenceModel,
    /// Samples: evidence, label, translation and rotation error of the attempt (∞ = no pose).
    pub samples: Vec<(Evidence, bool, f64, f64)>,
    /// Fraction of samples the fitted rule classifies correctly.
    pub accuracy: f64,
    /// Per sample: rotation between its pose and its hypothesis' coarse pose, degrees (1e9 =
    /// no pose). Empty in maps calibrated before it was recorded.
    #[serde(default)]
    pub corrections_deg: Vec<f64>,
    /// Calibrated bound on an accepted pose's rotation from its coarse pose (see
    /// [`CalibrationConfig::rotation_bound_margin`]); `None`: the configured one applies.
    #[serde(default)]
    pub max_accept_rotation_deg: Option<f64>,
}

/// Name of the place model directory inside the map.
pub const PLACE_DIR: &str = "place";
/// Name of the calibration record inside the map.
pub const CONFIDENCE_FILE: &str = "confidence.json";

/// File of block `b`'s ground-truth pairs.
pub fn pairs_file(b: usize) -> String {
    format!("{}/pairs.safetensors", block_dir(b))
}

/// File of block `b`'s query encoder.
pub fn encoder_file(b: usize) -> String {
    format!("{}/encoder.safetensors", block_dir(b))
}

/// File of block `b`'s selection record.
pub fn selection_file(b: usize) -> String {
    format!("{}/selection.json", block_dir(b))
}

/// Block `b`'s selection and how it was obtained.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SelectionRecord {
    /// Selected field dims.
    pub dims: Vec<usize>,
    /// Selector name.
    pub selector: String,
    /// Its objective value.
    pub objective: f64,
    /// GT pairs it was selected on (held-out views for a selection on renders).
    pub pairs: usize,
}

/// Block `b`'s GT pairs with its encoder's features at their query cells: what selectors
/// score dims on (the query side is what the encoder sees, not the NeRF at the true pose).
pub fn block_pair_set(map: &MapDir, dataset: &Dataset, b: usize) -> Result<PairSet, PipelineError> {
    let gt = GtPairSet::from_bytes(
        &map.read_file(&pairs_file(b))?,
        &map.path_of(&pairs_file(b))?,
    )
    .map_err(|e| PipelineError::Config(format!("pairs of block {b}: {e}")))?;
    let enc = load_encoder(map, b)?;
    let mut maps = Vec::new();
    for r in &gt.provenance.renders {
        if maps.iter().any(|(i, _)| *i == r.view.index) {
            continue;
        }
        let (image, _) = load_image(dataset, r.view.index)?;
        let m = enc
            .encode(&image)
            .map_err(|e| PipelineError::Encoder(e.to_string()))?;
        maps.push((r.view.index, m));
    }
    let qf = pair_query_features(&gt, &maps)?;
    PairSet::from_gt(&gt, Some(qf))
        .map_err(|e| PipelineError::Config(format!("pairs of block {b}: {e}")))
}

/// Greedy MNN-F1 selection of `n_s` dims for block `b`, on its GT pairs with the block's
/// encoder features as the query side.
fn greedy_selection(
    map: &MapDir,
    dataset: &Dataset,
    b: usize,
    n_s: usize,
) -> Result<SelectionRecord, PipelineError> {
    let pairs = block_pair_set(map, dataset, b)?;
    let mut rng = ChaCha8Rng::seed_from_u64(b as u64);
    let sel = MatchingSelector::default()
        .select(&pairs, n_s, &mut rng)
        .map_err(|e| PipelineError::Config(format!("selection of block {b}: {e}")))?;
    Ok(SelectionRecord {
        dims: sel.dims,
        selector: "greedy MNN-F1".into(),
        objective: sel.report.objective,
        pairs: pairs.len(),
    })
}

/// Selection of `config.select.dims` dims for block `b` on its held-out renders, scored as
/// the map's localizer will match (its window, its first-pass PnP threshold).
fn render_selection(
    map: &MapDir,
    dataset: &Dataset,
    partition: &Partition,
    config: &MapConfig,
    b: usize,
    all_dims: &[usize],
) -> Result<SelectionRecord, PipelineError> {
    let encoder = load_encoder(map, b)?;
    let matcher = block_matcher(&encoder, all_dims, window_px(map, &config.localize))?;
    let block = MapBlock {
        renderer: load_nerf(map, b, config.localize.render_steps)?,
        encoder,
        matcher,
        dims: all_dims.to_vec(),
        match_dims: None,
    };
    let cfg = &config.select.renders;
    let views = selection_views(&block, dataset, partition, config, b, cfg)?;
    let sel = select_on_renders(
        &block,
        &views,
        config.select.dims,
        config.localize.first_pass_threshold_cells,
        cfg,
    )?;
    Ok(SelectionRecord {
        dims: sel.dims,
        selector: sel.report.objective_name,
        objective: sel.report.objective,
        pairs: views.len(),
    })
}

/// The matching window of a map (see [`LocalizeOptions::window_fraction`]), for a grid as
/// wide as the map's images.
fn window_px(map: &MapDir, options: &LocalizeOptions) -> Option<f64> {
    let width = map
        .manifest()
        .scene
        .get("camera")
        .and_then(|c| c.get("width"))
        .and_then(|w| w.as_u64())
        .unwrap_or(320) as f64;
    (options.window_fraction > 0.0).then_some(options.window_fraction * width)
}

/// A training view of a block, with its frame index in the dataset.
pub(crate) fn views_of_block(
    dataset: &Dataset,
    partition: &Partition,
    b: usize,
    holdout_every: usize,
) -> (Vec<TrainingView>, Vec<TrainingView>) {
    let train = dataset.split_indices(Split::Train);
    let mut fit = Vec::new();
    let mut held = Vec::new();
    for (k, &id) in partition.blocks[b].pose_ids.iter().enumerate() {
        let Some(&i) = train.get(id) else { continue };
        let f = &dataset.frames[i];
        let v = TrainingView {
            index: i,
            camera: f.camera,
            cam_from_world: f.cam_from_world,
        };
        if holdout_every > 0 && k % holdout_every == holdout_every - 1 {
            held.push(v);
        } else {
            fit.push(v);
        }
    }
    (fit, held)
}

/// At most `n` evenly spaced elements.
pub(crate) fn spaced<T: Clone>(v: &[T], n: usize) -> Vec<T> {
    if n == 0 || v.len() <= n {
        return v.to_vec();
    }
    let step = v.len() as f64 / n as f64;
    (0..n)
        .map(|k| v[((k as f64 + 0.5) * step) as usize].clone())
        .collect()
}

pub(crate) fn load_image(
    dataset: &Dataset,
    index: usize,
) -> Result<(Image<f32>, Camera), PipelineError> {
    let f = &dataset.frames[index];
    matloc_data::images::load_frame_image(dataset, f, 1).map_err(|e| PipelineError::Io {
        path: dataset.image_path(f),
        source: std::io::Error::other(e.to_string()),
    })
}

/// Owned images, poses and group labels of [`rendered_place_views`].
#[derive(Default)]
struct RenderedViews {
    images: Vec<Image<f32>>,
    poses: Vec<matloc_core::Pose>,
    labels: Vec<usize>,
}

/// Views rendered by the sub-NeRFs at perturbed training poses, labelled with the group their
/// pose falls in (the source view's group when it falls in none).
fn rendered_place_views(
    map: &MapDir,
    dataset: &Dataset,
    train_idx: &[usize],
    partition: &Partition,
    groups: &PoseGroups,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<RenderedViews, PipelineError> {
    let rv = &config.place.rendered;
    let mut out = RenderedViews::default();
    if rv.per_view == 0 || train_idx.is_empty() {
        return Ok(out);
    }
    let perturb = Perturbation {
        kind: PerturbKind::UniformBall,
        translation_m: rv.translation_m,
        rotation_deg: rv.rotation_deg,
    };
    let width = if rv.width == 0 {
        2 * config.place.train.net.input_width
    } else {
        rv.width
    };
    let mut nerfs: Vec<Option<NerfViewRenderer>> = Vec::new();
    let mut rng = ChaCha8Rng::seed_from_u64(rv.seed);
    for (k, &i) in train_idx.iter().enumerate() {
        let f = &dataset.frames[i];
        let cam = f.camera;
        let height = ((width as f64 * cam.height as f64 / cam.width as f64).round() as u32).max(1);
        let small = cam
            .rescaled(width as u32, height)
            .map_err(PipelineError::Camera)?;
        let b = partition.block_of_member(k).unwrap_or(0);
        if nerfs.len() <= b {
            nerfs.resize_with(b + 1, || None);
        }
        if nerfs[b].is_none() {
            nerfs[b] = Some(load_nerf(map, b, 0)?);
        }
        let nerf = nerfs[b]
            .as_ref()
            .ok_or(PipelineError::Internal("NeRF not loaded"))?;
        for _ in 0..rv.per_view {
            let pose = perturb.apply(&f.cam_from_world, &mut rng);
            let view = matloc_render::render_view(
                nerf.model(),
                &small,
                &pose,
                &matloc_render::PixelSet::Full,
                &matloc_render::RenderRequest {
                    rgb: true,
                    dims: Vec::new(),
                    appearance: None,
                },
            )?;
            let image = view
                .rgb_image()
                .ok_or(PipelineError::Internal("rendered view without RGB"))?;
            out.labels
                .push(groups.assign(&pose).unwrap_or(groups.labels[k]));
            out.images.push(image);
            out.poses.push(pose);
        }
        progress(&BuildEvent::StageProgress {
            done: 0,
            message: format!("rendered views {}/{}", k + 1, train_idx.len()),
        });
    }
    Ok(out)
}

/// `model` rendering with `steps` march steps per ray (0 = unchanged).
fn with_render_steps(model: NerfModel, steps: usize) -> Result<NerfModel, PipelineError> {
    if steps == 0 {
        return Ok(model);
    }
    let mut view = model.config().render;
    view.march.steps = steps;
    Ok(model.with_view_config(view)?)
}

/// Block `b`'s NeRF; `render_steps > 0` replaces its ray-marching grid.
fn load_nerf(
    map: &MapDir,
    b: usize,
    render_steps: usize,
) -> Result<NerfViewRenderer, PipelineError> {
    let dir = map.path_of(&block_dir(b))?;
    let model = with_render_steps(NerfModel::load(&dir)?, render_steps)?;
    Ok(NerfViewRenderer::new(model, block_dir(b)))
}

fn load_encoder(map: &MapDir, b: usize) -> Result<QueryEncoder, PipelineError> {
    // Read through the map so the checksum is verified.
    let name = encoder_file(b);
    map.read_file(&name)?;
    QueryEncoder::load(&map.path_of(&name)?).map_err(|e| PipelineError::Encoder(e.to_string()))
}

/// The work of one stage: gets the map and the progress sink.
type StageBody<'a> =
    dyn FnMut(&mut MapDir, &mut dyn FnMut(&BuildEvent)) -> Result<(), PipelineError> + 'a;

/// Runs a stage unless the manifest says it is done.
fn stage(
    map: &mut MapDir,
    name: &str,
    total: u64,
    progress: &mut dyn FnMut(&BuildEvent),
    body: &mut StageBody<'_>,
) -> Result<(), PipelineError> {
    if map.stage_done(name) {
        progress(&BuildEvent::StageFinished {
            name: name.into(),
            seconds: 0.0,
            skipped: true,
        });
        return Ok(());
    }
    let t = Instant::now();
    progress(&BuildEvent::StageStarted {
        name: name.into(),
        total,
    });
    body(map, progress)?;
    let secs = t.elapsed().as_secs_f64();
    map.complete_stage(name, secs)?;
    progress(&BuildEvent::StageFinished {
        name: name.into(),
        seconds: secs,
        skipped: false,
    });
    Ok(())
}

/// Encoder feature map value of each pair's query cell.
fn pair_query_features(
    gt: &GtPairSet,
    maps: &[(usize, FeatureMap)],
) -> Result<Vec<f32>, PipelineError> {
    let nd = gt.dims();
    let mut qf = Vec::with_capacity(gt.len() * nd);
    for p in 0..gt.len() {
        let r = &gt.provenance.renders[gt.render[p] as usize];
        let m = &maps
            .iter()
            .find(|(i, _)| *i == r.view.index)
            .ok_or(PipelineError::Internal(
                "pair of a view that was not encoded",
            ))?
            .1;
        let q = gt.query_index[p] as usize;
        let (x, y) = (q % m.width(), q / m.width());
        if y >= m.height() {
            return Err(PipelineError::Internal(
                "pair cell outside the encoder grid",
            ));
        }
        qf.extend_from_slice(m.pixel(x, y));
    }
    Ok(qf)
}

/// Block `b`'s encoder training views: its training views less the hold-out, evenly spaced
/// down to the configured count.
pub fn encoder_views(
    dataset: &Dataset,
    partition: &Partition,
    config: &MapConfig,
    b: usize,
) -> Vec<TrainingView> {
    let (fit, _) = views_of_block(dataset, partition, b, config.calibration.holdout_every);
    spaced(&fit, config.encoder.views_per_block)
}

/// Trains block `b`'s query encoder on `views` into the `dims` of its sub-NeRF's features
/// (targets rendered at the views' true poses; statistics from the rendered surface cells).
pub fn train_block_encoder(
    map: &MapDir,
    dataset: &Dataset,
    config: &MapConfig,
    b: usize,
    views: &[TrainingView],
    dims: &[usize],
    progress: &mut dyn FnMut(&matloc_match::encoder::EncoderProgress),
) -> Result<QueryEncoder, PipelineError> {
    let renderer = load_nerf(map, b, 0)?;
    let mut samples = Vec::with_capacity(views.len());
    let mut rows = Vec::new();
    let nd = dims.len();
    for v in views {
        let (image, _) = load_image(dataset, v.index)?;
        let target = renderer
            .render_view(&v.camera, &v.cam_from_world, ENCODER_STRIDE, dims)
            .map_err(|e| PipelineError::RenderFailure(e.to_string()))?;
        for i in 0..target.cols * target.rows {
            if target.has_surface(i, config.encoder.train.min_accumulation) {
                rows.extend_from_slice(&target.features[i * nd..(i + 1) * nd]);
            }
        }
        samples.push(EncoderSample { image, target });
    }
    if rows.is_empty() {
        return Err(PipelineError::Config(format!(
            "block {b}: the sub-NeRF renders no surface at its training views"
        )));
    }
    let stats = FeatureStats::from_features(&rows, nd);
    let cfg = EncoderTrainConfig {
        seed: config.encoder.train.seed.wrapping_add(b as u64),
        ..config.encoder.train.clone()
    };
    train_encoder(&samples, dims.to_vec(), stats, &cfg, progress)
        .map_err(|e| PipelineError::Encoder(e.to_string()))
}

/// The stages after the sub-NeRFs (see the module docs).
pub(crate) fn run_after_nerf(
    dataset: &Dataset,
    partition: &Partition,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    let nb = partition.blocks.len();
    let all_dims: Vec<usize> = (0..matloc_nerf_field::FEATURE_DIM).collect();
    let holdout = config.calibration.holdout_every;

    for b in 0..nb {
        let (fit, _) = views_of_block(dataset, partition, b, holdout);
        if fit.is_empty() {
            return Err(PipelineError::Config(format!(
                "block {b} has no training views left after the hold-out"
            )));
        }
        // Pairs.
        let pair_views = spaced(&fit, config.pairs.views_per_block);
        stage(
            map,
            &format!("pairs/{b}"),
            pair_views.len() as u64,
            progress,
            &mut |map, _| {
                let renderer = load_nerf(map, b, 0)?;
                let gt_cfg = GtConfig {
                    stride: ENCODER_STRIDE,
                    perturbation: config.pairs.perturbation.clone(),
                    perturbations_per_view: config.pairs.perturbations_per_view,
                    ..GtConfig::default()
                };
                let set = generate_pairs(&renderer, &pair_views, &gt_cfg, b as u64)
                    .map_err(|e| PipelineError::Config(format!("pairs of block {b}: {e}")))?;
                let bytes = set
                    .to_bytes()
                    .map_err(|e| PipelineError::Config(format!("pairs of block {b}: {e}")))?;
                map.write_file(&pairs_file(b), &bytes)?;
                Ok(())
            },
        )?;

        // Encoder.
        let enc_views = encoder_views(dataset, partition, config, b);
        let steps = config.encoder.train.total_steps() as u64;
        stage(
            map,
            &format!("encoder/{b}"),
            steps,
            progress,
            &mut |map, progress| {
                let enc = train_block_encoder(
                    map,
                    dataset,
                    config,
                    b,
                    &enc_views,
                    &all_dims,
                    &mut |p| {
                        progress(&BuildEvent::StageProgress {
                            done: p.step as u64,
                            message: format!(
                                "loss {:.3} (mse {:.3}, nce {:.3})",
                                p.loss, p.mse, p.nce
                            ),
                        })
                    },
                )?;
                let path = map.path_of(&encoder_file(b))?;
                enc.save(&path)
                    .map_err(|e| PipelineError::Encoder(e.to_string()))?;
                map.register_file(&encoder_file(b))?;
                Ok(())
            },
        )?;

        // Selection.
        stage(map, &format!("select/{b}"), 0, progress, &mut |map, _| {
            let record = if config.select.dims >= all_dims.len() {
                SelectionRecord {
                    dims: all_dims.clone(),
                    selector: "all dims".into(),
                    objective: 0.0,
                    pairs: 0,
                }
            } else {
                match config.select.selector {
                    SelectorKind::GtPairs => greedy_selection(map, dataset, b, config.select.dims)?,
                    SelectorKind::Renders => {
                        render_selection(map, dataset, partition, config, b, &all_dims)?
                    }
                }
            };
            map.write_json(&selection_file(b), &record)?;
            if let Some(e) = map.manifest_mut().blocks.get_mut(b) {
                e.selected_dims = record.dims;
            }
            map.save()?;
            Ok(())
        })?;
    }

    // Pose groups and place classifier over all training poses.
    let train_idx = dataset.split_indices(Split::Train);
    stage(
        map,
        "place",
        config.place.train.epochs as u64,
        progress,
        &mut |map, progress| {
            let mut images = Vec::with_capacity(train_idx.len());
            let mut poses = Vec::with_capacity(train_idx.len());
            let mut view_points = Vec::with_capacity(train_idx.len());
            for (k, &i) in train_idx.iter().enumerate() {
                let f = &dataset.frames[i];
                let (image, camera) = load_image(dataset, i)?;
                let depth = match matloc_data::images::load_frame_depth(dataset, f, 1) {
                    Ok(Some(d)) => d,
                    // No depth in the dataset: the block's NeRF renders it.
                    _ => {
                        let b = partition.block_of_member(k).unwrap_or(0);
                        let r = load_nerf(map, b, 0)?;
                        let v = r
                            .render_view(&camera, &f.cam_from_world, 1, &[])
                            .map_err(|e| PipelineError::RenderFailure(e.to_string()))?;
                        Image::from_vec(v.cols, v.rows, 1, v.depth_z)
                            .map_err(|_| PipelineError::Internal("depth image shape"))?
                    }
                };
                let vp = view_point_from_depth(&camera, &f.cam_from_world, &depth, 4).ok_or_else(
                    || PipelineError::Place(format!("training view {i} sees no surface")),
                )?;
                images.push(image);
                poses.push(f.cam_from_world);
                view_points.push(vp);
            }
            let mut groups = PoseGroups::build(&poses, &view_points, &config.place.groups)
                .map_err(|e| PipelineError::Place(e.to_string()))?;
            groups.attach_blocks(|k| partition.block_of_member(k));
            let extra = rendered_place_views(
                map, dataset, &train_idx, partition, &groups, config, progress,
            )?;
            let model = PlaceModel::train_with_extra(
                PlaceMethod::ArcFace,
                &images,
                &poses,
                &groups,
                ExtraViews {
                    images: &extra.images,
                    poses: &extra.poses,
                    labels: &extra.labels,
                },
                &config.place.train,
                &mut |r| {
                    progress(&BuildEvent::StageProgress {
                        done: r.epoch as u64 + 1,
                        message: format!("{} groups, loss {:.3}", groups.len(), r.loss),
                    })
                },
            )
            .map_err(|e| PipelineError::Place(e.to_string()))?;
            let dir = map.path_of(PLACE_DIR)?;
            model
                .save(&dir)
                .map_err(|e| PipelineError::Place(e.to_string()))?;
            register_dir(map, PLACE_DIR)?;
            Ok(())
        },
    )?;

    // Confidence calibration on held-out views.
    let mut held = Vec::new();
    for b in 0..nb {
        held.extend(views_of_block(dataset, partition, b, holdout).1);
    }
    let held = spaced(&held, config.calibration.max_views);
    stage(
        map,
        "calibration",
        held.len() as u64,
        progress,
        &mut |map, progress| {
            let loaded = LoadedBlocks::load(map, nb, &config.localize)?;
            let mut place = PlaceModel::load(&map.path_of(PLACE_DIR)?)
                .map_err(|e| PipelineError::Place(e.to_string()))?;
            config.place.configure(&mut place);
            let solver = LoRansacPnp::default();
            let mut samples = Vec::new();
            let mut corrections = Vec::new();
            for (done, v) in held.iter().enumerate() {
                let (image, camera) = load_image(dataset, v.index)?;
                let hyps = place
                    .predict(
                        &image,
                        &camera,
                        config.calibration.hypotheses_per_view.max(1),
                    )
                    .map_err(|e| PipelineError::Place(e.to_string()))?;
                for h in hyps {
                    let h_coarse = h.cam_from_world;
                    let fixed = FixedPlace(vec![h]);
                    let options = LocalizeOptions {
                        top_k: 1,
                        confidence: ConfidenceModel {
                            accept_threshold: 0.0,
                            ..config.localize.confidence.clone()
                        },
                        ..config.localize.clone()
                    };
                    let localizer = loaded.localizer(&fixed, &solver, options);
                    let out = localizer.localize(&image, &camera)?;
                    let Some(rep) = out.hypotheses.first() else {
                        continue;
                    };
                    let evidence = Evidence {
                        inliers: rep.inliers,
                        inlier_ratio: if rep.matches == 0 {
                            0.0
                        } else {
                            rep.inliers as f64 / rep.matches as f64
                        },
                        matches: rep.matches,
                        alignment: rep.alignment,
                    };
                    let (te, re) = match &out.cam_from_world {
                        Some(p) => (
                            translation_error_m(p, &v.cam_from_world),
                            rotation_error_deg(p, &v.cam_from_world),
                        ),
                        None => (f64::INFINITY, f64::INFINITY),
                    };
                    let ok = te <= config.calibration.correct_translation_m
                        && re <= config.calibration.correct_rotation_deg;
                    samples.push((evidence, ok, te, re));
                    corrections.push(
                        out.cam_from_world
                            .as_ref()
                            .map_or(f64::INFINITY, |p| rotation_error_deg(p, &h_coarse)),
                    );
                }
                progress(&BuildEvent::StageProgress {
                    done: done as u64 + 1,
                    message: format!(
                        "{} attempts, {} correct",
                        samples.len(),
                        samples.iter().filter(|s| s.1).count()
                    ),
                });
            }
            let labelled: Vec<(Evidence, bool)> = samples.iter().map(|s| (s.0, s.1)).collect();
            let model = ConfidenceModel::fit(&labelled, config.calibration.accept_threshold)
                .map_err(|e| PipelineError::Config(format!("confidence calibration: {e}")))?;
            let right = labelled
                .iter()
                .filter(|(e, ok)| model.accept(e) == *ok)
                .count();
            let accuracy = right as f64 / labelled.len().max(1) as f64;
            let max_accept_rotation_deg = rotation_bound(
                samples
                    .iter()
                    .zip(&corrections)
                    .filter(|(s, _)| s.1)
                    .map(|(_, c)| *c),
                &config.calibration,
                config.localize.max_accept_rotation_deg,
            );
            // Infinite errors are not valid JSON numbers: store them as a large sentinel.
            let samples = samples
                .into_iter()
                .map(|(e, ok, t, r)| (e, ok, t.min(1e9), r.min(1e9)))
                .collect();
            map.write_json(
                CONFIDENCE_FILE,
                &CalibrationRecord {
                    model,
                    samples,
                    accuracy,
                    corrections_deg: corrections.iter().map(|c| c.min(1e9)).collect(),
                    max_accept_rotation_deg,
                },
            )?;
            Ok(())
        },
    )?;
    Ok(())
}

/// The calibrated rotation-correction bound: `margin ×` the 90th percentile of the corrections
/// of correct attempts, within `[min_rotation_bound_deg, configured]`; `None` when the margin
/// is 0 or no attempt was correct (the configured bound applies). A percentile, not the
/// largest: one correct attempt turned 4.1° on a map whose others stayed ≤ 2.1°, and the bound
/// it gave (10.2°) let through a wrong pose that had turned 8.2°.
pub fn rotation_bound(
    correct_corrections_deg: impl Iterator<Item = f64>,
    config: &CalibrationConfig,
    configured_deg: f64,
) -> Option<f64> {
    if config.rotation_bound_margin <= 0.0 {
        return None;
    }
    let mut c: Vec<f64> = correct_corrections_deg.filter(|c| c.is_finite()).collect();
    if c.is_empty() {
        return None;
    }
    c.sort_by(f64::total_cmp);
    let p90 = c[((c.len() - 1) as f64 * 0.9).round() as usize];
    Some(
        (config.rotation_bound_margin * p90)
            .max(config.min_rotation_bound_deg)
            .min(configured_deg),
    )
}

/// Lists every file under `dir` (relative to the map root) in the manifest.
pub(crate) fn register_dir(map: &mut MapDir, dir: &str) -> Result<(), PipelineError> {
    let path = map.path_of(dir)?;
    let entries = std::fs::read_dir(&path).map_err(|e| PipelineError::Io {
        path: path.clone(),
        source: e,
    })?;
    for entry in entries {
        let entry = entry.map_err(|e| PipelineError::Io {
            path: path.clone(),
            source: e,
        })?;
        let file = entry.file_name().to_string_lossy().to_string();
        if entry.path().is_file() && !file.ends_with(".tmp") {
            map.register_file(&format!("{dir}/{file}"))?;
        }
    }
    Ok(())
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

/// One block of a loaded map.
pub struct MapBlock {
    /// The sub-NeRF as a feature/depth renderer.
    pub renderer: NerfViewRenderer,
    /// Query encoder into this block's feature space.
    pub encoder: QueryEncoder,
    /// MNN matcher normalising with this block's feature statistics (windowed when
    /// [`LocalizeOptions::window_fraction`] is positive).
    pub matcher: MnnMatcher,
    /// Rendered dims (the matcher's feature space; see [`LocalizerBlock::dims`]).
    pub dims: Vec<usize>,
    /// Selected dims matched on, when fewer than `dims`.
    pub match_dims: Option<Vec<usize>>,
}

/// The MNN matcher of a block for matching on `dims`: the encoder's feature statistics
/// restricted to them (the matcher sees only those dims), windowed to `window_px`.
pub fn block_matcher(
    encoder: &QueryEncoder,
    dims: &[usize],
    window_px: Option<f64>,
) -> Result<MnnMatcher, PipelineError> {
    let full = encoder.stats();
    let channels = crate::localizer::positions_of(dims, encoder.dims())?;
    let stats = FeatureStats {
        mean: channels.iter().map(|&c| full.mean[c]).collect(),
        std: channels.iter().map(|&c| full.std[c]).collect(),
    };
    Ok(MnnMatcher::new(MnnConfig {
        stats: Some(stats),
        window_px,
        ..MnnConfig::default()
    }))
}

impl MapBlock {
    /// This block as the localizer sees it.
    pub fn localizer_block(&self) -> LocalizerBlock<'_> {
        LocalizerBlock {
            renderer: &self.renderer,
            encoder: &self.encoder,
            matcher: &self.matcher,
            dims: self.dims.clone(),
            match_dims: self.match_dims.clone(),
        }
    }
}

/// The blocks of a map, loaded.
pub struct LoadedBlocks(pub Vec<MapBlock>);

impl LoadedBlocks {
    /// Loads blocks `0..n` (NeRF, encoder, selection) from `map`, with the matching window
    /// ([`LocalizeOptions::window_fraction`], for a grid as wide as the map's images) and the
    /// render sampling ([`LocalizeOptions::render_steps`]) of `options`.
    pub fn load(map: &MapDir, n: usize, options: &LocalizeOptions) -> Result<Self, PipelineError> {
        let window_px = window_px(map, options);
        let mut blocks = Vec::with_capacity(n);
        for b in 0..n {
            let renderer = load_nerf(map, b, options.render_steps)?;
            let encoder = load_encoder(map, b)?;
            let sel: SelectionRecord = map.read_json(&selection_file(b))?;
            let (dims, match_dims) =
                if options.refine_on_all_dims && sel.dims.len() < encoder.dims().len() {
                    (encoder.dims().to_vec(), Some(sel.dims))
                } else {
                    (sel.dims, None)
                };
            let matcher = block_matcher(&encoder, &dims, window_px)?;
            blocks.push(MapBlock {
                renderer,
                encoder,
                matcher,
                dims,
                match_dims,
            });
        }
        Ok(Self(blocks))
    }

    /// A localizer over these blocks.
    pub fn localizer<'a>(
        &'a self,
        place: &'a dyn PlacePredictor,
        solver: &'a dyn matloc_pnp::PoseSolver,
        options: LocalizeOptions,
    ) -> Localizer<'a> {
        Localizer {
            place,
            blocks: self.0.iter().map(MapBlock::localizer_block).collect(),
            solver,
            options,
        }
    }
}

/// A built map, loaded and validated: everything localization and evaluation need.
pub struct LoadedMap {
    /// The map directory (manifest, checksums).
    pub dir: MapDir,
    /// The build configuration.
    pub config: MapConfig,
    /// The partition.
    pub partition: Partition,
    /// Blocks.
    pub blocks: LoadedBlocks,
    /// Place classifier.
    pub place: PlaceModel,
    /// Calibrated confidence.
    pub confidence: ConfidenceModel,
    /// Calibrated bound on an accepted pose's rotation from its coarse pose (`None`: the
    /// configured one).
    pub max_accept_rotation_deg: Option<f64>,
}

/// Stages a complete map has.
pub fn required_stages(blocks: usize) -> Vec<String> {
    let mut v = vec!["partition".to_string()];
    for b in 0..blocks {
        for s in ["nerf", "pairs", "encoder", "select"] {
            v.push(format!("{s}/{b}"));
        }
    }
    v.push("place".into());
    v.push("calibration".into());
    v
}

impl LoadedMap {
    /// Opens a map: validates the manifest and every checksum, checks that the build
    /// completed, and loads the models.
    pub fn open(root: &Path) -> Result<Self, PipelineError> {
        let dir = MapDir::open(root)?;
        dir.verify()?;
        let config: MapConfig = serde_json::from_value(dir.manifest().config.clone())
            .map_err(|e| PipelineError::Config(format!("manifest config: {e}")))?;
        let partition: Partition = dir.read_json(crate::build::PARTITION_FILE)?;
        let n = partition.blocks.len();
        for s in required_stages(n) {
            if !dir.stage_done(&s) {
                return Err(PipelineError::Incomplete {
                    root: root.to_path_buf(),
                    stage: s,
                });
            }
        }
        let blocks = LoadedBlocks::load(&dir, n, &config.localize)?;
        dir.read_file(&format!("{PLACE_DIR}/{}", matloc_place::MODEL_WEIGHTS))?;
        let mut place = PlaceModel::load(&dir.path_of(PLACE_DIR)?)
            .map_err(|e| PipelineError::Place(e.to_string()))?;
        config.place.configure(&mut place);
        let record: CalibrationRecord = dir.read_json(CONFIDENCE_FILE)?;
        Ok(Self {
            dir,
            config,
            partition,
            blocks,
            place,
            confidence: record.model,
            max_accept_rotation_deg: record.max_accept_rotation_deg,
        })
    }

    /// Localizer options: the stored ones with the calibrated confidence.
    pub fn options(&self) -> LocalizeOptions {
        let configured = self.config.localize.max_accept_rotation_deg;
        LocalizeOptions {
            confidence: self.confidence.clone(),
            max_accept_rotation_deg: self
                .max_accept_rotation_deg
                .map_or(configured, |b| b.min(configured)),
            ..self.config.localize.clone()
        }
    }

    /// The MatLoc localizer over this map's place classifier and blocks.
    pub fn localizer<'a>(&'a self, solver: &'a dyn matloc_pnp::PoseSolver) -> Localizer<'a> {
        self.blocks.localizer(&self.place, solver, self.options())
    }

    /// The NeRF of block `b`.
    pub fn nerf(&self, b: usize) -> Option<&NerfModel> {
        self.blocks.0.get(b).map(|x| x.renderer.model())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_render::ModelConfig;

    #[test]
    fn rotation_bound_scales_the_p90_correct_correction_within_limits() {
        let cfg = CalibrationConfig::default();
        let b = |c: &[f64], cfg: &CalibrationConfig| rotation_bound(c.iter().copied(), cfg, 45.0);
        // 2.5 × the 90th percentile (4° among these); non-finite corrections (no pose) are
        // ignored.
        let mut c: Vec<f64> = (1..=10).map(|i| i as f64 * 0.4).collect();
        c.push(f64::INFINITY);
        assert_eq!(b(&c, &cfg), Some(2.5 * 3.6));
        // One outlier among many does not move it.
        let mut outlier = vec![2.0; 19];
        outlier.push(9.0);
        assert_eq!(b(&outlier, &cfg), Some(6.0));
        // Never below the floor, never above the configured bound.
        assert_eq!(b(&[0.5], &cfg), Some(cfg.min_rotation_bound_deg));
        assert_eq!(b(&[30.0], &cfg), Some(45.0));
        // No correct attempt, or the bound turned off: the configured bound applies.
        assert_eq!(b(&[], &cfg), None);
        assert_eq!(b(&[f64::INFINITY], &cfg), None);
        let off = CalibrationConfig {
            rotation_bound_margin: 0.0,
            ..cfg
        };
        assert_eq!(b(&[4.0], &off), None);
    }

    #[test]
    fn render_steps_replace_only_the_march_grid() {
        let mut config = ModelConfig::for_scene([-4.0, -4.0, -1.0], [4.0, 4.0, 3.0], 5.0, 2);
        config.field.log2_table_size = 12;
        let model = NerfModel::new(config.clone()).unwrap();
        let same = with_render_steps(model.clone(), 0).unwrap();
        assert_eq!(same.config(), &config);
        let coarse = with_render_steps(model, 96).unwrap();
        assert_eq!(coarse.config().render.march.steps, 96);
        let mut expected = config;
        expected.render.march.steps = 96;
        assert_eq!(coarse.config(), &expected);
    }
}
