//! Non-linear least-squares pose refinement: Levenberg–Marquardt on the reprojection error in
//! pixels, through the full camera model (lens distortion included), with a robust loss.
//!
//! The pose is perturbed on the left, `cam_from_world ← (Exp(ω), v) · cam_from_world`, so a
//! camera-frame point moves by `ω × p_cam + v` and the Jacobian of a residual is
//! `∂r/∂p_cam · [−[p_cam]× | I]` — analytic, no finite differences. Robust losses enter by
//! iteratively reweighted least squares, and a step is kept only when it lowers the robust cost,
//! so refinement never makes the cost worse.

use matloc_core::{Camera, Distortion, Pose};
use nalgebra::{Matrix2, Matrix2x3, Matrix6, Point2, Point3, Vector2, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use crate::error::PnpError;
use crate::model::{PoseMatrix, exp_so3};

/// Robust loss `ρ(s)` applied to the squared reprojection error `s` (pixels²).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, tag = "kind", rename_all = "snake_case")]
pub enum RobustLoss {
    /// Plain least squares, `ρ(s) = s`.
    Trivial,
    /// Quadratic up to `scale_px`, linear beyond: `ρ(s) = s` or `2c√s − c²`.
    Huber {
        /// Residual (pixels) where the loss turns linear.
        scale_px: f64,
    },
    /// `ρ(s) = c² ln(1 + s/c²)`: outliers keep a small, decaying influence.
    Cauchy {
        /// Residual (pixels) where the loss is half way to flat.
        scale_px: f64,
    },
    /// MSAC's truncated quadratic, `ρ(s) = min(s, c²)`: points beyond `scale_px` have no influence.
    Truncated {
        /// Residual (pixels) beyond which a point is ignored.
        scale_px: f64,
    },
}

impl Default for RobustLoss {
    /// Cauchy at 3 px, the default inlier threshold. On 1 px noise it gave ~8 % lower median
    /// pose errors than a 1 px scale, which down-weights genuine inliers.
    fn default() -> Self {
        RobustLoss::Cauchy { scale_px: 3.0 }
    }
}

impl RobustLoss {
    /// `ρ(s)` for a squared residual `s` in pixels².
    #[inline]
    pub fn cost(&self, s: f64) -> f64 {
        match *self {
            RobustLoss::Trivial => s,
            RobustLoss::Huber { scale_px: c } => {
                if s <= c * c {
                    s
                } else {
                    2.0 * c * s.sqrt() - c * c
                }
            }
            RobustLoss::Cauchy { scale_px: c } => c * c * (s / (c * c)).ln_1p(),
            RobustLoss::Truncated { scale_px: c } => s.min(c * c),
        }
    }

    /// `ρ'(s)`, the IRLS weight of a residual with squared norm `s`.
    #[inline]
    pub fn weight(&self, s: f64) -> f64 {
        match *self {
            RobustLoss::Trivial => 1.0,
            RobustLoss::Huber { scale_px: c } => {
                if s <= c * c {
                    1.0
                } else {
                    c / s.sqrt()
                }
            }
            RobustLoss::Cauchy { scale_px: c } => 1.0 / (1.0 + s / (c * c)),
            RobustLoss::Truncated { scale_px: c } => {
                if s <= c * c {
                    1.0
                } else {
                    0.0
                }
            }
        }
    }

    fn validate(&self) -> Result<(), PnpError> {
        match *self {
            RobustLoss::Trivial => Ok(()),
            RobustLoss::Huber { scale_px }
            | RobustLoss::Cauchy { scale_px }
            | RobustLoss::Truncated { scale_px } => {
                if scale_px > 0.0 && scale_px.is_finite() {
                    Ok(())
                } else {
                    Err(PnpError::InvalidOption {
                        field: "loss.scale_px",
                        reason: "must be positive and finite",
                    })
                }
            }
        }
    }
}

/// Options of the Levenberg–Marquardt refinement.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefineOptions {
    /// Most LM iterations (linear solves), accepted or rejected.
    pub max_iterations: usize,
    /// Robust loss on the reprojection error in pixels.
    pub loss: RobustLoss,
    /// Stop when the largest gradient entry falls below this.
    pub gradient_tolerance: f64,
    /// Stop when the update (rotation in rad, translation relative to its norm) is this small.
    pub step_tolerance: f64,
    /// Initial LM damping, relative to the diagonal of the normal equations.
    pub initial_damping: f64,
}

impl Default for RefineOptions {
    fn default() -> Self {
        Self {
            max_iterations: 50,
            loss: RobustLoss::default(),
            gradient_tolerance: 1e-10,
            step_tolerance: 1e-10,
            initial_damping: 1e-4,
        }
    }
}

/// Outcome of [`refine_pose`].
#[derive(Clone, Debug, PartialEq)]
pub struct RefineReport {
    /// The refined `cam_from_world`.
    pub cam_from_world: Pose,
    /// Robust cost `Σ ρ(|r|²)` (pixels²) at the initial pose.
    pub initial_cost: f64,
    /// Robust cost at the refined pose; never larger than `initial_cost`.
    pub final_cost: f64,
    /// LM iterations run.
    pub iterations: usize,
}

/// Refines a `cam_from_world` pose by minimising `Σ ρ(|π(p_i) − x_i|²)` over the reprojection
/// errors in pixels through `camera` (distortion included).
///
/// Points behind the camera contribute a constant penalty, so they neither pull the pose nor
/// make the cost undefined. Errors: length mismatch, non-finite input, invalid camera or loss.
pub fn refine_pose(
    camera: &Camera,
    pixels: &[Point2<f64>],
    points_world: &[Point3<f64>],
    cam_from_world: &Pose,
    options: &RefineOptions,
) -> Result<RefineReport, PnpError> {
    camera.validate()?;
    options.loss.validate()?;
    if pixels.len() != points_world.len() {
        return Err(PnpError::LengthMismatch {
            pixels: pixels.len(),
            points: points_world.len(),
            scores: None,
        });
    }
    let mat = PoseMatrix::from_pose(cam_from_world);
    if !mat
        .rotation
        .iter()
        .chain(mat.translation.iter())
        .all(|v| v.is_finite())
    {
        return Err(PnpError::NonFiniteInput {
            index: 0,
            what: "initial pose",
        });
    }
    let mut obs = Vec::with_capacity(pixels.len());
    let mut pts = Vec::with_capacity(pixels.len());
    for (index, (px, p)) in pixels.iter().zip(points_world).enumerate() {
        if !(px.x.is_finite() && px.y.is_finite()) {
            return Err(PnpError::NonFiniteInput {
                index,
                what: "pixel",
            });
        }
        if !p.coords.iter().all(|v| v.is_finite()) {
            return Err(PnpError::NonFiniteInput {
                index,
                what: "world point",
            });
        }
        obs.push(camera.pixel_to_distorted_normalized(*px));
        pts.push(p.coords);
    }
    let problem = ReprojectionProblem {
        observations: &obs,
        points: &pts,
        indices: None,
        fx: camera.fx,
        fy: camera.fy,
        distortion: (!camera.is_pinhole()).then_some(camera.distortion),
    };
    let (refined, summary) = levenberg_marquardt(&problem, mat, &options.loss, options);
    Ok(RefineReport {
        cam_from_world: refined.to_pose(),
        initial_cost: summary.initial_cost,
        final_cost: summary.final_cost,
        iterations: summary.iterations,
    })
}

/// Squared residual charged to a point behind the camera (pixels²): large, but finite so that
/// costs stay comparable.
const BEHIND_CAMERA_SQ_PX: f64 = 1e12;

/// Reprojection residuals of a subset of correspondences, in pixels.
///
/// `observations` are distorted normalised coordinates `((u − cx)/fx, (v − cy)/fy)` when
/// `distortion` is set, or undistorted normalised coordinates when it is `None`; either way the
/// residual is `diag(fx, fy) (d(π(p_cam)) − observation)`, i.e. exactly pixels.
pub(crate) struct ReprojectionProblem<'a> {
    pub observations: &'a [Vector2<f64>],
    pub points: &'a [Vector3<f64>],
    pub indices: Option<&'a [usize]>,
    pub fx: f64,
    pub fy: f64,
    pub distortion: Option<Distortion>,
}

pub(crate) struct LmSummary {
    pub initial_cost: f64,
    pub final_cost: f64,
    pub iterations: usize,
}

impl ReprojectionProblem<'_> {
    fn for_each_index(&self, mut f: impl FnMut(usize)) {
        match self.indices {
            Some(idx) => idx.iter().for_each(|&i| f(i)),
            None => (0..self.points.len()).for_each(f),
        }
    }

    /// Robust cost, and when `normal` is given the IRLS normal equations `(JᵀWJ, JᵀWr)`.
    fn evaluate(
        &self,
        pose: &PoseMatrix,
        loss: &RobustLoss,
        mut normal: Option<(&mut Matrix6<f64>, &mut Vector6<f64>)>,
    ) -> f64 {
        let mut cost = 0.0;
        let f = Matrix2::new(self.fx, 0.0, 0.0, self.fy);
        self.for_each_index(|i| {
            let pc = pose.transform(&self.points[i]);
            if !(pc.z > 1e-9) {
                cost += loss.cost(BEHIND_CAMERA_SQ_PX);
                return;
            }
            let iz = 1.0 / pc.z;
            let n = Vector2::new(pc.x * iz, pc.y * iz);
            let (d, jd) = match &self.distortion {
                Some(dist) => (dist.apply(n), Some(dist.jacobian(n))),
                None => (n, None),
            };
            let o = self.observations[i];
            let r = Vector2::new(self.fx * (d.x - o.x), self.fy * (d.y - o.y));
            let s = r.norm_squared();
            cost += loss.cost(s);
            if let Some((h, g)) = normal.as_mut() {
                let w = loss.weight(s);
                if w == 0.0 {
                    return;
                }
                let dn = Matrix2x3::new(iz, 0.0, -n.x * iz, 0.0, iz, -n.y * iz);
                let jp = match jd {
                    Some(jd) => f * jd * dn,
                    None => f * dn,
                };
                // ∂p_cam/∂ω = −[p_cam]×, ∂p_cam/∂v = I.
                let jw = jp * (-pc.cross_matrix());
                let mut j = nalgebra::Matrix2x6::zeros();
                j.fixed_view_mut::<2, 3>(0, 0).copy_from(&jw);
                j.fixed_view_mut::<2, 3>(0, 3).copy_from(&jp);
                h.gemm_tr(w, &j, &j, 1.0);
                **g += w * (j.transpose() * r);
            }
        });
        cost
    }
}

/// Levenberg–Marquardt with Marquardt (diagonal) damping; only cost-decreasing steps are taken.
pub(crate) fn levenberg_marquardt(
    problem: &ReprojectionProblem<'_>,
    initial: PoseMatrix,
    loss: &RobustLoss,
    options: &RefineOptions,
) -> (PoseMatrix, LmSummary) {
    let mut pose = initial;
    let mut h = Matrix6::zeros();
    let mut g = Vector6::zeros();
    let mut cost = problem.evaluate(&pose, loss, Some((&mut h, &mut g)));
    let initial_cost = cost;
    let mut damping = options.initial_damping;
    let mut iterations = 0;
    while iterations < options.max_iterations {
        if g.amax() < options.gradient_tolerance || !cost.is_finite() {
            break;
        }
        iterations += 1;
        let mut a = h;
        for k in 0..6 {
            // Floor on the diagonal: a parameter the data do not constrain still gets damped.
            a[(k, k)] += damping * h[(k, k)].max(1e-9);
        }
        let Some(step) = a.cholesky().map(|c| -c.solve(&g)) else {
            damping *= 10.0;
            continue;
        };
        let omega = Vector3::new(step[0], step[1], step[2]);
        let v = Vector3::new(step[3], step[4], step[5]);
        if omega.norm() < options.step_tolerance
            && v.norm() < options.step_tolerance * (1.0 + pose.translation.norm())
        {
            break;
        }
        let rot = exp_so3(&omega);
        let candidate = PoseMatrix::new(rot * pose.rotation, rot * pose.translation + v);
        // Cost first: rejected steps (common once converged) then skip the Jacobians.
        let new_cost = problem.evaluate(&candidate, loss, None);
        if new_cost < cost {
            let relative_decrease = (cost - new_cost) / cost.max(1e-300);
            pose = candidate;
            cost = new_cost;
            damping = (damping * 0.1).max(1e-12);
            if relative_decrease < 1e-12 {
                break;
            }
            h = Matrix6::zeros();
            g = Vector6::zeros();
            problem.evaluate(&pose, loss, Some((&mut h, &mut g)));
        } else {
            damping *= 10.0;
            if damping > 1e8 {
                break;
            }
        }
    }
    (
        pose,
        LmSummary {
            initial_cost,
            final_cost: cost,
            iterations,
        },
    )
}
