//! Size-balanced k-medoids on a precomputed distance matrix.
//!
//! Initialisation is k-means++ style (first medoid uniform, then each next one drawn with
//! probability ∝ D², D the distance to the nearest chosen medoid). Each iteration assigns poses
//! under capacity bounds (greedy over (distance, pose, medoid) pairs ascending, then topping up
//! blocks below the lower bound with the cheapest moves), improves the assignment with moves and
//! pairwise swaps that respect the bounds, and re-picks each block's medoid as the member with the
//! smallest summed distance to the other members. Several restarts from one seed; the lowest
//! total cost wins. Everything is deterministic for a given seed.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::error::PartitionError;

/// A dense symmetric distance matrix (f32 halves the memory; distances live in [0, ~2]).
#[derive(Clone, Debug, PartialEq)]
pub struct DistanceMatrix {
    n: usize,
    d: Vec<f32>,
}

impl DistanceMatrix {
    /// Builds the matrix from a symmetric distance function (rows in parallel; `f(i, i)` is not
    /// called and the diagonal is 0).
    pub fn from_fn(n: usize, f: impl Fn(usize, usize) -> f64 + Sync) -> DistanceMatrix {
        let rows: Vec<Vec<f32>> = (0..n)
            .into_par_iter()
            .map(|i| (i + 1..n).map(|j| f(i, j) as f32).collect())
            .collect();
        let mut d = vec![0.0f32; n * n];
        for (i, row) in rows.into_iter().enumerate() {
            for (k, v) in row.into_iter().enumerate() {
                let j = i + 1 + k;
                d[i * n + j] = v;
                d[j * n + i] = v;
            }
        }
        DistanceMatrix { n, d }
    }

    /// Number of items.
    pub fn len(&self) -> usize {
        self.n
    }

    /// True for a 0 × 0 matrix.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Distance between items `i` and `j`.
    #[inline]
    pub fn get(&self, i: usize, j: usize) -> f64 {
        f64::from(self.d[i * self.n + j])
    }
}

/// Settings of [`balanced_k_medoids`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KMedoidsConfig {
    /// Number of clusters.
    pub k: usize,
    /// Allowed relative deviation of a cluster's size from the mean size `n / k`.
    pub tolerance: f64,
    /// Seed of the initialisation.
    pub seed: u64,
    /// Independent restarts (at least 1).
    pub restarts: usize,
    /// Assignment/update rounds per restart.
    pub max_iter: usize,
}

/// Result of a clustering.
#[derive(Clone, Debug, PartialEq)]
pub struct Clustering {
    /// Cluster of each item.
    pub labels: Vec<usize>,
    /// Medoid item of each cluster.
    pub medoids: Vec<usize>,
    /// Sum of distances of the items to their medoids.
    pub cost: f64,
    /// Inclusive size bounds the clusters were held to.
    pub size_bounds: (usize, usize),
}

/// Inclusive `(min, max)` cluster sizes for `n` items in `k` clusters at relative `tolerance`.
pub fn size_bounds(n: usize, k: usize, tolerance: f64) -> (usize, usize) {
    let mean = n as f64 / k.max(1) as f64;
    let lo = ((mean * (1.0 - tolerance)).floor() as usize)
        .max(1)
        .min(n / k.max(1));
    let hi = ((mean * (1.0 + tolerance)).ceil() as usize).max(n.div_ceil(k.max(1)));
    (lo, hi)
}

/// Clusters the items of `d` into `cfg.k` clusters whose sizes stay within
/// [`size_bounds`]`(n, k, tolerance)`.
pub fn balanced_k_medoids(
    d: &DistanceMatrix,
    cfg: &KMedoidsConfig,
) -> Result<Clustering, PartitionError> {
    let n = d.len();
    if cfg.k == 0 || n < cfg.k {
        return Err(PartitionError::TooFewPoses {
            poses: n,
            blocks: cfg.k.max(1),
        });
    }
    if !(cfg.tolerance.is_finite() && cfg.tolerance >= 0.0) {
        return Err(PartitionError::InvalidConfig {
            field: "balance_tolerance",
            reason: format!("must be finite and >= 0, got {}", cfg.tolerance),
        });
    }
    let bounds = size_bounds(n, cfg.k, cfg.tolerance);
    let mut best: Option<Clustering> = None;
    for restart in 0..cfg.restarts.max(1) {
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        rng.set_stream(restart as u64);
        let c = run_once(d, cfg, bounds, &mut rng);
        if best.as_ref().is_none_or(|b| c.cost < b.cost - 1e-9) {
            best = Some(c);
        }
    }
    best.ok_or_else(|| PartitionError::Inconsistent("no clustering produced".into()))
}

fn init_medoids(d: &DistanceMatrix, k: usize, rng: &mut ChaCha8Rng) -> Vec<usize> {
    let n = d.len();
    let mut medoids = vec![rng.random_range(0..n)];
    let mut nearest: Vec<f64> = (0..n).map(|i| d.get(i, medoids[0])).collect();
    while medoids.len() < k {
        let total: f64 = (0..n)
            .filter(|i| !medoids.contains(i))
            .map(|i| nearest[i] * nearest[i])
            .sum();
        let pick = if total > 0.0 {
            let mut r = rng.random::<f64>() * total;
            let mut chosen = None;
            for i in (0..n).filter(|i| !medoids.contains(i)) {
                r -= nearest[i] * nearest[i];
                chosen = Some(i);
                if r <= 0.0 {
                    break;
                }
            }
            chosen
        } else {
            // All remaining items coincide with medoids: any unused one will do.
            let free: Vec<usize> = (0..n).filter(|i| !medoids.contains(i)).collect();
            (!free.is_empty()).then(|| free[rng.random_range(0..free.len())])
        };
        let Some(m) = pick else { break };
        medoids.push(m);
        for i in 0..n {
            nearest[i] = nearest[i].min(d.get(i, m));
        }
    }
    medoids
}

/// Capacity-bounded assignment of every item to a medoid.
fn assign(d: &DistanceMatrix, medoids: &[usize], (lo, hi): (usize, usize)) -> Vec<usize> {
    let n = d.len();
    let k = medoids.len();
    let mut pairs: Vec<(f64, usize, usize)> = Vec::with_capacity(n * k);
    for i in 0..n {
        for (c, &m) in medoids.iter().enumerate() {
            // Medoids go first to their own cluster.
            let dist = if i == m { -1.0 } else { d.get(i, m) };
            pairs.push((dist, i, c));
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut labels = vec![usize::MAX; n];
    let mut sizes = vec![0usize; k];
    for &(_, i, c) in &pairs {
        if labels[i] == usize::MAX && sizes[c] < hi {
            labels[i] = c;
            sizes[c] += 1;
        }
    }
    // Top up clusters below the lower bound with the cheapest moves from clusters that can spare.
    while let Some(c) = (0..k).find(|&c| sizes[c] < lo) {
        let mut best: Option<(f64, usize)> = None;
        for i in 0..n {
            let from = labels[i];
            if from == c || sizes[from] <= lo || i == medoids[from] {
                continue;
            }
            let delta = d.get(i, medoids[c]) - d.get(i, medoids[from]);
            if best.is_none_or(|(bd, _)| delta < bd) {
                best = Some((delta, i));
            }
        }
        let Some((_, i)) = best else { break };
        sizes[labels[i]] -= 1;
        labels[i] = c;
        sizes[c] += 1;
    }
    labels
}

/// Moves and pairwise swaps that lower the cost without leaving the size bounds.
fn improve(d: &DistanceMatrix, medoids: &[usize], labels: &mut [usize], (lo, hi): (usize, usize)) {
    let n = d.len();
    let k = medoids.len();
    let mut sizes = vec![0usize; k];
    for &l in labels.iter() {
        sizes[l] += 1;
    }
    for _pass in 0..20 {
        let mut changed = false;
        for i in 0..n {
            let from = labels[i];
            if i == medoids[from] || sizes[from] <= lo {
                continue;
            }
            let here = d.get(i, medoids[from]);
            let best = (0..k)
                .filter(|&c| c != from && sizes[c] < hi)
                .map(|c| (d.get(i, medoids[c]), c))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((dist, c)) = best
                && dist < here - 1e-9
            {
                labels[i] = c;
                sizes[from] -= 1;
                sizes[c] += 1;
                changed = true;
            }
        }
        for i in 0..n {
            for j in i + 1..n {
                let (a, b) = (labels[i], labels[j]);
                if a == b || i == medoids[a] || j == medoids[b] {
                    continue;
                }
                let now = d.get(i, medoids[a]) + d.get(j, medoids[b]);
                let swapped = d.get(i, medoids[b]) + d.get(j, medoids[a]);
                if swapped < now - 1e-9 {
                    labels[i] = b;
                    labels[j] = a;
                    changed = true;
                }
            }
        }
        if !changed {
            break;
        }
    }
}

fn update_medoids(d: &DistanceMatrix, labels: &[usize], k: usize) -> Vec<usize> {
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); k];
    for (i, &l) in labels.iter().enumerate() {
        members[l].push(i);
    }
    members
        .iter()
        .map(|m| {
            // Clusters are never empty (the lower size bound is at least 1); 0 is a fallback.
            m.iter()
                .copied()
                .min_by(|&a, &b| {
                    let sa: f64 = m.iter().map(|&j| d.get(a, j)).sum();
                    let sb: f64 = m.iter().map(|&j| d.get(b, j)).sum();
                    sa.total_cmp(&sb).then(a.cmp(&b))
                })
                .unwrap_or(0)
        })
        .collect()
}

fn cost(d: &DistanceMatrix, medoids: &[usize], labels: &[usize]) -> f64 {
    labels
        .iter()
        .enumerate()
        .map(|(i, &l)| d.get(i, medoids[l]))
        .sum()
}

fn run_once(
    d: &DistanceMatrix,
    cfg: &KMedoidsConfig,
    bounds: (usize, usize),
    rng: &mut ChaCha8Rng,
) -> Clustering {
    let mut medoids = init_medoids(d, cfg.k, rng);
    let mut labels = assign(d, &medoids, bounds);
    improve(d, &medoids, &mut labels, bounds);
    for _ in 0..cfg.max_iter {
        let next = update_medoids(d, &labels, cfg.k);
        if next == medoids {
            break;
        }
        let mut next_labels = assign(d, &next, bounds);
        improve(d, &next, &mut next_labels, bounds);
        // Only accept rounds that lower the cost, so the loop cannot cycle.
        if cost(d, &next, &next_labels) >= cost(d, &medoids, &labels) - 1e-9 {
            break;
        }
        medoids = next;
        labels = next_labels;
    }
    Clustering {
        cost: cost(d, &medoids, &labels),
        labels,
        medoids,
        size_bounds: bounds,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line_points(n: usize) -> Vec<f64> {
        // Three well-separated groups on a line, with unequal sizes.
        (0..n)
            .map(|i| match i % 3 {
                0 => i as f64 * 0.01,
                1 => 100.0 + i as f64 * 0.01,
                _ => 200.0 + i as f64 * 0.01,
            })
            .collect()
    }

    fn cfg(k: usize, seed: u64) -> KMedoidsConfig {
        KMedoidsConfig {
            k,
            tolerance: 0.25,
            seed,
            restarts: 3,
            max_iter: 30,
        }
    }

    #[test]
    fn separated_groups_are_found() {
        let x = line_points(60);
        let d = DistanceMatrix::from_fn(60, |i, j| (x[i] - x[j]).abs());
        let c = balanced_k_medoids(&d, &cfg(3, 1)).unwrap();
        for i in 0..60 {
            for j in 0..60 {
                assert_eq!(c.labels[i] == c.labels[j], i % 3 == j % 3);
            }
        }
    }

    #[test]
    fn deterministic_and_balanced() {
        let x: Vec<f64> = (0..97).map(|i| ((i * 37) % 101) as f64).collect();
        let d = DistanceMatrix::from_fn(97, |i, j| (x[i] - x[j]).abs());
        let a = balanced_k_medoids(&d, &cfg(5, 7)).unwrap();
        let b = balanced_k_medoids(&d, &cfg(5, 7)).unwrap();
        assert_eq!(a, b);
        let (lo, hi) = a.size_bounds;
        for c in 0..5 {
            let s = a.labels.iter().filter(|&&l| l == c).count();
            assert!((lo..=hi).contains(&s), "size {s} outside {lo}..={hi}");
        }
    }

    #[test]
    fn too_few_items() {
        let d = DistanceMatrix::from_fn(2, |_, _| 1.0);
        assert!(matches!(
            balanced_k_medoids(&d, &cfg(3, 0)),
            Err(PartitionError::TooFewPoses {
                poses: 2,
                blocks: 3
            })
        ));
    }

    #[test]
    fn size_bounds_are_feasible() {
        for n in 1..200 {
            for k in 1..=n.min(12) {
                let (lo, hi) = size_bounds(n, k, 0.25);
                assert!(lo * k <= n && n <= hi * k, "n={n} k={k} lo={lo} hi={hi}");
                assert!(lo >= 1);
            }
        }
    }
}
