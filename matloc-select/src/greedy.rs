//! Selectors that target matching quality: greedy forward selection scored by mutual nearest
//! neighbours on the GT pairs among distractors, and a Fisher criterion with a redundancy
//! penalty.

use crate::error::SelectError;
use crate::pairs::PairSet;
use crate::{FeatureSelector, Selection, SelectionReport, check_budget};
use matloc_match::{FeatureStats, MnnConfig, Side, mnn_prepared, prepare_rows, tables};
use rand::RngCore;
use rand::seq::index::sample;
use serde::{Deserialize, Serialize};

/// What the matching-driven selector maximises.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum MatchScore {
    /// Fraction of MNN matches that are GT pairs. Alone it rewards degenerate dims (a constant
    /// dim yields a single, trivially "correct" match), hence not the default.
    MnnPrecision,
    /// Fraction of GT pairs recovered as MNN matches.
    MnnRecall,
    /// Harmonic mean of MNN precision and recall (default): what PnP needs is many correct
    /// matches at a high inlier ratio.
    #[default]
    MnnF1,
    /// Fraction of GT queries whose nearest map feature is their GT partner.
    Top1,
}

/// Settings of [`MatchingSelector`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MatchingSelectorConfig {
    /// Criterion.
    pub score: MatchScore,
    /// After the greedy pass, try replacing each selected dim by each unselected one and keep
    /// improvements, until no swap helps or `max_swap_rounds` passes are done.
    pub swap_refinement: bool,
    /// Maximum refinement passes.
    pub max_swap_rounds: usize,
    /// Stop adding dims when the best addition does not improve the score (else select exactly
    /// `N_s`).
    pub stop_when_no_gain: bool,
    /// Use at most this many pairs (random subset drawn with the injected RNG); 0 = all.
    pub max_pairs: usize,
    /// Use at most this many distractors per side; 0 = all.
    pub max_distractors: usize,
    /// Standardise dims with statistics of the (sub-sampled) features of both sides, as the map
    /// does at run time.
    pub standardise: bool,
    /// MNN settings (threshold, ratio test); its `stats` and `kernel` are ignored.
    pub mnn: MnnConfig,
}

impl Default for MatchingSelectorConfig {
    fn default() -> Self {
        MatchingSelectorConfig {
            score: MatchScore::MnnF1,
            swap_refinement: true,
            max_swap_rounds: 3,
            stop_when_no_gain: false,
            max_pairs: 4096,
            max_distractors: 4096,
            standardise: true,
            mnn: MnnConfig::default(),
        }
    }
}

/// Greedy forward selection (plus optional one-swap refinement) maximising a matching score of
/// the GT pairs among the distractors, computed with `matloc-match`'s MNN on the candidate dims.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MatchingSelector {
    /// Settings.
    pub config: MatchingSelectorConfig,
}

/// One matching problem: the first `pairs` query rows match the first `pairs` map rows, the
/// rest are distractors.
struct SubProblem {
    pairs: usize,
    query: Vec<f32>,
    map: Vec<f32>,
}

/// The sub-sampled problem a matching selector scores subsets on: one sub-problem per group of
/// pairs (or a single one), all standardised with the same statistics.
struct MatchProblem {
    dims: usize,
    subs: Vec<SubProblem>,
    stats: Option<FeatureStats>,
}

fn subsample(data: &[f32], dims: usize, max: usize, rng: &mut dyn RngCore) -> Vec<f32> {
    let rows = data.len() / dims;
    if max == 0 || rows <= max {
        return data.to_vec();
    }
    let mut idx = sample(rng, rows, max).into_vec();
    idx.sort_unstable();
    idx.iter()
        .flat_map(|&i| data[i * dims..(i + 1) * dims].iter().copied())
        .collect()
}

fn gather(src: &[f32], d: usize, idx: &[usize]) -> Vec<f32> {
    idx.iter()
        .flat_map(|&i| src[i * d..(i + 1) * d].iter().copied())
        .collect()
}

impl MatchProblem {
    fn new(pairs: &PairSet, cfg: &MatchingSelectorConfig, rng: &mut dyn RngCore) -> Self {
        let d = pairs.dims();
        let p = pairs.len();
        // Pair indices of each sub-problem.
        let mut members: Vec<Vec<usize>> = match pairs.groups() {
            Some(groups) => {
                let mut ids: Vec<u32> = groups.to_vec();
                ids.sort_unstable();
                ids.dedup();
                let mut by_group: Vec<Vec<usize>> = vec![Vec::new(); ids.len()];
                for (i, g) in groups.iter().enumerate() {
                    let k = ids.binary_search(g).expect("id collected above");
                    by_group[k].push(i);
                }
                // Whole groups in random order until the pair budget is used.
                let order = sample(rng, by_group.len(), by_group.len()).into_vec();
                let mut chosen = Vec::new();
                let mut total = 0;
                for k in order {
                    if cfg.max_pairs != 0 && total > 0 && total + by_group[k].len() > cfg.max_pairs
                    {
                        continue;
                    }
                    total += by_group[k].len();
                    chosen.push(std::mem::take(&mut by_group[k]));
                }
                chosen
            }
            None => {
                let mut idx: Vec<usize> = if cfg.max_pairs == 0 || p <= cfg.max_pairs {
                    (0..p).collect()
                } else {
                    sample(rng, p, cfg.max_pairs).into_vec()
                };
                idx.sort_unstable();
                vec![idx]
            }
        };
        members.retain(|m| !m.is_empty());
        let dq = subsample(pairs.distractors_2d(), d, cfg.max_distractors, rng);
        let dm = subsample(pairs.distractors_3d(), d, cfg.max_distractors, rng);
        let subs: Vec<SubProblem> = members
            .iter()
            .map(|idx| {
                let mut query = gather(pairs.f2d(), d, idx);
                let mut map = gather(pairs.f3d(), d, idx);
                query.extend_from_slice(&dq);
                map.extend_from_slice(&dm);
                SubProblem {
                    pairs: idx.len(),
                    query,
                    map,
                }
            })
            .collect();
        let stats = cfg.standardise.then(|| {
            let mut all = Vec::new();
            for s in &subs {
                all.extend_from_slice(&s.query);
                all.extend_from_slice(&s.map);
            }
            FeatureStats::from_features(&all, d)
        });
        MatchProblem {
            dims: d,
            subs,
            stats,
        }
    }

    fn score(&self, sel: &[usize], cfg: &MatchingSelectorConfig) -> Result<f64, SelectError> {
        let d = self.dims;
        let stats = self.stats.as_ref();
        let ds = sel.len();
        let (mut correct, mut matched, mut total) = (0usize, 0usize, 0usize);
        for sub in &self.subs {
            let qrows: Vec<usize> = (0..sub.query.len() / d).collect();
            let mrows: Vec<usize> = (0..sub.map.len() / d).collect();
            let q = prepare_rows(&sub.query, d, &qrows, sel, stats, true, Side::Query)?;
            let m = prepare_rows(&sub.map, d, &mrows, sel, stats, true, Side::Map)?;
            total += sub.pairs;
            if cfg.score == MatchScore::Top1 {
                let t = tables(
                    matloc_match::MnnKernel::Tiled,
                    &q,
                    qrows.len(),
                    &m,
                    mrows.len(),
                    ds,
                    false,
                );
                correct += (0..sub.pairs)
                    .filter(|&i| t.rows.arg[i] as usize == i)
                    .count();
                continue;
            }
            let mnn = MnnConfig {
                stats: None,
                kernel: matloc_match::MnnKernel::Tiled,
                ..cfg.mnn.clone()
            };
            let matches = mnn_prepared(&q, &m, ds, &mnn)?;
            matched += matches.len();
            correct += matches
                .iter()
                .filter(|x| x.query < sub.pairs && x.map == x.query)
                .count();
        }
        let total = total.max(1) as f64;
        if cfg.score == MatchScore::Top1 {
            return Ok(correct as f64 / total);
        }
        let correct = correct as f64;
        let precision = if matched == 0 {
            0.0
        } else {
            correct / matched as f64
        };
        let recall = correct / total;
        Ok(match cfg.score {
            MatchScore::MnnPrecision => precision,
            MatchScore::MnnRecall => recall,
            MatchScore::MnnF1 | MatchScore::Top1 => {
                if correct == 0.0 {
                    0.0
                } else {
                    2.0 * precision * recall / (precision + recall)
                }
            }
        })
    }
}

/// Greedy forward selection with optional one-swap refinement over any subset score (higher is
/// better). [`MatchingSelector`] scores subsets by MNN on GT pairs; callers with a costlier,
/// closer-to-use criterion (e.g. matching whole renders in an image window, or PnP) plug it in
/// here.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GreedySearch {
    /// After the greedy pass, try replacing each selected dim by each unselected one and keep
    /// improvements, until no swap helps or `max_swap_rounds` passes are done.
    pub swap_refinement: bool,
    /// Maximum refinement passes.
    pub max_swap_rounds: usize,
    /// Stop adding dims when the best addition does not improve the score (else select exactly
    /// `N_s`).
    pub stop_when_no_gain: bool,
}

impl Default for GreedySearch {
    fn default() -> Self {
        GreedySearch {
            swap_refinement: true,
            max_swap_rounds: 3,
            stop_when_no_gain: false,
        }
    }
}

/// What [`GreedySearch::run`] found.
#[derive(Clone, Debug, PartialEq)]
pub struct GreedyResult {
    /// Selected dims, ascending.
    pub dims: Vec<usize>,
    /// Score of the selection.
    pub score: f64,
    /// Score of every dim on its own (from the first greedy step).
    pub single: Vec<f64>,
    /// Subsets scored.
    pub evaluations: usize,
}

impl GreedySearch {
    /// Selects up to `n_s` of `d` dims maximising `score` (called with candidate subsets in
    /// insertion order, never empty). Ties go to the lowest dim index, so a deterministic
    /// score gives a deterministic selection.
    pub fn run<E>(
        &self,
        d: usize,
        n_s: usize,
        score: &mut dyn FnMut(&[usize]) -> Result<f64, E>,
    ) -> Result<GreedyResult, E> {
        let mut evaluations = 0usize;
        let mut selected: Vec<usize> = Vec::new();
        let mut current = f64::NEG_INFINITY;
        let mut single = vec![0.0f64; d];
        while selected.len() < n_s.min(d) {
            let mut best: Option<(usize, f64)> = None;
            for cand in 0..d {
                if selected.contains(&cand) {
                    continue;
                }
                let mut trial = selected.clone();
                trial.push(cand);
                let s = score(&trial)?;
                evaluations += 1;
                if selected.is_empty() {
                    single[cand] = s;
                }
                if best.is_none_or(|(_, bs)| s > bs) {
                    best = Some((cand, s));
                }
            }
            let Some((cand, s)) = best else { break };
            if self.stop_when_no_gain && !selected.is_empty() && s <= current {
                break;
            }
            selected.push(cand);
            current = s;
        }
        if self.swap_refinement {
            for _ in 0..self.max_swap_rounds {
                let mut improved = false;
                for slot in 0..selected.len() {
                    for cand in 0..d {
                        if selected.contains(&cand) {
                            continue;
                        }
                        let mut trial = selected.clone();
                        trial[slot] = cand;
                        let s = score(&trial)?;
                        evaluations += 1;
                        if s > current {
                            selected = trial;
                            current = s;
                            improved = true;
                        }
                    }
                }
                if !improved {
                    break;
                }
            }
        }
        selected.sort_unstable();
        Ok(GreedyResult {
            dims: selected,
            score: current,
            single,
            evaluations,
        })
    }
}

impl FeatureSelector for MatchingSelector {
    fn name(&self) -> &str {
        "greedy-mnn"
    }

    fn select(
        &self,
        pairs: &PairSet,
        n_s: usize,
        rng: &mut dyn RngCore,
    ) -> Result<Selection, SelectError> {
        check_budget(pairs, n_s)?;
        let cfg = &self.config;
        let prob = MatchProblem::new(pairs, cfg, rng);
        let search = GreedySearch {
            swap_refinement: cfg.swap_refinement,
            max_swap_rounds: cfg.max_swap_rounds,
            stop_when_no_gain: cfg.stop_when_no_gain,
        };
        let GreedyResult {
            dims: selected,
            score: current,
            single,
            evaluations,
        } = search.run(pairs.dims(), n_s, &mut |trial| prob.score(trial, cfg))?;
        Ok(Selection {
            dims: selected,
            report: SelectionReport {
                selector: self.name().to_string(),
                objective_name: format!("{:?} of MNN on GT pairs (maximised)", cfg.score),
                objective: current,
                per_dim_cost: single.iter().map(|s| -s).collect(),
                evaluations,
            },
        })
    }
}

/// Settings of [`FisherSelector`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FisherConfig {
    /// Weight of the redundancy penalty: the candidate's largest absolute correlation with an
    /// already selected dim, subtracted from its normalised Fisher score.
    pub redundancy_weight: f64,
    /// Added to the within-pair variance so noise-free dims do not divide by zero.
    pub epsilon: f64,
}

impl Default for FisherConfig {
    fn default() -> Self {
        FisherConfig {
            redundancy_weight: 0.5,
            epsilon: 1e-9,
        }
    }
}

/// Discriminative per-dim criterion: Fisher ratio of between-pair variance (variance over pairs
/// of the pair means) to within-pair variance (half the mean squared 2D–3D difference), chosen
/// greedily with an mRMR-style redundancy penalty. Cheap: no matching.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FisherSelector {
    /// Settings.
    pub config: FisherConfig,
}

impl FisherSelector {
    /// Normalised Fisher scores (max = 1) and the pair-mean matrix used for correlations.
    fn scores(&self, pairs: &PairSet) -> (Vec<f64>, Vec<Vec<f64>>) {
        let d = pairs.dims();
        let p = pairs.len();
        let mut means = vec![vec![0.0f64; p]; d];
        let mut within = vec![0.0f64; d];
        for (i, (a, b)) in pairs
            .f2d()
            .chunks_exact(d)
            .zip(pairs.f3d().chunks_exact(d))
            .enumerate()
        {
            for k in 0..d {
                let (x, y) = (a[k] as f64, b[k] as f64);
                means[k][i] = 0.5 * (x + y);
                within[k] += 0.5 * (x - y) * (x - y);
            }
        }
        let mut fisher = vec![0.0f64; d];
        for k in 0..d {
            let mu = means[k].iter().sum::<f64>() / p as f64;
            let between = means[k].iter().map(|v| (v - mu) * (v - mu)).sum::<f64>() / p as f64;
            fisher[k] = between / (within[k] / p as f64 + self.config.epsilon);
        }
        let max = fisher.iter().cloned().fold(0.0f64, f64::max);
        if max > 0.0 {
            fisher.iter_mut().for_each(|f| *f /= max);
        }
        (fisher, means)
    }
}

fn abs_corr(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let ma = a.iter().sum::<f64>() / n;
    let mb = b.iter().sum::<f64>() / n;
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    if saa <= 0.0 || sbb <= 0.0 {
        0.0
    } else {
        (sab / (saa * sbb).sqrt()).abs()
    }
}

impl FeatureSelector for FisherSelector {
    fn name(&self) -> &str {
        "fisher"
    }

    fn select(
        &self,
        pairs: &PairSet,
        n_s: usize,
        _rng: &mut dyn RngCore,
    ) -> Result<Selection, SelectError> {
        check_budget(pairs, n_s)?;
        if !(self.config.redundancy_weight >= 0.0 && self.config.epsilon > 0.0) {
            return Err(SelectError::InvalidConfig(
                "redundancy_weight must be >= 0 and epsilon > 0".into(),
            ));
        }
        let d = pairs.dims();
        let (fisher, means) = self.scores(pairs);
        let mut selected: Vec<usize> = Vec::new();
        let mut objective = 0.0;
        let mut evaluations = 0;
        while selected.len() < n_s {
            let mut best: Option<(usize, f64)> = None;
            for cand in 0..d {
                if selected.contains(&cand) {
                    continue;
                }
                let redundancy = selected
                    .iter()
                    .map(|&s| abs_corr(&means[cand], &means[s]))
                    .fold(0.0f64, f64::max);
                let v = fisher[cand] - self.config.redundancy_weight * redundancy;
                evaluations += 1;
                if best.is_none_or(|(_, bv)| v > bv) {
                    best = Some((cand, v));
                }
            }
            let Some((cand, v)) = best else { break };
            selected.push(cand);
            objective += v;
        }
        selected.sort_unstable();
        Ok(Selection {
            dims: selected,
            report: SelectionReport {
                selector: self.name().to_string(),
                objective_name: "sum of normalised Fisher ratio minus redundancy (maximised)"
                    .into(),
                objective,
                per_dim_cost: fisher.iter().map(|f| -f).collect(),
                evaluations,
            },
        })
    }
}
