//! The [`PoseSolver`] interface and its LO-RANSAC implementation.

use std::time::{Duration, Instant};

use matloc_core::{Camera, Pose};
use nalgebra::{Matrix3, Point2, Point3, SymmetricEigen, Vector2, Vector3};
use rand::RngCore;
use serde::{Deserialize, Serialize};

use crate::error::PnpError;
use crate::estimator::AbsolutePoseEstimator;
use crate::model::PoseMatrix;
use crate::ransac::{ProsacSampler, RansacOptions, Sampler, SamplerKind, UniformSampler, ransac};
use crate::refine::{RefineOptions, ReprojectionProblem, levenberg_marquardt};

/// Fewest correspondences any solver here accepts (P3P plus one to disambiguate).
pub const MIN_CORRESPONDENCES: usize = 4;

/// 2D–3D matches for one query image.
#[derive(Clone, Copy, Debug)]
pub struct PnpInput<'a> {
    /// Intrinsics (with distortion) of the query camera.
    pub camera: &'a Camera,
    /// Observed pixels (continuous coordinates, pixel centres at `+0.5`).
    pub pixels: &'a [Point2<f64>],
    /// World points, one per pixel.
    pub points_world: &'a [Point3<f64>],
    /// Optional match quality, higher is better (e.g. feature similarity); drives PROSAC.
    pub scores: Option<&'a [f64]>,
    /// Inlier threshold for these matches (pixels), overriding the solver's
    /// `ransac.max_error_px`: the caller knows how noisy its correspondences are (e.g. a
    /// coarse first pass of a localizer versus its refinement passes).
    pub max_error_px: Option<f64>,
}

impl<'a> PnpInput<'a> {
    /// Matches without scores.
    pub fn new(
        camera: &'a Camera,
        pixels: &'a [Point2<f64>],
        points_world: &'a [Point3<f64>],
    ) -> Self {
        Self {
            camera,
            pixels,
            points_world,
            scores: None,
            max_error_px: None,
        }
    }

    /// The same matches with per-match scores.
    pub fn with_scores(mut self, scores: &'a [f64]) -> Self {
        self.scores = Some(scores);
        self
    }

    /// The same matches with their own inlier threshold (see [`PnpInput::max_error_px`]).
    pub fn with_max_error_px(mut self, max_error_px: f64) -> Self {
        self.max_error_px = Some(max_error_px);
        self
    }
}

/// `options` with the input's threshold override applied.
fn effective_options(options: &PnpOptions, input: &PnpInput<'_>) -> PnpOptions {
    let mut o = options.clone();
    if let Some(px) = input.max_error_px {
        o.ransac.max_error_px = px;
    }
    o
}

/// Statistics of one solve.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PnpStats {
    /// RANSAC samples drawn.
    pub iterations: usize,
    /// Inliers of the returned pose (reprojection error below the threshold, through the
    /// full camera model).
    pub num_inliers: usize,
    /// `num_inliers` over the number of matches given.
    pub inlier_ratio: f64,
    /// MSAC score `Σ min(e², τ²)` of the returned pose over all matches (pixels²).
    pub score: f64,
    /// Local optimisations run inside RANSAC.
    pub local_optimizations: usize,
    /// Levenberg–Marquardt iterations of the final refinement.
    pub refinement_iterations: usize,
    /// Wall-clock time of the whole solve.
    pub elapsed: Duration,
}

/// A solved pose.
#[derive(Clone, Debug, PartialEq)]
pub struct PnpResult {
    /// The estimated `cam_from_world` (world → camera, OpenCV axes).
    pub cam_from_world: Pose,
    /// Per input match: whether it is an inlier of the returned pose.
    pub inliers: Vec<bool>,
    /// How the solve went.
    pub stats: PnpStats,
}

/// Estimates a camera pose from 2D–3D matches. Object safe: `Box<dyn PoseSolver>` works.
pub trait PoseSolver {
    /// Solves for `cam_from_world`; the RNG makes the result reproducible.
    fn solve(&self, input: &PnpInput<'_>, rng: &mut dyn RngCore) -> Result<PnpResult, PnpError>;
    /// Matches in the minimal sample a pose hypothesis is fitted to (3 for P3P): a consensus
    /// is judged beyond chance only for the inliers beyond these
    /// ([`crate::significance::log10_nfa`]).
    fn minimal_sample(&self) -> usize;
}

/// Options of [`LoRansacPnp`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PnpOptions {
    /// Robust estimation.
    pub ransac: RansacOptions,
    /// Final refinement on the inliers.
    pub refine: RefineOptions,
    /// Whether to run the final refinement at all.
    pub final_refinement: bool,
}

impl Default for PnpOptions {
    fn default() -> Self {
        Self {
            ransac: RansacOptions::default(),
            refine: RefineOptions::default(),
            final_refinement: true,
        }
    }
}

/// P3P in LO-RANSAC (MSAC, uniform or PROSAC sampling), then robust Levenberg–Marquardt on the
/// inliers through the full camera model.
#[derive(Clone, Debug, PartialEq)]
pub struct LoRansacPnp {
    /// Solver options.
    pub options: PnpOptions,
}

impl Default for LoRansacPnp {
    fn default() -> Self {
        Self::new(PnpOptions::default())
    }
}

impl LoRansacPnp {
    /// A solver with the given options.
    pub fn new(options: PnpOptions) -> Self {
        Self { options }
    }

    /// Base-10 NFA of a consensus of `inliers` among `matches` in `camera`'s image: a chance
    /// match is an inlier when it lands within this solver's RANSAC threshold of its
    /// projection, anywhere in the image ([`crate::significance`]).
    pub fn consensus_log10_nfa(&self, camera: &Camera, matches: usize, inliers: usize) -> f64 {
        let p_chance = crate::significance::chance_inlier_probability(
            self.options.ransac.max_error_px,
            camera.width,
            camera.height,
            None,
        );
        crate::significance::log10_nfa(matches, inliers, self.minimal_sample(), p_chance)
    }
}

/// Correspondences after validation and undistortion (usable matches only).
pub(crate) struct Prepared {
    /// Input index of each usable match.
    pub original: Vec<usize>,
    /// Undistorted normalised coordinates.
    pub normalized: Vec<Vector2<f64>>,
    /// Distorted normalised coordinates, `((u − cx)/fx, (v − cy)/fy)`.
    pub distorted: Vec<Vector2<f64>>,
    /// Unit bearings.
    pub bearings: Vec<Vector3<f64>>,
    /// World points.
    pub points: Vec<Vector3<f64>>,
    /// Scores of the usable matches.
    pub scores: Option<Vec<f64>>,
}

/// Validates the input and undistorts every pixel once.
///
/// Pixels whose undistortion does not converge (far outside the lens model's valid region) are
/// dropped rather than rejected: they cannot be inliers of any pose.
pub(crate) fn prepare(input: &PnpInput<'_>) -> Result<Prepared, PnpError> {
    input.camera.validate()?;
    let n = input.pixels.len();
    if input.points_world.len() != n || input.scores.is_some_and(|s| s.len() != n) {
        return Err(PnpError::LengthMismatch {
            pixels: n,
            points: input.points_world.len(),
            scores: input.scores.map(|s| s.len()),
        });
    }
    let mut prepared = Prepared {
        original: Vec::with_capacity(n),
        normalized: Vec::with_capacity(n),
        distorted: Vec::with_capacity(n),
        bearings: Vec::with_capacity(n),
        points: Vec::with_capacity(n),
        scores: input.scores.map(|_| Vec::with_capacity(n)),
    };
    for index in 0..n {
        let px = input.pixels[index];
        if !(px.x.is_finite() && px.y.is_finite()) {
            return Err(PnpError::NonFiniteInput {
                index,
                what: "pixel",
            });
        }
        let p = input.points_world[index];
        if !p.coords.iter().all(|v| v.is_finite()) {
            return Err(PnpError::NonFiniteInput {
                index,
                what: "world point",
            });
        }
        if let Some(s) = input.scores
            && !s[index].is_finite()
        {
            return Err(PnpError::NonFiniteInput {
                index,
                what: "score",
            });
        }
    }
    if n < MIN_CORRESPONDENCES {
        return Err(PnpError::InsufficientCorrespondences {
            required: MIN_CORRESPONDENCES,
            actual: n,
        });
    }
    for index in 0..n {
        let px = input.pixels[index];
        let Some(nrm) = input.camera.pixel_to_normalized(px) else {
            continue;
        };
        prepared.original.push(index);
        prepared.normalized.push(nrm);
        prepared
            .distorted
            .push(input.camera.pixel_to_distorted_normalized(px));
        prepared
            .bearings
            .push(Vector3::new(nrm.x, nrm.y, 1.0).normalize());
        prepared.points.push(input.points_world[index].coords);
        if let (Some(out), Some(s)) = (prepared.scores.as_mut(), input.scores) {
            out.push(s[index]);
        }
    }
    if prepared.points.len() < MIN_CORRESPONDENCES {
        return Err(PnpError::InsufficientCorrespondences {
            required: MIN_CORRESPONDENCES,
            actual: prepared.points.len(),
        });
    }
    check_spread(&prepared.points)?;
    Ok(prepared)
}

/// Rejects point sets that admit no unique pose whatever the sampling: all coincident or all on
/// one line.
fn check_spread(points: &[Vector3<f64>]) -> Result<(), PnpError> {
    let n = points.len() as f64;
    let centroid = points.iter().sum::<Vector3<f64>>() / n;
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = p - centroid;
        cov += d * d.transpose();
    }
    let mut ev = SymmetricEigen::new(cov / n).eigenvalues;
    ev.as_mut_slice().sort_by(|a, b| b.total_cmp(a));
    if !(ev[0] > 1e-18 * (1.0 + centroid.norm_squared())) {
        return Err(PnpError::Degenerate("all world points coincide"));
    }
    if ev[1] < 1e-14 * ev[0] {
        return Err(PnpError::Degenerate("all world points lie on one line"));
    }
    Ok(())
}

fn validate_options(options: &PnpOptions) -> Result<(), PnpError> {
    let r = &options.ransac;
    if !(r.max_error_px > 0.0 && r.max_error_px.is_finite()) {
        return Err(PnpError::InvalidOption {
            field: "ransac.max_error_px",
            reason: "must be positive and finite",
        });
    }
    if !(r.confidence > 0.0 && r.confidence < 1.0) {
        return Err(PnpError::InvalidOption {
            field: "ransac.confidence",
            reason: "must lie in (0, 1)",
        });
    }
    if r.max_iterations == 0 {
        return Err(PnpError::InvalidOption {
            field: "ransac.max_iterations",
            reason: "must be at least 1",
        });
    }
    Ok(())
}

impl PoseSolver for LoRansacPnp {
    fn minimal_sample(&self) -> usize {
        3
    }

    fn solve(&self, input: &PnpInput<'_>, rng: &mut dyn RngCore) -> Result<PnpResult, PnpError> {
        let start = Instant::now();
        let options = effective_options(&self.options, input);
        validate_options(&options)?;
        let prepared = prepare(input)?;
        let camera = input.camera;
        let ropt = &options.ransac;
        let estimator = AbsolutePoseEstimator::new(
            &prepared.normalized,
            &prepared.bearings,
            &prepared.points,
            camera.fx,
            camera.fy,
            ropt.max_error_px,
        );
        let n = prepared.points.len();
        let mut sampler: Box<dyn Sampler> = match (ropt.sampler, prepared.scores.as_deref()) {
            (SamplerKind::Auto | SamplerKind::Prosac, Some(scores)) => {
                Box::new(ProsacSampler::new(scores, 3, ropt.prosac_growth_samples))
            }
            _ => Box::new(UniformSampler::new(n)),
        };
        let found = ransac(&estimator, sampler.as_mut(), ropt, rng);
        let Some(mut pose) = found.model else {
            return Err(if found.num_hypotheses == 0 {
                PnpError::Degenerate("no minimal sample produced a pose")
            } else {
                PnpError::NoConsensus {
                    best_inliers: 0,
                    required: ropt.min_inliers,
                }
            });
        };
        if found.num_inliers < ropt.min_inliers {
            return Err(PnpError::NoConsensus {
                best_inliers: found.num_inliers,
                required: ropt.min_inliers,
            });
        }

        let threshold_sq = ropt.max_error_px * ropt.max_error_px;
        let distortion = (!camera.is_pinhole()).then_some(camera.distortion);
        let mut refinement_iterations = 0;
        if options.final_refinement {
            let inliers: Vec<usize> = (0..n)
                .filter(|&i| pixel_error_sq(&prepared, camera, &pose, i) < threshold_sq)
                .collect();
            let problem = ReprojectionProblem {
                observations: if distortion.is_some() {
                    &prepared.distorted
                } else {
                    &prepared.normalized
                },
                points: &prepared.points,
                indices: Some(&inliers),
                fx: camera.fx,
                fy: camera.fy,
                distortion,
            };
            let (refined, summary) =
                levenberg_marquardt(&problem, pose, &options.refine.loss, &options.refine);
            pose = refined;
            refinement_iterations = summary.iterations;
        }

        let mut inliers = vec![false; input.pixels.len()];
        let mut num_inliers = 0;
        let mut score = 0.0;
        for i in 0..n {
            let e = pixel_error_sq(&prepared, camera, &pose, i);
            if e < threshold_sq {
                inliers[prepared.original[i]] = true;
                num_inliers += 1;
                score += e;
            } else {
                score += threshold_sq;
            }
        }
        // Matches dropped during undistortion count as outliers.
        score += (input.pixels.len() - n) as f64 * threshold_sq;
        if num_inliers < ropt.min_inliers {
            return Err(PnpError::NoConsensus {
                best_inliers: num_inliers,
                required: ropt.min_inliers,
            });
        }
        Ok(PnpResult {
            cam_from_world: pose.to_pose(),
            inliers,
            stats: PnpStats {
                iterations: found.iterations,
                num_inliers,
                inlier_ratio: num_inliers as f64 / input.pixels.len() as f64,
                score,
                local_optimizations: found.local_optimizations,
                refinement_iterations,
                elapsed: start.elapsed(),
            },
        })
    }
}

/// Squared reprojection error in pixels through the full camera model (infinite behind).
fn pixel_error_sq(prepared: &Prepared, camera: &Camera, pose: &PoseMatrix, i: usize) -> f64 {
    let pc = pose.transform(&prepared.points[i]);
    if !(pc.z > 0.0) {
        return f64::INFINITY;
    }
    let n = Vector2::new(pc.x / pc.z, pc.y / pc.z);
    let d = camera.distortion.apply(n);
    let o = prepared.distorted[i];
    let (dx, dy) = (camera.fx * (d.x - o.x), camera.fy * (d.y - o.y));
    dx * dx + dy * dy
}

/// Solves with [`LoRansacPnp`] and a seeded RNG: the one-call entry point.
pub fn solve_pnp(
    input: &PnpInput<'_>,
    options: &PnpOptions,
    seed: u64,
) -> Result<PnpResult, PnpError> {
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    LoRansacPnp::new(options.clone()).solve(input, &mut rng)
}

/// EPnP on every match followed by the robust refinement: no outlier rejection beyond the loss,
/// for clean inlier sets (e.g. re-fitting after an earlier RANSAC).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EpnpPnp {
    /// Refinement options; `ransac.max_error_px` defines the reported inliers.
    pub options: PnpOptions,
}

impl PoseSolver for EpnpPnp {
    /// EPnP needs four matches.
    fn minimal_sample(&self) -> usize {
        4
    }

    fn solve(&self, input: &PnpInput<'_>, _rng: &mut dyn RngCore) -> Result<PnpResult, PnpError> {
        let start = Instant::now();
        let options = effective_options(&self.options, input);
        validate_options(&options)?;
        let prepared = prepare(input)?;
        let camera = input.camera;
        let mut pose = crate::epnp::epnp(&prepared.normalized, &prepared.points)
            .ok_or(PnpError::Degenerate("EPnP found no pose"))?;
        let distortion = (!camera.is_pinhole()).then_some(camera.distortion);
        let mut refinement_iterations = 0;
        if options.final_refinement {
            let problem = ReprojectionProblem {
                observations: if distortion.is_some() {
                    &prepared.distorted
                } else {
                    &prepared.normalized
                },
                points: &prepared.points,
                indices: None,
                fx: camera.fx,
                fy: camera.fy,
                distortion,
            };
            let (refined, summary) =
                levenberg_marquardt(&problem, pose, &options.refine.loss, &options.refine);
            pose = refined;
            refinement_iterations = summary.iterations;
        }
        let threshold_sq = options.ransac.max_error_px.powi(2);
        let mut inliers = vec![false; input.pixels.len()];
        let (mut num_inliers, mut score) = (0, 0.0);
        for i in 0..prepared.points.len() {
            let e = pixel_error_sq(&prepared, camera, &pose, i);
            if e < threshold_sq {
                inliers[prepared.original[i]] = true;
                num_inliers += 1;
                score += e;
            } else {
                score += threshold_sq;
            }
        }
        Ok(PnpResult {
            cam_from_world: pose.to_pose(),
            inliers,
            stats: PnpStats {
                iterations: 1,
                num_inliers,
                inlier_ratio: num_inliers as f64 / input.pixels.len() as f64,
                score,
                local_optimizations: 0,
                refinement_iterations,
                elapsed: start.elapsed(),
            },
        })
    }
}
