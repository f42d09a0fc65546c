//! A calibrated localization confidence: P(pose is correct | evidence), by logistic regression
//! on the solver's evidence, fitted at map-build time on held-out queries with known poses.
//!
//! "Correct" is defined by the caller when labelling the calibration set (the pipeline uses
//! within 5 m and 10°). Evidence features are the log inlier count, the inlier ratio, the log
//! match count and the feature-metric alignment contrast — all by-products of matching, PnP and
//! refinement. Fitted
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
    /// Feature-metric alignment contrast at the final pose (0 when not measured).
    #[serde(default)]
    pub alignment: f64,
}

/// Number of logistic features (bias included).
const NF: usize = 5;

impl Evidence {
    fn features(&self) -> [f64; NF] {
        [
            1.0,
            (1.0 + self.inliers as f64).ln(),
            self.inlier_ratio.clamp(0.0, 1.0),
            (1.0 + self.matches as f64).ln(),
            // Contrasts are ~0.1–0.2 for right poses and < 0.07 for wrong ones (small demo
            // map): scaled to O(1) like the other features, so one ridge fits all.
            10.0 * self.alignment,
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
#[serde(default, deny_unknown_fields)]
pub struct ConfidenceModel {
    /// Weights for (bias, ln(1+inliers), inlier ratio, ln(1+matches)).
    pub weights: [f64; 4],
    /// Weight of 10 × the feature-metric alignment contrast ([`Evidence::alignment`]); 0 in
    /// models calibrated before it existed.
    #[serde(default)]
    pub alignment_weight: f64,
    /// Queries with a confidence below this are refused ("not localized").
    pub accept_threshold: f64,
}

impl Default for ConfidenceModel {
    /// An uncalibrated prior: ~50 % at 12 inliers, rising with the inlier count and ratio.
    fn default() -> Self {
        Self {
            weights: [-6.0, 2.0, 2.0, 0.0],
            alignment_weight: 0.0,
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
        let w = self.all_weights();
        sigmoid((0..NF).map(|i| w[i] * x[i]).sum())
    }

    fn all_weights(&self) -> [f64; NF] {
        let w = &self.weights;
        [w[0], w[1], w[2], w[3], self.alignment_weight]
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
        let xs: Vec<[f64; NF]> = samples.iter().map(|(e, _)| e.features()).collect();
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
        let mut w = [0.0f64; NF];
        for _ in 0..50 {
            let mut g = [0.0f64; NF];
            let mut h = [[0.0f64; NF]; NF];
            for (x, (_, label)) in xs.iter().zip(samples) {
                let p = sigmoid((0..NF).map(|i| w[i] * x[i]).sum());
                let y = if *label { 1.0 } else { 0.0 };
                let s = (p * (1.0 - p)).max(1e-9);
                for i in 0..NF {
                    g[i] += (p - y) * x[i];
                    for j in 0..NF {
                        h[i][j] += s * x[i] * x[j];
                    }
                }
            }
            for i in 0..NF {
                let r = if i == 0 { bias_ridge } else { ridge };
                g[i] += r * w[i];
                h[i][i] += r;
            }
            let Some(step) = solve(h, g) else { break };
            let mut max_step = 0.0f64;
            for i in 0..NF {
                w[i] -= step[i];
                max_step = max_step.max(step[i].abs());
            }
            if max_step < 1e-9 {
                break;
            }
        }
        Ok(Self {
            weights: [w[0], w[1], w[2], w[3]],
            alignment_weight: w[4],
            accept_threshold,
        })
    }
}

/// Solves the system `h x = g` by Gaussian elimination with partial pivoting.
fn solve(mut h: [[f64; NF]; NF], mut g: [f64; NF]) -> Option<[f64; NF]> {
    for c in 0..NF {
        let p = (c..NF).max_by(|&a, &b| h[a][c].abs().total_cmp(&h[b][c].abs()))?;
        if h[p][c].abs() < 1e-15 {
            return None;
        }
        h.swap(c, p);
        g.swap(c, p);
        for r in c + 1..NF {
            let f = h[r][c] / h[c][c];
            for k in c..NF {
                h[r][k] -= f * h[c][k];
            }
            g[r] -= f * g[c];
        }
    }
    let mut x = [0.0; NF];
    for r in (0..NF).rev() {
        let s: f64 = (r + 1..NF).map(|k| h[r][k] * x[k]).sum();
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
            alignment: 0.0,
        }
    }

    #[test]
    fn learns_from_the_alignment_contrast() {
        // Same inlier counts for right and wrong poses; only the contrast separates them.
        let samples: Vec<_> = (0..100)
            .map(|k| {
                let ok = k % 2 == 0;
                let e = Evidence {
                    alignment: if ok { 0.12 + 0.001 * k as f64 } else { 0.02 },
                    ..ev(20 + k % 7, 0.2)
                };
                (e, ok)
            })
            .collect();
        let m = ConfidenceModel::fit(&samples, 0.5).unwrap();
        assert!(m.alignment_weight > 0.0);
        let with = |a: f64| Evidence {
            alignment: a,
            ..ev(22, 0.2)
        };
        assert!(m.accept(&with(0.15)) && !m.accept(&with(0.01)));
        // Models stored before the alignment feature read with weight 0.
        let old: ConfidenceModel =
            serde_json::from_str(r#"{"weights":[-6,2,2,0],"accept_threshold":0.5}"#).unwrap();
        assert_eq!(old.alignment_weight, 0.0);
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
