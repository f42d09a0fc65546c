//! Localizing one query with any of the four methods on a loaded map, from the same coarse
//! pose: MatLoc (the [`Localizer`](crate::Localizer)), rendered-RGB + keypoints, iNeRF and
//! curriculum iNeRF. The baselines start from MatLoc's best place hypothesis and render the
//! block that serves it, as in the paper's comparison.

use std::fmt;
use std::str::FromStr;
use std::time::Instant;

use matloc_core::pose::camera_center;
use matloc_core::{Camera, Image, Pose};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::baselines::{InerfOptions, KeypointBaselineOptions, inerf, rgb_keypoints};
use crate::error::PipelineError;
use crate::localizer::HypothesisReport;
use crate::localizer::options::query_at_working_size;
use crate::map::load::LoadedMap;

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
}

impl Method {
    /// Every method, in the paper's table order.
    pub const ALL: [Method; 4] = [
        Method::Matloc,
        Method::RgbKeypoints,
        Method::CurriculumInerf,
        Method::Inerf,
    ];

    /// Command-line name.
    pub fn name(self) -> &'static str {
        match self {
            Method::Matloc => "matloc",
            Method::RgbKeypoints => "rgb-keypoints",
            Method::CurriculumInerf => "curriculum-inerf",
            Method::Inerf => "inerf",
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
    /// Calibrated confidence (MatLoc) or `null`.
    pub confidence: Option<f64>,
    /// PnP inliers (MatLoc, keypoints).
    pub inliers: usize,
    /// Optimisation iterations (iNeRF) or refinement passes (MatLoc).
    pub iterations: u32,
    /// Place hypotheses tried (MatLoc) or the one the baseline started from.
    pub hypotheses: Vec<HypothesisReport>,
    /// Seconds per stage.
    pub stage_seconds: Vec<(String, f64)>,
    /// End-to-end seconds.
    pub total_seconds: f64,
}

/// Per-method settings.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MethodOptions {
    /// Keypoint baseline.
    pub keypoints: KeypointBaselineOptions,
    /// iNeRF (the curriculum variant uses its own schedule with these step sizes).
    pub inerf: InerfOptions,
}

/// Localizes `image` (taken with `camera`) with `method` on `map`.
pub fn localize_with(
    map: &LoadedMap,
    method: Method,
    name: &str,
    image: &Image<f32>,
    camera: &Camera,
    options: &MethodOptions,
) -> Result<QueryResult, PipelineError> {
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
    let out = match method {
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
        Method::Matloc => return Err(PipelineError::Internal("handled above")),
    };
    let mut stage_seconds = vec![("place".to_string(), place_s)];
    stage_seconds.extend(out.stage_seconds);
    Ok(QueryResult {
        name: name.to_string(),
        method,
        localized: out.cam_from_world.is_some(),
        camera_center: out
            .cam_from_world
            .as_ref()
            .map(|p| camera_center(p).coords.into()),
        cam_from_world: out.cam_from_world,
        confidence: None,
        inliers: out.inliers,
        iterations: out.iterations,
        hypotheses: vec![HypothesisReport {
            group: hyp.group,
            score: hyp.score,
            block,
            coarse_cam_from_world: hyp.cam_from_world,
            matches: out.matches,
            inliers: out.inliers,
            confidence: 0.0,
            passes: out.iterations as usize,
            accepted: out.cam_from_world.is_some(),
            failure: None,
            alignment: 0.0,
            log10_nfa: None,
        }],
        stage_seconds,
        total_seconds: start.elapsed().as_secs_f64(),
    })
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
        }
    }
}
