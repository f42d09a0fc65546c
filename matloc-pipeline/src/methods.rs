//! Localizing one query with any of the methods on a loaded map: MatLoc (the
//! [`Localizer`](crate::Localizer)), rendered-RGB + keypoints, iNeRF and curriculum iNeRF
//! (the paper's four), and `structure`: keypoints matched to the map's triangulated training
//! images ([`matloc_structure`]), the default. The NeRF baselines start from MatLoc's best
//! place hypothesis and render the block that serves it, as in the paper's comparison;
//! `structure` and MatLoc try the same top-k place hypotheses in order.
//!
//! A method is a [`LocalizationMethod`]: the built-in ones are the variants of [`Method`], any
//! other is registered by name in a [`MethodRegistry`]; [`localize_with`] runs either with the
//! checks every method shares.

use std::fmt;
use std::str::FromStr;
use std::sync::Arc;
use std::time::Instant;

use matloc_core::pose::camera_center;
use matloc_core::{Camera, Image, Pose};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::baselines::{
    InerfOptions, KeypointBaselineOptions, inerf, render_colour, rgb_keypoints,
};
use crate::error::PipelineError;
use crate::localizer::HypothesisReport;
use crate::localizer::options::query_at_working_size;
use crate::map::load::LoadedMap;
use crate::volume::MappedVolume;

/// A localization method.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Matching the query against selected NeRF features (this project).
    Matloc,
    /// Rendered RGB + keypoints + PnP.
    RgbKeypoints,
    /// Curriculum iNeRF (200 iterations, coarse to fine).
    CurriculumInerf,
    /// iNeRF (300 iterations).
    Inerf,
    /// Query keypoints matched to the triangulated keypoints of the training images nearest
    /// each place hypothesis, then PnP (the default).
    Structure,
}

impl Method {
    /// Every method: the default (`structure`) first, then the paper's table order.
    pub const ALL: [Method; 5] = [
        Method::Structure,
        Method::Matloc,
        Method::RgbKeypoints,
        Method::CurriculumInerf,
        Method::Inerf,
    ];

    /// The method `localize`, `serve` and `eval` use unless told otherwise.
    pub const DEFAULT: Method = Method::Structure;

    /// Command-line name.
    pub fn name(self) -> &'static str {
        match self {
            Method::Matloc => "matloc",
            Method::RgbKeypoints => "rgb-keypoints",
            Method::CurriculumInerf => "curriculum-inerf",
            Method::Inerf => "inerf",
            Method::Structure => "structure",
        }
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Method::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                format!(
                    "unknown method {s:?} (expected one of {})",
                    Method::ALL.map(|m| m.name()).join(", ")
                )
            })
    }
}

/// A localization method: a query image with its camera → a pose, or a refusal, on a loaded
/// map. The built-in methods are the variants of [`Method`]; another method implements this
/// trait and is registered by name in a [`MethodRegistry`], and every entry point
/// ([`localize_with`], [`crate::query::localize_batch`], the server) takes any of them.
pub trait LocalizationMethod: Send + Sync {
    /// The name it is registered and asked for by (`structure`, `matloc`, ...).
    fn name(&self) -> &str;

    /// Localizes `image` (taken with `camera`, of the image's size) on `map`. The checks every
    /// method shares (plausible intrinsics, a pose inside the mapped volume) are
    /// [`localize_with`]'s; call that rather than this.
    fn localize(
        &self,
        map: &LoadedMap,
        name: &str,
        image: &Image<f32>,
        camera: &Camera,
        options: &MethodOptions,
    ) -> Result<QueryResult, PipelineError>;
}

impl fmt::Debug for dyn LocalizationMethod {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "LocalizationMethod({})", self.name())
    }
}

impl LocalizationMethod for Method {
    fn name(&self) -> &str {
        Method::name(*self)
    }

    fn localize(
        &self,
        map: &LoadedMap,
        name: &str,
        image: &Image<f32>,
        camera: &Camera,
        options: &MethodOptions,
    ) -> Result<QueryResult, PipelineError> {
        match self {
            Method::Structure => localize_structure(map, name, image, camera, &options.structure),
            Method::Matloc => localize_matloc(map, name, image, camera, options),
            Method::RgbKeypoints => localize_nerf_baseline(
                map,
                NerfBaseline::RgbKeypoints,
                name,
                image,
                camera,
                options,
            ),
            Method::Inerf => {
                localize_nerf_baseline(map, NerfBaseline::Inerf, name, image, camera, options)
            }
            Method::CurriculumInerf => localize_nerf_baseline(
                map,
                NerfBaseline::CurriculumInerf,
                name,
                image,
                camera,
                options,
            ),
        }
    }
}

/// Why a method cannot be registered or found.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum MethodRegistryError {
    /// No method has the name.
    #[error("unknown method {name:?} (expected one of {known})")]
    Unknown {
        /// The name asked for.
        name: String,
        /// The registered names, comma-separated.
        known: String,
    },
    /// A method of that name is registered already.
    #[error("a method named {0:?} is registered already")]
    Duplicate(String),
}

/// Localization methods by name: the built-in ones ([`MethodRegistry::builtin`]) and any a
/// caller registers.
#[derive(Clone, Debug)]
pub struct MethodRegistry {
    methods: Vec<Arc<dyn LocalizationMethod>>,
}

impl MethodRegistry {
    /// The built-in methods ([`Method::ALL`], the default first).
    pub fn builtin() -> Self {
        MethodRegistry {
            methods: Method::ALL
                .into_iter()
                .map(|m| Arc::new(m) as Arc<dyn LocalizationMethod>)
                .collect(),
        }
    }

    /// Adds `method` under its name; a name taken already is refused.
    pub fn register(
        &mut self,
        method: Arc<dyn LocalizationMethod>,
    ) -> Result<(), MethodRegistryError> {
        if self.methods.iter().any(|m| m.name() == method.name()) {
            return Err(MethodRegistryError::Duplicate(method.name().to_string()));
        }
        self.methods.push(method);
        Ok(())
    }

    /// The method registered as `name`.
    pub fn get(&self, name: &str) -> Result<Arc<dyn LocalizationMethod>, MethodRegistryError> {
        self.methods
            .iter()
            .find(|m| m.name() == name)
            .cloned()
            .ok_or_else(|| MethodRegistryError::Unknown {
                name: name.to_string(),
                known: self.names().join(", "),
            })
    }

    /// The registered names, in registration order.
    pub fn names(&self) -> Vec<&str> {
        self.methods.iter().map(|m| m.name()).collect()
    }
}

/// The result of localizing one query: what `matloc localize` prints as a JSON line.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QueryResult {
    /// Query name (image path).
    pub name: String,
    /// The method's registered name ([`LocalizationMethod::name`]).
    pub method: String,
    /// Whether a pose is returned (`false` = "not localized").
    pub localized: bool,
    /// World → camera pose (OpenCV camera axes), when localized.
    pub cam_from_world: Option<Pose>,
    /// Camera centre in world coordinates, when localized.
    pub camera_center: Option<[f64; 3]>,
    /// Confidence in the answer: MatLoc's calibrated model, the structure method's and
    /// rgb-keypoints' 1 − NFA (0 when no consensus was found); `null` for iNeRF.
    pub confidence: Option<f64>,
    /// PnP inliers (MatLoc, keypoints).
    pub inliers: usize,
    /// Optimisation iterations (iNeRF) or refinement passes (MatLoc, rgb-keypoints).
    pub iterations: u32,
    /// Place hypotheses tried (MatLoc) or the one the baseline started from.
    pub hypotheses: Vec<HypothesisReport>,
    /// Seconds per stage.
    pub stage_seconds: Vec<(String, f64)>,
    /// End-to-end seconds.
    pub total_seconds: f64,
}

/// Per-method settings (`matloc localize` / `eval --method-options FILE` reads them as JSON).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MethodOptions {
    /// Keypoint baseline.
    pub keypoints: KeypointBaselineOptions,
    /// iNeRF (the curriculum variant uses its own schedule with these step sizes).
    pub inerf: InerfOptions,
    /// Structure localizer (also the settings of MatLoc's keypoint finish).
    pub structure: matloc_structure::StructureOptions,
    /// MatLoc beyond the map's own localizer settings.
    pub matloc: MatlocOptions,
}

/// Settings of the `matloc` method beyond the map's `localize` section.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MatlocOptions {
    /// Place hypotheses to try, best first (`None`: the map's `localize.top_k`).
    pub top_k: Option<usize>,
    /// Finish with keypoints: the poses MatLoc's NeRF-feature passes reached (the accepted
    /// one, else each refused hypothesis' with the most inliers first) start the structure
    /// localizer ([`matloc_structure::localize_with_references`], with
    /// [`MethodOptions::structure`]): the query's keypoints matched to the training images
    /// that look the way the pose does, solved and patch-aligned. A pose that passes its
    /// tests replaces MatLoc's; otherwise the query is refused (see `keep_unconfirmed`).
    /// Needs a map with the structure stage (without one the finish is skipped).
    pub keypoint_finish: bool,
    /// With the keypoint finish, a pose MatLoc accepted that the finish cannot confirm is
    /// kept (`false`: refused, so every answer is one the keypoints confirmed).
    pub keep_unconfirmed: bool,
}

impl Default for MatlocOptions {
    fn default() -> Self {
        MatlocOptions {
            top_k: None,
            keypoint_finish: true,
            keep_unconfirmed: false,
        }
    }
}

/// Localizes `image` (taken with `camera`) with `method` on `map`.
///
/// Intrinsics no real camera has ([`Camera::check_plausible`]) are rejected before anything
/// runs ([`PipelineError::ImplausibleCamera`], naming the field and the bound). A pose whose
/// camera lies outside the map's [`MappedVolume`] is refused, whichever method solved it: the
/// answer is "not localized", the hypothesis that had been accepted carries the reason as its
/// failure, and the reason is logged.
pub fn localize_with(
    map: &LoadedMap,
    method: &dyn LocalizationMethod,
    name: &str,
    image: &Image<f32>,
    camera: &Camera,
    options: &MethodOptions,
) -> Result<QueryResult, PipelineError> {
    camera.check_plausible()?;
    let mut result = method.localize(map, name, image, camera, options)?;
    if let Some(pose) = result.cam_from_world
        && let Some(reason) = MappedVolume::of_map(&map.partition, map.structure.as_ref())
            .and_then(|v| v.refusal(&pose))
    {
        tracing::info!(
            query = name,
            method = method.name(),
            "pose refused: {reason}"
        );
        result.localized = false;
        result.cam_from_world = None;
        result.camera_center = None;
        if let Some(c) = result.confidence.as_mut() {
            *c = 0.0;
        }
        for h in result.hypotheses.iter_mut().filter(|h| h.accepted) {
            h.accepted = false;
            h.failure = Some(reason.clone());
        }
    }
    Ok(result)
}

/// The paper's NeRF baselines.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum NerfBaseline {
    RgbKeypoints,
    Inerf,
    CurriculumInerf,
}

impl NerfBaseline {
    fn method(self) -> Method {
        match self {
            NerfBaseline::RgbKeypoints => Method::RgbKeypoints,
            NerfBaseline::Inerf => Method::Inerf,
            NerfBaseline::CurriculumInerf => Method::CurriculumInerf,
        }
    }
}

/// A NeRF baseline from MatLoc's best place hypothesis, rendering the block that serves it.
fn localize_nerf_baseline(
    map: &LoadedMap,
    baseline: NerfBaseline,
    name: &str,
    image: &Image<f32>,
    camera: &Camera,
    options: &MethodOptions,
) -> Result<QueryResult, PipelineError> {
    let method = baseline.method();
    let start = Instant::now();
    let (image, camera) = query_at_working_size(image, camera, map.options().max_side);
    let (image, camera) = (image.as_ref(), &camera);
    let t = Instant::now();
    let hyps = map.place.predict(image, camera, 1)?;
    let place_s = t.elapsed().as_secs_f64();
    let hyp = hyps.first().ok_or(PipelineError::NoPlaceHypothesis)?;
    let block = hyp.block.unwrap_or(0);
    let model = map
        .nerf(block)
        .ok_or(PipelineError::Internal("hypothesis of a missing block"))?;
    let mut rng = ChaCha8Rng::seed_from_u64(map.config.localize.seed);
    let mut out = match baseline {
        NerfBaseline::RgbKeypoints => rgb_keypoints(
            model,
            camera,
            image,
            &hyp.cam_from_world,
            &options.keypoints,
            &mut rng,
        )?,
        NerfBaseline::Inerf => inerf(
            model,
            camera,
            image,
            &hyp.cam_from_world,
            &options.inerf,
            &mut rng,
        )?,
        NerfBaseline::CurriculumInerf => {
            let o = InerfOptions {
                iterations: InerfOptions::curriculum().iterations,
                curriculum: InerfOptions::curriculum().curriculum,
                ..options.inerf.clone()
            };
            inerf(model, camera, image, &hyp.cam_from_world, &o, &mut rng)?
        }
    };
    // rgb-keypoints refuses a pose no training image looks like, as the structure method does
    // (its wrong poses on `small` looked 42° and 61° away from every training view;
    // docs/DECISIONS.md). Maps without the structure stage keep every pose.
    let mut failure = out.failure.take();
    if baseline == NerfBaseline::RgbKeypoints
        && let (Some(pose), Some(structure)) = (out.cam_from_world, map.structure.as_ref())
        && structure
            .images_looking_like(&pose, options.structure.max_view_angle_deg)
            .next()
            .is_none()
    {
        out.cam_from_world = None;
        failure = Some("no training image looks the way the solved pose does".to_string());
    }
    let mut stage_seconds = vec![("place".to_string(), place_s)];
    stage_seconds.extend(out.stage_seconds);
    // rgb-keypoints: 1 − NFA of its consensus, as the structure method's; iNeRF: none.
    let confidence = (baseline == NerfBaseline::RgbKeypoints).then(|| {
        structure_confidence(
            out.log10_nfa,
            out.inliers,
            options.keypoints.pnp.ransac.min_inliers,
        )
    });
    Ok(QueryResult {
        name: name.to_string(),
        method: method.name().to_string(),
        localized: out.cam_from_world.is_some(),
        camera_center: out
            .cam_from_world
            .as_ref()
            .map(|p| camera_center(p).coords.into()),
        cam_from_world: out.cam_from_world,
        confidence,
        inliers: out.inliers,
        iterations: out.iterations,
        hypotheses: vec![HypothesisReport {
            group: hyp.group,
            score: hyp.score,
            block,
            coarse_cam_from_world: hyp.cam_from_world,
            matches: out.matches,
            inliers: out.inliers,
            confidence: confidence.unwrap_or(0.0),
            passes: out.iterations as usize,
            accepted: out.cam_from_world.is_some(),
            failure,
            alignment: 0.0,
            log10_nfa: out.log10_nfa,
            refined_cam_from_world: out.cam_from_world,
        }],
        stage_seconds,
        total_seconds: start.elapsed().as_secs_f64(),
    })
}

/// MatLoc: the map's localizer (place → NeRF features → PnP), then the keypoint finish
/// ([`MatlocOptions::keypoint_finish`]).
fn localize_matloc(
    map: &LoadedMap,
    name: &str,
    image: &Image<f32>,
    camera: &Camera,
    options: &MethodOptions,
) -> Result<QueryResult, PipelineError> {
    let start = Instant::now();
    let mut localize_options = map.options();
    if let Some(k) = options.matloc.top_k {
        localize_options.top_k = k.max(1);
    }
    // Reduced to the working size once, for the localizer and the keypoint finish (the
    // localizer leaves a query already within `max_side` as it is); a query whose image and
    // camera disagree is refused before, with their given sizes.
    let (w, h, c) = image.shape();
    if w != camera.width as usize || h != camera.height as usize || c != 3 {
        return Err(PipelineError::QueryShape {
            image: (w, h, c),
            camera: (camera.width, camera.height),
        });
    }
    let (image, camera) = query_at_working_size(image, camera, localize_options.max_side);
    let (image, camera) = (image.as_ref(), &camera);
    let loc = map
        .blocks
        .localizer(map.place.as_ref(), map.solver.as_ref(), localize_options)
        .localize(image, camera)?;
    let passes = loc.hypotheses.iter().map(|h| h.passes as u32).sum::<u32>();
    let mut result = QueryResult {
        name: name.to_string(),
        method: Method::Matloc.name().to_string(),
        localized: loc.cam_from_world.is_some(),
        camera_center: None,
        cam_from_world: loc.cam_from_world,
        confidence: Some(loc.confidence),
        inliers: loc.inliers,
        iterations: passes,
        hypotheses: loc.hypotheses,
        stage_seconds: loc.stage_seconds,
        total_seconds: 0.0,
    };
    if options.matloc.keypoint_finish
        && let Some(structure) = map.structure.as_ref()
    {
        let t = Instant::now();
        // (hypothesis index, pose): the accepted one first, then the refused by inliers.
        let mut from: Vec<(usize, Pose)> = result
            .hypotheses
            .iter()
            .enumerate()
            .filter_map(|(i, h)| h.refined_cam_from_world.map(|p| (i, p)))
            .collect();
        from.sort_by_key(|&(i, _)| {
            let h = &result.hypotheses[i];
            (!h.accepted, std::cmp::Reverse(h.inliers))
        });
        let starts: Vec<Pose> = from.iter().map(|s| s.1).collect();
        if !starts.is_empty() {
            let mut rng = ChaCha8Rng::seed_from_u64(map.config.localize.seed);
            let r = matloc_structure::localize_with_references(
                structure,
                image,
                camera,
                &starts,
                &options.structure,
                Some(&NerfReferences { map }),
                &mut rng,
            )?;
            if let Some(pose) = r.cam_from_world {
                tracing::debug!(
                    query = name,
                    inliers = r.inliers,
                    start = r.chosen_start,
                    "keypoint finish accepted"
                );
                if let Some(&(i, _)) = r.chosen_start.and_then(|c| from.get(c)) {
                    for (k, h) in result.hypotheses.iter_mut().enumerate() {
                        h.accepted = k == i;
                        if k == i {
                            h.failure = None;
                        }
                    }
                }
                result.cam_from_world = Some(pose);
                result.localized = true;
                result.inliers = r.inliers;
                result.confidence = Some(structure_confidence(
                    r.log10_nfa,
                    r.inliers,
                    options.structure.min_inliers,
                ));
            } else if result.localized && !options.matloc.keep_unconfirmed {
                tracing::debug!(
                    query = name,
                    "pose refused: the keypoint finish cannot confirm it"
                );
                result.cam_from_world = None;
                result.localized = false;
                result.confidence = Some(0.0);
                for h in result.hypotheses.iter_mut().filter(|h| h.accepted) {
                    h.accepted = false;
                    h.failure = Some(
                        "the keypoints do not confirm the pose (no consensus of the query's \
                         keypoints with the training images that look its way)"
                            .to_string(),
                    );
                }
            }
        }
        result
            .stage_seconds
            .push(("keypoints".to_string(), t.elapsed().as_secs_f64()));
    }
    result.camera_center = result
        .cam_from_world
        .as_ref()
        .map(|p| camera_center(p).coords.into());
    result.total_seconds = start.elapsed().as_secs_f64();
    Ok(result)
}

/// The structure method: the top place hypotheses as start poses, in order
/// (`StructureOptions::place_hypotheses` of them, at least the map's top-k).
fn localize_structure(
    map: &LoadedMap,
    name: &str,
    image: &Image<f32>,
    camera: &Camera,
    options: &matloc_structure::StructureOptions,
) -> Result<QueryResult, PipelineError> {
    let start = Instant::now();
    let structure = map.structure.as_ref().ok_or_else(|| {
        PipelineError::Config(format!(
            "{}: the map has no keypoint structure (built without the structure stage); \
             rebuild it, or localize with --method matloc",
            map.dir.root().display()
        ))
    })?;
    let localize_options = map.options();
    let (image, camera) = query_at_working_size(image, camera, localize_options.max_side);
    let (image, camera) = (image.as_ref(), &camera);
    let t = Instant::now();
    let k = options.hypotheses_to_try(localize_options.top_k);
    let hyps = map.place.predict(image, camera, k)?;
    let place_s = t.elapsed().as_secs_f64();
    // In a process that serves some blocks, the places are tried up to the first one in a
    // block it does not serve (a prefix, so the indices stay the hypotheses'): when the best
    // place is elsewhere the query is refused, as with the other methods, and the process
    // that serves it answers.
    let starts: Vec<Pose> = hyps
        .iter()
        .take_while(|h| map.serves(h.block.unwrap_or(0)))
        .map(|h| h.cam_from_world)
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(map.config.localize.seed);
    let references = NerfReferences { map };
    let r = matloc_structure::localize_with_references(
        structure,
        image,
        camera,
        &starts,
        options,
        Some(&references),
        &mut rng,
    )?;
    let hypotheses = hyps
        .iter()
        .enumerate()
        .filter_map(|(i, h)| {
            let block = h.block.unwrap_or(0);
            let tried: Vec<_> = r.starts.iter().filter(|s| s.start == i).collect();
            let mut report = HypothesisReport {
                group: h.group,
                score: h.score,
                block,
                coarse_cam_from_world: h.cam_from_world,
                matches: 0,
                inliers: 0,
                confidence: 0.0,
                passes: tried.len(),
                accepted: false,
                failure: None,
                alignment: 0.0,
                log10_nfa: None,
                refined_cam_from_world: None,
            };
            match tried.last() {
                Some(last) => {
                    report.matches = last.matches;
                    report.inliers = last.inliers;
                    report.confidence =
                        structure_confidence(last.log10_nfa, last.inliers, options.min_inliers);
                    report.accepted = r.cam_from_world.is_some() && r.chosen_start == Some(i);
                    report.failure = if last.images == 0 {
                        Some("no training image looks the way this hypothesis does".into())
                    } else if let Some(unseen) = tried.iter().find(|s| s.unseen) {
                        Some(if options.rendered.enabled {
                            let agreed = unseen.render_agreement.map_or_else(
                                || "no patch of it could be compared".to_string(),
                                |a| format!("{:.0} % of its patches agree", 100.0 * a),
                            );
                            format!(
                                "no training image looks the way the solved pose does, and the \
                                 view the map renders there disagrees with the query ({agreed}, \
                                 {:.0} % needed)",
                                100.0 * options.rendered.min_agreement
                            )
                        } else {
                            "no training image looks the way the solved pose does".into()
                        })
                    } else if tried.iter().any(|s| s.behind) {
                        Some(
                            "the solved pose sees the map's points from behind the surface \
                             the survey saw them on (a mirrored image?)"
                                .into(),
                        )
                    } else if tried.iter().any(|s| s.unconfirmed) {
                        Some(
                            "the consensus covers a small part of the image and the map points \
                             in view disagree with the rest (a mirrored image?)"
                                .into(),
                        )
                    } else {
                        None
                    };
                    report.log10_nfa = last.log10_nfa;
                    report.refined_cam_from_world = last.cam_from_world;
                    Some(report)
                }
                // A place another process serves is reported (the server answers
                // `outside_blocks` from it); one left after an accepted pose is not.
                None => (!map.serves(block)).then(|| {
                    report.failure = Some(format!("block {block} is not served by this process"));
                    report
                }),
            }
        })
        .collect();
    let mut stage_seconds = vec![("place".to_string(), place_s)];
    stage_seconds.extend(r.stage_seconds);
    Ok(QueryResult {
        name: name.to_string(),
        method: Method::Structure.name().to_string(),
        localized: r.cam_from_world.is_some(),
        camera_center: r
            .cam_from_world
            .as_ref()
            .map(|p| camera_center(p).coords.into()),
        cam_from_world: r.cam_from_world,
        confidence: Some(structure_confidence(
            r.log10_nfa,
            r.inliers,
            options.min_inliers,
        )),
        inliers: r.inliers,
        iterations: r.starts.len() as u32,
        hypotheses,
        stage_seconds,
        total_seconds: start.elapsed().as_secs_f64(),
    })
}

/// The map's block NeRFs as the structure method's renderer of views no training image
/// shares: the served block whose scene box holds the point the view looks at (the nearest
/// box when none does) draws it in colour with its depth.
pub struct NerfReferences<'a> {
    map: &'a LoadedMap,
}

impl<'a> NerfReferences<'a> {
    /// The renderer over `map`'s block NeRFs.
    pub fn new(map: &'a LoadedMap) -> Self {
        NerfReferences { map }
    }
}

impl matloc_structure::ReferenceRenderer for NerfReferences<'_> {
    fn render_reference(
        &self,
        camera: &Camera,
        cam_from_world: &Pose,
        looking_at: &nalgebra::Point3<f64>,
    ) -> Option<matloc_structure::RenderedReference> {
        let p = [looking_at.x, looking_at.y, looking_at.z];
        let outside = |b: &matloc_partition::Block| -> f64 {
            (0..3)
                .map(|a| {
                    (b.bounds.min[a] - p[a])
                        .max(p[a] - b.bounds.max[a])
                        .max(0.0)
                })
                .map(|d| d * d)
                .sum()
        };
        let block = self
            .map
            .partition
            .blocks
            .iter()
            .filter(|b| self.map.serves(b.id) && self.map.nerf(b.id).is_some())
            .min_by(|a, b| outside(a).total_cmp(&outside(b)))?;
        let model = self.map.nerf(block.id)?;
        let (view, image) = render_colour(model, camera, cam_from_world).ok()?;
        Some(matloc_structure::RenderedReference {
            image,
            z_depth: view.z_depth,
            accumulation: view.accumulation,
        })
    }
}

/// The structure method's confidence: 1 − NFA, where the number of false alarms bounds the
/// chance that a consensus this large among these matches is an accident (not calibrated on
/// held-out views as MatLoc's is; every accepted pose has at least 1 − 10^max_log10_nfa).
/// 0 for a consensus below the method's inlier floor, which it refuses whatever its NFA (a
/// refused query showed 1 − NFA ≈ 1 otherwise), and when no start found one to score.
fn structure_confidence(log10_nfa: Option<f64>, inliers: usize, min_inliers: usize) -> f64 {
    match log10_nfa {
        Some(l) if inliers >= min_inliers => 1.0 - 10f64.powf(l).min(1.0),
        _ => 0.0,
    }
}

impl QueryResult {
    /// The evaluation record of this result against a ground-truth pose.
    pub fn outcome(&self, cam_from_world_gt: Pose) -> crate::QueryOutcome {
        crate::QueryOutcome {
            name: self.name.clone(),
            cam_from_world_gt,
            cam_from_world_est: self.cam_from_world,
            stage_seconds: self.stage_seconds.clone(),
            total_seconds: self.total_seconds,
            iterations: Some(self.iterations),
            confidence: self.confidence,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::structure_confidence;

    #[test]
    fn a_consensus_below_the_inlier_floor_has_no_confidence() {
        assert!((structure_confidence(Some(-6.0), 40, 15) - (1.0 - 1e-6)).abs() < 1e-12);
        // Refused on the floor, however unlikely by chance: 0.
        assert_eq!(structure_confidence(Some(-6.0), 14, 15), 0.0);
        // Refused on its NFA: below the acceptance level 1 − 10^-2.
        assert!(structure_confidence(Some(-1.0), 40, 15) < 0.99);
        assert_eq!(structure_confidence(Some(3.0), 40, 15), 0.0);
        assert_eq!(structure_confidence(None, 0, 15), 0.0);
    }
}
