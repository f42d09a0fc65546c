//! Localizing a query against a [`StructureMap`] from one or more start poses.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use matloc_core::pose::{Pose, camera_center};
use matloc_core::{Camera, Image};
use matloc_keypoints::{
    Descriptor, GradientDescriptor, GrayImage, Keypoint, KeypointConfig, MatchConfig,
    describe_gradients_at, detect_and_describe, detect_and_describe_gradients, match_descriptors,
};
use matloc_pnp::{LoRansacPnp, PnpInput, PnpOptions, PoseSolver};
use nalgebra::{Point2, Point3, Vector2, Vector3};
use rand::RngCore;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::align::{AlignOptions, QueryPlanes, align, local_affine, template, zncc_at};
use crate::error::StructureError;
use crate::rendered::{ReferenceRenderer, RenderedOptions};
use crate::store::StructureMap;

/// Settings of the structure localizer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StructureOptions {
    /// Query keypoints (the map's keypoints were detected with the same detector: detection
    /// at 2×, as the structure stage's triangulation does).
    pub keypoints: KeypointConfig,
    /// Which descriptor the query is matched with; maps built without gradient descriptors
    /// use `binary` whatever this says.
    pub descriptor: QueryDescriptor,
    /// Binary-descriptor matching between the query and each nearby training image.
    pub matching: MatchConfig,
    /// Gradient-descriptor matching between the query and each nearby training image.
    pub gradient_matching: MatchConfig,
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
    /// When every start is refused: groups of training images chosen by what they share with
    /// the query (its descriptors matched against every training image, each image scored by
    /// its matches), tried as further starts; 0 = off. A viewpoint the survey never flew puts
    /// every place hypothesis on a survey pose that looks elsewhere, and matching against the
    /// images nearest those finds too few points.
    pub retrieval: usize,
    /// An accepted consensus with fewer inliers than this is weak: the next
    /// `weak_more_starts` starts are tried as well and the consensus with the most inliers
    /// is kept. A repeated part of the scene (a street block like the next) ranked first by
    /// the place predictor gives such a consensus.
    pub weak_inliers: usize,
    /// See `weak_inliers`.
    pub weak_more_starts: usize,
    /// Solve again from the images nearest the first estimate.
    pub second_pass: bool,
    /// Unsharp-mask amount of the query's gray image before detection (σ = 1 px; 0 = off):
    /// `small`'s second flight (0.5 px blur, noise, other light) localized to a median of
    /// 0.050 m without it and 0.037 m with 1.0, the same flight to 0.030 and 0.034 m.
    pub query_sharpen: f32,
    /// Patch alignment of the accepted pose's correspondences to the training images, then
    /// a last solve.
    pub align: AlignOptions,
    /// Share of a consensus's inliers the query must see from the side the training cameras
    /// saw them from (its ray to the point within 90° of their mean ray), else the consensus
    /// is refused: an image mirrored top to bottom or left to right is consistent with a
    /// camera reflected to the far side of nearly flat ground, under it, whose view rendered
    /// by the map (the surface from behind) agrees with the image. 0 = off.
    pub min_front_side: f64,
    /// A consensus whose inliers' convex hull covers less than this share of the query image
    /// is refused: a mirrored image matches the map only on mirror-symmetric parts of the
    /// scene, and their consensus sits in one part of it (tiny's mirrored views: at most 0.19
    /// of the image; every pose of a real view, its second flight included, at least 0.23).
    /// 0 = off.
    pub min_inlier_hull: f64,
    /// A consensus whose hull covers less than this share (and at least `min_inlier_hull`) is
    /// accepted only when the rest of the image confirms it (`min_agreement`).
    pub confirmed_hull: f64,
    /// Share of the map points the consensus's training images see that must agree with the
    /// query where the pose puts them (their training patch, laid into the query through the
    /// pose, correlating at [`AGREEING_ZNCC`] or more) for a consensus below
    /// `confirmed_hull` to be accepted (tiny's mirrored views: at most 0.53; real views at
    /// least 0.58). A map without its training images' gray values cannot confirm one.
    pub min_agreement: f64,
    /// References rendered by the map's radiance field where no training image looks the
    /// query's way ([`localize_with_references`]; without a renderer, unused).
    pub rendered: RenderedOptions,
}

/// Which descriptors a query is matched with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum QueryDescriptor {
    /// Rotated BRIEF.
    Binary,
    /// Gradient histograms: more correct matches under another light or viewpoint, placed
    /// less precisely (a histogram cell tolerates a pixel of shift).
    Gradient,
    /// Binary; when every start is refused, the whole search again with gradient
    /// histograms: the binary descriptor's precision wherever it finds a pose, the gradient
    /// descriptor's matches where it does not.
    #[default]
    BinaryThenGradient,
}

/// Camera centres closer than this are the same place to the weak-consensus search, metres.
const WEAK_SAME_PLACE_M: f64 = 5.0;

/// Normalised cross-correlation at which a map point's training patch agrees with the query.
pub const AGREEING_ZNCC: f64 = 0.5;

impl Default for StructureOptions {
    fn default() -> Self {
        StructureOptions {
            keypoints: KeypointConfig {
                max_keypoints: 2000,
                upsample: true,
                ..KeypointConfig::default()
            },
            descriptor: QueryDescriptor::BinaryThenGradient,
            matching: MatchConfig::default(),
            gradient_matching: MatchConfig {
                ratio: 0.9,
                ..MatchConfig::gradient()
            },
            neighbours: 6,
            max_view_angle_deg: 37.0,
            pnp: PnpOptions::default(),
            min_inliers: 15,
            max_log10_nfa: -2.0,
            place_hypotheses: 30,
            retrieval: 0,
            weak_inliers: 45,
            weak_more_starts: 30,
            second_pass: true,
            query_sharpen: 1.0,
            align: AlignOptions::default(),
            min_front_side: 0.5,
            min_inlier_hull: 0.15,
            confirmed_hull: 0.3,
            min_agreement: 0.5,
            rendered: RenderedOptions::default(),
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
    /// The pose passed the inlier and NFA tests but no training image looks within
    /// `max_view_angle_deg` of its viewing direction, so it was not accepted.
    pub unseen: bool,
    /// The pose passed the other tests, but its inliers cover less than `min_inlier_hull` of
    /// the image, or less than `confirmed_hull` with fewer than `min_agreement` of the map
    /// points in view agreeing with the query, so it was not accepted.
    #[serde(default)]
    pub unconfirmed: bool,
    /// The pose passed the inlier and NFA tests but sees fewer than `min_front_side` of its
    /// inliers from the side the training images saw them from, so it was not accepted.
    #[serde(default)]
    pub behind: bool,
    /// The pose was confirmed by (or solved from) a view rendered at it, no training image
    /// looking its way.
    #[serde(default)]
    pub rendered: bool,
    /// The pose this start solved (accepted or not; `None` when the solver found none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cam_from_world: Option<Pose>,
    /// Share of a view rendered at the pose that agreed with the query, when one was
    /// rendered to confirm it ([`render_agreement`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub render_agreement: Option<f64>,
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
    /// The start whose pose was returned (`None` when refused, or when the pose was solved
    /// from renders after every start was refused).
    pub chosen_start: Option<usize>,
    /// Inliers of the last solve on the aligned correspondences, whose pose is returned (0
    /// when nothing was aligned: then the pose is the descriptor matches' own).
    pub aligned_inliers: usize,
    /// Seconds per stage (`keypoints`, `match`, `pnp`).
    pub stage_seconds: Vec<(String, f64)>,
}

#[derive(Clone)]
struct Solve {
    pose: Option<Pose>,
    report: StartReport,
    matches: Matches,
    inliers: Vec<bool>,
    /// The training images matched.
    images: Vec<usize>,
}

/// A start's 2D–3D matches with where each came from.
#[derive(Clone, Default)]
struct Matches {
    pixels: Vec<Point2<f64>>,
    points: Vec<Point3<f64>>,
    scores: Vec<f64>,
    /// Per match: (training image, observation in it).
    source: Vec<(u32, u32)>,
    /// Per match: the point.
    point: Vec<u32>,
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
    localize_with_references(map, image, camera, starts, options, None, rng)
}

/// [`localize`] with a renderer of the map's scene for viewpoints no training image shares:
/// a consensus that passes every test but whose pose no training image looks towards is
/// accepted only when a view rendered at the pose agrees with the query
/// (`options.rendered.min_agreement`, [`render_agreement`]). With
/// `options.rendered.max_renders`, when every start is refused, the refused poses with the
/// most inliers are rendered, solved from the render, rendered again at that solution and
/// solved once more; the second solve is accepted when it has `options.rendered.min_inliers`
/// inliers, an NFA within `max_log10_nfa` (counted over every attempt), inliers over
/// `confirmed_hull` of the image, and agrees with the first.
pub fn localize_with_references(
    map: &StructureMap,
    image: &Image<f32>,
    camera: &Camera,
    starts: &[Pose],
    options: &StructureOptions,
    renderer: Option<&dyn ReferenceRenderer>,
    rng: &mut dyn RngCore,
) -> Result<StructureResult, StructureError> {
    let (w, h, c) = image.shape();
    if w != camera.width as usize || h != camera.height as usize || c != 3 {
        return Err(StructureError::QueryShape {
            image: (w, h, c),
            camera: (camera.width, camera.height),
        });
    }
    let gradients = map.has_gradients();
    let t = Instant::now();
    // Sharpened before detection: a photo from another flight or camera is softer than the
    // map's training images.
    let plain = GrayImage::from_image(image);
    let gray = plain.clone().unsharp(options.query_sharpen, 1.0);
    let gradient_first = options.descriptor == QueryDescriptor::Gradient && gradients;
    let (keypoints, descriptors) = describe_query(&gray, gradient_first, options);
    let prepared = Prepared {
        plain,
        gray,
        keypoints,
    };
    let first = localize_once(
        map,
        &prepared,
        descriptors.as_ref(),
        t.elapsed().as_secs_f64(),
        camera,
        starts,
        options,
        0,
        renderer,
        rng,
    )?;
    if options.descriptor != QueryDescriptor::BinaryThenGradient
        || first.cam_from_world.is_some()
        || !gradients
    {
        return Ok(first);
    }
    // The second search describes the same keypoints with gradient histograms; its
    // consensuses are further tests of the same query, their false alarms counted after the
    // first search's.
    let t = Instant::now();
    let gradient = OwnedDescriptors::Gradient(describe_gradients_at(
        &prepared.gray,
        &options.keypoints,
        &prepared.keypoints,
    ));
    let tests = first.starts.iter().map(|s| s.start + 1).max().unwrap_or(0);
    let mut second = localize_once(
        map,
        &prepared,
        gradient.as_ref(),
        t.elapsed().as_secs_f64(),
        camera,
        starts,
        options,
        tests,
        renderer,
        rng,
    )?;
    // The time of both attempts, per stage.
    for (stage, secs) in first.stage_seconds {
        match second.stage_seconds.iter_mut().find(|(s, _)| *s == stage) {
            Some((_, t)) => *t += secs,
            None => second.stage_seconds.push((stage, secs)),
        }
    }
    Ok(second)
}

/// A query's gray images and keypoints, shared by both searches.
struct Prepared {
    /// The gray image as taken.
    plain: GrayImage,
    /// Sharpened for detection and alignment.
    gray: GrayImage,
    keypoints: Vec<Keypoint>,
}

/// One localization with one kind of descriptor (gradient descriptors only where the map has
/// them); `keypoint_seconds` is what describing the query took.
#[allow(clippy::too_many_arguments)]
fn localize_once(
    map: &StructureMap,
    prepared: &Prepared,
    descriptors: QueryDescriptors<'_>,
    keypoint_seconds: f64,
    camera: &Camera,
    starts: &[Pose],
    options: &StructureOptions,
    earlier_tests: usize,
    renderer: Option<&dyn ReferenceRenderer>,
    rng: &mut dyn RngCore,
) -> Result<StructureResult, StructureError> {
    let renderer = renderer.filter(|_| options.rendered.enabled);
    let (plain, gray, keypoints) = (&prepared.plain, &prepared.gray, &prepared.keypoints);
    let mut seconds = vec![("keypoints".to_string(), keypoint_seconds)];
    let mut time = Timer {
        earlier_tests,
        ..Timer::default()
    };
    let planes = QueryPlanes::new(gray);
    let query = Query {
        camera,
        keypoints,
        descriptors,
        matched: Mutex::new(vec![None; map.images().len()]),
    };
    let mut reports = Vec::new();
    let mut best: Option<Solve> = None;
    let mut aligned_inliers = 0;
    let mut attempts: Vec<Attempt> = starts.iter().map(Attempt::Start).collect();
    let mut retrieved = false;
    // Refused poses worth a render: (inliers, pose, a point the consensus saw).
    let mut refused: Vec<(usize, Pose, Point3<f64>)> = Vec::new();
    // The accepted consensus with the most inliers so far, with its attempt's index; after a
    // weak one, the attempts up to `look_until` are tried as well.
    let mut accepted: Option<(usize, Solve)> = None;
    let mut look_until: Option<usize> = None;
    // Consensuses that passed the inlier, false-alarm and side tests but that nothing
    // confirmed (unseen, or unconfirmed): rivals of a weak accepted one elsewhere.
    let mut rivals: Vec<Solve> = Vec::new();
    // Each attempt draws from its own generator, seeded from the caller's and its index: the
    // attempts are solved a batch at a time in parallel and judged in order, with the same
    // outcome whatever the batch.
    let seed = rng.next_u64();
    let batch = rayon::current_num_threads().max(1);
    let mut solved: std::collections::VecDeque<Solve> = std::collections::VecDeque::new();
    let mut i = 0;
    while i < attempts.len() && look_until.is_none_or(|end| i < end) {
        if solved.is_empty() {
            let end = (i + batch)
                .min(attempts.len())
                .min(look_until.unwrap_or(usize::MAX));
            let jobs: Vec<(usize, Attempt)> = (i..end)
                .map(|k| (k, std::mem::replace(&mut attempts[k], Attempt::Done)))
                .collect();
            let earlier_tests = time.earlier_tests;
            let results: Vec<(Solve, Timer)> = jobs
                .into_par_iter()
                .map(|(k, job)| {
                    let mut rng = attempt_rng(seed, k);
                    let mut time = Timer {
                        earlier_tests,
                        ..Timer::default()
                    };
                    let solve = match job {
                        Attempt::Start(start) => {
                            solve_from(map, &query, start, k, options, &mut rng, &mut time)
                        }
                        Attempt::Images(images, per_image) => solve_images(
                            map, &query, images, per_image, k, options, &mut rng, &mut time,
                        ),
                        Attempt::Done => unreachable!("an attempt is solved once"),
                    };
                    (solve, time)
                })
                .collect();
            for (solve, t) in results {
                time.matching += t.matching;
                time.pnp += t.pnp;
                solved.push_back(solve);
            }
        }
        let Some(mut first) = solved.pop_front() else {
            break;
        };
        // A camera on the far side of the surface its inliers lie on: no photograph sees
        // ground from under it.
        if first.report.accepted
            && let Some(pose) = first.pose
            && front_side(map, &pose, &first) < options.min_front_side
        {
            first.report.accepted = false;
            first.report.behind = true;
        }
        // A pose the survey never looked at is a consensus with the wrong part of the scene:
        // on `building` one such pose had 16 inliers at NFA 10^-14, 54 m and 83° off.
        // A viewpoint beyond the survey: only a view rendered there can confirm it.
        if first.report.accepted
            && let Some(pose) = first.pose
            && nearest_images(map, &pose, options).is_empty()
        {
            let confirmed = renderer.is_some_and(|r| {
                let t = Instant::now();
                let reference =
                    inlier_centroid(&first).and_then(|at| r.render_reference(camera, &pose, &at));
                time.render += t.elapsed().as_secs_f64();
                let t = Instant::now();
                let agreement = reference
                    .and_then(|reference| render_agreement(plain, &reference, &options.rendered));
                time.matching += t.elapsed().as_secs_f64();
                first.report.render_agreement = agreement;
                agreement.is_some_and(|a| a >= options.rendered.min_agreement)
            });
            if confirmed {
                first.report.rendered = true;
            } else {
                first.report.accepted = false;
                first.report.unseen = true;
            }
        }
        // A consensus on one small part of the image that the rest of it does not confirm: a
        // mirrored image matched on the mirror-symmetric parts of the scene.
        if first.report.accepted && !confirmed(map, &planes, camera, &first, options) {
            first.report.accepted = false;
            first.report.unconfirmed = true;
        }
        reports.push(first.report.clone());
        i += 1;
        if !first.report.accepted {
            if first.report.unseen || first.report.unconfirmed {
                rivals.push(first.clone());
            }
            if let Some(pose) = first.pose
                && first.report.inliers >= options.rendered.min_start_inliers
                && let Some(at) = inlier_centroid(&first)
            {
                refused.push((first.report.inliers, pose, at));
            }
            if best
                .as_ref()
                .is_none_or(|b| first.report.inliers > b.report.inliers)
            {
                best = Some(first);
            }
            // Every start refused: the images that share most with the query, once.
            if i == attempts.len() && options.retrieval > 0 && !retrieved && accepted.is_none() {
                retrieved = true;
                let t = Instant::now();
                attempts.extend(
                    retrieve(map, &query, options)
                        .into_iter()
                        .map(|(images, per_image)| Attempt::Images(images, per_image)),
                );
                time.matching += t.elapsed().as_secs_f64();
            }
            continue;
        }
        let strong = first.report.inliers >= options.weak_inliers;
        // Another place with more inliers replaces the weak consensus; the same place found
        // again from other images does not (its pose is no better for having more inliers).
        let elsewhere = |a: &Solve| match (a.pose, first.pose) {
            (Some(p), Some(q)) => {
                (camera_center(&p) - camera_center(&q)).norm() > WEAK_SAME_PLACE_M
            }
            _ => true,
        };
        if accepted
            .as_ref()
            .is_none_or(|(_, a)| first.report.inliers > a.report.inliers && elsewhere(a))
        {
            accepted = Some((i - 1, first));
        }
        // A weak consensus may be a repeated part of the scene the place predictor ranked
        // first: the next starts may hold the right one, with more inliers.
        if strong {
            break;
        }
        if look_until.is_none() {
            look_until = Some(i + options.weak_more_starts);
        }
    }
    // A weak consensus may be a repeated part of the scene (a street block like the next)
    // while the right place's consensus went unconfirmed: the views rendered at both decide.
    if let Some(r) = renderer
        && let Some((_, weak)) = accepted.as_mut()
        && weak.report.inliers < options.weak_inliers
        && let Some(rival) = rendered_rival(r, plain, camera, weak, rivals, options, &mut time)
    {
        if let Some(report) = reports
            .iter_mut()
            .rev()
            .find(|s| s.start == rival.report.start)
        {
            *report = rival.report.clone();
        }
        accepted = Some((rival.report.start, rival));
    }
    let chosen_start = accepted.as_ref().map(|(index, _)| *index);
    if let Some((index, mut chosen)) = accepted {
        if options.second_pass
            && let Some(pose) = chosen.pose
        {
            let again = solve_from(map, &query, &pose, index, options, rng, &mut time);
            reports.push(again.report.clone());
            if again.report.accepted && again.report.inliers >= chosen.report.inliers {
                chosen = again;
            }
        }
        // One pass: a second one, from the aligned pose, changed nothing on `small`.
        if options.align.enabled
            && let Some(pose) = chosen.pose
        {
            let t = Instant::now();
            let refined = aligned(map, &planes, camera, &pose, &chosen, &options.align);
            time.align += t.elapsed().as_secs_f64();
            if let Some(matches) = refined {
                let again = solve_matches(matches, index, options, camera, rng, &mut time);
                // The pose only: acceptance, inliers and false alarms stay those of the
                // descriptor matches (the tracked points were found with this pose, so
                // their consensus says nothing about whether it is right).
                if again.report.accepted && again.report.inliers >= chosen.report.inliers {
                    chosen.pose = again.pose;
                    aligned_inliers = again.report.inliers;
                }
            }
        }
        best = Some(chosen);
    }
    if let Some(r) = renderer
        && !best.as_ref().is_some_and(|b| b.report.accepted)
        && let Some(s) = from_renders(r, &query, refused, i, options, rng, &mut time, &mut reports)
    {
        best = Some(s);
    }
    seconds.push(("match".to_string(), time.matching));
    seconds.push(("pnp".to_string(), time.pnp));
    if options.align.enabled {
        seconds.push(("align".to_string(), time.align));
    }
    if renderer.is_some() {
        seconds.push(("render".to_string(), time.render));
    }
    let accepted = best.as_ref().is_some_and(|b| b.report.accepted);
    Ok(StructureResult {
        cam_from_world: best.as_ref().filter(|_| accepted).and_then(|b| b.pose),
        inliers: best.as_ref().map_or(0, |b| b.report.inliers),
        matches: best.as_ref().map_or(0, |b| b.report.matches),
        log10_nfa: best.as_ref().and_then(|b| b.report.log10_nfa),
        starts: reports,
        chosen_start: chosen_start.filter(|_| accepted),
        aligned_inliers,
        stage_seconds: seconds,
    })
}

/// What a localization attempt solves from: a start pose (the images nearest it), or a group
/// of training images retrieved by what they share with the query.
enum Attempt<'a> {
    Start(&'a Pose),
    /// The images and their matches with the query (made when they were ranked).
    Images(Vec<usize>, ImageMatches),
    /// Taken to be solved.
    Done,
}

/// The generator of attempt `index` of a search seeded with `seed`.
fn attempt_rng(seed: u64, index: usize) -> rand_chacha::ChaCha8Rng {
    use rand::SeedableRng;
    rand_chacha::ChaCha8Rng::seed_from_u64(
        seed ^ (index as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
    )
}

struct Query<'a> {
    camera: &'a Camera,
    keypoints: &'a [Keypoint],
    descriptors: QueryDescriptors<'a>,
    /// Per training image, the query's matches with it once made: the starts share most of
    /// their images, and a match does not depend on the start.
    matched: Mutex<Vec<Option<SharedMatches>>>,
}

/// A query's descriptors, of the kind it is matched with.
enum OwnedDescriptors {
    Binary(Vec<Descriptor>),
    Gradient(Vec<GradientDescriptor>),
}

impl OwnedDescriptors {
    fn as_ref(&self) -> QueryDescriptors<'_> {
        match self {
            OwnedDescriptors::Binary(d) => QueryDescriptors::Binary(d),
            OwnedDescriptors::Gradient(d) => QueryDescriptors::Gradient(d),
        }
    }
}

#[derive(Clone, Copy)]
enum QueryDescriptors<'a> {
    Binary(&'a [Descriptor]),
    Gradient(&'a [GradientDescriptor]),
}

/// Largest binary (Hamming) and gradient (quantised Euclidean) distance: a match's distance
/// over it is its normalised distance.
const BINARY_MAX_DISTANCE: f32 = 256.0;
const GRADIENT_MAX_DISTANCE: f32 = 724.0;

/// Keypoints of a gray image with the descriptors of the kind asked for.
fn describe_query(
    gray: &GrayImage,
    gradient: bool,
    options: &StructureOptions,
) -> (Vec<Keypoint>, OwnedDescriptors) {
    if gradient {
        let (k, d) = detect_and_describe_gradients(gray, &options.keypoints);
        (k, OwnedDescriptors::Gradient(d))
    } else {
        let (k, d) = detect_and_describe(gray, &options.keypoints);
        (k, OwnedDescriptors::Binary(d))
    }
}

/// Matches of the query's descriptors with a set of the same kind: (query keypoint, other,
/// normalised distance in `[0, 1]`). `binary` / `gradient` are the other set's descriptors
/// of each kind (the one the query does not use may be empty).
fn match_query(
    query: QueryDescriptors<'_>,
    binary: &[Descriptor],
    gradient: &[GradientDescriptor],
    options: &StructureOptions,
) -> Vec<(usize, usize, f32)> {
    match query {
        QueryDescriptors::Binary(q) => match_descriptors(q, binary, &options.matching)
            .into_iter()
            .map(|m| (m.a, m.b, m.distance as f32 / BINARY_MAX_DISTANCE))
            .collect(),
        QueryDescriptors::Gradient(q) => match_descriptors(q, gradient, &options.gradient_matching)
            .into_iter()
            .map(|m| (m.a, m.b, m.distance as f32 / GRADIENT_MAX_DISTANCE))
            .collect(),
    }
}

#[derive(Default)]
struct Timer {
    matching: f64,
    pnp: f64,
    align: f64,
    render: f64,
    /// Tests an earlier search of the same query made: every false-alarm count of this one
    /// starts after them.
    earlier_tests: usize,
}

/// The training images nearest `start` (camera centre) among those looking within the
/// angle, at most `options.neighbours`.
fn nearest_images(map: &StructureMap, start: &Pose, options: &StructureOptions) -> Vec<usize> {
    let center = camera_center(start);
    let mut near: Vec<(f64, usize)> = map
        .images_looking_like(start, options.max_view_angle_deg)
        .map(|i| ((map.images()[i].center() - center).norm(), i))
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    near.into_iter()
        .take(options.neighbours)
        .map(|(_, i)| i)
        .collect()
}

/// A query keypoint's match: (normalised distance, point, training image, observation).
type Candidate = (f32, u32, u32, u32);

/// Per training image of a group, the query's matches with it: (query keypoint, candidate).
type ImageMatches = Vec<Vec<(usize, Candidate)>>;

/// The query's matches with one training image, kept for every start that uses it.
type SharedMatches = Arc<[(usize, Candidate)]>;

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
    let per_image = matches_with(map, query, &images, options);
    time.matching += t.elapsed().as_secs_f64();
    solve_images(map, query, images, per_image, index, options, rng, time)
}

/// The query's matches with each of `images` (in their order), made once per image and
/// query.
fn matches_with(
    map: &StructureMap,
    query: &Query<'_>,
    images: &[usize],
    options: &StructureOptions,
) -> ImageMatches {
    let missing: Vec<usize> = {
        let matched = query.matched.lock().unwrap_or_else(|e| e.into_inner());
        let mut missing: Vec<usize> = images
            .iter()
            .copied()
            .filter(|&i| matched[i].is_none())
            .collect();
        missing.sort_unstable();
        missing.dedup();
        missing
    };
    let made: Vec<(usize, SharedMatches)> = missing
        .par_iter()
        .map(|&i| (i, match_image(map, query, i, options).into()))
        .collect();
    let mut matched = query.matched.lock().unwrap_or_else(|e| e.into_inner());
    for (i, m) in made {
        matched[i] = Some(m);
    }
    images
        .iter()
        .map(|&i| matched[i].as_deref().map_or_else(Vec::new, <[_]>::to_vec))
        .collect()
}

/// The query's descriptor matches with training image `i`: (query keypoint, candidate).
fn match_image(
    map: &StructureMap,
    query: &Query<'_>,
    i: usize,
    options: &StructureOptions,
) -> Vec<(usize, Candidate)> {
    let im = &map.images()[i];
    match_query(query.descriptors, &im.descriptor, &im.gradient, options)
        .into_iter()
        .map(|(a, b, d)| (a, (d, im.point[b], i as u32, b as u32)))
        .collect()
}

/// Groups of training images to solve from, chosen by what they share with the query: every
/// image scored by its descriptor matches with the query; group `g` is the `g`-th best image
/// with the best-scored images looking within `max_view_angle_deg` of it, `neighbours` in
/// all, for `options.retrieval` groups whose seeds are not already in an earlier group.
fn retrieve(
    map: &StructureMap,
    query: &Query<'_>,
    options: &StructureOptions,
) -> Vec<(Vec<usize>, ImageMatches)> {
    let all: Vec<usize> = (0..map.images().len()).collect();
    let matches = matches_with(map, query, &all, options);
    let votes: Vec<usize> = matches.iter().map(Vec::len).collect();
    let mut ranked: Vec<usize> = (0..votes.len()).collect();
    ranked.sort_by(|&a, &b| votes[b].cmp(&votes[a]).then(a.cmp(&b)));
    let cos_max = options.max_view_angle_deg.to_radians().cos();
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for &seed in &ranked {
        if groups.len() >= options.retrieval {
            break;
        }
        if votes[seed] == 0 || groups.iter().any(|g| g.contains(&seed)) {
            continue;
        }
        let dir = map.images()[seed].viewing_direction();
        let mut group = vec![seed];
        group.extend(
            ranked
                .iter()
                .copied()
                .filter(|&j| j != seed && votes[j] > 0)
                .filter(|&j| map.images()[j].viewing_direction().dot(&dir) >= cos_max)
                .take(options.neighbours.saturating_sub(1)),
        );
        groups.push(group);
    }
    groups
        .into_iter()
        .map(|g| {
            let per_image = g.iter().map(|&i| matches[i].clone()).collect();
            (g, per_image)
        })
        .collect()
}

/// Solves from the matches of `images` (`per_image`, in the same order).
#[allow(clippy::too_many_arguments)]
fn solve_images(
    map: &StructureMap,
    query: &Query<'_>,
    images: Vec<usize>,
    per_image: Vec<Vec<(usize, Candidate)>>,
    index: usize,
    options: &StructureOptions,
    rng: &mut dyn RngCore,
    time: &mut Timer,
) -> Solve {
    // Per query keypoint, its closest match (distance, point, image, observation) over the
    // images.
    let mut best: Vec<Option<Candidate>> = vec![None; query.keypoints.len()];
    for (q, c) in per_image.into_iter().flatten() {
        if best[q].is_none_or(|(bd, ..)| c.0 < bd) {
            best[q] = Some(c);
        }
    }
    let mut matches = Matches::default();
    for (q, b) in best.iter().enumerate() {
        if let Some((d, p, i, o)) = b {
            let k = &query.keypoints[q];
            matches
                .pixels
                .push(Point2::new(f64::from(k.x), f64::from(k.y)));
            matches.points.push(map.points()[*p as usize]);
            matches.scores.push(1.0 - f64::from(*d));
            matches.source.push((*i, *o));
            matches.point.push(*p);
        }
    }
    let mut solve = solve_matches(matches, index, options, query.camera, rng, time);
    solve.report.images = images.len();
    solve.images = images;
    solve
}

/// Solves the pose of `matches` and judges it (start `index` for the false-alarm count).
fn solve_matches(
    matches: Matches,
    index: usize,
    options: &StructureOptions,
    camera: &Camera,
    rng: &mut dyn RngCore,
    time: &mut Timer,
) -> Solve {
    let t = Instant::now();
    let mut report = StartReport {
        start: index,
        images: 0,
        matches: matches.pixels.len(),
        inliers: 0,
        log10_nfa: None,
        accepted: false,
        unseen: false,
        unconfirmed: false,
        behind: false,
        rendered: false,
        cam_from_world: None,
        render_agreement: None,
    };
    let solver = LoRansacPnp::new(options.pnp.clone());
    let solved = solver.solve(
        &PnpInput::new(camera, &matches.pixels, &matches.points).with_scores(&matches.scores),
        rng,
    );
    time.pnp += t.elapsed().as_secs_f64();
    let (pose, inliers) = match solved {
        Ok(r) => {
            // Bonferroni over the starts: start `index` is the (index + 1)-th test of this
            // search, after those of an earlier one.
            let nfa = solver.consensus_log10_nfa(camera, matches.pixels.len(), r.stats.num_inliers)
                + ((time.earlier_tests + index + 1) as f64).log10();
            report.inliers = r.stats.num_inliers;
            report.log10_nfa = Some(nfa);
            report.accepted =
                r.stats.num_inliers >= options.min_inliers && nfa <= options.max_log10_nfa;
            report.cam_from_world = Some(r.cam_from_world);
            (Some(r.cam_from_world), r.inliers)
        }
        Err(_) => (None, Vec::new()),
    };
    Solve {
        pose,
        report,
        matches,
        inliers,
        images: Vec::new(),
    }
}

/// The share of a view rendered at `solve`'s pose that agrees with the query (`None` when
/// nothing could be rendered or compared); a share measured before is reused.
fn rendered_share(
    renderer: &dyn ReferenceRenderer,
    query: &GrayImage,
    camera: &Camera,
    solve: &Solve,
    options: &RenderedOptions,
    time: &mut Timer,
) -> Option<f64> {
    if solve.report.render_agreement.is_some() {
        return solve.report.render_agreement;
    }
    let pose = solve.pose?;
    let at = inlier_centroid(solve)?;
    let t = Instant::now();
    let reference = renderer.render_reference(camera, &pose, &at);
    time.render += t.elapsed().as_secs_f64();
    let t = Instant::now();
    let share = reference.and_then(|reference| render_agreement(query, &reference, options));
    time.matching += t.elapsed().as_secs_f64();
    share
}

/// The rival of a weak accepted consensus that a rendered view prefers: the rivals more than
/// [`WEAK_SAME_PLACE_M`] from it (the one with the most inliers per place, at most
/// `options.rendered.max_rivals`, most inliers first) are rendered with it, and the rival
/// whose view agrees most with the query replaces it when that share is at least
/// `options.rendered.min_agreement` and above the weak consensus's own. The rival comes back
/// accepted and marked rendered.
fn rendered_rival(
    renderer: &dyn ReferenceRenderer,
    query: &GrayImage,
    camera: &Camera,
    weak: &mut Solve,
    mut rivals: Vec<Solve>,
    options: &StructureOptions,
    time: &mut Timer,
) -> Option<Solve> {
    let centre = camera_center(&weak.pose?);
    rivals.sort_by_key(|s| std::cmp::Reverse(s.report.inliers));
    let mut places: Vec<Solve> = Vec::new();
    for rival in rivals {
        let Some(c) = rival.pose.map(|p| camera_center(&p)) else {
            continue;
        };
        let near = |p: &Solve| {
            p.pose
                .is_some_and(|q| (camera_center(&q) - c).norm() <= WEAK_SAME_PLACE_M)
        };
        if (c - centre).norm() > WEAK_SAME_PLACE_M && !places.iter().any(near) {
            places.push(rival);
        }
        if places.len() >= options.rendered.max_rivals {
            break;
        }
    }
    if places.is_empty() {
        return None;
    }
    let own = rendered_share(renderer, query, camera, weak, &options.rendered, time);
    weak.report.render_agreement = own;
    let mut best: Option<(f64, Solve)> = None;
    for mut rival in places {
        let share = rendered_share(renderer, query, camera, &rival, &options.rendered, time);
        rival.report.render_agreement = share;
        if let Some(share) = share
            && share >= options.rendered.min_agreement
            && own.is_none_or(|o| share > o)
            && best.as_ref().is_none_or(|(b, _)| share > *b)
        {
            best = Some((share, rival));
        }
    }
    best.map(|(_, mut rival)| {
        rival.report.accepted = true;
        rival.report.unseen = false;
        rival.report.unconfirmed = false;
        rival.report.rendered = true;
        rival
    })
}

/// Mean of the 3D points of `solve`'s inliers (`None` without inliers).
fn inlier_centroid(solve: &Solve) -> Option<Point3<f64>> {
    let (mut sum, mut n) = (Vector3::zeros(), 0usize);
    for (k, x) in solve.matches.points.iter().enumerate() {
        if solve.inliers.get(k).copied().unwrap_or(false) {
            sum += x.coords;
            n += 1;
        }
    }
    (n > 0).then(|| Point3::from(sum / n as f64))
}

/// Whether poses `a` and `b` lie within `options.agree_m` and `options.agree_deg`.
fn agrees(a: &Pose, b: &Pose, options: &RenderedOptions) -> bool {
    let dt = (camera_center(a) - camera_center(b)).norm();
    let dr = (a.rotation * b.rotation.inverse()).angle().to_degrees();
    dt <= options.agree_m && dr <= options.agree_deg
}

/// Whether a pose solved from a render passes: enough inliers, a significant consensus, and
/// inliers spread over `options.confirmed_hull` of the image.
fn rendered_accepted(solve: &Solve, camera: &Camera, options: &StructureOptions) -> bool {
    let significant = solve.report.inliers >= options.rendered.min_inliers
        && solve
            .report
            .log10_nfa
            .is_some_and(|nfa| nfa <= options.max_log10_nfa);
    let inliers = (0..solve.matches.pixels.len())
        .filter(|&k| solve.inliers.get(k).copied().unwrap_or(false))
        .map(|k| solve.matches.pixels[k]);
    significant
        && solve.pose.is_some()
        && hull_fraction(inliers, camera.width, camera.height) >= options.confirmed_hull
}

/// Share of the textured patches of a view rendered at a pose that agree with the query
/// there: each 13 px square of the render (both images blurred by `options.blur_px`), on a
/// grid of 12 px, where the render is opaque and varies, correlated with the query at
/// the same place or up to 2 px from it, agreeing at [`AGREEING_ZNCC`] or more. `None`
/// when fewer than `MIN_COMPARED` patches could be compared.
pub fn render_agreement(
    query: &GrayImage,
    reference: &crate::rendered::RenderedReference,
    options: &RenderedOptions,
) -> Option<f64> {
    const STEP: usize = 12;
    const HALF: usize = 6;
    const SHIFT: isize = 2;
    let (min_accumulation, sigma) = (options.min_accumulation, options.blur_px);
    const MIN_STD: f32 = 0.02;
    const MIN_COMPARED: usize = 10;
    let render = GrayImage::from_image(&reference.image).gaussian_blur(sigma);
    let (w, h) = (render.width(), render.height());
    if query.width() != w || query.height() != h || reference.accumulation.len() != w * h {
        return None;
    }
    let q = query.gaussian_blur(sigma);
    let side = 2 * HALF + 1;
    let n = (side * side) as f32;
    let margin = HALF + SHIFT as usize;
    let mut centres = Vec::new();
    let mut y = margin;
    while y + margin < h {
        let mut x = margin;
        while x + margin < w {
            centres.push((x, y));
            x += STEP;
        }
        y += STEP;
    }
    let patch = |img: &GrayImage, cx: usize, cy: usize| -> Option<Vec<f32>> {
        let mut v = Vec::with_capacity(side * side);
        for yy in cy - HALF..=cy + HALF {
            for xx in cx - HALF..=cx + HALF {
                v.push(img.at(xx, yy));
            }
        }
        let mean = v.iter().sum::<f32>() / n;
        v.iter_mut().for_each(|a| *a -= mean);
        let norm = v.iter().map(|a| a * a).sum::<f32>().sqrt();
        (norm / n.sqrt() >= MIN_STD).then(|| {
            v.iter_mut().for_each(|a| *a /= norm);
            v
        })
    };
    let compared: Vec<bool> = centres
        .par_iter()
        .filter_map(|&(cx, cy)| {
            if reference.accumulation[cy * w + cx] < min_accumulation {
                return None;
            }
            let r = patch(&render, cx, cy)?;
            let mut best = f32::NEG_INFINITY;
            for dy in -SHIFT..=SHIFT {
                for dx in -SHIFT..=SHIFT {
                    let (qx, qy) = ((cx as isize + dx) as usize, (cy as isize + dy) as usize);
                    if let Some(qp) = patch(&q, qx, qy) {
                        best = best.max(r.iter().zip(&qp).map(|(a, b)| a * b).sum());
                    } else {
                        best = best.max(0.0);
                    }
                }
            }
            Some(f64::from(best) >= AGREEING_ZNCC)
        })
        .collect();
    (compared.len() >= MIN_COMPARED)
        .then(|| compared.iter().filter(|&&a| a).count() as f64 / compared.len() as f64)
}

/// Side of the window whose rendered depths must agree for a render keypoint to be lifted:
/// a keypoint on an occluding edge mixes two surfaces.
const DEPTH_WINDOW: usize = 1;

/// Largest relative spread of the rendered depths around a lifted keypoint.
const MAX_DEPTH_SPREAD: f32 = 0.05;

/// Solves the query's pose from a view rendered at `pose` (start `index` for the false-alarm
/// count): the render's keypoints matched to the query's, lifted by the rendered depth where
/// it is opaque and smooth. `None` when nothing could be rendered.
#[allow(clippy::too_many_arguments)]
fn solve_rendered(
    renderer: &dyn ReferenceRenderer,
    query: &Query<'_>,
    pose: &Pose,
    looking_at: &Point3<f64>,
    index: usize,
    options: &StructureOptions,
    rng: &mut dyn RngCore,
    time: &mut Timer,
) -> Option<Solve> {
    let camera = query.camera;
    let t = Instant::now();
    let reference = renderer.render_reference(camera, pose, looking_at);
    time.render += t.elapsed().as_secs_f64();
    let reference = reference?;
    let (w, h, _) = reference.image.shape();
    if w != camera.width as usize
        || h != camera.height as usize
        || reference.z_depth.len() != w * h
        || reference.accumulation.len() != w * h
    {
        return None;
    }
    let t = Instant::now();
    let gray = GrayImage::from_image(&reference.image).unsharp(options.query_sharpen, 1.0);
    let gradient = matches!(query.descriptors, QueryDescriptors::Gradient(_));
    let (kr, dr) = describe_query(&gray, gradient, options);
    let found = match dr {
        OwnedDescriptors::Binary(d) => match_query(query.descriptors, &d, &[], options),
        OwnedDescriptors::Gradient(d) => match_query(query.descriptors, &[], &d, options),
    };
    let world_from_cam = pose.inverse();
    let mut matches = Matches::default();
    for &(a, b, distance) in &found {
        let k = kr[b];
        let (c, r) = (k.x.floor() as usize, k.y.floor() as usize);
        if c >= w || r >= h || reference.accumulation[r * w + c] < options.rendered.min_accumulation
        {
            continue;
        }
        let Some(z) = smooth_depth(&reference.z_depth, w, h, c, r) else {
            continue;
        };
        let Some(bearing) = camera.unproject(Point2::new(f64::from(k.x), f64::from(k.y))) else {
            continue;
        };
        let p_cam = bearing * (f64::from(z) / bearing.z);
        let q = &query.keypoints[a];
        matches
            .pixels
            .push(Point2::new(f64::from(q.x), f64::from(q.y)));
        matches.points.push(world_from_cam * Point3::from(p_cam));
        matches.scores.push(1.0 - f64::from(distance));
        matches.source.push((u32::MAX, b as u32));
        matches.point.push(u32::MAX);
    }
    time.matching += t.elapsed().as_secs_f64();
    let mut solve = solve_matches(matches, index, options, camera, rng, time);
    solve.report.accepted = false;
    solve.report.rendered = true;
    Some(solve)
}

/// The depth at `(c, r)` when every depth in its window is positive and within
/// [`MAX_DEPTH_SPREAD`] of it.
fn smooth_depth(depth: &[f32], w: usize, h: usize, c: usize, r: usize) -> Option<f32> {
    let z = depth[r * w + c];
    if !(z > 0.0 && z.is_finite()) {
        return None;
    }
    let (c0, c1) = (
        c.saturating_sub(DEPTH_WINDOW),
        (c + DEPTH_WINDOW).min(w - 1),
    );
    let (r0, r1) = (
        r.saturating_sub(DEPTH_WINDOW),
        (r + DEPTH_WINDOW).min(h - 1),
    );
    for rr in r0..=r1 {
        for cc in c0..=c1 {
            let d = depth[rr * w + cc];
            if d.is_nan() || d <= 0.0 || (d - z).abs() > MAX_DEPTH_SPREAD * z {
                return None;
            }
        }
    }
    Some(z)
}

/// When every start is refused: the refused poses with the most inliers (distinct by more
/// than `agree_m`), at most `max_renders`, each rendered and solved from the render, then
/// rendered again at that solution and solved once more; the first second solve that
/// passes [`rendered_accepted`] and agrees with the first is the answer. Attempts are
/// counted from `index` for the false alarms; every solve is reported.
#[allow(clippy::too_many_arguments)]
fn from_renders(
    renderer: &dyn ReferenceRenderer,
    query: &Query<'_>,
    mut refused: Vec<(usize, Pose, Point3<f64>)>,
    mut index: usize,
    options: &StructureOptions,
    rng: &mut dyn RngCore,
    time: &mut Timer,
    reports: &mut Vec<StartReport>,
) -> Option<Solve> {
    let o = &options.rendered;
    refused.sort_by_key(|r| std::cmp::Reverse(r.0));
    let mut chosen: Vec<&(usize, Pose, Point3<f64>)> = Vec::new();
    for r in &refused {
        if chosen.len() >= o.max_renders {
            break;
        }
        if chosen
            .iter()
            .all(|c| (camera_center(&c.1) - camera_center(&r.1)).norm() > o.agree_m)
        {
            chosen.push(r);
        }
    }
    for (_, pose, at) in chosen {
        let Some(first) = solve_rendered(renderer, query, pose, at, index, options, rng, time)
        else {
            continue;
        };
        index += 1;
        reports.push(first.report.clone());
        let (Some(p1), true) = (first.pose, first.report.inliers >= o.min_start_inliers) else {
            continue;
        };
        let at = inlier_centroid(&first).unwrap_or(*at);
        let Some(mut second) = solve_rendered(renderer, query, &p1, &at, index, options, rng, time)
        else {
            continue;
        };
        index += 1;
        let accepted = second.pose.is_some_and(|p2| agrees(&p2, &p1, o))
            && rendered_accepted(&second, query.camera, options);
        second.report.accepted = accepted;
        reports.push(second.report.clone());
        if accepted {
            return Some(second);
        }
    }
    None
}

/// Share of `solve`'s inliers that the camera at `pose` sees from the side their training
/// images saw them from: the ray from the point to the camera within 90° of the mean of the
/// unit rays from the point to the training cameras that observe it (1 without inliers).
fn front_side(map: &StructureMap, pose: &Pose, solve: &Solve) -> f64 {
    let centre = camera_center(pose);
    let (mut front, mut all) = (0usize, 0usize);
    for (k, &p) in solve.matches.point.iter().enumerate() {
        if !solve.inliers.get(k).copied().unwrap_or(false) {
            continue;
        }
        let x = map.points()[p as usize];
        let mean: Vector3<f64> = map
            .track(p as usize)
            .iter()
            .filter_map(|&(i, _)| (map.images()[i as usize].center() - x).try_normalize(0.0))
            .sum();
        all += 1;
        front += usize::from(mean.dot(&(centre - x)) > 0.0);
    }
    if all == 0 {
        1.0
    } else {
        front as f64 / all as f64
    }
}

/// Whether `solve`'s consensus holds for the whole query: its inliers cover at least
/// `options.confirmed_hull` of the image, or at least `options.min_inlier_hull` with at least
/// `options.min_agreement` of the map points its training images see agreeing with the query
/// under its pose ([`agreement`]).
fn confirmed(
    map: &StructureMap,
    planes: &QueryPlanes,
    camera: &Camera,
    solve: &Solve,
    options: &StructureOptions,
) -> bool {
    let Some(pose) = solve.pose else {
        return false;
    };
    let inliers = (0..solve.matches.pixels.len())
        .filter(|&k| solve.inliers.get(k).copied().unwrap_or(false))
        .map(|k| solve.matches.pixels[k]);
    let hull = hull_fraction(inliers, camera.width, camera.height);
    if hull >= options.confirmed_hull {
        return true;
    }
    hull >= options.min_inlier_hull
        && agreement(map, planes, camera, &pose, &solve.images)
            .is_some_and(|a| a >= options.min_agreement)
}

/// Share of a `width` × `height` image covered by the convex hull of `points` (0 for fewer
/// than three points or points on a line).
pub(crate) fn hull_fraction(
    points: impl Iterator<Item = Point2<f64>>,
    width: u32,
    height: u32,
) -> f64 {
    let mut pts: Vec<Point2<f64>> = points
        .filter(|p| p.x.is_finite() && p.y.is_finite())
        .collect();
    pts.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    pts.dedup();
    if pts.len() < 3 {
        return 0.0;
    }
    // Andrew's monotone chain: the lower hull, then the upper.
    let mut hull: Vec<Point2<f64>> = Vec::with_capacity(2 * pts.len());
    for pass in 0..2 {
        let start = hull.len();
        let ordered: Box<dyn Iterator<Item = &Point2<f64>>> = if pass == 0 {
            Box::new(pts.iter())
        } else {
            Box::new(pts.iter().rev())
        };
        for &p in ordered {
            while hull.len() >= start + 2 {
                let (a, b) = (hull[hull.len() - 2], hull[hull.len() - 1]);
                if (b - a).perp(&(p - a)) > 0.0 {
                    break;
                }
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    let twice_area: f64 = (0..hull.len())
        .map(|i| {
            let (a, b) = (hull[i], hull[(i + 1) % hull.len()]);
            a.x * b.y - b.x * a.y
        })
        .sum();
    let image = f64::from(width) * f64::from(height);
    if image > 0.0 {
        (0.5 * twice_area.abs() / image).min(1.0)
    } else {
        0.0
    }
}

/// Share of the map points seen by training `images` that agree with the query under `pose`:
/// of those that project into the query with a textured training patch, the share whose patch,
/// laid into the query through the pose ([`local_affine`]), correlates at [`AGREEING_ZNCC`] or
/// more where the point projects. `None` when no point could be compared (the map keeps no
/// gray values, or none projects into the image).
fn agreement(
    map: &StructureMap,
    planes: &QueryPlanes,
    camera: &Camera,
    pose: &Pose,
    images: &[usize],
) -> Option<f64> {
    let mut seen = std::collections::HashSet::new();
    let mut pairs = Vec::new();
    for &img in images {
        for (obs, &p) in map.images().get(img)?.point.iter().enumerate() {
            if seen.insert(p) {
                pairs.push((img, obs, p));
            }
        }
    }
    let compared: Vec<bool> = pairs
        .par_iter()
        .filter_map(|&(img, obs, p)| {
            let im = &map.images()[img];
            let app = im.appearance.as_ref()?;
            let x = map.points().get(p as usize)?;
            if !camera.contains(camera.project_world(pose, x)?) {
                return None;
            }
            let px = im.pixel.get(obs)?;
            let map_px = Point2::new(f64::from(px[0]), f64::from(px[1]));
            let (at, affine) =
                local_affine(&app.camera, &im.cam_from_world, map_px, x, camera, pose)?;
            let patch = template(
                &app.gray,
                app.camera.width as usize,
                app.camera.height as usize,
                map_px,
                AGREEMENT_HALF_WINDOW,
            )?;
            Some(zncc_at(planes, &patch, &affine, at)? >= AGREEING_ZNCC)
        })
        .collect();
    (!compared.is_empty())
        .then(|| compared.iter().filter(|&&a| a).count() as f64 / compared.len() as f64)
}

/// Half side of the patches [`agreement`] compares, training-image pixels.
const AGREEMENT_HALF_WINDOW: usize = 4;

/// `solve`'s matches with each inlier aligned under `pose`: its query pixel moved to where
/// the patches of the point's observations in the start's training images fit (the mean
/// over those that align), its point moved onto those observations' rays at its depth (the
/// mean); with `options.track`, the points those images see that no match reached are added
/// the same way from their projections. `None` when the map keeps no gray values or nothing
/// aligned. Numbers behind each part: docs/DECISIONS.md, "Patch alignment".
fn aligned(
    map: &StructureMap,
    planes: &QueryPlanes,
    camera: &Camera,
    pose: &Pose,
    solve: &Solve,
    options: &AlignOptions,
) -> Option<Matches> {
    let m = &solve.matches;
    // One observation: the aligned query pixel and the point on the observation's ray.
    let one = |img: u32, obs: u32, x: &Point3<f64>, from: Point2<f64>| {
        let im = &map.images()[img as usize];
        let app = im.appearance.as_ref()?;
        let px = im.pixel.get(obs as usize)?;
        let map_px = Point2::new(f64::from(px[0]), f64::from(px[1]));
        let (_, affine) = local_affine(&app.camera, &im.cam_from_world, map_px, x, camera, pose)?;
        let patch = template(
            &app.gray,
            app.camera.width as usize,
            app.camera.height as usize,
            map_px,
            options.half_window,
        )?;
        let u = align(planes, &patch, &affine, from, options)?;
        let c = camera_center(&im.cam_from_world);
        let dir = im
            .cam_from_world
            .inverse()
            .transform_vector(&app.camera.unproject(map_px)?);
        let on_ray = c + dir * (x - c).dot(&dir);
        Some((u.coords, on_ray.coords))
    };
    // Every observation of point `p` in the start's images (and in `also`): the means.
    let over_track = |p: u32, from: Point2<f64>, also: Option<u32>| {
        let x = &map.points()[p as usize];
        let (mut u, mut y, mut n) = (Vector2::zeros(), Vector3::zeros(), 0usize);
        for &(img, obs) in map.track(p as usize) {
            if Some(img) != also && !solve.images.contains(&(img as usize)) {
                continue;
            }
            if let Some((du, dy)) = one(img, obs, x, from) {
                u += du;
                y += dy;
                n += 1;
            }
        }
        (n > 0).then(|| (Point2::from(u / n as f64), Point3::from(y / n as f64)))
    };
    let moved: Vec<Option<(Point2<f64>, Point3<f64>)>> = (0..m.pixels.len())
        .into_par_iter()
        .map(|k| {
            if !solve.inliers.get(k).copied().unwrap_or(false) {
                return None;
            }
            over_track(m.point[k], m.pixels[k], Some(m.source[k].0))
        })
        .collect();
    let mut tracked: Vec<(Point2<f64>, Point3<f64>, u32)> = Vec::new();
    if options.track {
        let mut seen: std::collections::HashSet<u32> = m.point.iter().copied().collect();
        let mut candidates = Vec::new();
        for &img in &solve.images {
            for &p in &map.images()[img].point {
                if seen.insert(p) {
                    candidates.push(p);
                }
            }
        }
        tracked = candidates
            .par_iter()
            .filter_map(|&p| {
                let from = camera.project_world(pose, &map.points()[p as usize])?;
                if !camera.contains(from) {
                    return None;
                }
                let (u, y) = over_track(p, from, None)?;
                Some((u, y, p))
            })
            .collect();
    }
    if moved.iter().all(Option::is_none) {
        return None;
    }
    let mut out = Matches {
        pixels: m.pixels.clone(),
        points: m.points.clone(),
        scores: m.scores.clone(),
        source: m.source.clone(),
        point: m.point.clone(),
    };
    for (k, p) in moved.into_iter().enumerate() {
        if let Some((p, x)) = p {
            out.pixels[k] = p;
            out.points[k] = x;
        }
    }
    for (u, y, p) in tracked {
        out.pixels.push(u);
        out.points.push(y);
        out.scores.push(0.5);
        out.source.push(map.track(p as usize)[0]);
        out.point.push(p);
    }
    Some(out)
}

#[cfg(test)]
mod tests;
