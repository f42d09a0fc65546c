//! Generic LO-RANSAC in the shape of COLMAP / kornia-rs: an [`Estimator`] (what is fitted), a
//! [`Sampler`] (which minimal samples are drawn) and MSAC consensus with adaptive termination
//! and local optimisation.

use rand::seq::SliceRandom;
use rand::{Rng, RngCore};
use serde::{Deserialize, Serialize};

/// A model family that RANSAC can fit: minimal and non-minimal solvers plus residuals.
pub trait Estimator {
    /// The hypothesis type.
    type Model: Clone;

    /// Number of data points a minimal sample needs.
    fn min_sample_size(&self) -> usize;

    /// Number of data points.
    fn num_data(&self) -> usize;

    /// Appends every model (typically up to 4 for P3P) consistent with a minimal sample;
    /// degenerate samples append nothing.
    fn fit_minimal(&self, sample: &[usize], models: &mut Vec<Self::Model>);

    /// Fits one model to a larger set of data points, optionally starting from `initial`.
    fn fit_nonminimal(
        &self,
        indices: &[usize],
        initial: Option<&Self::Model>,
    ) -> Option<Self::Model>;

    /// Squared residual of one data point, in the units of the threshold (pixels²).
    fn squared_residual(&self, model: &Self::Model, index: usize) -> f64;

    /// MSAC score `Σ min(e², τ²)` and inlier count of a model over all data, or `None` once the
    /// partial score reaches `bound` (the model cannot beat the best one).
    ///
    /// The default loops over [`Estimator::squared_residual`]; scoring dominates RANSAC's run
    /// time at high outlier ratios, so an estimator may override it with a faster loop.
    fn score(&self, model: &Self::Model, threshold_sq: f64, bound: f64) -> Option<(f64, usize)> {
        let mut score = 0.0;
        let mut inliers = 0;
        for i in 0..self.num_data() {
            let e = self.squared_residual(model, i);
            if e < threshold_sq {
                score += e;
                inliers += 1;
            } else {
                score += threshold_sq;
            }
            if score >= bound {
                return None;
            }
        }
        Some((score, inliers))
    }
}

/// Draws minimal samples (indices into the data, without repetition).
pub trait Sampler {
    /// Fills `sample` with distinct indices below the number of data points.
    fn sample(&mut self, rng: &mut dyn RngCore, sample: &mut [usize]);

    /// The most recent sample came from the first `pool_size()` entries of [`Sampler::order`].
    ///
    /// Adaptive termination uses it: the chance that a sample was all-inlier depends on the
    /// inlier ratio within the pool it was drawn from, not in the whole data.
    fn pool_size(&self) -> usize;

    /// Data indices in priority order; `None` means the identity (uniform samplers).
    fn order(&self) -> Option<&[usize]> {
        None
    }
}

/// Uniform sampling without replacement.
#[derive(Clone, Debug)]
pub struct UniformSampler {
    num_data: usize,
}

impl UniformSampler {
    /// A sampler over `num_data` points.
    ///
    /// Sampling panics if `num_data` is below the requested sample size.
    pub fn new(num_data: usize) -> Self {
        Self { num_data }
    }
}

/// Fills `sample` with distinct indices drawn uniformly from `0..n` (rejection; samples are tiny).
///
/// Panics when `n < sample.len()` (no such sample exists; [`ransac`] never asks for one).
fn distinct_uniform(rng: &mut dyn RngCore, n: usize, sample: &mut [usize]) {
    assert!(
        n >= sample.len(),
        "cannot draw {} distinct indices from {n}",
        sample.len()
    );
    for k in 0..sample.len() {
        loop {
            let candidate = rng.random_range(0..n);
            if !sample[..k].contains(&candidate) {
                sample[k] = candidate;
                break;
            }
        }
    }
}

impl Sampler for UniformSampler {
    fn sample(&mut self, rng: &mut dyn RngCore, sample: &mut [usize]) {
        distinct_uniform(rng, self.num_data, sample);
    }

    fn pool_size(&self) -> usize {
        self.num_data
    }
}

/// PROSAC (Chum & Matas, CVPR 2005): samples first from the best-scored matches and grows the
/// pool following the schedule of the paper, degrading to uniform sampling after
/// `growth_max_samples` draws.
#[derive(Clone, Debug)]
pub struct ProsacSampler {
    /// Data indices sorted by decreasing score.
    order: Vec<usize>,
    sample_size: usize,
    /// Current pool size.
    pool: usize,
    /// Samples drawn so far.
    drawn: usize,
    /// Expected number of samples (real-valued T_n of the paper) for the current pool.
    t_n: f64,
    /// Integer schedule T'_n at which the pool grows.
    t_n_prime: usize,
}

impl ProsacSampler {
    /// A sampler for matches with the given quality scores (higher is better).
    ///
    /// `growth_max_samples` is the paper's `T_N`: after that many samples every match is in the
    /// pool.
    pub fn new(scores: &[f64], sample_size: usize, growth_max_samples: usize) -> Self {
        let n = scores.len();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]));
        let m = sample_size.min(n);
        // T_m = T_N · C(m, m) / C(N, m).
        let mut t_n = growth_max_samples.max(1) as f64;
        for i in 0..m {
            t_n *= (m - i) as f64 / (n - i) as f64;
        }
        Self {
            order,
            sample_size: m,
            pool: m,
            drawn: 0,
            t_n,
            t_n_prime: 1,
        }
    }
}

impl Sampler for ProsacSampler {
    fn sample(&mut self, rng: &mut dyn RngCore, sample: &mut [usize]) {
        let n = self.order.len();
        let m = self.sample_size;
        self.drawn += 1;
        if self.drawn > self.t_n_prime && self.pool < n {
            let next = self.t_n * (self.pool + 1) as f64 / (self.pool + 1 - m) as f64;
            self.t_n_prime += ((next - self.t_n).ceil() as usize).max(1);
            self.t_n = next;
            self.pool += 1;
        }
        if self.t_n_prime < self.drawn || self.pool <= m || sample.len() != m {
            distinct_uniform(rng, self.pool, sample);
        } else {
            // m − 1 from the pool without its newest member, plus the newest member.
            let last = sample.len() - 1;
            distinct_uniform(rng, self.pool - 1, &mut sample[..last]);
            sample[last] = self.pool - 1;
        }
        for s in sample.iter_mut() {
            *s = self.order[*s];
        }
    }

    fn pool_size(&self) -> usize {
        self.pool
    }

    fn order(&self) -> Option<&[usize]> {
        Some(&self.order)
    }
}

/// How minimal samples are drawn.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SamplerKind {
    /// PROSAC when match scores are given, uniform otherwise.
    #[default]
    Auto,
    /// Always uniform, scores ignored.
    Uniform,
    /// PROSAC ordered by the scores (uniform when none are given).
    Prosac,
}

/// RANSAC options (plain data: `Default` + serde).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RansacOptions {
    /// Inlier threshold on the reprojection error, pixels.
    pub max_error_px: f64,
    /// Probability of having drawn at least one all-inlier sample when stopping.
    pub confidence: f64,
    /// Fewest iterations, whatever the confidence says.
    pub min_iterations: usize,
    /// Most iterations.
    pub max_iterations: usize,
    /// Fewest inliers for a pose to be returned (otherwise [`crate::PnpError::NoConsensus`]).
    pub min_inliers: usize,
    /// Whether to run local optimisation when a new best model is found.
    pub local_optimization: bool,
    /// Most refit rounds per local optimisation.
    pub lo_iterations: usize,
    /// Candidates for a local refit lie within this multiple of `max_error_px`.
    pub lo_threshold_factor: f64,
    /// Sampling strategy.
    pub sampler: SamplerKind,
    /// PROSAC's `T_N`: samples after which it has grown to all matches.
    pub prosac_growth_samples: usize,
    /// Wald's sequential probability ratio test (Chum & Matas, "Optimal Randomized RANSAC",
    /// 2008): hypotheses are verified on the data in random order and dropped as soon as the
    /// likelihood ratio says "bad", typically after a few dozen points; termination accounts
    /// for the (≤ 1/A) chance of dropping a good one.
    pub sprt: bool,
}

impl Default for RansacOptions {
    fn default() -> Self {
        Self {
            max_error_px: 3.0,
            confidence: 0.9999,
            min_iterations: 50,
            max_iterations: 10_000,
            min_inliers: 6,
            local_optimization: true,
            lo_iterations: 3,
            lo_threshold_factor: 2.0,
            sampler: SamplerKind::Auto,
            prosac_growth_samples: 20_000,
            sprt: true,
        }
    }
}

/// What a RANSAC run found.
#[derive(Clone, Debug)]
pub struct RansacOutput<M> {
    /// Best model, `None` when no sample produced one better than "all outliers".
    pub model: Option<M>,
    /// MSAC score `Σ min(e², τ²)` of the best model (pixels²; lower is better).
    pub score: f64,
    /// Inliers of the best model.
    pub num_inliers: usize,
    /// Samples drawn.
    pub iterations: usize,
    /// Hypotheses produced by the minimal solver over all samples.
    pub num_hypotheses: usize,
    /// Local optimisations run.
    pub local_optimizations: usize,
}

/// Number of samples needed so that an all-inlier sample has been drawn with probability
/// `confidence`, given `num_inliers` of `num_data` (sampling without replacement).
pub fn required_iterations(
    num_inliers: usize,
    num_data: usize,
    sample_size: usize,
    confidence: f64,
) -> f64 {
    if num_inliers < sample_size || num_data < sample_size {
        return f64::INFINITY;
    }
    let mut p_good = 1.0;
    for i in 0..sample_size {
        p_good *= (num_inliers - i) as f64 / (num_data - i) as f64;
    }
    if p_good >= 1.0 - 1e-15 {
        return 0.0;
    }
    ((1.0 - confidence).ln() / (1.0 - p_good).ln()).ceil()
}

/// `ln P(a sample of size m from the first `pool` entries does not yield an accepted
/// all-inlier model)`, sampling without replacement; `inlier_prefix[k]` counts inliers among
/// the first `k` entries and `accept` is the chance that verification keeps a good model.
fn log_miss_probability(inlier_prefix: &[u32], pool: usize, m: usize, accept: f64) -> f64 {
    let inliers = inlier_prefix[pool] as usize;
    if inliers < m {
        return 0.0;
    }
    let mut p_good = 1.0;
    for i in 0..m {
        p_good *= (inliers - i) as f64 / (pool - i) as f64;
    }
    (1.0 - p_good * accept).max(0.0).ln()
}

/// State of the sequential probability ratio test.
struct Sprt {
    /// Probability that a point is consistent with a bad model (estimated from rejections).
    delta: f64,
    /// Probability that a point is consistent with a good model (best inlier ratio so far).
    epsilon: f64,
    /// Decision threshold on the likelihood ratio; infinite while the test is off.
    a: f64,
    /// Likelihood-ratio factors for a consistent and an inconsistent point.
    consistent_factor: f64,
    inconsistent_factor: f64,
    tested: f64,
    consistent: f64,
    rejections: usize,
}

/// Cost of generating the hypotheses of one sample, in single-point verifications
/// (P3P ≈ 0.4 µs against a few ns per residual), and hypotheses per sample.
const SPRT_SAMPLE_COST: f64 = 200.0;
const SPRT_MODELS_PER_SAMPLE: f64 = 2.0;

impl Sprt {
    fn new() -> Self {
        Self {
            delta: 0.01,
            epsilon: 0.0,
            a: f64::INFINITY,
            consistent_factor: 1.0,
            inconsistent_factor: 1.0,
            tested: 0.0,
            consistent: 0.0,
            rejections: 0,
        }
    }

    /// Recomputes the threshold A (Chum & Matas, eq. 2: A = K + 1 + ln A).
    fn update(&mut self, epsilon: f64) {
        self.epsilon = epsilon;
        let (d, e) = (self.delta, epsilon);
        // The test only discriminates when good models explain clearly more points.
        if !(e > 1.5 * d) || e >= 1.0 {
            self.a = f64::INFINITY;
            return;
        }
        let c = (1.0 - d) * ((1.0 - d) / (1.0 - e)).ln() + d * (d / e).ln();
        let k = SPRT_SAMPLE_COST / (SPRT_MODELS_PER_SAMPLE * c);
        let mut a = k + 1.0;
        for _ in 0..10 {
            a = k + 1.0 + a.ln();
        }
        self.a = a;
        self.consistent_factor = d / e;
        self.inconsistent_factor = (1.0 - d) / (1.0 - e);
    }

    /// Probability that a good model survives the test.
    fn acceptance(&self) -> f64 {
        1.0 - 1.0 / self.a
    }

    fn record_rejection(&mut self, tested: usize, consistent: usize) {
        self.tested += tested as f64;
        self.consistent += consistent as f64;
        self.rejections += 1;
        if self.rejections.is_multiple_of(64) {
            self.delta = (self.consistent / self.tested).clamp(1e-4, 0.5);
            self.update(self.epsilon);
        }
    }
}

enum Verdict {
    /// Fully scored and better than the bound.
    Scored(f64, usize),
    /// The exact MSAC bound was reached.
    Bound,
    /// SPRT rejected the model after `tested` points, `consistent` of them inliers.
    Rejected { tested: usize, consistent: usize },
}

/// MSAC scoring in the order `order` with the SPRT early rejection.
fn verify<E: Estimator>(
    estimator: &E,
    model: &E::Model,
    order: &[usize],
    threshold_sq: f64,
    bound: f64,
    sprt: &Sprt,
) -> Verdict {
    let mut score = 0.0;
    let mut inliers = 0;
    let mut lambda = 1.0;
    for (k, &i) in order.iter().enumerate() {
        let e = estimator.squared_residual(model, i);
        if e < threshold_sq {
            score += e;
            inliers += 1;
            lambda *= sprt.consistent_factor;
        } else {
            score += threshold_sq;
            lambda *= sprt.inconsistent_factor;
            if lambda > sprt.a {
                return Verdict::Rejected {
                    tested: k + 1,
                    consistent: inliers,
                };
            }
        }
        if score >= bound {
            return Verdict::Bound;
        }
    }
    Verdict::Scored(score, inliers)
}

/// Runs LO-RANSAC with MSAC scoring.
///
/// Termination is adaptive: sampling stops (after `min_iterations`, at most `max_iterations`)
/// once, given the best model's inliers, the probability that no drawn sample was all-inlier
/// falls below `1 − confidence`. Each sample counts with the inlier ratio of the pool it was
/// drawn from, so PROSAC's early, inlier-rich samples earn their due and it stops sooner. On each new best model, local optimisation refits on the
/// points within `lo_threshold_factor × max_error_px` (up to `lo_iterations` rounds while the
/// score improves).
pub fn ransac<E: Estimator, S: Sampler + ?Sized>(
    estimator: &E,
    sampler: &mut S,
    options: &RansacOptions,
    rng: &mut dyn RngCore,
) -> RansacOutput<E::Model> {
    let n = estimator.num_data();
    let m = estimator.min_sample_size();
    let threshold_sq = options.max_error_px * options.max_error_px;
    let lo_threshold_sq = threshold_sq * options.lo_threshold_factor * options.lo_threshold_factor;
    // A model must beat "every point is an outlier".
    let mut best_score = n as f64 * threshold_sq;
    let mut best: Option<E::Model> = None;
    let mut best_inliers = 0;
    let mut out = RansacOutput {
        model: None,
        score: best_score,
        num_inliers: 0,
        iterations: 0,
        num_hypotheses: 0,
        local_optimizations: 0,
    };
    if n < m || m == 0 {
        return out;
    }
    let log_miss_target = (1.0 - options.confidence).ln();
    // Σ over drawn samples of ln P(sample not all-inlier | best model's inliers), kept per pool
    // size so it can be re-evaluated whenever the best model (and so the inlier set) changes.
    let mut pool_history: Vec<(usize, usize)> = Vec::new();
    let mut inlier_prefix: Vec<u32> = vec![0; n + 1];
    let mut log_miss = 0.0;
    let mut accept = 1.0;
    let mut best_minimal_inliers = 0;
    let mut sample = vec![0usize; m];
    let mut models = Vec::with_capacity(4);
    let mut candidates = Vec::new();
    // SPRT needs the points in random order (inputs are often sorted, e.g. by score).
    let mut order: Vec<usize> = (0..n).collect();
    let mut sprt = Sprt::new();
    if options.sprt {
        order.shuffle(rng);
    }
    while out.iterations < options.max_iterations {
        if out.iterations >= options.min_iterations && log_miss <= log_miss_target {
            break;
        }
        out.iterations += 1;
        sampler.sample(rng, &mut sample);
        let pool = sampler.pool_size().clamp(m, n);
        match pool_history.last_mut() {
            Some((p, count)) if *p == pool => *count += 1,
            _ => pool_history.push((pool, 1)),
        }
        models.clear();
        estimator.fit_minimal(&sample, &mut models);
        out.num_hypotheses += models.len();
        let mut improved = false;
        for model in &models {
            let verdict = if options.sprt && sprt.a.is_finite() {
                verify(estimator, model, &order, threshold_sq, best_score, &sprt)
            } else {
                match estimator.score(model, threshold_sq, best_score) {
                    Some((score, inliers)) => Verdict::Scored(score, inliers),
                    None => Verdict::Bound,
                }
            };
            match verdict {
                Verdict::Scored(score, inliers) => {
                    best_score = score;
                    best_inliers = inliers;
                    best_minimal_inliers = best_minimal_inliers.max(inliers);
                    best = Some(model.clone());
                    improved = true;
                }
                Verdict::Rejected { tested, consistent } => {
                    sprt.record_rejection(tested, consistent)
                }
                Verdict::Bound => {}
            }
        }
        if !improved {
            log_miss += log_miss_probability(&inlier_prefix, pool, m, accept);
            continue;
        }
        if options.local_optimization {
            out.local_optimizations += 1;
            for _ in 0..options.lo_iterations {
                let Some(current) = best.as_ref() else { break };
                candidates.clear();
                candidates.extend(
                    (0..n).filter(|&i| estimator.squared_residual(current, i) < lo_threshold_sq),
                );
                if candidates.len() <= m {
                    break;
                }
                let Some(refit) = estimator.fit_nonminimal(&candidates, Some(current)) else {
                    break;
                };
                match estimator.score(&refit, threshold_sq, best_score) {
                    Some((score, inliers)) => {
                        best_score = score;
                        best_inliers = inliers;
                        best = Some(refit);
                    }
                    None => break,
                }
            }
        }
        if let Some(current) = best.as_ref() {
            let order = sampler.order();
            let mut count = 0u32;
            for k in 0..n {
                let i = order.map_or(k, |o| o[k]);
                if estimator.squared_residual(current, i) < threshold_sq {
                    count += 1;
                }
                inlier_prefix[k + 1] = count;
            }
            if options.sprt {
                // ε from unrefined hypotheses: a good minimal sample explains fewer points than
                // the locally optimised model, and must not be judged against the latter.
                sprt.update(best_minimal_inliers as f64 / n as f64);
            }
            accept = if options.sprt { sprt.acceptance() } else { 1.0 };
            log_miss = pool_history
                .iter()
                .map(|&(p, c)| c as f64 * log_miss_probability(&inlier_prefix, p, m, accept))
                .sum();
        }
    }
    out.model = best;
    out.score = best_score;
    out.num_inliers = best_inliers;
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn samplers_draw_distinct_valid_indices() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let scores: Vec<f64> = (0..50).map(|i| i as f64).collect();
        let mut prosac = ProsacSampler::new(&scores, 3, 1000);
        let mut uniform = UniformSampler::new(50);
        let mut s = [0usize; 3];
        let mut early_max = 0;
        for it in 0..2000 {
            prosac.sample(&mut rng, &mut s);
            assert!(s[0] != s[1] && s[1] != s[2] && s[0] != s[2] && s.iter().all(|&i| i < 50));
            if it < 5 {
                // Early PROSAC samples come from the best-scored matches (highest indices here).
                early_max = early_max.max(50 - s.iter().min().unwrap());
            }
            uniform.sample(&mut rng, &mut s);
            assert!(s[0] != s[1] && s[1] != s[2] && s[0] != s[2] && s.iter().all(|&i| i < 50));
        }
        assert!(
            early_max <= 8,
            "early PROSAC samples reach rank {early_max}"
        );
    }

    #[test]
    fn required_iterations_matches_the_formula() {
        assert_eq!(required_iterations(100, 100, 3, 0.9999), 0.0);
        let k = required_iterations(20, 100, 3, 0.99);
        // p = 20·19·18 / (100·99·98)
        let p: f64 = 20.0 * 19.0 * 18.0 / (100.0 * 99.0 * 98.0);
        assert_eq!(k, ((0.01f64).ln() / (1.0 - p).ln()).ceil());
        assert!(required_iterations(2, 100, 3, 0.99).is_infinite());
    }
}
