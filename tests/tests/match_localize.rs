//! Localization from a perturbed pose on the tiny synthetic preset: render the map at the coarse
//! pose, match query features against it, solve PnP. Query features are rendered at the true
//! pose (a perfect encoder), so this checks the matching + PnP chain, the sub-cell refinement
//! and the geometry of the lifted map points, not the encoder.

use matloc_core::FeatureMap;
use matloc_core::metrics::{median, rotation_error_deg, translation_error_m};
use matloc_data::dataset::Split;
use matloc_match::ViewRenderer;
use matloc_match::localize::{
    LocalizeConfig, correct_matches, localize, render_map_points, solve_pose, timed_match,
};
use matloc_match::{
    FeatureStats, MatchError, Matcher, MnnConfig, MnnMatcher, QueryFeatures, SubcellConfig,
};
use matloc_pipeline::gt::{PerturbKind, Perturbation};
use matloc_pnp::LoRansacPnp;
use matloc_synth::oracle::{SynthFeatureField, SynthFeatureRenderer, SynthFieldConfig};
use matloc_synth::{SurveyPlan, SynthConfig, World, plan_survey};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// The tiny preset's survey plan, its analytic feature renderer and all of its feature dims.
fn tiny_scene() -> (SurveyPlan, SynthFeatureRenderer, Vec<usize>) {
    let cfg = SynthConfig::preset("tiny").unwrap();
    let world = World::generate(&cfg.world, cfg.seed).unwrap();
    let plan = plan_survey(&world, &cfg.survey, cfg.seed).unwrap();
    let renderer =
        SynthFeatureRenderer::new(world, SynthFeatureField::new(SynthFieldConfig::default()));
    let all: Vec<usize> = (0..renderer.num_features()).collect();
    (plan, renderer, all)
}

#[test]
fn localizes_from_a_perturbed_pose() {
    let (plan, renderer, all) = tiny_scene();
    let tests: Vec<_> = plan
        .frames
        .iter()
        .filter(|f| f.split == Split::Test)
        .take(4)
        .collect();
    assert!(!tests.is_empty());
    // Stated perturbation of the start: uniform ball, 3 m and 5 degrees.
    let perturb = Perturbation {
        kind: PerturbKind::UniformBall,
        translation_m: 3.0,
        rotation_deg: 5.0,
    };
    let solver = LoRansacPnp::default();
    let (mut t0, mut t1, mut t2, mut r1, mut precision) = (vec![], vec![], vec![], vec![], vec![]);
    let mut t_off = vec![];
    for (k, f) in tests.iter().enumerate() {
        let truth = &f.cam_from_world;
        let q = renderer.render_view(&f.camera, truth, 4, &all).unwrap();
        let qmap = FeatureMap::from_vec(q.cols, q.rows, all.len(), q.features.clone()).unwrap();
        let query = QueryFeatures::new(qmap, 4.0);
        let mut rng = ChaCha8Rng::seed_from_u64(k as u64);
        let coarse = perturb.apply(truth, &mut rng);
        let map = render_map_points(&renderer, &f.camera, &coarse, 4, &all, 0.5).unwrap();
        let stats = FeatureStats::from_features(map.features(), map.dims());
        let matcher = MnnMatcher::new(MnnConfig {
            stats: Some(stats),
            ..Default::default()
        });
        let tm = timed_match(&matcher, &query, &map, None).unwrap();
        assert!(tm.matches.len() > 100, "{} matches", tm.matches.len());
        let ok = correct_matches(&tm.matches, &f.camera, truth, 2.0);
        precision.push(ok as f64 / tm.matches.len() as f64);
        let res = solve_pose(&tm.matches, &f.camera, &solver, &mut rng).unwrap();
        t0.push(translation_error_m(&coarse, truth));
        t1.push(translation_error_m(&res.cam_from_world, truth));
        // The same round without sub-cell refinement.
        let plain = MnnMatcher::new(MnnConfig {
            subcell: SubcellConfig::off(),
            ..matcher.config.clone()
        });
        let tp = timed_match(&plain, &query, &map, None).unwrap();
        let rp = solve_pose(&tp.matches, &f.camera, &solver, &mut rng).unwrap();
        t_off.push(translation_error_m(&rp.cam_from_world, truth));
        r1.push(rotation_error_deg(&res.cam_from_world, truth));
        // The library loop: two render-match-PnP rounds, the second at the first estimate.
        let two = localize(
            &renderer,
            &matcher,
            &solver,
            &query,
            &f.camera,
            &coarse,
            &all,
            None,
            &LocalizeConfig {
                iterations: 2,
                ..Default::default()
            },
            &mut rng,
        )
        .unwrap();
        assert_eq!(two.match_time.len(), 2);
        t2.push(translation_error_m(&two.cam_from_world, truth));
    }
    let (m0, m1, mr) = (
        median(&t0).unwrap(),
        median(&t1).unwrap(),
        median(&r1).unwrap(),
    );
    let m2 = median(&t2).unwrap();
    let mp = precision.iter().sum::<f64>() / precision.len() as f64;
    eprintln!(
        "start {m0:.3} m, one round {m1:.3} m / {mr:.3} deg, two rounds {m2:.3} m, \
         unrefined {:.3} m",
        median(&t_off).unwrap()
    );
    // Measured (2026-12-01): start 2.62 m; one round 0.152 m / 0.26° (unrefined 0.254 m, the
    // stride-4 grid's quantisation at ~0.3 m per cell on the ground); two rounds 0.076 m (the
    // unrefined loop cannot improve on round one). Thresholds leave ~40 % margin.
    assert!(mp > 0.5, "match precision {mp:.3}");
    let m_off = median(&t_off).unwrap();
    assert!(
        m1 < 0.22 && m1 < m0 / 10.0,
        "median t error {m1:.3} m from {m0:.3} m"
    );
    assert!(
        m1 < 0.8 * m_off,
        "refined {m1:.3} m vs unrefined {m_off:.3} m"
    );
    assert!(mr < 0.5, "median R error {mr:.3} deg");
    assert!(
        m2 < 0.12 && m2 < m0 / 20.0,
        "two rounds: median t error {m2:.3} m from {m0:.3} m"
    );
}

#[test]
fn dimension_mismatch_and_empty_map_are_typed_errors() {
    let q = QueryFeatures::new(FeatureMap::new(2, 2, 5), 4.0);
    let map =
        matloc_match::RenderedPoints::new(4, vec![0.0; 4], vec![[0.0; 3]], vec![true]).unwrap();
    let m = MnnMatcher::default();
    assert!(matches!(
        m.match_features(&q, &map, None),
        Err(MatchError::DimensionMismatch { query: 5, map: 4 })
    ));
    let empty =
        matloc_match::RenderedPoints::new(5, vec![0.0; 5], vec![[0.0; 3]], vec![false]).unwrap();
    assert!(matches!(
        m.match_features(&q, &empty, None),
        Err(MatchError::Empty { .. })
    ));
}

/// Feature-metric refinement after PnP (what the pipeline's localizer does after each pass),
/// with a perfect encoder: it must keep the accuracy of sub-cell matching + PnP (measured over
/// 6 test views from 3 m / 5° starts, median 2.48 m: PnP 0.111 m, refined 0.112 m; on another
/// draw of starts 0.061 → 0.049 m).
///
/// Its gain is with a learned encoder, whose matches are few and a cell or two off
/// (`research/examples/encoder_study.rs`, tiny NeRF: PnP median 1.58 m → 0.61 m, 8 → 23 of 30 starts
/// within 1 m). With independent per-cell noise on exact features (±0.3, standing in for an
/// encoder) it does not help (0.32 m → 0.91 m): interpolating between cells averages the
/// noise, so the cost is lowest where points fall between cells, a bias that a learned
/// encoder's spatially smooth errors do not show. That case is stated here, not asserted.
#[test]
fn feature_metric_refinement_keeps_exact_matching_accuracy() {
    use matloc_match::featuremetric::{FeatureMetricConfig, refine_pose};
    let (plan, renderer, all) = tiny_scene();
    let perturb = Perturbation {
        kind: PerturbKind::UniformBall,
        translation_m: 3.0,
        rotation_deg: 5.0,
    };
    let solver = LoRansacPnp::default();
    let (mut e_start, mut e_pnp, mut e_fm) = (vec![], vec![], vec![]);
    for (k, f) in plan
        .frames
        .iter()
        .filter(|f| f.split == Split::Test)
        .take(6)
        .enumerate()
    {
        let truth = &f.cam_from_world;
        let q = renderer.render_view(&f.camera, truth, 4, &all).unwrap();
        let query = QueryFeatures::new(
            FeatureMap::from_vec(q.cols, q.rows, all.len(), q.features.clone()).unwrap(),
            4.0,
        );
        let mut rng = ChaCha8Rng::seed_from_u64(100 + k as u64);
        let coarse = perturb.apply(truth, &mut rng);
        let map = render_map_points(&renderer, &f.camera, &coarse, 4, &all, 0.5).unwrap();
        let stats = FeatureStats::from_features(map.features(), map.dims());
        let matcher = MnnMatcher::new(MnnConfig {
            stats: Some(stats.clone()),
            ..Default::default()
        });
        let tm = timed_match(&matcher, &query, &map, None).unwrap();
        let pnp = solve_pose(&tm.matches, &f.camera, &solver, &mut rng).unwrap();
        let fm = refine_pose(
            &query,
            &map,
            &f.camera,
            &pnp.cam_from_world,
            None,
            Some(&stats),
            true,
            &FeatureMetricConfig::default(),
        )
        .unwrap();
        e_start.push(translation_error_m(&coarse, truth));
        e_pnp.push(translation_error_m(&pnp.cam_from_world, truth));
        e_fm.push(translation_error_m(&fm.cam_from_world, truth));
        // A right pose: the features agree there much better than two cells off.
        assert!(fm.contrast > 0.1, "contrast {}", fm.contrast);
        assert!(fm.final_cost <= fm.initial_cost);
    }
    let (m0, m_pnp, m_fm) = (
        median(&e_start).unwrap(),
        median(&e_pnp).unwrap(),
        median(&e_fm).unwrap(),
    );
    println!("exact features: start {m0:.2} m, PnP {m_pnp:.3} m, + feature-metric {m_fm:.3} m");
    // The same bound as one round of `localizes_from_a_perturbed_pose`.
    assert!(m_fm < 0.22 && m_fm < m0 / 10.0, "{m_fm} m from {m0} m");
    assert!(
        m_fm <= 1.05 * m_pnp,
        "PnP {m_pnp:.3} m, refined {m_fm:.3} m"
    );
}
