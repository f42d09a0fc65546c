//! Localizing one query with any of the methods on a loaded map: MatLoc (the
//! [`Localizer`](crate::Localizer)), rendered-RGB + keypoints, iNeRF and curriculum iNeRF
//! (the paper's four), and `structure`: keypoints matched to the map's triangulated training
//! images ([`matloc_structure`]), the default. The NeRF baselines start from MatLoc's best
//! place hypothesis and render the block that serves it, as in the paper's comparison;
//! `structure` and MatLoc try the same top-k place hypotheses in order.

use std::fmt;
use std::str::FromStr;
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

/// The result of localizing one query: what `matloc localize` prints as a JSON line.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QueryResult {
    /// Query name (image path).
    pub name: String,
    /// Method.
    pub method: Method,
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
    /// Structure localizer.
    pub structure: matloc_structure::StructureOptions,
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
    method: Method,
    name: &str,
    image: &Image<f32>,
    camera: &Camera,
    options: &MethodOptions,
) -> Result<QueryResult, PipelineError> {
    camera.check_plausible()?;
    let mut result = localize_method(map, method, name, image, camera, options)?;
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

/// [`localize_with`] before the shared checks.
fn localize_method(
    map: &LoadedMap,
    method: Method,
    name: &str,
    image: &Image<f32>,
    camera: &Camera,
    options: &MethodOptions,
) -> Result<QueryResult, PipelineError> {
    if method == Method::Structure {
        return localize_structure(map, name, image, camera, &options.structure);
    }
    if method == Method::Matloc {
        let loc = map.localizer().localize(image, camera)?;
        let passes = loc.hypotheses.iter().map(|h| h.passes as u32).sum::<u32>();
        return Ok(QueryResult {
            name: name.to_string(),
            method,
            localized: loc.cam_from_world.is_some(),
            camera_center: loc
                .cam_from_world
                .as_ref()
                .map(|p| camera_center(p).coords.into()),
            cam_from_world: loc.cam_from_world,
            confidence: Some(loc.confidence),
            inliers: loc.inliers,
            iterations: passes,
            hypotheses: loc.hypotheses,
            stage_seconds: loc.stage_seconds,
            total_seconds: loc.total_seconds,
        });
    }
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
    let mut out = match method {
        Method::RgbKeypoints => rgb_keypoints(
            model,
            camera,
            image,
            &hyp.cam_from_world,
            &options.keypoints,
            &mut rng,
        )?,
        Method::Inerf => inerf(
            model,
            camera,
            image,
            &hyp.cam_from_world,
            &options.inerf,
            &mut rng,
        )?,
        Method::CurriculumInerf => {
            let o = InerfOptions {
                iterations: InerfOptions::curriculum().iterations,
                curriculum: InerfOptions::curriculum().curriculum,
                ..options.inerf.clone()
            };
            inerf(model, camera, image, &hyp.cam_from_world, &o, &mut rng)?
        }
        Method::Matloc | Method::Structure => {
            return Err(PipelineError::Internal("handled above"));
        }
    };
    // rgb-keypoints refuses a pose no training image looks like, as the structure method does
    // (its wrong poses on `small` looked 42° and 61° away from every training view;
    // docs/DECISIONS.md). Maps without the structure stage keep every pose.
    let mut failure = out.failure.take();
    if method == Method::RgbKeypoints
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
    let confidence = (method == Method::RgbKeypoints).then(|| {
        structure_confidence(
            out.log10_nfa,
            out.inliers,
            options.keypoints.pnp.ransac.min_inliers,
        )
    });
    Ok(QueryResult {
        name: name.to_string(),
        method,
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
        }],
        stage_seconds,
        total_seconds: start.elapsed().as_secs_f64(),
    })
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
                    } else if tried.iter().any(|s| s.unseen) {
                        Some(if options.rendered.enabled {
                            "no training image looks the way the solved pose does, and the \
                             view the map renders there disagrees with the query"
                                .into()
                        } else {
                            "no training image looks the way the solved pose does".into()
                        })
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
        method: Method::Structure,
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
