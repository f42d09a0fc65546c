//! Selector exactness, behaviour on synthetic features with known informative dims,
//! determinism and typed errors.

use matloc_select::*;
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// `p` pairs of `d`-dim features: dims in `signal` hold a per-point value shared by both sides
/// (plus small noise); dims in `offset` are constant with a different constant on each side;
/// all other dims are independent noise on each side. Plus `distractors` map-side and
/// query-side features drawn like unmatched points.
fn synthetic(
    d: usize,
    p: usize,
    signal: &[usize],
    offset: &[usize],
    distractors: usize,
    seed: u64,
) -> PairSet {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut f2 = Vec::new();
    let mut f3 = Vec::new();
    for _ in 0..p {
        for k in 0..d {
            if signal.contains(&k) {
                let v: f32 = rng.random_range(-1.0..1.0);
                f2.push(v + rng.random_range(-0.02..0.02));
                f3.push(v + rng.random_range(-0.02..0.02));
            } else if offset.contains(&k) {
                f2.push(0.3);
                f3.push(0.31);
            } else {
                f2.push(rng.random_range(-1.0..1.0));
                f3.push(rng.random_range(-1.0..1.0));
            }
        }
    }
    let mut gen_side = |is3: bool| -> Vec<f32> {
        (0..distractors * d)
            .map(|i| {
                let k = i % d;
                if offset.contains(&k) {
                    if is3 { 0.31 } else { 0.3 }
                } else {
                    rng.random_range(-1.0..1.0)
                }
            })
            .collect()
    };
    let d2 = gen_side(false);
    let d3 = gen_side(true);
    PairSet::with_distractors(d, f2, f3, d2, d3).unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn bnb_mean_matches_brute_force(costs in prop::collection::vec(0.0f64..10.0, 1..11), ns in 1usize..11) {
        let ns = ns.min(costs.len());
        let obj = SeparableObjective { costs: costs.clone(), aggregate: Aggregate::Mean };
        let b = branch_and_bound(&obj, ns);
        let f = brute_force(&obj, ns);
        prop_assert_eq!(b.value, f.value);
        prop_assert!((obj.value(&b.subset) - b.value).abs() < 1e-12);
        // The mean objective's optimum is a single dim (the cheapest).
        prop_assert_eq!(b.subset.len(), 1);
        let min = costs.iter().cloned().fold(f64::INFINITY, f64::min);
        prop_assert_eq!(b.value, min);
    }

    #[test]
    fn bnb_sum_matches_brute_force(costs in prop::collection::vec(-5.0f64..5.0, 1..11), ns in 1usize..11) {
        let ns = ns.min(costs.len());
        let obj = SeparableObjective { costs, aggregate: Aggregate::Sum };
        let b = branch_and_bound(&obj, ns);
        let f = brute_force(&obj, ns);
        prop_assert!((b.value - f.value).abs() < 1e-9, "{} vs {}", b.value, f.value);
        prop_assert!(b.subset.len() <= ns && !b.subset.is_empty());
        prop_assert!((obj.value(&b.subset) - b.value).abs() < 1e-9);
    }

    /// A non-separable objective through the generic trait: sum of costs plus pairwise
    /// interaction penalties (>= 0), bounded by ignoring interactions of the candidates.
    #[test]
    fn bnb_generic_matches_brute_force(costs in prop::collection::vec(-3.0f64..3.0, 2..9), w in 0.0f64..2.0, ns in 1usize..9) {
        struct Pairwise { costs: Vec<f64>, w: f64 }
        impl SubsetObjective for Pairwise {
            fn dims(&self) -> usize { self.costs.len() }
            fn value(&self, s: &[usize]) -> f64 {
                let base: f64 = s.iter().map(|&d| self.costs[d]).sum();
                let mut inter = 0.0;
                for (i, &a) in s.iter().enumerate() {
                    for &b in &s[i + 1..] {
                        inter += self.w * ((a as f64 - b as f64).abs()).recip();
                    }
                }
                base + inter
            }
            fn lower_bound(&self, chosen: &[usize], cands: &[usize], max: usize) -> f64 {
                let sep = SeparableObjective { costs: self.costs.clone(), aggregate: Aggregate::Sum };
                let inter = self.value(chosen) - sep.value(chosen);
                let lb = sep.lower_bound(chosen, cands, max);
                if chosen.is_empty() { lb } else { lb + inter }
            }
        }
        let ns = ns.min(costs.len());
        let obj = Pairwise { costs, w };
        let b = branch_and_bound(&obj, ns);
        let f = brute_force(&obj, ns);
        prop_assert!((b.value - f.value).abs() < 1e-9, "{} vs {}", b.value, f.value);
    }

    /// On an additive score greedy forward selection is optimal: it picks the `N_s` best dims
    /// (the brute force of the negated costs), with or without swaps, and reports every dim's
    /// own score.
    #[test]
    fn greedy_search_is_exact_on_additive_scores(gains in prop::collection::vec(-5.0f64..5.0, 1..10), ns in 1usize..10, swap in any::<bool>()) {
        let ns = ns.min(gains.len());
        let search = GreedySearch { swap_refinement: swap, ..GreedySearch::default() };
        let found = search
            .run(gains.len(), ns, &mut |s: &[usize]| Ok::<f64, ()>(s.iter().map(|&d| gains[d]).sum()))
            .unwrap();
        prop_assert_eq!(found.dims.len(), ns);
        prop_assert!(found.dims.windows(2).all(|w| w[0] < w[1]));
        let mut sorted = gains.clone();
        sorted.sort_by(|a, b| b.total_cmp(a));
        let best: f64 = sorted[..ns].iter().sum();
        prop_assert!((found.score - best).abs() < 1e-9, "{} vs {}", found.score, best);
        prop_assert_eq!(&found.single, &gains);
    }

    /// Swaps never make the selection worse than the greedy pass, and the reported score is
    /// the score of the returned dims.
    #[test]
    fn greedy_swaps_never_hurt(gains in prop::collection::vec(-3.0f64..3.0, 3..9), w in -2.0f64..2.0, ns in 2usize..6) {
        let ns = ns.min(gains.len());
        let score = |s: &[usize]| -> f64 {
            let base: f64 = s.iter().map(|&d| gains[d]).sum();
            let mut inter = 0.0;
            for (i, &a) in s.iter().enumerate() {
                for &b in &s[i + 1..] {
                    inter += w * (((a * b + a + b) % 5) as f64 - 2.0);
                }
            }
            base + inter
        };
        let plain = GreedySearch { swap_refinement: false, ..GreedySearch::default() }
            .run(gains.len(), ns, &mut |s: &[usize]| Ok::<f64, ()>(score(s)))
            .unwrap();
        let swapped = GreedySearch::default()
            .run(gains.len(), ns, &mut |s: &[usize]| Ok::<f64, ()>(score(s)))
            .unwrap();
        prop_assert!(swapped.score >= plain.score - 1e-12);
        prop_assert!((score(&swapped.dims) - swapped.score).abs() < 1e-9);
        // Swaps exist only when some dim stays out.
        prop_assert_eq!(swapped.evaluations > plain.evaluations, ns < gains.len());
    }
}

#[test]
fn paper_bip_picks_the_single_cheapest_dim() {
    // dims 3 and 7 carry the signal; dim 5 is a constant offset of 0.01 (cheapest in |F2d-F3d|
    // but useless for matching).
    let pairs = synthetic(12, 300, &[3, 7], &[5], 300, 1);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    for ns in [1, 5, 10] {
        let sel = PaperBipSelector::default()
            .select(&pairs, ns, &mut rng)
            .unwrap();
        assert_eq!(sel.dims, vec![5], "N_s = {ns}");
        let costs = pairs.abs_diff_costs();
        let min = costs.iter().cloned().fold(f64::INFINITY, f64::min);
        assert_eq!(sel.report.objective, min);
        // exhaustive check with the same objective
        let obj = SeparableObjective {
            costs,
            aggregate: Aggregate::Mean,
        };
        assert_eq!(brute_force(&obj, ns.min(4)).value, sel.report.objective);
    }
}

#[test]
fn paper_bip_at_full_size_is_fast() {
    // D = 47, N_s = 10: C(47, 10) ≈ 5e9 subsets, pruned to a handful of nodes.
    let pairs = synthetic(47, 200, &[1, 2, 3], &[], 0, 2);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let sel = PaperBipSelector::default()
        .select(&pairs, 10, &mut rng)
        .unwrap();
    assert_eq!(sel.dims.len(), 1);
    assert!(sel.report.evaluations < 1000, "{}", sel.report.evaluations);
}

#[test]
fn matching_selector_finds_informative_dims() {
    let signal = [2usize, 9, 13, 17];
    let pairs = synthetic(20, 400, &signal, &[5, 6], 400, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let sel = MatchingSelector::default()
        .select(&pairs, 4, &mut rng)
        .unwrap();
    assert_eq!(sel.dims, signal.to_vec(), "{:?}", sel.report);
    assert!(sel.report.objective > 0.8, "{:?}", sel.report);
    // The BIP on the same data picks a single constant-offset dim instead.
    let bip = PaperBipSelector::default()
        .select(&pairs, 4, &mut rng)
        .unwrap();
    assert_eq!(bip.dims.len(), 1);
    assert!([5usize, 6].contains(&bip.dims[0]));
    let fisher = FisherSelector::default()
        .select(&pairs, 4, &mut rng)
        .unwrap();
    assert_eq!(fisher.dims, signal.to_vec(), "{:?}", fisher.report);
    for score in [MatchScore::Top1, MatchScore::MnnRecall] {
        let cfg = MatchingSelectorConfig {
            score,
            swap_refinement: false,
            ..Default::default()
        };
        let s = MatchingSelector { config: cfg }
            .select(&pairs, 4, &mut rng)
            .unwrap();
        assert_eq!(s.dims, signal.to_vec(), "{score:?}");
    }
}

#[test]
fn deterministic_by_seed() {
    let pairs = synthetic(16, 300, &[1, 4, 8], &[], 200, 4);
    let cfg = MatchingSelectorConfig {
        max_pairs: 100,
        max_distractors: 100,
        ..Default::default()
    };
    let sel = MatchingSelector { config: cfg };
    let run = |s: &dyn FeatureSelector, seed: u64| {
        s.select(&pairs, 3, &mut ChaCha8Rng::seed_from_u64(seed))
            .unwrap()
    };
    assert_eq!(run(&sel, 9), run(&sel, 9));
    let r = RandomSelector::default();
    assert_eq!(run(&r, 9), run(&r, 9));
    assert_eq!(run(&r, 9).dims.len(), 3);
    let differs = (0..10).any(|s| run(&r, s).dims != run(&r, 9).dims);
    assert!(differs);
}

#[test]
fn greedy_search_passes_score_errors_on() {
    let err = GreedySearch::default().run(4, 2, &mut |s: &[usize]| {
        if s.contains(&2) {
            Err("dim 2 cannot be scored")
        } else {
            Ok(1.0)
        }
    });
    assert_eq!(err, Err("dim 2 cannot be scored"));
}

#[test]
fn typed_errors() {
    assert_eq!(
        PairSet::new(3, vec![], vec![]),
        Err(SelectError::EmptyPairs)
    );
    assert!(matches!(
        PairSet::new(3, vec![0.0; 4], vec![0.0; 3]),
        Err(SelectError::DimensionMismatch { .. })
    ));
    assert!(matches!(
        PairSet::new(3, vec![0.0; 6], vec![0.0; 3]),
        Err(SelectError::Shape(_))
    ));
    assert!(matches!(
        PairSet::new(2, vec![0.0, f32::NAN], vec![0.0; 2]),
        Err(SelectError::NonFinite { index: 0, .. })
    ));
    let pairs = synthetic(4, 10, &[0], &[], 0, 5);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let selectors: Vec<Box<dyn FeatureSelector>> = vec![
        Box::new(PaperBipSelector::default()),
        Box::new(MatchingSelector::default()),
        Box::new(FisherSelector::default()),
        Box::new(RandomSelector::default()),
    ];
    for s in &selectors {
        assert_eq!(
            s.select(&pairs, 0, &mut rng).unwrap_err(),
            SelectError::InvalidBudget { n_s: 0, dims: 4 }
        );
        assert_eq!(
            s.select(&pairs, 5, &mut rng).unwrap_err(),
            SelectError::InvalidBudget { n_s: 5, dims: 4 }
        );
        let ok = s.select(&pairs, 2, &mut rng).unwrap();
        assert!(!ok.dims.is_empty() && ok.dims.len() <= 2);
        assert!(ok.dims.windows(2).all(|w| w[0] < w[1]));
    }
}

#[test]
fn region_selections_roundtrip() {
    let a = synthetic(8, 100, &[1, 2], &[], 50, 6);
    let b = synthetic(8, 100, &[5, 6], &[], 50, 7);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let (sel, reports) = select_per_region(
        &MatchingSelector::default(),
        &[(10, &a), (11, &b)],
        2,
        &mut rng,
    )
    .unwrap();
    assert_eq!(reports.len(), 2);
    assert_eq!(sel.get(10), Some(&[1usize, 2][..]));
    assert_eq!(sel.get(11), Some(&[5usize, 6][..]));
    assert_eq!(sel.get(12), None);
    let json = serde_json::to_string(&sel).unwrap();
    let back: RegionSelections = serde_json::from_str(&json).unwrap();
    assert_eq!(back, sel);
    let mut s2 = sel.clone();
    s2.insert(10, vec![0]);
    assert_eq!(s2.get(10), Some(&[0usize][..]));
    assert_eq!(s2.per_region.len(), 2);
}
