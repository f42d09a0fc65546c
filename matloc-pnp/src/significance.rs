//! A-contrario significance of a RANSAC consensus: could this many inliers be chance?
//!
//! The background model is the one of Moisan and Stival's a-contrario RANSAC (ORSA): wrong
//! matches land anywhere in the image, so a wrong match falls within the inlier radius of a
//! pose's projection with probability `p = π r² / (width · height)`. For `n` matches, a pose
//! from a minimal sample of `s` of them and `k` inliers (the sample included), the number of
//! false alarms is
//!
//! ```text
//! NFA = (n − s) · C(n, k) · C(k, s) · p^(k − s)
//! ```
//!
//! — the expected number of consensus sets at least this large that pure chance would produce
//! over all the ways of choosing them. `NFA < 1` means the consensus is unlikely to be noise,
//! whatever a learned confidence says: a confidence calibrated on a few dozen attempts cannot
//! tell 8 chance inliers out of 25 matches from 8 real ones, this bound can.

/// Base-10 logarithm of the number of false alarms of a consensus of `inliers` among
/// `matches`, for a model fit to `sample_size` of them, when a chance match is an inlier with
/// probability `inlier_probability` (clamped to `(0, 1]`).
///
/// Returns `+∞` when the consensus is no larger than the minimal sample (it then says
/// nothing) or when the inputs are inconsistent (`inliers > matches`).
pub fn log10_nfa(
    matches: usize,
    inliers: usize,
    sample_size: usize,
    inlier_probability: f64,
) -> f64 {
    if inliers <= sample_size || inliers > matches || !(inlier_probability > 0.0) {
        return f64::INFINITY;
    }
    let p = inlier_probability.min(1.0);
    let tests = (matches - sample_size) as f64;
    let ln = tests.ln()
        + ln_choose(matches, inliers)
        + ln_choose(inliers, sample_size)
        + (inliers - sample_size) as f64 * p.ln();
    ln / std::f64::consts::LN_10
}

/// Probability that a chance match lands within `radius_px` of its predicted pixel in a
/// `width × height` image: the disc's area over the image's, at most 1. When matches were
/// restricted to an image-space window of radius `window_px` around each point's predicted
/// pixel, a chance match lands anywhere in that disc instead, so the probability is the
/// larger of `(radius / window)²` and the whole-image one.
pub fn chance_inlier_probability(
    radius_px: f64,
    width: u32,
    height: u32,
    window_px: Option<f64>,
) -> f64 {
    let area = width as f64 * height as f64;
    if !(area > 0.0) {
        return 1.0;
    }
    let image = (std::f64::consts::PI * radius_px * radius_px / area).min(1.0);
    match window_px {
        Some(w) if w > 0.0 => image.max((radius_px / w).powi(2).min(1.0)),
        _ => image,
    }
}

/// `ln C(n, k)` by summing logarithms (exact enough for the counts of one image's matches,
/// and no gamma function needed).
fn ln_choose(n: usize, k: usize) -> f64 {
    let k = k.min(n - k);
    (0..k)
        .map(|i| ((n - i) as f64).ln() - ((i + 1) as f64).ln())
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn choose_matches_small_cases() {
        assert!((ln_choose(5, 2) - 10f64.ln()).abs() < 1e-12);
        assert!((ln_choose(25, 8) - 1_081_575f64.ln()).abs() < 1e-9);
        assert_eq!(ln_choose(7, 0), 0.0);
        assert_eq!(ln_choose(7, 7), 0.0);
    }

    #[test]
    fn noise_level_consensus_is_not_significant_and_a_real_one_is() {
        // 160×120 query, 3-cell (12 px) radius: p ≈ 0.024.
        let p = chance_inlier_probability(12.0, 160, 120, None);
        assert!((p - 0.02356).abs() < 1e-4);
        // 6 or 7 of 25 matches: what the tiny map's wrong places give.
        assert!(log10_nfa(25, 6, 3, p) > 1.0);
        assert!(log10_nfa(25, 7, 3, p) > 0.5);
        // 12 of 25 is beyond chance.
        assert!(log10_nfa(25, 12, 3, p) < -1.0);
        // A 320×240 map with 60 of 200 inliers: overwhelming.
        let p = chance_inlier_probability(12.0, 320, 240, None);
        assert!(log10_nfa(200, 60, 3, p) < -50.0);
    }

    #[test]
    fn a_window_raises_the_chance_probability() {
        let image = std::f64::consts::PI * 12.0 * 12.0 / (160.0 * 120.0);
        assert_eq!(chance_inlier_probability(12.0, 160, 120, None), image);
        // 32 px window: (12 / 32)² = 0.14, six times the whole-image 0.024.
        let w = chance_inlier_probability(12.0, 160, 120, Some(32.0));
        assert!((w - 0.140625).abs() < 1e-12);
        // A window larger than the image changes nothing.
        assert_eq!(chance_inlier_probability(12.0, 160, 120, Some(1e4)), image);
        assert_eq!(chance_inlier_probability(12.0, 160, 120, Some(5.0)), 1.0);
    }

    #[test]
    fn degenerate_inputs_are_never_significant() {
        assert_eq!(log10_nfa(10, 3, 3, 0.01), f64::INFINITY);
        assert_eq!(log10_nfa(10, 11, 3, 0.01), f64::INFINITY);
        assert_eq!(log10_nfa(10, 5, 3, 0.0), f64::INFINITY);
        assert_eq!(log10_nfa(10, 5, 3, f64::NAN), f64::INFINITY);
        assert_eq!(chance_inlier_probability(1e6, 10, 10, None), 1.0);
        assert_eq!(chance_inlier_probability(3.0, 0, 10, None), 1.0);
    }

    proptest! {
        #[test]
        fn more_inliers_of_the_same_matches_are_more_significant(
            n in 10usize..400, k in 4usize..400, p in 1e-4f64..0.05,
        ) {
            // While the consensus is a minority of matches at small p, each extra inlier
            // multiplies the NFA by ~ (n − k) / (k − s) · p < 1.
            prop_assume!(k < n && (n - k) as f64 * p < (k - 3) as f64 * 0.5);
            prop_assert!(log10_nfa(n, k + 1, 3, p) < log10_nfa(n, k, 3, p));
        }

        #[test]
        fn a_larger_inlier_radius_is_less_significant(
            n in 10usize..400, k in 4usize..400, p in 1e-4f64..0.5, f in 1.01f64..4.0,
        ) {
            prop_assume!(k <= n);
            prop_assert!(log10_nfa(n, k, 3, (p * f).min(1.0)) >= log10_nfa(n, k, 3, p));
        }
    }
}
