//! Localizing a query against a [`StructureMap`] from one or more start poses.

use std::time::Instant;

use matloc_core::pose::{Pose, camera_center, viewing_direction};
use matloc_core::{Camera, Image};
use matloc_keypoints::{
    GrayImage, Keypoint, KeypointConfig, MatchConfig, detect_and_describe, match_descriptors,
};
use matloc_pnp::significance::log10_nfa;
use matloc_pnp::{LoRansacPnp, PnpInput, PnpOptions, PoseSolver};
use nalgebra::{Point2, Point3};
use rand::RngCore;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::StructureError;
use crate::store::StructureMap;

/// Settings of the structure localizer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StructureOptions {
    /// Query keypoints (the map's keypoints were detected with the same detector: detection
    /// at 2×, as the structure stage's triangulation does).
    pub keypoints: KeypointConfig,
    /// Descriptor matching between the query and each nearby training image.
    pub matching: MatchConfig,
    /// Training images matched per start: the nearest by camera centre among those looking
    /// the same way.
    pub neighbours: usize,
    /// A training image is used only when its viewing direction is within this of the
    /// start's, degrees.
    pub max_view_angle_deg: f64,
    /// Pose solver.
    pub pnp: PnpOptions,
    /// Inliers an accepted pose needs.
    pub min_inliers: usize,
    /// Largest base-10 number of false alarms of an accepted consensus (a chance match
    /// falls inside the inlier threshold with the probability of its disk's share of the
    /// image), counted over the starts tried so far: the `i`-th start (from 0) adds
    /// `log10(i + 1)`, so that trying more starts does not make a chance consensus likelier
    /// to pass.
    pub max_log10_nfa: f64,
    /// Place hypotheses a caller tries as starts, in order, up to the first accepted (the
    /// structure method of `matloc-pipeline` asks the place predictor for this many, or the
    /// map's top-k when that is more): a refused start costs a few hundredths of a second,
    /// and a photo from another day can rank the right place below the first three.
    pub place_hypotheses: usize,
    /// Solve again from the images nearest the first estimate.
    pub second_pass: bool,
    /// Unsharp-mask amount of the query's gray image before detection (σ = 1 px; 0 = off):
    /// `small`'s second flight (0.5 px blur, noise, other light) localized to a median of
    /// 0.050 m without it and 0.037 m with 1.0, the same flight to 0.030 and 0.034 m.
    pub query_sharpen: f32,
}

impl Default for StructureOptions {
    fn default() -> Self {
        StructureOptions {
            keypoints: KeypointConfig {
                max_keypoints: 2000,
                upsample: true,
                ..KeypointConfig::default()
            },
            matching: MatchConfig::default(),
            neighbours: 6,
            max_view_angle_deg: 37.0,
            pnp: PnpOptions::default(),
            min_inliers: 15,
            max_log10_nfa: -2.0,
            place_hypotheses: 30,
            second_pass: true,
            query_sharpen: 1.0,
        }
    }
}

impl StructureOptions {
    /// Place hypotheses to try when the map's other methods get `top_k`: the more of
    /// `place_hypotheses` and `top_k`, at least one.
    pub fn hypotheses_to_try(&self, top_k: usize) -> usize {
        top_k.max(self.place_hypotheses).max(1)
    }
}

/// What one start gave.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StartReport {
    /// Index of the start in the list given.
    pub start: usize,
    /// Training images matched.
    pub images: usize,
    /// 2D–3D matches given to the solver.
    pub matches: usize,
    /// Inliers of the solved pose (0 when none).
    pub inliers: usize,
    /// Base-10 number of false alarms of the consensus (`None` when no pose).
    pub log10_nfa: Option<f64>,
    /// Whether the pose passed the acceptance rule.
    pub accepted: bool,
}

/// The outcome of a structure localization.
#[derive(Clone, Debug, PartialEq)]
pub struct StructureResult {
    /// The accepted pose, `None` when refused.
    pub cam_from_world: Option<Pose>,
    /// Inliers of the accepted pose (or of the best refused one).
    pub inliers: usize,
    /// Matches behind it.
    pub matches: usize,
    /// Its number of false alarms, base 10.
    pub log10_nfa: Option<f64>,
    /// Per start tried, in order (a second pass appears as its own report).
    pub starts: Vec<StartReport>,
    /// Seconds per stage (`keypoints`, `match`, `pnp`).
    pub stage_seconds: Vec<(String, f64)>,
}

struct Solve {
    pose: Option<Pose>,
    report: StartReport,
}

/// Localizes `image` (taken with `camera`) from the start poses in order: the first accepted
/// pose is returned (improved by a second pass when enabled), else a refusal.
pub fn localize(
    map: &StructureMap,
    image: &Image<f32>,
    camera: &Camera,
    starts: &[Pose],
    options: &StructureOptions,
    rng: &mut dyn RngCore,
) -> Result<StructureResult, StructureError> {
    let (w, h, c) = image.shape();
    if w != camera.width as usize || h != camera.height as usize || c != 3 {
        return Err(StructureError::QueryShape {
            image: (w, h, c),
            camera: (camera.width, camera.height),
        });
    }
    let t = Instant::now();
    // Sharpened before detection: a photo from another flight or camera is softer than the
    // map's training images.
    let gray = GrayImage::from_image(image).unsharp(options.query_sharpen, 1.0);
    let (keypoints, descriptors) = detect_and_describe(&gray, &options.keypoints);
    let mut seconds = vec![("keypoints".to_string(), t.elapsed().as_secs_f64())];
    let mut time = Timer::default();
    let query = Query {
        camera,
        keypoints: &keypoints,
        descriptors: &descriptors,
    };
    let mut reports = Vec::new();
    let mut best: Option<Solve> = None;
    for (i, start) in starts.iter().enumerate() {
        let first = solve_from(map, &query, start, i, options, rng, &mut time);
        reports.push(first.report.clone());
        if !first.report.accepted {
            if best
                .as_ref()
                .is_none_or(|b| first.report.inliers > b.report.inliers)
            {
                best = Some(first);
            }
            continue;
        }
        let mut chosen = first;
        if options.second_pass
            && let Some(pose) = chosen.pose
        {
            let again = solve_from(map, &query, &pose, i, options, rng, &mut time);
            reports.push(again.report.clone());
            if again.report.accepted && again.report.inliers >= chosen.report.inliers {
                chosen = again;
            }
        }
        best = Some(chosen);
        break;
    }
    seconds.push(("match".to_string(), time.matching));
    seconds.push(("pnp".to_string(), time.pnp));
    let accepted = best.as_ref().is_some_and(|b| b.report.accepted);
    Ok(StructureResult {
        cam_from_world: best.as_ref().filter(|_| accepted).and_then(|b| b.pose),
        inliers: best.as_ref().map_or(0, |b| b.report.inliers),
        matches: best.as_ref().map_or(0, |b| b.report.matches),
        log10_nfa: best.as_ref().and_then(|b| b.report.log10_nfa),
        starts: reports,
        stage_seconds: seconds,
    })
}

struct Query<'a> {
    camera: &'a Camera,
    keypoints: &'a [Keypoint],
    descriptors: &'a [matloc_keypoints::Descriptor],
}

#[derive(Default)]
struct Timer {
    matching: f64,
    pnp: f64,
}

/// The training images nearest `start` (camera centre) among those looking within the
/// angle, at most `options.neighbours`.
fn nearest_images(map: &StructureMap, start: &Pose, options: &StructureOptions) -> Vec<usize> {
    let (center, dir) = (camera_center(start), viewing_direction(start));
    let cos_max = options.max_view_angle_deg.to_radians().cos();
    let mut near: Vec<(f64, usize)> = map
        .images()
        .iter()
        .enumerate()
        .filter(|(_, im)| im.viewing_direction().dot(&dir) >= cos_max)
        .map(|(i, im)| ((im.center() - center).norm(), i))
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    near.into_iter()
        .take(options.neighbours)
        .map(|(_, i)| i)
        .collect()
}

fn solve_from(
    map: &StructureMap,
    query: &Query<'_>,
    start: &Pose,
    index: usize,
    options: &StructureOptions,
    rng: &mut dyn RngCore,
    time: &mut Timer,
) -> Solve {
    let t = Instant::now();
    let images = nearest_images(map, start, options);
    // Per query keypoint, its closest match (Hamming distance, point) over the images.
    let per_image: Vec<Vec<(usize, u32, u32)>> = images
        .par_iter()
        .map(|&i| {
            let im = &map.images()[i];
            match_descriptors(query.descriptors, &im.descriptor, &options.matching)
                .into_iter()
                .map(|m| (m.a, m.distance, im.point[m.b]))
                .collect()
        })
        .collect();
    let mut best: Vec<Option<(u32, u32)>> = vec![None; query.keypoints.len()];
    for (q, d, p) in per_image.into_iter().flatten() {
        if best[q].is_none_or(|(bd, _)| d < bd) {
            best[q] = Some((d, p));
        }
    }
    let (mut pixels, mut points, mut scores) = (Vec::new(), Vec::<Point3<f64>>::new(), Vec::new());
    for (q, b) in best.iter().enumerate() {
        if let Some((d, p)) = b {
            let k = &query.keypoints[q];
            pixels.push(Point2::new(f64::from(k.x), f64::from(k.y)));
            points.push(map.points()[*p as usize]);
            scores.push(1.0 - f64::from(*d) / 256.0);
        }
    }
    time.matching += t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut report = StartReport {
        start: index,
        images: images.len(),
        matches: pixels.len(),
        inliers: 0,
        log10_nfa: None,
        accepted: false,
    };
    let solver = LoRansacPnp::new(options.pnp.clone());
    let solved = solver.solve(
        &PnpInput::new(query.camera, &pixels, &points).with_scores(&scores),
        rng,
    );
    time.pnp += t.elapsed().as_secs_f64();
    let pose = match solved {
        Ok(r) => {
            let tau = options.pnp.ransac.max_error_px;
            let area = f64::from(query.camera.width) * f64::from(query.camera.height);
            let p_chance = (std::f64::consts::PI * tau * tau / area.max(1.0)).min(1.0);
            // Bonferroni over the starts: start `index` is the (index + 1)-th test.
            let nfa = log10_nfa(
                pixels.len(),
                r.stats.num_inliers,
                solver.minimal_sample(),
                p_chance,
            ) + ((index + 1) as f64).log10();
            report.inliers = r.stats.num_inliers;
            report.log10_nfa = Some(nfa);
            report.accepted =
                r.stats.num_inliers >= options.min_inliers && nfa <= options.max_log10_nfa;
            Some(r.cam_from_world)
        }
        Err(_) => None,
    };
    Solve { pose, report }
}

#[cfg(test)]
mod tests;
