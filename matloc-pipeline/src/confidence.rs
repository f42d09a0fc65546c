//! A calibrated localization confidence: P(pose is correct | evidence), by logistic regression
//! on the solver's evidence, fitted at map-build time on held-out queries with known poses.
//!
//! "Correct" is defined by the caller when labelling the calibration set (the pipeline uses
//! within 1 m and 5°). Evidence features are the log inlier count, the inlier ratio and the
//! log mean similarity gap of the matches — all cheap by-products of matching and PnP. Fitted
//! by Newton's method (IRLS) with a ridge term, so separable or one-class calibration sets still
//! give finite weights.

use serde::{Deserialize, Serialize};

/// What the solver reports about one localization attempt.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Evidence {
    /// PnP inliers.
    pub inliers: usize,
    /// Inliers / matches.
    pub inlier_ratio: f64,
    /// Matches fed to PnP.
    pub matches: usize,
}

impl Evidence {
    fn features(&self) -> [f64; 4] {
        [
            1.0,
            (1.0 + self.inliers as f64).ln(),
            self.inlier_ratio.clamp(0.0, 1.0),
            (1.0 + self.matches as f64).ln(),
        ]
    }
}

/// Errors of calibration.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CalibrationError {
    /// No calibration samples.
    #[error("confidence calibration needs at least one sample")]
    Empty,
    /// A non-finite evidence value at this sample.
    #[error("calibration sample {index} has a non-finite value")]
    NonFinite {
        /// Sample index.
        index: usize,
    },
}

/// Logistic model over [`Evidence`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ConfidenceModel {
    /// Weights for (bias, ln(1+inliers), inlier ratio, ln(1+matches)).
    pub weights: [f64; 4],
    /// Queries with a confidence below this are refused ("not localized").
    pub accept_threshold: f64,
}

impl Default for ConfidenceModel {
    /// An uncalibrated prior: ~50 % at 12 inliers, rising with the inlier count and ratio.
    fn default() -> Self {
        Self {
            weights: [-6.0, 2.0, 2.0, 0.0],
            accept_threshold: 0.5,
        }
    }
}

fn sigmoid(z: f64) -> f64 {
    1.0 / (1.0 + (-z).exp())
}

impl ConfidenceModel {
    /// Probability that the pose is correct.
    pub fn confidence(&self, e: &Evidence) -> f64 {
        let x = e.features();
        sigmoid((0..4).map(|i| self.weights[i] * x[i]).sum())
    }

    /// Whether to accept the pose.
    pub fn accept(&self, e: &Evidence) -> bool {
        self.confidence(e) >= self.accept_threshold
    }

    /// Fits the weights on labelled samples (`true` = the pose was correct).
    pub fn fit(
        samples: &[(Evidence, bool)],
        accept_threshold: f64,
    ) -> Result<Self, CalibrationError> {
        if samples.is_empty() {
            return Err(CalibrationError::Empty);
        }
        let xs: Vec<[f64; 4]> = samples.iter().map(|(e, _)| e.features()).collect();
        for (i, x) in xs.iter().enumerate() {
            if x.iter().any(|v| !v.is_finite()) {
                return Err(CalibrationError::NonFinite { index: i });
            }
        }
        // Ridge on the slopes (feature units are ln-counts and ratios, O(1)): keeps separable
        // calibration sets — common, since wrong poses have few inliers — from driving the
        // weights to infinity. A weak prior on the bias keeps one-class sets finite.
        let ridge = 1.0;
        let bias_ridge = 1e-3;
        let mut w = [0.0f64; 4];
        for _ in 0..50 {
            let mut g = [0.0f64; 4];
            let mut h = [[0.0f64; 4]; 4];
            for (x, (_, label)) in xs.iter().zip(samples) {
                let p = sigmoid((0..4).map(|i| w[i] * x[i]).sum());
                let y = if *label { 1.0 } else { 0.0 };
                let s = (p * (1.0 - p)).max(1e-9);
                for i in 0..4 {
                    g[i] += (p - y) * x[i];
                    for j in 0..4 {
                        h[i][j] += s * x[i] * x[j];
                    }
                }
            }
            for i in 0..4 {
                let r = if i == 0 { bias_ridge } else { ridge };
                g[i] += r * w[i];
                h[i][i] += r;
            }
            let Some(step) = solve4(h, g) else { break };
            let mut max_step = 0.0f64;
            for i in 0..4 {
                w[i] -= step[i];
                max_step = max_step.max(step[i].abs());
            }
            if max_step < 1e-9 {
                break;
            }
        }
        Ok(Self {
            weights: w,
            accept_threshold,
        })
    }
}

/// Solves the 4×4 system `h x = g` by Gaussian elimination with partial pivoting.
fn solve4(mut h: [[f64; 4]; 4], mut g: [f64; 4]) -> Option<[f64; 4]> {
    for c in 0..4 {
        let p = (c..4).max_by(|&a, &b| h[a][c].abs().total_cmp(&h[b][c].abs()))?;
        if h[p][c].abs() < 1e-15 {
            return None;
        }
        h.swap(c, p);
        g.swap(c, p);
        for r in c + 1..4 {
            let f = h[r][c] / h[c][c];
            for k in c..4 {
                h[r][k] -= f * h[c][k];
            }
            g[r] -= f * g[c];
        }
    }
    let mut x = [0.0; 4];
    for r in (0..4).rev() {
        let s: f64 = (r + 1..4).map(|k| h[r][k] * x[k]).sum();
        x[r] = (g[r] - s) / h[r][r];
    }
    Some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ev(inliers: usize, ratio: f64) -> Evidence {
        Evidence {
            inliers,
            inlier_ratio: ratio,
            matches: (inliers as f64 / ratio.max(1e-3)) as usize,
        }
    }

    #[test]
    fn learns_that_more_inliers_mean_correct() {
        // Correct when ≥ 30 inliers, with some label noise near the boundary.
        let mut samples = Vec::new();
        for k in 0..200 {
            let inliers = 5 + (k * 7) % 200;
            let ratio = 0.05 + (k % 10) as f64 * 0.05;
            let label = inliers >= 30 || (inliers >= 25 && k % 3 == 0);
            samples.push((ev(inliers, ratio), label));
        }
        let m = ConfidenceModel::fit(&samples, 0.5).unwrap();
        assert!(m.confidence(&ev(150, 0.3)) > 0.95);
        assert!(m.confidence(&ev(8, 0.3)) < 0.05);
        assert!(m.confidence(&ev(60, 0.3)) > m.confidence(&ev(40, 0.3)));
        assert!(m.accept(&ev(100, 0.3)) && !m.accept(&ev(6, 0.3)));
    }

    #[test]
    fn degenerate_calibration_sets_stay_finite() {
        let all_good: Vec<_> = (0..20).map(|k| (ev(50 + k, 0.5), true)).collect();
        let m = ConfidenceModel::fit(&all_good, 0.5).unwrap();
        assert!(m.weights.iter().all(|w| w.is_finite()));
        assert!(m.confidence(&ev(60, 0.5)) > 0.9);
        assert_eq!(ConfidenceModel::fit(&[], 0.5), Err(CalibrationError::Empty));
        let bad = [(ev(10, f64::NAN), true)];
        // NaN ratio clamps to NaN → reported, not propagated.
        assert!(matches!(
            ConfidenceModel::fit(&bad, 0.5),
            Err(CalibrationError::NonFinite { index: 0 })
        ));
    }
}
