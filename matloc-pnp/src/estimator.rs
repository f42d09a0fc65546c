//! The absolute-pose [`Estimator`]: P3P on minimal samples, EPnP or Gauss–Newton on larger sets,
//! residuals in pixels.

use nalgebra::{Vector2, Vector3};

use crate::epnp::epnp;
use crate::model::PoseMatrix;
use crate::p3p::p3p;
use crate::ransac::Estimator;
use crate::refine::{RefineOptions, ReprojectionProblem, RobustLoss, levenberg_marquardt};

/// Absolute pose from undistorted correspondences.
///
/// Residuals are reprojection errors in *undistorted* pixels, `diag(fx, fy)` times the error in
/// normalised coordinates: exact pixels for a pinhole camera, and for a distorted lens a
/// local approximation that the final refinement (which goes through the distortion) replaces.
#[derive(Clone, Debug)]
pub struct AbsolutePoseEstimator<'a> {
    normalized: &'a [Vector2<f64>],
    bearings: &'a [Vector3<f64>],
    points: &'a [Vector3<f64>],
    fx: f64,
    fy: f64,
    threshold_px: f64,
}

impl<'a> AbsolutePoseEstimator<'a> {
    /// An estimator over undistorted normalised points (`x/z`, `y/z`), their unit bearings and
    /// world points (equal lengths), for focal lengths `fx`, `fy` and an inlier threshold in
    /// pixels (used by the local refits).
    pub fn new(
        normalized: &'a [Vector2<f64>],
        bearings: &'a [Vector3<f64>],
        points: &'a [Vector3<f64>],
        fx: f64,
        fy: f64,
        threshold_px: f64,
    ) -> Self {
        assert_eq!(
            normalized.len(),
            points.len(),
            "normalized and points differ in length"
        );
        assert_eq!(
            bearings.len(),
            points.len(),
            "bearings and points differ in length"
        );
        Self {
            normalized,
            bearings,
            points,
            fx,
            fy,
            threshold_px,
        }
    }

    fn problem<'b>(&'b self, indices: &'b [usize]) -> ReprojectionProblem<'b> {
        ReprojectionProblem {
            observations: self.normalized,
            points: self.points,
            indices: Some(indices),
            fx: self.fx,
            fy: self.fy,
            distortion: None,
        }
    }
}

/// Local refits are short: they only need to move a minimal-sample pose to the inlier set's.
const LOCAL_REFIT_ITERATIONS: usize = 10;

impl Estimator for AbsolutePoseEstimator<'_> {
    type Model = PoseMatrix;

    fn min_sample_size(&self) -> usize {
        3
    }

    fn num_data(&self) -> usize {
        self.points.len()
    }

    fn fit_minimal(&self, sample: &[usize], models: &mut Vec<PoseMatrix>) {
        let bearings = [
            self.bearings[sample[0]],
            self.bearings[sample[1]],
            self.bearings[sample[2]],
        ];
        let points = [
            self.points[sample[0]],
            self.points[sample[1]],
            self.points[sample[2]],
        ];
        p3p(&bearings, &points, models);
    }

    fn fit_nonminimal(
        &self,
        indices: &[usize],
        initial: Option<&PoseMatrix>,
    ) -> Option<PoseMatrix> {
        if indices.len() < 4 {
            return None;
        }
        let start = match initial {
            Some(pose) => *pose,
            None => {
                let obs: Vec<Vector2<f64>> = indices.iter().map(|&i| self.normalized[i]).collect();
                let pts: Vec<Vector3<f64>> = indices.iter().map(|&i| self.points[i]).collect();
                epnp(&obs, &pts)?
            }
        };
        // Truncated loss: the refit minimises the MSAC score itself, so candidates that turn
        // out to be outliers stop pulling the pose.
        let loss = RobustLoss::Truncated {
            scale_px: self.threshold_px,
        };
        let options = RefineOptions {
            max_iterations: LOCAL_REFIT_ITERATIONS,
            loss,
            ..RefineOptions::default()
        };
        let (pose, _) = levenberg_marquardt(&self.problem(indices), start, &loss, &options);
        Some(pose)
    }

    #[inline]
    fn squared_residual(&self, model: &PoseMatrix, index: usize) -> f64 {
        let pc = model.transform(&self.points[index]);
        if !(pc.z > 0.0) {
            return f64::INFINITY;
        }
        let iz = 1.0 / pc.z;
        let m = self.normalized[index];
        let dx = self.fx * (pc.x * iz - m.x);
        let dy = self.fy * (pc.y * iz - m.y);
        dx * dx + dy * dy
    }
}
