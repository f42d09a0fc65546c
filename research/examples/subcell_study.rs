//! Sub-cell refinement study on the synthetic world: localization from perturbed starts with
//! query features rendered at the true pose (optionally plus uniform noise, a stand-in for an
//! imperfect encoder), for each refinement setting.
//!
//! `cargo run --release -p matloc-research --example subcell_study -- [preset] [views] [noise]`

use matloc_core::FeatureMap;
use matloc_core::metrics::{median, rotation_error_deg, translation_error_m};
use matloc_data::dataset::Split;
use matloc_match::ViewRenderer;
use matloc_match::localize::{LocalizeConfig, localize, render_map_points, timed_match};
use matloc_match::{
    FeatureStats, MnnConfig, MnnMatcher, QueryFeatures, SubcellConfig, SubcellFit, SubcellSide,
};
use matloc_pipeline::gt::{PerturbKind, Perturbation};
use matloc_pnp::LoRansacPnp;
use matloc_synth::oracle::{SynthFeatureField, SynthFeatureRenderer, SynthFieldConfig};
use matloc_synth::{SynthConfig, World, plan_survey};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let preset = args.get(1).map(String::as_str).unwrap_or("tiny");
    let views: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(10);
    let noise: f32 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(0.0);
    let cfg = SynthConfig::preset(preset).unwrap();
    let world = World::generate(&cfg.world, cfg.seed).unwrap();
    let plan = plan_survey(&world, &cfg.survey, cfg.seed).unwrap();
    let renderer =
        SynthFeatureRenderer::new(world, SynthFeatureField::new(SynthFieldConfig::default()));
    let all: Vec<usize> = (0..renderer.num_features()).collect();
    let tests: Vec<_> = plan
        .frames
        .iter()
        .filter(|f| f.split == Split::Test)
        .take(views)
        .collect();
    let perturb = Perturbation {
        kind: PerturbKind::UniformBall,
        translation_m: 3.0,
        rotation_deg: 5.0,
    };
    let sc = |side, fit| SubcellConfig {
        side,
        fit,
        ..Default::default()
    };
    use SubcellFit::{Gradient, Parabola, Quadratic};
    use SubcellSide::{Map, Off, Query};
    let settings: Vec<(&str, SubcellConfig, usize)> = vec![
        ("off", sc(Off, Parabola), 1),
        ("off x3", sc(Off, Parabola), 3),
        ("query-parabola", sc(Query, Parabola), 1),
        ("query-gradient", sc(Query, Gradient), 1),
        ("query-quadratic", sc(Query, Quadratic), 1),
        ("query-quadratic x3", sc(Query, Quadratic), 3),
        ("map-parabola", sc(Map, Parabola), 1),
        ("map-gradient", sc(Map, Gradient), 1),
        ("map-quadratic", sc(Map, Quadratic), 1),
        ("map-gradient x3", sc(Map, Gradient), 3),
        ("map-quadratic x2", sc(Map, Quadratic), 2),
        ("map-quadratic x3", sc(Map, Quadratic), 3),
    ];
    println!(
        "{preset}: {} test views, noise ±{noise}, start 3 m / 5° ball",
        tests.len()
    );
    let solver = LoRansacPnp::default();
    let mut starts = vec![];
    for (name, sc, iters) in &settings {
        let (mut t, mut r, mut px) = (vec![], vec![], vec![]);
        let (mut ms47, mut ms5) = (vec![], vec![]);
        starts.clear();
        for (k, f) in tests.iter().enumerate() {
            let truth = &f.cam_from_world;
            let q = renderer.render_view(&f.camera, truth, 4, &all).unwrap();
            let mut nrng = ChaCha8Rng::seed_from_u64(1000 + k as u64);
            let feats: Vec<f32> = q
                .features
                .iter()
                .map(|v| v + noise * nrng.random_range(-1.0f32..1.0))
                .collect();
            let qmap = FeatureMap::from_vec(q.cols, q.rows, all.len(), feats).unwrap();
            let query = QueryFeatures::new(qmap, 4.0);
            let mut rng = ChaCha8Rng::seed_from_u64(k as u64);
            let coarse = perturb.apply(truth, &mut rng);
            starts.push(translation_error_m(&coarse, truth));
            let map = render_map_points(&renderer, &f.camera, &coarse, 4, &all, 0.5).unwrap();
            let matcher = MnnMatcher::new(MnnConfig {
                stats: Some(FeatureStats::from_features(map.features(), map.dims())),
                subcell: sc.clone(),
                ..Default::default()
            });
            // Correspondence quality of one round at the start: reprojection error at the truth.
            let tm = timed_match(&matcher, &query, &map, None).unwrap();
            let t5 = timed_match(&matcher, &query, &map, Some(&[3, 9, 20, 33, 40])).unwrap();
            ms47.push(tm.elapsed.as_secs_f64() * 1e3);
            ms5.push(t5.elapsed.as_secs_f64() * 1e3);
            for m in &tm.matches {
                if let Some(u) = f
                    .camera
                    .project_world(truth, &nalgebra::Point3::from(m.point_world))
                {
                    px.push((u.x - m.query_px[0]).hypot(u.y - m.query_px[1]));
                }
            }
            match localize(
                &renderer,
                &matcher,
                &solver,
                &query,
                &f.camera,
                &coarse,
                &all,
                None,
                &LocalizeConfig {
                    iterations: *iters,
                    ..Default::default()
                },
                &mut rng,
            ) {
                Ok(o) => {
                    t.push(translation_error_m(&o.cam_from_world, truth));
                    r.push(rotation_error_deg(&o.cam_from_world, truth));
                }
                Err(e) => eprintln!("{name} view {k}: {e}"),
            }
        }
        let mut ts = t.clone();
        ts.sort_by(f64::total_cmp);
        println!(
            "{name:>18}: median t {:.3} m (start {:.2} m), R {:.3}°, n={} max t {:.3}; reproj px median {:.3} p25 {:.3}; match ms 47-d {:.2} 5-d {:.2}",
            median(&t).unwrap_or(f64::NAN),
            median(&starts).unwrap_or(f64::NAN),
            median(&r).unwrap_or(f64::NAN),
            t.len(),
            ts.last().copied().unwrap_or(f64::NAN),
            median(&px).unwrap_or(f64::NAN),
            {
                px.sort_by(f64::total_cmp);
                px.get(px.len() / 4).copied().unwrap_or(f64::NAN)
            },
            median(&ms47).unwrap_or(f64::NAN),
            median(&ms5).unwrap_or(f64::NAN)
        );
    }
}
