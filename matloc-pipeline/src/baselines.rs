//! The paper's baselines, on the same map and from the same coarse poses as MatLoc:
//!
//! - **rgb-keypoints** (FVLocNeRF-style): render RGB and depth at the coarse pose, match
//!   ORB-like keypoints between the render and the query, lift the rendered keypoints with the
//!   rendered depth, solve PnP in LO-RANSAC; any consensus PnP finds is returned, with the
//!   a-contrario NFA of that consensus as its confidence (as the structure localizer's).
//!   By default a second pass renders again at the solved pose (FVLocNeRF's iteration; the
//!   paper's single render is `passes: 1`) and refuses when that pass finds no consensus or
//!   moves the pose further than the first did.
//! - **iNeRF**: minimise the photometric error of rendered vs query pixels over the pose by
//!   Adam on se(3), 300 iterations, pixels resampled each iteration (half around keypoints —
//!   iNeRF's interest-region sampling — half uniform).
//! - **curriculum iNeRF**: 200 iterations over a coarse-to-fine schedule (the query and camera
//!   at 1/4, 1/2, then full resolution, with step sizes shrinking per stage).
//!
//! The pose gradient of iNeRF is taken by central finite differences of the rendered loss in
//! the six tangent directions at the current pose (12 extra renders of the sampled pixels per
//! iteration), not by backpropagation through the field: the field's hand-written backward
//! pass gives parameter gradients, not input-position gradients. This makes an iteration
//! ~4× costlier than with analytic gradients (13 forward renders vs ~1 forward + backward ≈ 3);
//! reports state the iteration count and time side by side so the comparison stays readable.

use std::time::Instant;

use matloc_core::pose::camera_center;
use matloc_core::{Camera, Image, Pose};
use matloc_keypoints::{
    GrayImage, KeypointConfig, MatchConfig, detect_and_describe, match_descriptors,
};
use matloc_pnp::{LoRansacPnp, PnpInput, PnpOptions, PoseSolver};
use matloc_render::{NerfModel, PixelSet, RenderRequest, RenderedView, render_view};
use nalgebra::{Isometry3, Point2, Point3, Translation3, UnitQuaternion, Vector3, Vector6};
use rand::{Rng, RngCore};
use serde::{Deserialize, Serialize};

use crate::error::PipelineError;

/// The result of one baseline localization attempt.
#[derive(Clone, Debug, PartialEq)]
pub struct BaselineOutcome {
    /// Estimated pose, `None` when the method could not produce one (refused).
    pub cam_from_world: Option<Pose>,
    /// Optimisation iterations (iNeRF) or render–match–PnP passes run (keypoints).
    pub iterations: u32,
    /// Seconds per stage.
    pub stage_seconds: Vec<(String, f64)>,
    /// Matches fed to PnP (keypoints) or pixels per iteration (iNeRF).
    pub matches: usize,
    /// PnP inliers (keypoints only).
    pub inliers: usize,
    /// Base-10 NFA of the PnP consensus (keypoints only; `None` without one).
    pub log10_nfa: Option<f64>,
    /// Why a later pass refused the query (keypoints: no consensus, or the passes diverged).
    pub failure: Option<String>,
}

fn check_query(camera: &Camera, query: &Image<f32>) -> Result<(), PipelineError> {
    let (w, h, c) = query.shape();
    if w != camera.width as usize || h != camera.height as usize || c != 3 {
        return Err(PipelineError::QueryShape {
            image: (w, h, c),
            camera: (camera.width, camera.height),
        });
    }
    Ok(())
}

/// Options of the rendered-RGB + keypoints baseline.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct KeypointBaselineOptions {
    /// Detector settings (same for render and query).
    pub keypoints: KeypointConfig,
    /// Descriptor matching.
    pub matching: MatchConfig,
    /// PnP settings.
    pub pnp: PnpOptions,
    /// Render–match–PnP passes, each after the first rendering at the pose the previous one
    /// solved (FVLocNeRF's iteration); 1 is the paper's single render at the coarse pose. A
    /// later pass that finds no consensus, or moves the pose further than the pass before,
    /// refuses the query. Default 2 (docs/DECISIONS.md).
    pub passes: u32,
}

impl Default for KeypointBaselineOptions {
    fn default() -> Self {
        Self {
            keypoints: KeypointConfig::default(),
            matching: MatchConfig::default(),
            pnp: PnpOptions::default(),
            passes: 2,
        }
    }
}

/// `model`'s view at `cam_from_world`, every pixel of `camera`, with its colour image.
pub(crate) fn render_colour(
    model: &NerfModel,
    camera: &Camera,
    cam_from_world: &Pose,
) -> Result<(RenderedView, Image<f32>), PipelineError> {
    let view = render_view(
        model,
        camera,
        cam_from_world,
        &PixelSet::Full,
        &RenderRequest {
            rgb: true,
            dims: Vec::new(),
            appearance: None,
        },
    )?;
    let rgb = view
        .rgb_image()
        .ok_or(PipelineError::Internal("rendered view without RGB"))?;
    Ok((view, rgb))
}

/// Rendered RGB + keypoints + PnP from a coarse pose, `options.passes` times (each pass
/// renders at the pose the previous one solved).
pub fn rgb_keypoints(
    model: &NerfModel,
    camera: &Camera,
    query: &Image<f32>,
    coarse_cam_from_world: &Pose,
    options: &KeypointBaselineOptions,
    rng: &mut dyn RngCore,
) -> Result<BaselineOutcome, PipelineError> {
    check_query(camera, query)?;
    let mut seconds = [0.0f64; 4];
    let t = Instant::now();
    let query_keypoints = detect_and_describe(&GrayImage::from_image(query), &options.keypoints);
    seconds[1] += t.elapsed().as_secs_f64();
    let mut pose = *coarse_cam_from_world;
    let mut outcome = KeypointPass::default();
    let (mut passes, mut last_move, mut failure) = (0, f64::INFINITY, None);
    for pass in 0..options.passes.max(1) {
        outcome = keypoint_pass(
            model,
            camera,
            &query_keypoints,
            &pose,
            options,
            rng,
            &mut seconds,
        )?;
        passes = pass + 1;
        let Some(p) = outcome.cam_from_world else {
            if pass > 0 {
                failure = Some(format!(
                    "pass {passes} found no consensus at the pose the one before solved"
                ));
            }
            break;
        };
        // Rendering closer to the query must move the pose less each pass; a pass that moves
        // it further than the one before has lost the scene (on `small` such a second pass
        // took a 5.6 m pose to 26 m).
        let moved = (camera_center(&p) - camera_center(&pose)).norm();
        if moved > last_move {
            failure = Some(format!(
                "pass {passes} moved the pose {moved:.2} m, further than the pass before \
                 ({last_move:.2} m)"
            ));
            outcome.cam_from_world = None;
            break;
        }
        (pose, last_move) = (p, moved);
    }
    let names = ["render", "keypoints", "match", "pnp"];
    Ok(BaselineOutcome {
        failure,
        cam_from_world: outcome.cam_from_world,
        iterations: passes,
        stage_seconds: names
            .iter()
            .zip(seconds)
            .map(|(n, s)| (n.to_string(), s))
            .collect(),
        matches: outcome.matches,
        inliers: outcome.inliers,
        log10_nfa: outcome.log10_nfa,
    })
}

/// One render–match–PnP pass of the keypoint baseline.
#[derive(Default)]
struct KeypointPass {
    cam_from_world: Option<Pose>,
    matches: usize,
    inliers: usize,
    log10_nfa: Option<f64>,
}

/// Renders at `cam_from_world`, matches the render's keypoints to the query's, lifts them with
/// the rendered depth and solves PnP; adds its seconds to `seconds` (render, keypoints, match,
/// PnP).
fn keypoint_pass(
    model: &NerfModel,
    camera: &Camera,
    (kq, dq): &(
        Vec<matloc_keypoints::Keypoint>,
        Vec<matloc_keypoints::Descriptor>,
    ),
    cam_from_world: &Pose,
    options: &KeypointBaselineOptions,
    rng: &mut dyn RngCore,
    seconds: &mut [f64; 4],
) -> Result<KeypointPass, PipelineError> {
    let t = Instant::now();
    let (view, rendered) = render_colour(model, camera, cam_from_world)?;
    seconds[0] += t.elapsed().as_secs_f64();

    let t = Instant::now();
    let (kr, dr) = detect_and_describe(&GrayImage::from_image(&rendered), &options.keypoints);
    seconds[1] += t.elapsed().as_secs_f64();

    let t = Instant::now();
    let matches = match_descriptors(dq, &dr, &options.matching);
    let world_from_cam = cam_from_world.inverse();
    let (w, h) = (view.width, view.height);
    let mut pixels = Vec::new();
    let mut points = Vec::new();
    let mut scores = Vec::new();
    for m in &matches {
        let k = kr[m.b];
        let (c, r) = (k.x.floor() as usize, k.y.floor() as usize);
        if c >= w || r >= h {
            continue;
        }
        let i = r * w + c;
        if !view.valid[i] || view.accumulation[i] < 0.5 || view.z_depth[i] <= 0.0 {
            continue;
        }
        let Some(bearing) = camera.unproject(Point2::new(k.x as f64, k.y as f64)) else {
            continue;
        };
        let p_cam = bearing * (view.z_depth[i] as f64 / bearing.z);
        points.push(world_from_cam * Point3::from(p_cam));
        let q = kq[m.a];
        pixels.push(Point2::new(q.x as f64, q.y as f64));
        scores.push(1.0 - m.distance as f64 / 256.0);
    }
    seconds[2] += t.elapsed().as_secs_f64();

    let t = Instant::now();
    let solver = LoRansacPnp::new(options.pnp.clone());
    let input = PnpInput::new(camera, &pixels, &points).with_scores(&scores);
    let result = solver.solve(&input, rng);
    seconds[3] += t.elapsed().as_secs_f64();
    Ok(match result {
        Ok(r) => {
            let n = r.stats.num_inliers;
            KeypointPass {
                cam_from_world: Some(r.cam_from_world),
                matches: pixels.len(),
                inliers: n,
                log10_nfa: Some(solver.consensus_log10_nfa(camera, pixels.len(), n)),
            }
        }
        Err(_) => KeypointPass {
            matches: pixels.len(),
            ..KeypointPass::default()
        },
    })
}

/// Options of iNeRF and curriculum iNeRF.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InerfOptions {
    /// Iterations (iNeRF 300, curriculum 200).
    pub iterations: u32,
    /// Pixels sampled per iteration.
    pub pixels: usize,
    /// Adam step on the translation (metres per step) at the start.
    pub lr_translation_m: f64,
    /// Adam step on the rotation (radians per step) at the start.
    pub lr_rotation_rad: f64,
    /// Learning rate multiplier reached at the last iteration (exponential decay).
    pub final_lr_factor: f64,
    /// Finite-difference step on translation (metres).
    pub fd_step_m: f64,
    /// Finite-difference step on rotation (radians).
    pub fd_step_rad: f64,
    /// Coarse-to-fine schedule: resolution divisors per stage, in order (empty = full
    /// resolution throughout, plain iNeRF).
    pub curriculum: Vec<u32>,
}

impl InerfOptions {
    /// iNeRF: 300 iterations at full resolution.
    pub fn inerf() -> Self {
        Self::default()
    }

    /// Curriculum iNeRF: 200 iterations at 1/4, 1/2, then full resolution.
    pub fn curriculum() -> Self {
        Self {
            iterations: 200,
            curriculum: vec![4, 2, 1],
            ..Self::default()
        }
    }
}

impl Default for InerfOptions {
    fn default() -> Self {
        Self {
            iterations: 300,
            pixels: 256,
            lr_translation_m: 0.1,
            lr_rotation_rad: 0.004,
            final_lr_factor: 0.1,
            fd_step_m: 0.05,
            fd_step_rad: 0.002,
            curriculum: Vec::new(),
        }
    }
}

/// `exp` of a tangent vector `(ω, v)` as an isometry acting in the camera frame.
fn tangent_to_isometry(xi: &Vector6<f64>) -> Isometry3<f64> {
    let omega = Vector3::new(xi[0], xi[1], xi[2]);
    let v = Vector3::new(xi[3], xi[4], xi[5]);
    Isometry3::from_parts(
        Translation3::from(v),
        UnitQuaternion::from_scaled_axis(omega),
    )
}

/// Photometric loss of rendered vs query colours at `pixels` (mean squared error).
fn photometric_loss(
    model: &NerfModel,
    camera: &Camera,
    cam_from_world: &Pose,
    pixels: &[Point2<f64>],
    target: &[f32],
) -> Result<f64, PipelineError> {
    let view = render_view(
        model,
        camera,
        cam_from_world,
        &PixelSet::List(pixels.to_vec()),
        &RenderRequest {
            rgb: true,
            dims: Vec::new(),
            appearance: None,
        },
    )?;
    let mut sum = 0.0f64;
    for (a, b) in view.rgb.iter().zip(target) {
        sum += ((a - b) as f64).powi(2);
    }
    Ok(sum / target.len().max(1) as f64)
}

/// What iNeRF minimises, measured on a fixed grid: the mean squared colour error between
/// `query` and `model`'s render at `cam_from_world`, over pixel centres every `stride` pixels.
pub fn photometric_error(
    model: &NerfModel,
    camera: &Camera,
    query: &Image<f32>,
    cam_from_world: &Pose,
    stride: usize,
) -> Result<f64, PipelineError> {
    check_query(camera, query)?;
    let stride = stride.max(1);
    let mut pixels = Vec::new();
    let mut target = Vec::new();
    for r in (0..query.height()).step_by(stride) {
        for c in (0..query.width()).step_by(stride) {
            pixels.push(Point2::new(c as f64 + 0.5, r as f64 + 0.5));
            target.extend_from_slice(query.pixel(c, r));
        }
    }
    photometric_loss(model, camera, cam_from_world, &pixels, &target)
}

/// iNeRF / curriculum iNeRF from a coarse pose. Never refuses: it always returns the pose it
/// ends at (as the method does).
pub fn inerf(
    model: &NerfModel,
    camera: &Camera,
    query: &Image<f32>,
    coarse_cam_from_world: &Pose,
    options: &InerfOptions,
    rng: &mut dyn RngCore,
) -> Result<BaselineOutcome, PipelineError> {
    check_query(camera, query)?;
    let start = Instant::now();
    let stages_div: Vec<u32> = if options.curriculum.is_empty() {
        vec![1]
    } else {
        options.curriculum.clone()
    };
    let iterations = options.iterations.max(1);
    let per_stage = iterations.div_ceil(stages_div.len() as u32);
    let mut pose = *coarse_cam_from_world;
    let (mut m, mut v) = (Vector6::<f64>::zeros(), Vector6::<f64>::zeros());
    let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8f64);
    let mut it_total = 0u32;
    for &div in &stages_div {
        let div = div.max(1);
        let cam = camera.downscaled(div)?;
        let img = matloc_core::image::downscale_box(query, div);
        let gray = GrayImage::from_image(&img);
        // Interest regions: keypoints of the query at this resolution.
        let (kps, _) = detect_and_describe(
            &gray,
            &KeypointConfig {
                levels: 1,
                ..KeypointConfig::default()
            },
        );
        let (w, h) = (img.width(), img.height());
        let fd = (
            options.fd_step_rad * div as f64,
            options.fd_step_m * div as f64,
        );
        let stage_iters = per_stage.min(iterations - it_total);
        for _ in 0..stage_iters {
            let progress = it_total as f64 / iterations as f64;
            let decay = options.final_lr_factor.max(1e-6).powf(progress);
            // Sample pixels: half near keypoints (±2 px), half uniform.
            let mut pixels = Vec::with_capacity(options.pixels);
            let mut target = Vec::with_capacity(options.pixels * 3);
            for k in 0..options.pixels {
                let (x, y) = if k % 2 == 0 && !kps.is_empty() {
                    let kp = kps[rng.random_range(0..kps.len())];
                    (
                        (kp.x as f64 + rng.random_range(-2.0..2.0)).clamp(0.0, w as f64 - 1e-3),
                        (kp.y as f64 + rng.random_range(-2.0..2.0)).clamp(0.0, h as f64 - 1e-3),
                    )
                } else {
                    (
                        rng.random_range(0.0..w as f64),
                        rng.random_range(0.0..h as f64),
                    )
                };
                let (c, r) = (x as usize, y as usize);
                pixels.push(Point2::new(c as f64 + 0.5, r as f64 + 0.5));
                target.extend_from_slice(img.pixel(c, r));
            }
            let mut grad = Vector6::<f64>::zeros();
            for d in 0..6 {
                let step = if d < 3 { fd.0 } else { fd.1 };
                let mut xi = Vector6::zeros();
                xi[d] = step;
                let plus = tangent_to_isometry(&xi) * pose;
                xi[d] = -step;
                let minus = tangent_to_isometry(&xi) * pose;
                let lp = photometric_loss(model, &cam, &plus, &pixels, &target)?;
                let lm = photometric_loss(model, &cam, &minus, &pixels, &target)?;
                grad[d] = (lp - lm) / (2.0 * step);
            }
            it_total += 1;
            m = m * b1 + grad * (1.0 - b1);
            v = v * b2 + grad.component_mul(&grad) * (1.0 - b2);
            let mh = m / (1.0 - b1.powi(it_total as i32));
            let vh = v / (1.0 - b2.powi(it_total as i32));
            let mut delta = Vector6::zeros();
            for d in 0..6 {
                let lr = if d < 3 {
                    options.lr_rotation_rad
                } else {
                    options.lr_translation_m
                } * decay;
                delta[d] = -lr * mh[d] / (vh[d].sqrt() + eps);
            }
            pose = tangent_to_isometry(&delta) * pose;
        }
    }
    Ok(BaselineOutcome {
        cam_from_world: Some(pose),
        iterations: it_total,
        stage_seconds: vec![("optimise".to_string(), start.elapsed().as_secs_f64())],
        matches: options.pixels,
        inliers: 0,
        log10_nfa: None,
        failure: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tangent_exp_is_identity_at_zero_and_composes_small_steps() {
        let id = tangent_to_isometry(&Vector6::zeros());
        assert!((id.to_homogeneous() - nalgebra::Matrix4::identity()).norm() < 1e-15);
        let xi = Vector6::new(0.0, 0.0, 0.1, 1.0, 0.0, 0.0);
        let t = tangent_to_isometry(&xi);
        assert!((t.rotation.angle() - 0.1).abs() < 1e-12);
        assert!((t.translation.vector - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
    }

    /// The keypoint baseline's confidence tells a chance consensus from a real one.
    #[test]
    fn keypoint_consensus_significance_grows_with_the_inliers() {
        // 6 of 200 matches within 3 px on a 320 × 240 image could be chance; 20 could not.
        let solver = LoRansacPnp::default();
        let camera = Camera::pinhole(320, 240, 300.0, 300.0, 160.0, 120.0).unwrap();
        assert!(solver.consensus_log10_nfa(&camera, 200, 6) > -2.0);
        assert!(solver.consensus_log10_nfa(&camera, 200, 20) < -2.0);
    }

    #[test]
    fn box_downscale_averages() {
        let mut img = Image::new(4, 2, 3);
        for (i, v) in img.data_mut().iter_mut().enumerate() {
            *v = (i / 3 % 2) as f32; // alternating columns 0, 1
        }
        let d = matloc_core::image::downscale_box(&img, 2);
        assert_eq!(d.shape(), (2, 1, 3));
        assert!(d.data().iter().all(|v| (v - 0.5).abs() < 1e-6));
    }
}
