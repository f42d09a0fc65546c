//! Everything that defines a map build ([`MapConfig`]), stage by stage. Stored in the map's
//! manifest; a build resumes only with the same config. Missing fields take their defaults.

use matloc_encoder::{EncoderTrainConfig, HeadPhaseConfig};
use matloc_partition::{PoseAwareConfig, SampleConfig};
use matloc_place::{GroupConfig, PlaceModel, TrainConfig};
use matloc_select::GreedySearch;
use matloc_surface::{SunlightConfig, SurfaceConfig, VirtualViewsConfig};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::gt::{PerturbKind, Perturbation};
use crate::localizer::options::LocalizeOptions;

/// Everything that defines a map build. Stored in the manifest; resuming a build requires the
/// same config.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MapConfig {
    /// Working resolution of every stage.
    pub images: ImageConfig,
    /// Where the scene surface comes from for training views without a depth file.
    pub surface: SurfaceConfig,
    /// Ray samples of each training pose for the partition.
    pub samples: SampleConfig,
    /// Pose-aware partition (target ~150 poses per block, as the paper).
    pub partition: PoseAwareConfig,
    /// Sub-NeRF training.
    pub nerf: NerfStageConfig,
    /// Ground-truth pairs per block.
    pub pairs: PairStageConfig,
    /// Query encoder per block.
    pub encoder: EncoderStageConfig,
    /// Feature selection per block.
    pub select: SelectStageConfig,
    /// Pose groups and the place classifier.
    pub place: PlaceStageConfig,
    /// Held-out views and the confidence calibration.
    pub calibration: CalibrationConfig,
    /// Triangulated keypoints of the training images (the structure localizer).
    pub structure: StructureStageConfig,
    /// Lifting the cast shadows of the map's sun out of the training images before the NeRFs
    /// are fitted (off by default; left out of the stored config while it is the default, so
    /// maps from before it resume unchanged).
    #[serde(skip_serializing_if = "SunlightConfig::is_default")]
    pub sunlight: SunlightConfig,
    /// Virtual viewpoints beyond the survey: poses sampled over the ground the training
    /// cameras saw (`matloc_surface::viewpoints`), rendered by the block NeRFs at the size of
    /// `place.rendered` and added to the place classifier's training views, each labelled with
    /// the pose group whose views saw most of its footprint (the place stage records their
    /// counts). Off by default, and left out of the stored config while it is the default, so
    /// maps from before it resume unchanged.
    #[serde(
        rename = "virtual",
        skip_serializing_if = "VirtualViewsConfig::is_default"
    )]
    pub virtual_views: VirtualViewsConfig,
    /// Localizer settings stored with the map (the confidence model is replaced by the
    /// calibrated one when the map is loaded).
    pub localize: LocalizeOptions,
}

impl MapConfig {
    /// Checks the values no stage can run with, naming each field, its value and the bound:
    /// a build with no NeRF steps, an empty feature selection, no place hypotheses or no
    /// render/match pass, a matching window outside `[0, 1]`, place training without epochs,
    /// a `virtual.*` setting out of range ([`VirtualViewsConfig::problems`]).
    /// The build's plan step calls it before anything is written (and so does the CLI when it
    /// reads a config file). `localize.render_steps = 0` is valid: each model's own setting.
    /// The error is every offending field, `; `-separated.
    pub fn validate(&self) -> Result<(), String> {
        let mut bad = Vec::new();
        let mut check = |ok: bool, field: &str, value: String, bound: &str| {
            if !ok {
                bad.push(format!("`{field}` = {value}: {bound}"));
            }
        };
        let c = self;
        check(
            c.nerf.steps >= 1,
            "nerf.steps",
            c.nerf.steps.to_string(),
            "must be at least 1",
        );
        check(
            c.select.dims >= 1,
            "select.dims",
            c.select.dims.to_string(),
            "must be at least 1 (47 or more keeps every dim)",
        );
        check(
            c.place.train.epochs >= 1,
            "place.train.epochs",
            c.place.train.epochs.to_string(),
            "must be at least 1",
        );
        check(
            c.localize.top_k >= 1,
            "localize.top_k",
            c.localize.top_k.to_string(),
            "must be at least 1",
        );
        check(
            c.localize.max_passes >= 1,
            "localize.max_passes",
            c.localize.max_passes.to_string(),
            "must be at least 1",
        );
        check(
            (0.0..=1.0).contains(&c.localize.window_fraction),
            "localize.window_fraction",
            c.localize.window_fraction.to_string(),
            "must be within [0, 1] of the image width (0: global matching)",
        );
        for p in c.virtual_views.problems() {
            bad.push(format!("`{}` = {}: {}", p.field, p.value, p.bound));
        }
        if bad.is_empty() {
            Ok(())
        } else {
            Err(bad.join("; "))
        }
    }

    /// The default config as JSON with every section, also those a stored config leaves out
    /// while they are at their default (`sunlight`, `virtual`): what `matloc map config
    /// --print-default` shows.
    pub fn documented_default() -> serde_json::Value {
        let mut v = serde_json::to_value(MapConfig::default())
            .expect("the default config serialises to JSON");
        if let Some(o) = v.as_object_mut() {
            o.insert(
                "sunlight".into(),
                serde_json::to_value(SunlightConfig::default())
                    .expect("the sunlight config serialises to JSON"),
            );
            o.insert(
                "virtual".into(),
                serde_json::to_value(VirtualViewsConfig::default())
                    .expect("the virtual views config serialises to JSON"),
            );
        }
        v
    }

    /// The full configuration a partial one (a user's file: only the keys they change) stands
    /// for, as JSON: each key it gives replaces the default's, objects key by key, so a
    /// section keeps the map's defaults for what it leaves out — `{"encoder": {"train":
    /// {"steps": 900}}}` keeps the encoder's head phase, which serde alone would reset to the
    /// training type's own default. An object that names a key the default lacks (another
    /// enum variant, or a typo, which deserialising then reports) or another `kind` replaces
    /// the default's object whole. Deserialise the result (`serde_json::from_value`).
    pub fn overlay_on_default(partial: serde_json::Value) -> serde_json::Value {
        let mut full = MapConfig::documented_default();
        overlay_json(&mut full, partial);
        full
    }
}

/// Why a map config file cannot be used; each names the file (`origin`).
#[derive(Debug, thiserror::Error)]
pub enum ConfigFileError {
    /// The file cannot be read.
    #[error("reading {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The text is not JSON.
    #[error("parsing map config {origin}: {source}")]
    Json {
        /// The file (or what the value came from).
        origin: String,
        /// The parser's error, with line and column.
        source: serde_json::Error,
    },
    /// The top level is not an object of sections.
    #[error("map config {origin}: the top level must be a JSON object of sections, got {found}")]
    NotObject {
        /// The file.
        origin: String,
        /// What it is instead (`an array`, `a string`, ...).
        found: &'static str,
    },
    /// A key has the wrong type or an unknown name.
    #[error("map config {origin}: field `{field}`: {message}")]
    Field {
        /// The file.
        origin: String,
        /// The dotted path of the key (`nerf.steps`).
        field: String,
        /// What is wrong with it.
        message: String,
    },
    /// Values no stage can run with ([`MapConfig::validate`]).
    #[error("map config {origin}: {message}")]
    Invalid {
        /// The file.
        origin: String,
        /// Every offending field.
        message: String,
    },
}

impl MapConfig {
    /// Reads a map config file: a JSON object with only the keys a user changes, laid over
    /// the map's defaults ([`MapConfig::overlay_on_default`]), then validated. Errors name
    /// the file and the key.
    pub fn from_path(path: &Path) -> Result<MapConfig, ConfigFileError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigFileError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let origin = path.display().to_string();
        let value: serde_json::Value =
            serde_json::from_str(&text).map_err(|source| ConfigFileError::Json {
                origin: origin.clone(),
                source,
            })?;
        MapConfig::from_partial(value, &origin)
    }

    /// A partial config (the keys a user changes) laid over the map's defaults and validated;
    /// `origin` names where it came from in errors.
    pub fn from_partial(
        partial: serde_json::Value,
        origin: &str,
    ) -> Result<MapConfig, ConfigFileError> {
        use serde_json::Value;
        let found = match &partial {
            Value::Object(_) => None,
            Value::Array(_) => Some("an array"),
            Value::String(_) => Some("a string"),
            Value::Number(_) => Some("a number"),
            Value::Bool(_) => Some("a boolean"),
            Value::Null => Some("null"),
        };
        if let Some(found) = found {
            return Err(ConfigFileError::NotObject {
                origin: origin.to_string(),
                found,
            });
        }
        // The path of the offending key (`nerf.steps`) goes into the message, which serde
        // alone gives only as a line and column.
        let config: MapConfig = serde_path_to_error::deserialize(MapConfig::overlay_on_default(
            partial,
        ))
        .map_err(|e| ConfigFileError::Field {
            origin: origin.to_string(),
            field: e.path().to_string(),
            message: e.inner().to_string(),
        })?;
        config
            .validate()
            .map_err(|message| ConfigFileError::Invalid {
                origin: origin.to_string(),
                message,
            })?;
        Ok(config)
    }
}

/// Writes `over` onto `base`: each key `over` gives replaces `base`'s, objects key by key;
/// an object that names a key `base` lacks (another enum variant, or a typo that
/// deserialising then reports) or another `kind` replaces `base`'s object whole. The one
/// overlay of every partial JSON config (map configs, NeRF model overrides).
pub fn overlay_json(base: &mut serde_json::Value, over: serde_json::Value) {
    use serde_json::Value;
    match (base, over) {
        (Value::Object(b), Value::Object(o))
            if o.keys().all(|k| b.contains_key(k))
                && o.get("kind").is_none_or(|k| b.get("kind") == Some(k)) =>
        {
            for (k, v) in o {
                overlay_json(b.get_mut(&k).expect("key checked above"), v);
            }
        }
        (b, o) => *b = o,
    }
}

/// The dotted paths of the keys of `over` that `result` (the overlaid value after a round trip
/// through its type) does not have: fields the type does not know, which a type without
/// `deny_unknown_fields` would otherwise drop without a word.
pub fn unknown_overlay_keys(over: &serde_json::Value, result: &serde_json::Value) -> Vec<String> {
    use serde_json::Value;
    let mut out = Vec::new();
    if let (Value::Object(o), Value::Object(r)) = (over, result) {
        for (k, v) in o {
            match r.get(k) {
                None => out.push(k.clone()),
                Some(rv) => out.extend(
                    unknown_overlay_keys(v, rv)
                        .into_iter()
                        .map(|p| format!("{k}.{p}")),
                ),
            }
        }
    }
    out
}

/// The resolution a map is built at.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImageConfig {
    /// Every training image is box-downscaled by the smallest integer factor that brings its
    /// longer side to at most this (`None`: the images' own size), with intrinsics scaled to
    /// match; every stage (NeRF, pairs, encoder, place, calibration) works at that size, the
    /// NeRF's own `nerf.downscale` on top of it. Queries are reduced the same way
    /// ([`crate::LocalizeOptions::max_side`]).
    pub max_side: Option<u32>,
}

/// Sub-NeRF training settings of a map build.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NerfStageConfig {
    /// Training steps per block.
    pub steps: u64,
    /// Steps between checkpoints (resume granularity).
    pub checkpoint_every: u64,
    /// Integer image downscale for training.
    pub downscale: u32,
    /// Changes to the model config derived from the dataset, as a JSON object merged into it
    /// (e.g. `{"field": {"log2_table_size": 15}, "train": {"batch_rays": 1024}}`).
    pub model_overrides: serde_json::Value,
    /// Blocks trained at the same time, each on its share of the cores (1 = one after the
    /// other, each on all cores). Per training step both use the cores fully; side by side
    /// overlaps each run's serial start and end (2 cores, 2 × 300 steps: 127 vs 143 s).
    pub parallel_blocks: usize,
}

impl Default for NerfStageConfig {
    fn default() -> Self {
        Self {
            steps: 3000,
            checkpoint_every: 500,
            downscale: 1,
            model_overrides: serde_json::Value::Null,
            parallel_blocks: 2,
        }
    }
}

/// Ground-truth pair generation per block.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
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
#[serde(default, deny_unknown_fields)]
pub struct EncoderStageConfig {
    /// Training views per block (evenly spaced; held-out views excluded).
    pub views_per_block: usize,
    /// Network and optimiser settings.
    pub train: EncoderTrainConfig,
}

impl Default for EncoderStageConfig {
    /// 600 end-to-end steps, then 3000 head-only steps on the frozen trunk's cell buffer of
    /// each view and two augmented copies (the recipe and its measurements: docs/DECISIONS.md,
    /// "Query encoder recipe", "Queries from another flight").
    fn default() -> Self {
        Self {
            views_per_block: 128,
            train: EncoderTrainConfig {
                steps: 600,
                head_phase: HeadPhaseConfig {
                    steps: 3000,
                    copies: 3,
                    ..HeadPhaseConfig::default()
                },
                ..EncoderTrainConfig::default()
            },
        }
    }
}

/// Feature selection per block.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
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
    /// ([`crate::build::select`]); localizes more starts than the GT-pair greedy at N_s = 5.
    #[default]
    Renders,
}

impl Default for SelectStageConfig {
    /// All 47 dims: with the learned encoder, matching on every dim localizes more than any 5-
    /// to 16-dim selection, at about four times the matching time. Selection remains the
    /// paper's speed lever (`dims: 5` in a map config) and what Table 3 measures.
    fn default() -> Self {
        Self {
            dims: 47,
            selector: SelectorKind::default(),
            renders: RenderSelectConfig::default(),
        }
    }
}

/// What a subset is scored by on the selection views.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
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
#[serde(default, deny_unknown_fields)]
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
            perturbation: PairStageConfig::default().perturbation,
            seed: 0,
        }
    }
}

/// Pose groups and the place classifier.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
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
    /// (`PlaceModel::set_member_weight`); off (0): it raised top-k accuracy but not
    /// localization.
    pub member_weight: f32,
    /// Blend temperature of a coarse pose between the nearest member and its most similar
    /// neighbour (`PlaceModel::set_member_blend`; 0 = off): survey queries fall between two
    /// database poses, and the blend brings the coarse pose closer.
    pub member_blend: f32,
    /// The blend is a second hypothesis of the top group, tried only when the nearest
    /// member's fails (`PlaceModel::set_blend_as_extra`): replacing the nearest member made
    /// localization worse, as a fallback it cut refusals (docs/DECISIONS.md).
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
#[serde(default, deny_unknown_fields)]
pub struct RenderedViewsConfig {
    /// Views rendered per training view (0 = off); one raised the top-1 group accuracy, more
    /// gained nothing (docs/DECISIONS.md).
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
#[serde(default, deny_unknown_fields)]
pub struct CalibrationConfig {
    /// Every n-th training view of a block is held out of pairs and encoder (0 = none).
    pub holdout_every: usize,
    /// At most this many held-out views are localized for calibration.
    pub max_views: usize,
    /// Place hypotheses per view, each localized on its own (wrong places give the negatives).
    pub hypotheses_per_view: usize,
    /// A pose within this translation error counts as correct, metres (default 5 m / 10°, the
    /// evaluation's loosest recall threshold: the refusal exists to avoid false accepts) ...
    pub correct_translation_m: f64,
    /// ... and within this rotation error, degrees.
    pub correct_rotation_deg: f64,
    /// Refusal threshold on the calibrated probability.
    pub accept_threshold: f64,
    /// The localizer accepts a pose only within this many times the 90th percentile of the
    /// rotation corrections (pose vs coarse pose) of correct calibration attempts
    /// ([`LocalizeOptions::max_accept_rotation_deg`]; 0 = no calibrated bound): wrong poses
    /// that PnP and the confidence accept slide along the near-nadir tilt/shift ambiguity,
    /// away from the coarse attitude.
    pub rotation_bound_margin: f64,
    /// Lower limit of the calibrated rotation bound, degrees.
    pub min_rotation_bound_deg: f64,
    /// What the confidence is fitted on ([`CalibrationQueries`]).
    pub queries: CalibrationQueries,
}

/// The images the calibration stage localizes. The default is the one whose confidence
/// predicted the test queries' outcomes better on `small` (docs/DECISIONS.md).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CalibrationQueries {
    /// The held-out views' own photos. The place predictor trained on them, so its nearest
    /// member — the coarse pose — is the view itself: easier starts than a query gets.
    #[default]
    HeldOut,
    /// For each held-out view, a view rendered by its block's NeRF halfway (position and
    /// attitude) to the view's nearest neighbour in the block: an image and pose the place
    /// predictor never saw, so its hypotheses and coarse pose come as a query's do.
    Rendered,
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
            queries: CalibrationQueries::default(),
        }
    }
}

/// Settings of the structure stage.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StructureStageConfig {
    /// Build the structure (without it only the NeRF methods localize).
    pub enabled: bool,
    /// Keypoints, neighbours and gates of the triangulation; its `max_side` is replaced by
    /// the map's working size, so that training images and queries are detected at one size.
    pub triangulate: matloc_surface::TriangulateConfig,
}

impl Default for StructureStageConfig {
    fn default() -> Self {
        StructureStageConfig {
            enabled: true,
            triangulate: matloc_surface::TriangulateConfig {
                upsample: true,
                ..matloc_surface::TriangulateConfig::default()
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use serde_json::{Value, json};

    use super::*;

    /// Paths of every JSON object in the default config that a config struct serialises to
    /// (externally tagged enum variants, one upper-case key, are left out).
    fn struct_paths(v: &Value, path: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
        let Value::Object(m) = v else { return };
        let variant = m.len() == 1 && m.keys().all(|k| k.starts_with(char::is_uppercase));
        if !variant {
            out.push(path.clone());
        }
        for (k, child) in m {
            path.push(k.clone());
            struct_paths(child, path, out);
            path.pop();
        }
    }

    fn at<'a>(v: &'a mut Value, path: &[String]) -> &'a mut Value {
        path.iter().fold(v, |v, k| &mut v[k.as_str()])
    }

    fn default_paths() -> (Value, Vec<Vec<String>>) {
        let value = serde_json::to_value(MapConfig::default()).unwrap();
        let mut paths = Vec::new();
        struct_paths(&value, &mut Vec::new(), &mut paths);
        (value, paths)
    }

    /// Every struct reachable from the config takes its defaults for missing fields: an empty
    /// object anywhere parses.
    #[test]
    fn an_empty_section_at_any_depth_parses() {
        let (value, paths) = default_paths();
        assert!(paths.len() > 20, "{paths:?}");
        // Enum values: an empty object names no variant.
        let enums = ["localize.pnp.refine.loss", "select.renders.score.MatchF1"];
        let failed: Vec<String> = paths
            .iter()
            .filter(|path| !enums.contains(&path.join(".").as_str()))
            .filter_map(|path| {
                let mut v = value.clone();
                *at(&mut v, path) = json!({});
                let e = serde_json::from_value::<MapConfig>(v).err()?;
                Some(format!("{}: {e}", path.join(".")))
            })
            .collect();
        assert!(failed.is_empty(), "{failed:#?}");
    }

    /// An unknown key in any config struct is an error naming it.
    #[test]
    fn an_unknown_key_at_any_depth_is_named() {
        let (value, paths) = default_paths();
        let failed: Vec<String> = paths
            .iter()
            .filter_map(|path| {
                let mut v = value.clone();
                at(&mut v, path)["no_such_key"] = json!(1);
                match serde_json::from_value::<MapConfig>(v) {
                    Ok(_) => Some(format!("{}: accepted", path.join("."))),
                    Err(e) if e.to_string().contains("no_such_key") => None,
                    Err(e) => Some(format!("{}: {e}", path.join("."))),
                }
            })
            .collect();
        assert!(failed.is_empty(), "{failed:#?}");
    }

    #[test]
    fn partial_sections_keep_the_other_defaults() {
        let d = MapConfig::default();
        let c: MapConfig = serde_json::from_value(json!({
            "partition": {"voxel_size": 2.0},
            "encoder": {"train": {"head_phase": {"images": 3}}},
            "localize": {"pnp": {}, "featuremetric": {}},
            "place": {"train": {"augment": {}}},
        }))
        .unwrap();
        assert_eq!(c.partition.voxel_size, 2.0);
        assert_eq!(c.partition.target_size, d.partition.target_size);
        assert_eq!(c.encoder.train.head_phase.images, 3);
        assert_eq!(c.encoder.views_per_block, d.encoder.views_per_block);
        assert_eq!(c.localize, d.localize);
        assert_eq!(c.place, d.place);
        assert_eq!(c.nerf, d.nerf);
    }

    /// A section that sets one field keeps the map's defaults for its other fields, also
    /// where they differ from the field type's own default (the encoder's steps and head
    /// phase, the structure's 2× detection); other enum variants and unknown keys replace or
    /// fail as they would without the overlay.
    #[test]
    fn a_partial_file_keeps_the_map_defaults_below_the_section() {
        let d = MapConfig::default();
        let parse = |v: Value| -> Result<MapConfig, serde_json::Error> {
            serde_json::from_value(MapConfig::overlay_on_default(v))
        };
        let c = parse(json!({
            "encoder": {"train": {"net": {"width": 32}}},
            "structure": {"triangulate": {"max_side": 200}},
            "select": {"renders": {"max_views": 4}},
        }))
        .unwrap();
        assert_eq!(c.encoder.train.net.width, 32);
        assert_eq!(c.encoder.train.steps, d.encoder.train.steps);
        assert_eq!(c.encoder.train.head_phase, d.encoder.train.head_phase);
        assert_eq!(c.encoder.train.jitter, d.encoder.train.jitter);
        assert!(c.structure.triangulate.upsample);
        assert_eq!(c.select.renders.search, d.select.renders.search);
        assert_eq!(c.select.renders.max_views, 4);
        // Serde alone resets what the section leaves out to the type's defaults.
        let plain: MapConfig =
            serde_json::from_value(json!({"encoder": {"train": {"net": {"width": 32}}}})).unwrap();
        assert_ne!(plain.encoder.train.head_phase, d.encoder.train.head_phase);
        // Another variant of an internally tagged enum replaces the default's fields.
        let kind = d.pairs.perturbation.kind;
        let other = json!({"pairs": {"perturbation": {"kind": "Gaussian", "translation_m": 1.0, "rotation_deg": 2.0}}});
        let c = parse(other.clone()).unwrap();
        assert_ne!(c.pairs.perturbation.kind, kind);
        assert_eq!(c.pairs.perturbation.translation_m, 1.0);
        let c = parse(json!({"localize": {"pnp": {"refine": {"loss": {"kind": "trivial"}}}}}));
        assert_eq!(
            c.unwrap().localize.pnp.refine.loss,
            matloc_pnp::RobustLoss::Trivial
        );
        // Unknown keys are still refused, nulls and arrays replace.
        assert!(parse(json!({"encoder": {"train": {"stepz": 3}}})).is_err());
        let c =
            parse(json!({"partition": {"num_blocks": 2}, "images": {"max_side": null}})).unwrap();
        assert_eq!(c.partition.num_blocks, Some(2));
        let c = parse(json!({"encoder": {"train": {"net": {"dilations": [1]}}}})).unwrap();
        assert_eq!(c.encoder.train.net.dilations, vec![1]);
        assert_eq!(parse(json!({})).unwrap(), d);
    }

    /// `nerf.model_overrides` is free-form.
    #[test]
    fn model_overrides_take_any_keys() {
        let c: MapConfig =
            serde_json::from_value(json!({"nerf": {"model_overrides": {"anything": {"x": 1}}}}))
                .unwrap();
        assert_eq!(c.nerf.model_overrides, json!({"anything": {"x": 1}}));
    }

    #[test]
    fn the_default_round_trips() {
        let d = MapConfig::default();
        let text = serde_json::to_string_pretty(&d).unwrap();
        assert_eq!(serde_json::from_str::<MapConfig>(&text).unwrap(), d);
        // The printed default shows the sunlight section and reads back as the default.
        let shown = MapConfig::documented_default();
        assert!(shown.get("sunlight").is_some());
        assert!(shown.get("virtual").is_some());
        assert_eq!(serde_json::from_value::<MapConfig>(shown).unwrap(), d);
    }

    #[test]
    fn sunlight_is_stored_only_when_set() {
        let d = serde_json::to_value(MapConfig::default()).unwrap();
        assert!(
            d.get("sunlight").is_none(),
            "maps from before it resume unchanged"
        );
        let c: MapConfig = serde_json::from_value(MapConfig::overlay_on_default(
            json!({"sunlight": {"enabled": true}}),
        ))
        .unwrap();
        assert!(c.sunlight.enabled);
        assert_eq!(c.sunlight.neighbours, SunlightConfig::default().neighbours);
        // The other sections keep the map's defaults (not their types').
        assert_eq!(c.encoder, MapConfig::default().encoder);
        assert!(serde_json::to_value(&c).unwrap().get("sunlight").is_some());
    }

    #[test]
    fn virtual_views_are_off_stored_only_when_set_and_validated_by_name() {
        let d = MapConfig::default();
        assert!(!d.virtual_views.enabled);
        assert!(
            serde_json::to_value(&d).unwrap().get("virtual").is_none(),
            "maps from before it resume unchanged"
        );
        let c: MapConfig = serde_json::from_value(MapConfig::overlay_on_default(
            json!({"virtual": {"enabled": true, "altitude_band": [0.5, 1.2]}}),
        ))
        .unwrap();
        assert!(c.virtual_views.enabled);
        assert_eq!(c.virtual_views.altitude_band, [0.5, 1.2]);
        assert_eq!(
            c.virtual_views.pitch_deg,
            VirtualViewsConfig::default().pitch_deg
        );
        assert!(c.validate().is_ok());
        let stored = serde_json::to_value(&c).unwrap();
        assert_eq!(stored["virtual"]["enabled"], json!(true));
        assert_eq!(serde_json::from_value::<MapConfig>(stored).unwrap(), c);
        // Unknown keys are refused; out-of-range values name their field.
        assert!(
            serde_json::from_value::<MapConfig>(json!({"virtual": {"per_view": 1}}))
                .unwrap_err()
                .to_string()
                .contains("per_view")
        );
        let bad: MapConfig = serde_json::from_value(json!({
            "virtual": {"pitch_deg": [10.0, 95.0], "min_coverage": 2.0}
        }))
        .unwrap();
        let e = bad.validate().unwrap_err();
        assert!(e.contains("`virtual.pitch_deg` = [10.0, 95.0]"), "{e}");
        assert!(e.contains("`virtual.min_coverage` = 2"), "{e}");
    }

    #[test]
    fn config_errors_name_the_key_and_refuse_a_non_object() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.json");
        std::fs::write(&path, r#"{"nerf": {"steps": "many"}}"#).unwrap();
        let e = MapConfig::from_path(&path).unwrap_err().to_string();
        assert!(
            e.contains("field `nerf.steps`") && e.contains("c.json"),
            "{e}"
        );
        std::fs::write(&path, "[]").unwrap();
        let e = MapConfig::from_path(&path).unwrap_err().to_string();
        assert!(
            e.contains("must be a JSON object") && e.contains("an array"),
            "{e}"
        );
        std::fs::write(&path, r#"{"nerf": {"steps": 7}}"#).unwrap();
        assert_eq!(MapConfig::from_path(&path).unwrap().nerf.steps, 7);
    }
}
