//! MNN matcher properties and kernel exactness.

use matloc_core::FeatureMap;
#[cfg(feature = "faer")]
use matloc_match::kernel::nn_tables_faer;
use matloc_match::kernel::{nn_tables_reference, nn_tables_tiled};
use matloc_match::*;
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_unit(rng: &mut ChaCha8Rng, n: usize, d: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..n * d).map(|_| rng.random_range(-1.0f32..1.0)).collect();
    for row in v.chunks_exact_mut(d) {
        let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
        row.iter_mut().for_each(|x| *x /= norm);
    }
    v
}

fn tables_equal(a: &NnTables, b: &NnTables, second: bool) {
    assert_eq!(a.rows.arg, b.rows.arg, "row argmax");
    assert_eq!(a.cols.arg, b.cols.arg, "column argmax");
    assert_eq!(a.rows.best, b.rows.best, "row best");
    assert_eq!(a.cols.best, b.cols.best, "column best");
    if second {
        assert_eq!(a.rows.second, b.rows.second, "row second");
        assert_eq!(a.cols.second, b.cols.second, "column second");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Sizes that are not multiples of the 4 × 16 tile or the 64-row chunk, D on both sides of
    /// the const-generic range.
    #[test]
    fn tiled_equals_reference(n in 1usize..150, m in 1usize..150, d in 1usize..48, seed in any::<u64>()) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let a = random_unit(&mut rng, n, d);
        let b = random_unit(&mut rng, m, d);
        let r = nn_tables_reference(&a, n, &b, m, d);
        tables_equal(&nn_tables_tiled(&a, n, &b, m, d, true), &r, true);
        tables_equal(&nn_tables_tiled(&a, n, &b, m, d, false), &r, false);
    }

    /// Quantised features produce many exact ties: lowest index must win in both kernels.
    #[test]
    fn ties_break_to_lowest_index(n in 1usize..90, m in 1usize..90, d in 1usize..6, seed in any::<u64>()) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let a: Vec<f32> = (0..n * d).map(|_| rng.random_range(-1i32..=1) as f32).collect();
        let b: Vec<f32> = (0..m * d).map(|_| rng.random_range(-1i32..=1) as f32).collect();
        let r = nn_tables_reference(&a, n, &b, m, d);
        tables_equal(&nn_tables_tiled(&a, n, &b, m, d, true), &r, true);
        for i in 0..n {
            let j = r.rows.arg[i] as usize;
            for jj in 0..j {
                let s: f32 = (0..d).map(|k| a[i * d + k] * b[jj * d + k]).sum();
                prop_assert!(s < r.rows.best[i]);
            }
        }
    }

    /// Every returned pair is each other's argmax.
    #[test]
    fn mutuality(n in 1usize..120, m in 1usize..120, d in 1usize..20, seed in any::<u64>()) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let a = random_unit(&mut rng, n, d);
        let b = random_unit(&mut rng, m, d);
        let matches = mnn_prepared(&a, &b, d, &MnnConfig::default()).unwrap();
        let r = nn_tables_reference(&a, n, &b, m, d);
        let mut seen_q = vec![false; n];
        let mut seen_m = vec![false; m];
        for mt in &matches {
            prop_assert_eq!(r.rows.arg[mt.query] as usize, mt.map);
            prop_assert_eq!(r.cols.arg[mt.map] as usize, mt.query);
            prop_assert!(!seen_q[mt.query] && !seen_m[mt.map]);
            seen_q[mt.query] = true;
            seen_m[mt.map] = true;
        }
        // and every mutual pair is returned
        let mutual = (0..n).filter(|&i| r.cols.arg[r.rows.arg[i] as usize] as usize == i).count();
        prop_assert_eq!(mutual, matches.len());
    }

    /// Permuting map points permutes the matches accordingly.
    #[test]
    fn permutation_invariance(n in 1usize..100, m in 1usize..100, d in 2usize..16, seed in any::<u64>()) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let a = random_unit(&mut rng, n, d);
        let b = random_unit(&mut rng, m, d);
        let mut perm: Vec<usize> = (0..m).collect();
        for i in (1..m).rev() {
            perm.swap(i, rng.random_range(0..=i));
        }
        // permuted[k] = b[perm[k]]
        let bp: Vec<f32> = perm.iter().flat_map(|&j| b[j * d..(j + 1) * d].to_vec()).collect();
        let cfg = MnnConfig::default();
        let m1 = mnn_prepared(&a, &b, d, &cfg).unwrap();
        let m2 = mnn_prepared(&a, &bp, d, &cfg).unwrap();
        // A tie breaks to the lowest index, which a permutation moves: in d = 1 every vector is
        // +-1 and ties are the rule; in d = 2 two similarities can round to the same f32 (n = 64,
        // m = 43, seed 65534142464215385). The property holds for inputs without ties.
        let t = nn_tables_reference(&a, n, &b, m, d);
        let tied = |side: &NnTable| side.best.iter().zip(&side.second).any(|(x, y)| x == y);
        prop_assume!(!tied(&t.rows) && !tied(&t.cols));
        let mut mapped: Vec<(usize, usize)> = m2.iter().map(|x| (x.query, perm[x.map])).collect();
        mapped.sort();
        let orig: Vec<(usize, usize)> = m1.iter().map(|x| (x.query, x.map)).collect();
        prop_assert_eq!(orig, mapped);
    }

    /// Identical sets of distinct random vectors match to the identity. (From d = 3 on: 200
    /// random unit vectors in 2-D come closer than f32 can resolve in a dot product.)
    #[test]
    fn identical_features_identity(n in 1usize..200, d in 3usize..48, seed in any::<u64>()) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let a = random_unit(&mut rng, n, d);
        let matches = mnn_prepared(&a, &a, d, &MnnConfig::default()).unwrap();
        prop_assert_eq!(matches.len(), n);
        for (i, mt) in matches.iter().enumerate() {
            prop_assert_eq!((mt.query, mt.map), (i, i));
        }
    }

    /// Threshold and ratio test keep exactly the mutual pairs that pass their definitions.
    #[test]
    fn threshold_and_ratio_semantics(n in 2usize..80, m in 2usize..80, d in 1usize..10, th in -0.5f32..0.9, ratio in 0.3f32..1.0, seed in any::<u64>()) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let a = random_unit(&mut rng, n, d);
        let b = random_unit(&mut rng, m, d);
        let r = nn_tables_reference(&a, n, &b, m, d);
        let all = mnn_prepared(&a, &b, d, &MnnConfig::default()).unwrap();
        let cfg = MnnConfig { min_similarity: Some(th), ratio: Some(ratio), ..Default::default() };
        let got = mnn_prepared(&a, &b, d, &cfg).unwrap();
        let dist = |s: f32| (2.0 - 2.0 * s).max(0.0).sqrt();
        let expect: Vec<RawMatch> = all.into_iter().filter(|x| {
            x.similarity >= th
                && dist(x.similarity) <= ratio * dist(r.rows.second[x.query])
                && dist(x.similarity) <= ratio * dist(r.cols.second[x.map])
        }).collect();
        prop_assert_eq!(got, expect);
    }
}

#[cfg(feature = "faer")]
#[test]
fn faer_baseline_agrees_on_generic_data() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let (n, m, d) = (300, 257, 10);
    let a = random_unit(&mut rng, n, d);
    let b = random_unit(&mut rng, m, d);
    let r = nn_tables_reference(&a, n, &b, m, d);
    let f = nn_tables_faer(&a, n, &b, m, d);
    // Different summation order: values agree to rounding, argmax almost everywhere.
    let agree = (0..n).filter(|&i| r.rows.arg[i] == f.rows.arg[i]).count();
    assert!(agree >= n - 2, "{agree}/{n}");
    for i in 0..n {
        assert!((r.rows.best[i] - f.rows.best[i]).abs() < 1e-5);
    }
}

#[test]
fn large_problem_tiled_equals_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for &(n, m, d) in &[
        (1203, 977, 5),
        (517, 1031, 47),
        (64, 4096, 3),
        (999, 17, 33),
    ] {
        let a = random_unit(&mut rng, n, d);
        let b = random_unit(&mut rng, m, d);
        tables_equal(
            &nn_tables_tiled(&a, n, &b, m, d, true),
            &nn_tables_reference(&a, n, &b, m, d),
            true,
        );
    }
}

fn query_from(w: usize, h: usize, d: usize, data: Vec<f32>, stride: f64) -> QueryFeatures {
    QueryFeatures::new(FeatureMap::from_vec(w, h, d, data).unwrap(), stride)
}

#[test]
fn matcher_maps_indices_pixels_and_points() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let (w, h, d) = (7, 5, 6);
    let n = w * h;
    let f = random_unit(&mut rng, n, d);
    // Map = query features, reversed, with every third point invalid.
    let mut feats = Vec::new();
    let mut points = Vec::new();
    let mut valid = Vec::new();
    for k in 0..n {
        let src = n - 1 - k;
        feats.extend_from_slice(&f[src * d..(src + 1) * d]);
        points.push([src as f64, 0.0, 1.0]);
        valid.push(k % 3 != 0);
    }
    let map = RenderedPoints::new(d, feats, points, valid).unwrap();
    let q = query_from(w, h, d, f, 4.0);
    let matches = MnnMatcher::default()
        .match_features(&q, &map, None)
        .unwrap();
    assert_eq!(matches.len(), map.valid_indices().len());
    for mt in &matches {
        assert_eq!(mt.map_index, n - 1 - mt.query_index);
        assert!(map.valid()[mt.map_index]);
        assert_eq!(mt.point_world[0] as usize, mt.query_index);
        let (col, row) = (mt.query_index % w, mt.query_index / w);
        assert_eq!(
            mt.query_px,
            [4.0 * (col as f64 + 0.5), 4.0 * (row as f64 + 0.5)]
        );
        assert!((mt.similarity - 1.0).abs() < 1e-5);
    }
    // Selecting dims keeps the identity on distinct data.
    let sel = [0usize, 2, 5];
    let m2 = MnnMatcher::default()
        .match_features(&q, &map, Some(&sel))
        .unwrap();
    assert!(m2.iter().all(|mt| mt.map_index == n - 1 - mt.query_index));
    let boxed: Box<dyn Matcher> = Box::new(MnnMatcher::default());
    assert_eq!(boxed.match_features(&q, &map, None).unwrap(), matches);
}

#[test]
fn standardisation_is_applied_to_both_sides() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (w, h, d) = (6, 6, 4);
    // Every dim carries the signal (shared by both sides up to small noise), but dim 0 sits on
    // an offset of 1e4: after plain L2 normalisation all vectors point along dim 0 and their
    // differences fall below f32 resolution; standardisation removes the offset on both sides.
    let mut fq = Vec::new();
    let mut fm = Vec::new();
    for _ in 0..w * h {
        for k in 0..d {
            let v = rng.random_range(-1.0f32..1.0) + if k == 0 { 1e4 } else { 0.0 };
            fq.push(v + rng.random_range(-0.01f32..0.01));
            fm.push(v + rng.random_range(-0.01f32..0.01));
        }
    }
    let stats = FeatureStats::from_features(&fm, d);
    let points = vec![[0.0; 3]; w * h];
    let map = RenderedPoints::all_valid(d, fm, points).unwrap();
    let q = query_from(w, h, d, fq, 1.0);
    let correct = |cfg: MnnConfig| {
        MnnMatcher::new(cfg)
            .match_features(&q, &map, None)
            .unwrap()
            .iter()
            .filter(|m| m.query_index == m.map_index)
            .count()
    };
    let plain = correct(MnnConfig::default());
    let std = correct(MnnConfig {
        stats: Some(stats),
        ..Default::default()
    });
    assert_eq!(std, w * h, "{std} correct with standardisation");
    assert!(plain < std, "{plain} correct without, {std} with");
}

#[test]
fn typed_errors() {
    let q = query_from(2, 2, 3, vec![0.5; 12], 1.0);
    let map4 = RenderedPoints::all_valid(4, vec![0.5; 8], vec![[0.0; 3]; 2]).unwrap();
    let mm = MnnMatcher::default();
    assert_eq!(
        mm.match_features(&q, &map4, None),
        Err(MatchError::DimensionMismatch { query: 3, map: 4 })
    );
    let empty_map = RenderedPoints::all_valid(3, vec![], vec![]).unwrap();
    assert_eq!(
        mm.match_features(&q, &empty_map, None),
        Err(MatchError::Empty { side: Side::Map })
    );
    let invalid_map =
        RenderedPoints::new(3, vec![0.5; 6], vec![[0.0; 3]; 2], vec![false; 2]).unwrap();
    assert_eq!(
        mm.match_features(&q, &invalid_map, None),
        Err(MatchError::Empty { side: Side::Map })
    );
    let empty_q = query_from(0, 0, 3, vec![], 1.0);
    let map3 = RenderedPoints::all_valid(3, vec![0.5; 6], vec![[0.0; 3]; 2]).unwrap();
    assert_eq!(
        mm.match_features(&empty_q, &map3, None),
        Err(MatchError::Empty { side: Side::Query })
    );
    let mut qdata = vec![0.5; 12];
    qdata[7] = f32::NAN;
    let qnan = query_from(2, 2, 3, qdata, 1.0);
    assert_eq!(
        mm.match_features(&qnan, &map3, None),
        Err(MatchError::NonFinite {
            side: Side::Query,
            index: 2,
            dim: 1
        })
    );
    let mut mdata = vec![0.5; 6];
    mdata[5] = f32::INFINITY;
    let mnan = RenderedPoints::all_valid(3, mdata, vec![[0.0; 3]; 2]).unwrap();
    assert_eq!(
        mm.match_features(&q, &mnan, None),
        Err(MatchError::NonFinite {
            side: Side::Map,
            index: 1,
            dim: 2
        })
    );
    assert_eq!(
        mm.match_features(&q, &map3, Some(&[0, 3])),
        Err(MatchError::DimOutOfRange { dim: 3, dims: 3 })
    );
    assert!(matches!(
        mm.match_features(&q, &map3, Some(&[])),
        Err(MatchError::InvalidSelection(_))
    ));
    assert!(matches!(
        mm.match_features(&q, &map3, Some(&[1, 1])),
        Err(MatchError::InvalidSelection(_))
    ));
    assert!(RenderedPoints::all_valid(3, vec![0.5; 5], vec![[0.0; 3]; 2]).is_err());
    let bad = MnnMatcher::new(MnnConfig {
        ratio: Some(-1.0),
        ..Default::default()
    });
    assert!(matches!(
        bad.match_features(&q, &map3, None),
        Err(MatchError::InvalidConfig(_))
    ));
    assert_eq!(
        mnn_prepared(&[], &[1.0], 1, &MnnConfig::default()),
        Err(MatchError::Empty { side: Side::Query })
    );
}

/// A smooth 24-d field over the plane (periods 6–24 cells, distinct directions).
/// Rows are prepared in parallel blocks; the error must still name the first bad row.
#[test]
fn first_non_finite_row_is_reported_across_blocks() {
    let mm = MnnMatcher::default();
    let (w, h, d) = (50, 40, 3);
    let mut qdata = vec![0.5; w * h * d];
    qdata[1500 * d + 2] = f32::NAN;
    qdata[700 * d + 1] = f32::INFINITY;
    let q = query_from(w, h, d, qdata, 1.0);
    let map = RenderedPoints::all_valid(d, vec![0.5; 2 * d], vec![[0.0; 3]; 2]).unwrap();
    assert_eq!(
        mm.match_features(&q, &map, None),
        Err(MatchError::NonFinite {
            side: Side::Query,
            index: 700,
            dim: 1
        })
    );
}

fn smooth_field(x: f64, y: f64) -> Vec<f32> {
    (0..24)
        .map(|k| {
            let a = k as f64 * 2.399;
            let w = std::f64::consts::TAU / (6.0 + 18.0 * (k as f64 / 24.0));
            (w * (a.cos() * x + a.sin() * y) + 0.7 * k as f64).sin() as f32
        })
        .collect()
}

/// Query grid at integer field positions, map grid shifted by a fraction of a cell, each map
/// point at its field position `(x, y, 0)`. A correct continuous correspondence has
/// `point.xy == query_px − 0.5` (stride 1, cell centres at +0.5).
#[test]
fn subcell_refinement_removes_the_grid_offset() {
    let (cols, rows) = (16usize, 12usize);
    let (sx, sy) = (0.3, -0.2);
    let qdata: Vec<f32> = (0..cols * rows)
        .flat_map(|i| smooth_field((i % cols) as f64, (i / cols) as f64))
        .collect();
    let mut mdata = Vec::new();
    let mut points = Vec::new();
    for i in 0..cols * rows {
        let (x, y) = ((i % cols) as f64 + sx, (i / cols) as f64 + sy);
        mdata.extend(smooth_field(x, y));
        points.push([x, y, 0.0]);
    }
    let query = QueryFeatures::new(FeatureMap::from_vec(cols, rows, 24, qdata).unwrap(), 1.0);
    let map = RenderedPoints::all_valid(24, mdata, points)
        .unwrap()
        .with_grid(cols, rows)
        .unwrap();
    assert_eq!(map.grid(), Some((cols, rows)));
    let median_error = |side: SubcellSide| {
        let m = MnnMatcher::new(MnnConfig {
            subcell: SubcellConfig {
                side,
                ..Default::default()
            },
            ..Default::default()
        });
        let matches = m.match_features(&query, &map, None).unwrap();
        assert!(matches.len() > cols * rows / 2, "{} matches", matches.len());
        let mut e: Vec<f64> = matches
            .iter()
            .map(|m| {
                (m.point_world[0] - (m.query_px[0] - 0.5))
                    .hypot(m.point_world[1] - (m.query_px[1] - 0.5))
            })
            .collect();
        e.sort_by(f64::total_cmp);
        e[e.len() / 2]
    };
    let off = median_error(SubcellSide::Off);
    let map_side = median_error(SubcellSide::Map);
    let query_side = median_error(SubcellSide::Query);
    // Unrefined: the full grid offset |(0.3, -0.2)| = 0.36 cells.
    assert!((off - 0.36).abs() < 0.01, "off {off:.3}");
    assert!(map_side < 0.05, "map side {map_side:.3}");
    assert!(query_side < 0.05, "query side {query_side:.3}");
    // Without a grid layout the map side cannot refine and leaves the matches as they are.
    let plain =
        RenderedPoints::all_valid(24, map.features().to_vec(), map.points().to_vec()).unwrap();
    let m = MnnMatcher::default();
    let a = m.match_features(&query, &plain, None).unwrap();
    for x in &a {
        assert_eq!(x.point_world, plain.points()[x.map_index]);
        assert_eq!(x.query_px, query.cell_px(x.query_index));
    }
}

#[test]
fn grid_layout_must_fit_the_points() {
    let map = RenderedPoints::all_valid(1, vec![0.0; 6], vec![[0.0; 3]; 6]).unwrap();
    assert!(map.clone().with_grid(4, 2).is_err());
    assert_eq!(map.with_grid(3, 2).unwrap().grid(), Some((3, 2)));
}

/// The windowed MNN equals the full one when the window covers the image, and never pairs
/// cells farther apart than the window otherwise.
#[test]
fn windowed_mnn_matches_full_mnn_and_respects_the_window() {
    let (cols, rows, d) = (12usize, 9usize, 6usize);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let q = random_unit(&mut rng, cols * rows, d);
    let m = random_unit(&mut rng, cols * rows, d);
    let valid: Vec<bool> = (0..cols * rows).map(|i| i % 7 != 3).collect();
    let points: Vec<[f64; 3]> = (0..cols * rows).map(|i| [i as f64, 0.0, 1.0]).collect();
    let query = QueryFeatures::new(FeatureMap::from_vec(cols, rows, d, q).unwrap(), 4.0);
    let map = RenderedPoints::new(d, m, points, valid)
        .unwrap()
        .with_grid(cols, rows)
        .unwrap()
        .with_pixel_grid(QueryGrid::with_stride(4.0))
        .unwrap();
    let run = |window_px: Option<f64>, ratio: Option<f32>| {
        MnnMatcher::new(MnnConfig {
            window_px,
            ratio,
            subcell: SubcellConfig::off(),
            ..Default::default()
        })
        .match_features(&query, &map, None)
        .unwrap()
    };
    for ratio in [None, Some(0.9)] {
        assert_eq!(run(Some(1e6), ratio), run(None, ratio));
    }
    let near = run(Some(9.0), None);
    assert!(!near.is_empty());
    for x in &near {
        let c = x.map_index;
        let p = [(c % cols) as f64 * 4.0 + 2.0, (c / cols) as f64 * 4.0 + 2.0];
        let dist = (p[0] - x.query_px[0]).hypot(p[1] - x.query_px[1]);
        assert!(dist <= 9.0, "{dist}");
        assert!(map.valid()[c]);
    }
    // Bad window: typed error.
    let bad = MnnMatcher::new(MnnConfig {
        window_px: Some(-1.0),
        ..Default::default()
    });
    assert!(matches!(
        bad.match_features(&query, &map, None),
        Err(MatchError::InvalidConfig(_))
    ));
    // A pixel grid needs the grid layout.
    let plain = RenderedPoints::all_valid(1, vec![0.0; 2], vec![[0.0; 3]; 2]).unwrap();
    assert!(plain.with_pixel_grid(QueryGrid::with_stride(4.0)).is_err());
}
