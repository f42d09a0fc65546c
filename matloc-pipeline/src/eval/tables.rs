//! Evaluation of localization runs: accuracy, refusals and timing per method, in the layout of
//! the paper's Table 1 (accuracy) and Table 2 (iterations, time).
//!
//! Medians over *all* queries count a refused query as an infinite error (so a method cannot
//! improve its median by refusing hard queries); the medians over accepted queries are reported
//! alongside. A *false accept* is an accepted pose outside the loosest recall threshold.

use matloc_core::Pose;
use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use serde::{Deserialize, Serialize};

/// A recall threshold: both errors must be within.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecallThreshold {
    /// Translation threshold, metres.
    pub translation_m: f64,
    /// Rotation threshold, degrees.
    pub rotation_deg: f64,
}

/// The default thresholds reported for every method: (0.25 m, 2°), (0.5 m, 5°) — the common
/// pair of the visual-localization benchmarks —, the paper's (1 m, 5°), and (5 m, 10°).
pub const RECALL_THRESHOLDS: [RecallThreshold; 4] = [
    RecallThreshold {
        translation_m: 0.25,
        rotation_deg: 2.0,
    },
    RecallThreshold {
        translation_m: 0.5,
        rotation_deg: 5.0,
    },
    RecallThreshold {
        translation_m: 1.0,
        rotation_deg: 5.0,
    },
    RecallThreshold {
        translation_m: 5.0,
        rotation_deg: 10.0,
    },
];

impl RecallThreshold {
    /// Parses `T,R` (metres, degrees), e.g. `0.25,2`.
    pub fn parse(text: &str) -> Result<RecallThreshold, String> {
        let (t, r) = text
            .split_once(',')
            .ok_or_else(|| format!("threshold `{text}`: expected METRES,DEGREES"))?;
        let num = |v: &str, what: &str| -> Result<f64, String> {
            let x: f64 = v
                .trim()
                .parse()
                .map_err(|_| format!("threshold `{text}`: {what} `{v}` is not a number"))?;
            if x.is_finite() && x > 0.0 {
                Ok(x)
            } else {
                Err(format!(
                    "threshold `{text}`: {what} must be positive and finite"
                ))
            }
        };
        Ok(RecallThreshold {
            translation_m: num(t, "metres")?,
            rotation_deg: num(r, "degrees")?,
        })
    }

    /// The column label, e.g. `0.25 m, 2°`.
    pub fn label(&self) -> String {
        format!("{} m, {}°", self.translation_m, self.rotation_deg)
    }
}

/// The result of localizing one query with one method.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QueryOutcome {
    /// Query name (image file).
    pub name: String,
    /// Ground-truth pose.
    pub cam_from_world_gt: Pose,
    /// Estimated pose, or `None` when the method refused ("not localized").
    pub cam_from_world_est: Option<Pose>,
    /// Seconds per stage, in pipeline order (e.g. `place`, `render`, `encode`, `match`, `pnp`).
    #[serde(default)]
    pub stage_seconds: Vec<(String, f64)>,
    /// End-to-end seconds for the query.
    pub total_seconds: f64,
    /// Optimisation iterations, for iterative methods (iNeRF) or refinement passes.
    #[serde(default)]
    pub iterations: Option<u32>,
    /// The method's confidence in its answer, when it has one (MatLoc's calibrated model,
    /// the structure method's 1 − NFA).
    #[serde(default)]
    pub confidence: Option<f64>,
}

impl QueryOutcome {
    /// Translation (m) and rotation (°) errors, `None` when refused.
    pub fn errors(&self) -> Option<(f64, f64)> {
        self.cam_from_world_est.as_ref().map(|est| {
            (
                translation_error_m(est, &self.cam_from_world_gt),
                rotation_error_deg(est, &self.cam_from_world_gt),
            )
        })
    }
}

/// Summary of one method over a query set.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MethodSummary {
    /// Method name.
    pub method: String,
    /// Number of queries.
    pub queries: usize,
    /// Queries with a pose (not refused).
    pub accepted: usize,
    /// Median translation error over all queries (refused = ∞), metres.
    pub median_translation_m: f64,
    /// Median rotation error over all queries (refused = ∞), degrees.
    pub median_rotation_deg: f64,
    /// Median translation error over accepted queries (NaN when none), metres.
    pub median_translation_accepted_m: f64,
    /// Median rotation error over accepted queries (NaN when none), degrees.
    pub median_rotation_accepted_deg: f64,
    /// Fraction of all queries within each threshold (by default [`RECALL_THRESHOLDS`]).
    pub recall: Vec<(RecallThreshold, f64)>,
    /// Fraction of queries refused.
    pub refusal_rate: f64,
    /// Fraction of queries accepted with an error outside the loosest threshold.
    pub false_accept_rate: f64,
    /// Mean seconds per query.
    pub mean_seconds: f64,
    /// 95th percentile seconds per query.
    pub p95_seconds: f64,
    /// Mean seconds per stage (stages in first-seen order).
    pub stage_mean_seconds: Vec<(String, f64)>,
    /// Mean iterations, when the method reports them.
    pub mean_iterations: Option<f64>,
    /// How well the confidence predicts a correct answer, when the method reports one.
    #[serde(default)]
    pub reliability: Option<Reliability>,
}

/// Reliability of a confidence on a query set: equal-width bins of the confidence against
/// the fraction of correct answers in each (a reliability diagram), and the expected
/// calibration error. "Correct" is a returned pose within the loosest recall threshold (the
/// false-accept boundary); a refused query is never correct.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Reliability {
    /// Queries with a confidence.
    pub queries: usize,
    /// Expected calibration error: Σ over bins of (bin queries / queries) × |mean confidence
    /// − fraction correct|.
    pub ece: f64,
    /// The bins that hold at least one query, in increasing confidence.
    pub bins: Vec<ReliabilityBin>,
}

/// One bin of a [`Reliability`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReliabilityBin {
    /// Confidence range `[lower, upper)` (the last bin includes 1).
    pub lower: f64,
    /// Upper end of the range.
    pub upper: f64,
    /// Queries in the bin.
    pub queries: usize,
    /// Their mean confidence.
    pub mean_confidence: f64,
    /// The fraction of them answered correctly.
    pub fraction_correct: f64,
}

/// Equal-width confidence bins of [`Reliability`].
pub const RELIABILITY_BINS: usize = 10;

/// The reliability of `(confidence, correct)` pairs in [`RELIABILITY_BINS`] bins; `None` when
/// there are none. Confidences outside [0, 1] (or NaN) count in the nearest end bin.
pub fn reliability(samples: &[(f64, bool)]) -> Option<Reliability> {
    if samples.is_empty() {
        return None;
    }
    let nb = RELIABILITY_BINS;
    let mut sum_conf = vec![0.0; nb];
    let mut correct = vec![0usize; nb];
    let mut count = vec![0usize; nb];
    for &(c, ok) in samples {
        let c = if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) };
        let b = ((c * nb as f64) as usize).min(nb - 1);
        sum_conf[b] += c;
        correct[b] += usize::from(ok);
        count[b] += 1;
    }
    let n = samples.len() as f64;
    let mut ece = 0.0;
    let mut bins = Vec::new();
    for b in 0..nb {
        if count[b] == 0 {
            continue;
        }
        let k = count[b] as f64;
        let mean_confidence = sum_conf[b] / k;
        let fraction_correct = correct[b] as f64 / k;
        ece += k / n * (mean_confidence - fraction_correct).abs();
        bins.push(ReliabilityBin {
            lower: b as f64 / nb as f64,
            upper: (b + 1) as f64 / nb as f64,
            queries: count[b],
            mean_confidence,
            fraction_correct,
        });
    }
    Some(Reliability {
        queries: samples.len(),
        ece,
        bins,
    })
}

/// Median of finite-or-infinite values (NaN for an empty slice); the mean of the two middle
/// values for even counts, so ∞ appears only when at least half are ∞.
fn median_with_inf(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(|a, b| a.total_cmp(b));
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        let (a, b) = (values[n / 2 - 1], values[n / 2]);
        if b.is_infinite() { b } else { 0.5 * (a + b) }
    }
}

/// Nearest-rank percentile (`q` in `[0, 1]`) of non-empty values.
fn percentile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut v = values.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let rank = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len());
    v[rank - 1]
}

/// Summarises one method's outcomes at the default thresholds ([`RECALL_THRESHOLDS`]).
pub fn summarize(method: &str, outcomes: &[QueryOutcome]) -> MethodSummary {
    summarize_with(method, outcomes, &RECALL_THRESHOLDS)
}

/// Summarises one method's outcomes at `thresholds` (the loosest, by translation, defines a
/// false accept; none given means the defaults).
pub fn summarize_with(
    method: &str,
    outcomes: &[QueryOutcome],
    thresholds: &[RecallThreshold],
) -> MethodSummary {
    let thresholds = if thresholds.is_empty() {
        &RECALL_THRESHOLDS[..]
    } else {
        thresholds
    };
    let n = outcomes.len();
    let errors: Vec<Option<(f64, f64)>> = outcomes.iter().map(QueryOutcome::errors).collect();
    let accepted: Vec<(f64, f64)> = errors.iter().flatten().copied().collect();
    let mut t_all: Vec<f64> = errors
        .iter()
        .map(|e| e.map_or(f64::INFINITY, |e| e.0))
        .collect();
    let mut r_all: Vec<f64> = errors
        .iter()
        .map(|e| e.map_or(f64::INFINITY, |e| e.1))
        .collect();
    let mut t_acc: Vec<f64> = accepted.iter().map(|e| e.0).collect();
    let mut r_acc: Vec<f64> = accepted.iter().map(|e| e.1).collect();
    let frac = |count: usize| if n == 0 { 0.0 } else { count as f64 / n as f64 };
    let within =
        |e: &(f64, f64), th: &RecallThreshold| e.0 <= th.translation_m && e.1 <= th.rotation_deg;
    let recall = thresholds
        .iter()
        .map(|th| (*th, frac(accepted.iter().filter(|e| within(e, th)).count())))
        .collect();
    let loosest = *thresholds
        .iter()
        .max_by(|a, b| {
            (a.translation_m, a.rotation_deg)
                .partial_cmp(&(b.translation_m, b.rotation_deg))
                .unwrap_or(std::cmp::Ordering::Equal)
        })
        .expect("thresholds are not empty");
    let false_accepts = accepted.iter().filter(|e| !within(e, &loosest)).count();
    let confidences: Vec<(f64, bool)> = outcomes
        .iter()
        .zip(&errors)
        .filter_map(|(o, e)| {
            o.confidence
                .map(|c| (c, e.as_ref().is_some_and(|e| within(e, &loosest))))
        })
        .collect();
    let times: Vec<f64> = outcomes.iter().map(|o| o.total_seconds).collect();
    let mut stage_names: Vec<String> = Vec::new();
    for o in outcomes {
        for (s, _) in &o.stage_seconds {
            if !stage_names.contains(s) {
                stage_names.push(s.clone());
            }
        }
    }
    let stage_mean_seconds = stage_names
        .into_iter()
        .map(|s| {
            let total: f64 = outcomes
                .iter()
                .flat_map(|o| o.stage_seconds.iter())
                .filter(|(name, _)| *name == s)
                .map(|(_, t)| t)
                .sum();
            let mean = if n == 0 { 0.0 } else { total / n as f64 };
            (s, mean)
        })
        .collect();
    let iterations: Vec<f64> = outcomes
        .iter()
        .filter_map(|o| o.iterations.map(f64::from))
        .collect();
    MethodSummary {
        method: method.to_string(),
        queries: n,
        accepted: accepted.len(),
        median_translation_m: median_with_inf(&mut t_all),
        median_rotation_deg: median_with_inf(&mut r_all),
        median_translation_accepted_m: median_with_inf(&mut t_acc),
        median_rotation_accepted_deg: median_with_inf(&mut r_acc),
        recall,
        refusal_rate: frac(n - accepted.len()),
        false_accept_rate: frac(false_accepts),
        mean_seconds: if n == 0 {
            0.0
        } else {
            times.iter().sum::<f64>() / n as f64
        },
        p95_seconds: percentile(&times, 0.95),
        stage_mean_seconds,
        mean_iterations: if iterations.is_empty() {
            None
        } else {
            Some(iterations.iter().sum::<f64>() / iterations.len() as f64)
        },
        reliability: reliability(&confidences),
    }
}

/// Each method's confidence reliability as a markdown table (ECE, then the bins as
/// `confidence range: queries, mean confidence → fraction correct`); empty when no method
/// reports a confidence.
pub fn reliability_table(summaries: &[MethodSummary]) -> String {
    let mut s = String::new();
    for m in summaries {
        let Some(r) = &m.reliability else { continue };
        if s.is_empty() {
            s.push_str(
                "| method | queries | ECE | bins: range — queries, mean confidence → fraction correct |\n|---|---|---|---|\n",
            );
        }
        let bins: Vec<String> = r
            .bins
            .iter()
            .map(|b| {
                format!(
                    "[{:.1}, {:.1}) — {}, {:.2} → {:.2}",
                    b.lower, b.upper, b.queries, b.mean_confidence, b.fraction_correct
                )
            })
            .collect();
        s.push_str(&format!(
            "| {} | {} | {:.3} | {} |\n",
            m.method,
            r.queries,
            r.ece,
            bins.join("; ")
        ));
    }
    s
}

fn fmt_num(v: f64, decimals: usize) -> String {
    if v.is_nan() {
        "—".to_string()
    } else if v.is_infinite() {
        "∞".to_string()
    } else {
        format!("{v:.decimals$}")
    }
}

/// The paper's Table 1 layout (accuracy) as a markdown table.
pub fn accuracy_table(summaries: &[MethodSummary]) -> String {
    // Recall columns from the first summary's thresholds (all are summarised alike).
    let thresholds: Vec<RecallThreshold> = summaries
        .first()
        .map(|m| m.recall.iter().map(|(t, _)| *t).collect())
        .unwrap_or_else(|| RECALL_THRESHOLDS.to_vec());
    let mut s = String::from("| method | median t (m) | median r (°) | median t / r accepted |");
    for t in &thresholds {
        s.push_str(&format!(" recall {} |", t.label()));
    }
    s.push_str(" refused | false accept |\n|---|---|---|---|");
    s.push_str(&"---|".repeat(thresholds.len() + 2));
    s.push('\n');
    for m in summaries {
        let recall: Vec<String> = m
            .recall
            .iter()
            .map(|(_, r)| format!("{:.1} %", 100.0 * r))
            .collect();
        s.push_str(&format!(
            "| {} | {} | {} | {} / {} | {} | {:.1} % | {:.1} % |\n",
            m.method,
            fmt_num(m.median_translation_m, 3),
            fmt_num(m.median_rotation_deg, 3),
            fmt_num(m.median_translation_accepted_m, 3),
            fmt_num(m.median_rotation_accepted_deg, 3),
            recall.join(" | "),
            100.0 * m.refusal_rate,
            100.0 * m.false_accept_rate,
        ));
    }
    s
}

/// The paper's Table 2 layout (iterations and time) as a markdown table, with per-stage means.
pub fn timing_table(summaries: &[MethodSummary]) -> String {
    let mut s = String::from(
        "| method | iterations | mean s / query | p95 s / query | per stage (mean s) |\n|---|---|---|---|---|\n",
    );
    for m in summaries {
        let stages: Vec<String> = m
            .stage_mean_seconds
            .iter()
            .map(|(name, t)| format!("{name} {t:.3}"))
            .collect();
        s.push_str(&format!(
            "| {} | {} | {:.3} | {:.3} | {} |\n",
            m.method,
            m.mean_iterations
                .map_or("—".to_string(), |i| format!("{i:.0}")),
            m.mean_seconds,
            m.p95_seconds,
            stages.join(", "),
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn pose(x: f64, yaw_deg: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(x, 0.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_deg.to_radians()),
        )
    }

    fn outcome(err_m: Option<f64>, t: f64) -> QueryOutcome {
        QueryOutcome {
            name: "q".into(),
            cam_from_world_gt: pose(0.0, 0.0),
            cam_from_world_est: err_m.map(|e| pose(e, 0.0)),
            stage_seconds: vec![("match".into(), t / 2.0), ("pnp".into(), t / 2.0)],
            total_seconds: t,
            iterations: None,
            confidence: None,
        }
    }

    #[test]
    fn refusals_count_as_infinite_in_the_overall_median() {
        let outs = vec![
            outcome(Some(0.1), 1.0),
            outcome(Some(0.2), 1.0),
            outcome(None, 1.0),
            outcome(Some(9.0), 3.0),
        ];
        let s = summarize("m", &outs);
        assert_eq!(s.accepted, 3);
        assert!((s.median_translation_m - (0.2 + 9.0) / 2.0).abs() < 1e-9);
        assert!((s.median_translation_accepted_m - 0.2).abs() < 1e-9);
        assert_eq!(s.refusal_rate, 0.25);
        assert_eq!(s.false_accept_rate, 0.25);
        assert_eq!(s.recall[0].1, 0.5);
        assert_eq!(s.recall[3].1, 0.5);
        assert!((s.mean_seconds - 1.5).abs() < 1e-12);
        assert_eq!(s.p95_seconds, 3.0);
        assert_eq!(s.stage_mean_seconds[0].0, "match");
        assert!((s.stage_mean_seconds[1].1 - 0.75).abs() < 1e-12);
        let all_refused = summarize("r", &[outcome(None, 1.0), outcome(None, 1.0)]);
        assert!(all_refused.median_translation_m.is_infinite());
        assert!(all_refused.median_translation_accepted_m.is_nan());
        let table = accuracy_table(&[s, all_refused]);
        assert!(table.contains("| r | ∞ | ∞ | — / — |"), "{table}");
    }

    #[test]
    fn thresholds_are_configurable_and_the_loosest_defines_a_false_accept() {
        let outs = vec![
            outcome(Some(0.3), 1.0),
            outcome(Some(0.8), 1.0),
            outcome(Some(3.0), 1.0),
        ];
        let th = [
            RecallThreshold::parse("0.5,5").unwrap(),
            RecallThreshold::parse("2, 10").unwrap(),
        ];
        let s = summarize_with("m", &outs, &th);
        let got: Vec<f64> = s.recall.iter().map(|r| r.1).collect();
        assert_eq!(got, [1.0 / 3.0, 2.0 / 3.0]);
        assert!((s.false_accept_rate - 1.0 / 3.0).abs() < 1e-12);
        let table = accuracy_table(&[s]);
        assert!(
            table.contains("| recall 0.5 m, 5° | recall 2 m, 10° | refused |"),
            "{table}"
        );
        assert_eq!(table.lines().nth(1).unwrap().matches("---").count(), 8);
        // The defaults carry the common (0.5 m, 5°) next to the paper's three.
        let d = summarize("m", &outs);
        assert_eq!(d.recall.len(), 4);
        assert!(
            accuracy_table(&[d]).contains(
                "recall 0.25 m, 2° | recall 0.5 m, 5° | recall 1 m, 5° | recall 5 m, 10°"
            )
        );
        for bad in ["1", "a,2", "0,2", "1,-3", "1,inf"] {
            assert!(RecallThreshold::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn empty_input_summarises_without_panic() {
        let s = summarize("none", &[]);
        assert_eq!(s.queries, 0);
        assert!(s.median_translation_m.is_nan());
        assert!(timing_table(&[s]).contains("| none | — |"));
    }

    #[test]
    fn reliability_bins_confidence_against_correct_answers() {
        let mut samples = Vec::new();
        for k in 0..4 {
            samples.push((0.25, k == 0)); // mean 0.25, 1/4 correct
        }
        for k in 0..4 {
            samples.push((0.95, k < 2)); // mean 0.95, 2/4 correct: off by 0.45
        }
        let r = reliability(&samples).unwrap();
        assert_eq!(r.queries, 8);
        assert_eq!(r.bins.len(), 2);
        assert_eq!(r.bins[0].queries, 4);
        assert!((r.bins[0].lower - 0.2).abs() < 1e-12);
        assert!((r.bins[1].fraction_correct - 0.5).abs() < 1e-12);
        assert!((r.ece - 0.5 * 0.45).abs() < 1e-12, "{}", r.ece);
        // Ends and NaN land in the end bins; nothing means no reliability.
        let r = reliability(&[(1.0, true), (1.7, true), (-0.2, false), (f64::NAN, false)]).unwrap();
        assert_eq!(r.bins.len(), 2);
        assert!(r.ece.abs() < 1e-12);
        assert!(reliability(&[]).is_none());
    }

    #[test]
    fn a_refused_query_with_a_confidence_counts_as_wrong() {
        let mut outs = vec![outcome(Some(0.1), 1.0), outcome(None, 1.0)];
        outs[0].confidence = Some(0.9);
        outs[1].confidence = Some(0.1);
        let s = summarize("m", &outs);
        let r = s.reliability.as_ref().unwrap();
        assert_eq!(r.queries, 2);
        assert!((r.ece - 0.1).abs() < 1e-12, "{}", r.ece);
        assert!(reliability_table(&[s]).contains("| m | 2 | 0.100 |"));
        assert!(
            summarize("n", &[outcome(Some(0.1), 1.0)])
                .reliability
                .is_none()
        );
    }
}
