//! End to end on the `tiny` synthetic world: build a map (interrupted mid-stage and resumed),
//! load it, localize the test views with MatLoc (and with a perfect query encoder, which
//! checks everything but the CNN), refuse an unrelated image.

use std::panic::{AssertUnwindSafe, catch_unwind};

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::{Image, Pose};
use matloc_data::synth::{SynthConfig, synthesize};
use matloc_data::{Split, read_dataset};
use matloc_pipeline::build::{BuildEvent, MapConfig, build_map};
use matloc_pipeline::diagnostics::RenderedQueryEncoder;
use matloc_pipeline::methods::{Method, MethodOptions, localize_with};
use matloc_pipeline::render_select::{
    RenderScore, RenderSelectConfig, select_on_renders, selection_views,
};
use matloc_pipeline::stages::LoadedMap;
use matloc_pipeline::{LocalizeOptions, Localizer, LocalizerBlock};
use matloc_pnp::LoRansacPnp;

fn tiny_config() -> MapConfig {
    let mut c = MapConfig::default();
    c.nerf.steps = 300;
    c.nerf.checkpoint_every = 100;
    // A smaller field and batch (as the renderer's own CI tests): same architecture.
    c.nerf.model_overrides = serde_json::json!({
        "field": {"log2_table_size": 15, "max_resolution": 512},
        "train": {"batch_rays": 1024, "march": {"steps": 128, "max_samples": 24},
                  "occupancy_warmup_steps": 32},
        "render": {"march": {"steps": 128}},
    });
    c.encoder.train.steps = 150;
    c.place.train.epochs = 20;
    c.calibration.max_views = 8;
    c
}

#[test]
fn tiny_map_is_built_resumed_and_localizes() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let cfg = SynthConfig::preset("tiny").unwrap();
    synthesize(&cfg, &data, &|_| {}).unwrap();
    let dataset = read_dataset(&data).unwrap();
    let out = dir.path().join("map");
    let config = tiny_config();

    // A build that dies in the middle of training the first encoder.
    let crashed = catch_unwind(AssertUnwindSafe(|| {
        build_map(&dataset, &out, &config, &mut |e| {
            if let BuildEvent::StageFinished { name, seconds, .. } = e {
                eprintln!("stage {name}: {seconds:.1} s");
            }
            if let BuildEvent::StageProgress { done, .. } = e
                && *done >= 10
                && !out.join("blocks/0/encoder.safetensors").exists()
                && out.join("blocks/0/pairs.safetensors").exists()
            {
                panic!("simulated crash");
            }
        })
    }));
    assert!(crashed.is_err(), "the simulated crash did not happen");
    assert!(
        LoadedMap::open(&out).is_err(),
        "an unfinished map must not load"
    );

    // Resume: finished stages are skipped.
    let mut skipped_stages = Vec::new();
    build_map(&dataset, &out, &config, &mut |e| {
        if let BuildEvent::StageFinished {
            name,
            skipped,
            seconds,
        } = e
        {
            eprintln!(
                "stage {name}: {seconds:.1} s{}",
                if *skipped { " (skipped)" } else { "" }
            );
            if *skipped {
                skipped_stages.push(name.clone());
            }
        }
    })
    .unwrap();
    for s in ["partition", "nerf/0", "pairs/0"] {
        assert!(
            skipped_stages.iter().any(|x| x == s),
            "{s} was redone: {skipped_stages:?}"
        );
    }

    let map = LoadedMap::open(&out).unwrap();
    let options = MethodOptions::default();
    let solver = LoRansacPnp::default();
    let within = |p: &Pose, gt: &Pose, t: f64, r: f64| {
        translation_error_m(p, gt) <= t && rotation_error_deg(p, gt) <= r
    };
    let (mut matloc_ok, mut matloc_false, mut oracle_ok, mut oracle_t) = (0, 0, 0, Vec::new());
    let tests: Vec<_> = dataset.split(Split::Test).collect();
    for f in &tests {
        let (image, camera) = matloc_data::images::load_frame_image(&dataset, f, 1).unwrap();
        // The full pipeline: place → encoder → selected features → MNN → PnP → refinement.
        let r = localize_with(&map, Method::Matloc, "q", &image, &camera, &options).unwrap();
        if let Some(p) = r.cam_from_world {
            if within(&p, &f.cam_from_world, 1.0, 5.0) {
                matloc_ok += 1;
            }
            if !within(&p, &f.cam_from_world, 5.0, 10.0) {
                matloc_false += 1;
            }
        }
        // The same map with a perfect query encoder (the block's NeRF features rendered at the
        // true pose), from the place classifier's hypotheses and the uncalibrated prior
        // confidence: what NeRF features, depth, matching, PnP and refinement reach.
        let blk = &map.blocks.0[0];
        let oracle = RenderedQueryEncoder {
            renderer: &blk.renderer,
            camera,
            cam_from_world: f.cam_from_world,
            dims: (0..47).collect(),
            stride: 4,
        };
        let localizer = Localizer {
            place: &map.place,
            blocks: vec![LocalizerBlock {
                renderer: &blk.renderer,
                encoder: &oracle,
                matcher: &blk.matcher,
                dims: blk.dims.clone(),
                match_dims: blk.match_dims.clone(),
            }],
            solver: &solver,
            options: LocalizeOptions::default(),
        };
        match localizer.localize(&image, &camera).unwrap().cam_from_world {
            Some(p) => {
                oracle_t.push(translation_error_m(&p, &f.cam_from_world));
                if within(&p, &f.cam_from_world, 1.0, 2.0) {
                    oracle_ok += 1;
                }
            }
            None => oracle_t.push(f64::INFINITY),
        }
    }
    eprintln!(
        "tiny end to end: matloc {matloc_ok}/{} within 1 m / 5 deg, {matloc_false} false accepts; \
         perfect encoder {oracle_ok} within 1 m / 2 deg, errors {oracle_t:?}",
        tests.len()
    );
    // Measured 2026-12-02 (session 11, two builds; training is not bit-reproducible across
    // runs): 10 of 10 within 0.04–0.66 m and 0.06–0.59 m, medians 0.12 and 0.30 m (session 8:
    // 10 of 10 within 0.03–0.53 m). The median bound is twice the worse of the two.
    assert!(
        oracle_ok >= 3,
        "perfect-encoder run: only {oracle_ok} of 10 localized"
    );
    oracle_t.sort_by(f64::total_cmp);
    let median = 0.5 * (oracle_t[oracle_t.len() / 2 - 1] + oracle_t[oracle_t.len() / 2]);
    assert!(
        median <= 0.6,
        "perfect-encoder run: median translation error {median:.3} m (refusals count as ∞)"
    );
    // The learned encoder is at the edge of working on this CI-sized map (measured
    // 2026-12-02: 3–6 of 10 within 1 m across builds; most maps built with other seeds refuse
    // everything, see docs/BENCHMARKS.md); what must hold is that the calibrated confidence
    // and the a-contrario floor refuse instead of returning wrong poses.
    assert!(matloc_false <= 1, "{matloc_false} wrong poses returned");

    // The paper's Table 3 on this map: every feature set matches and localizes from
    // perturbed true poses with the map's own encoder and localizer.
    let t3cfg = matloc_pipeline::table3::Table3Config {
        max_queries: 4,
        render_scores: vec![RenderScore::MatchF1 { tol_px: 4.0 }],
        ..Default::default()
    };
    let t3 = matloc_pipeline::table3::evaluate(&map, &dataset, &t3cfg, &mut |_, _, _| {}).unwrap();
    eprint!("{}", matloc_pipeline::table3::markdown(&t3));
    let names: Vec<&str> = t3.rows.iter().map(|r| r.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "all-47",
            "pos-32",
            "mlp-15",
            "greedy N_s=10",
            "greedy N_s=5",
            "paper-BIP N_s=10",
            "random-5",
            "render-F1 4 px N_s=5"
        ]
    );
    let sizes: Vec<usize> = t3.rows.iter().map(|r| r.dims[0].len()).collect();
    // The BIP as printed minimises a mean, so it picks a single dim whatever the budget.
    assert_eq!(sizes, [47, 32, 15, 10, 5, 1, 5, 5]);
    assert_eq!((t3.queries, t3.starts), (4, 4));
    assert!(t3.start_t_m <= 3.0 && t3.start_r_deg <= 5.0);
    let all = &t3.rows[0];
    assert!(all.match_ms.is_finite() && all.matches > 0.0);
    assert!(
        all.localized.t_m < t3.start_t_m,
        "all dims: {:.2} m after localization from {:.2} m",
        all.localized.t_m,
        t3.start_t_m
    );
    // Per-start errors back the medians and the paired comparison against all dims.
    for r in &t3.rows {
        assert_eq!(r.localized.per_start_t_m.len(), t3.starts);
        assert_eq!(
            Some(r.localized.t_m),
            matloc_core::metrics::median(&r.localized.per_start_t_m)
        );
    }
    let paired = matloc_pipeline::table3::paired_markdown(&t3);
    eprint!("{paired}");
    assert_eq!(paired.lines().count(), 2 + t3.rows.len());
    assert!(paired.contains("| all-47 |") && paired.contains("+0.000 m [+0.000, +0.000]"));

    // Selection on held-out renders directly: sorted distinct dims, a positive F1 (the
    // encoder matches some cells within a cell of the truth), bad budgets are typed errors.
    let rs_cfg = RenderSelectConfig::default();
    let blk = &map.blocks.0[0];
    let views = selection_views(blk, &dataset, &map.partition, &map.config, 0, &rs_cfg).unwrap();
    assert!(!views.is_empty());
    let sel = select_on_renders(blk, &views, 3, 3.0, &rs_cfg).unwrap();
    assert_eq!(sel.dims.len(), 3);
    assert!(sel.dims.windows(2).all(|w| w[0] < w[1]) && sel.dims[2] < 47);
    assert!(sel.report.objective > 0.0, "{:?}", sel.report);
    for bad in [0, 48] {
        assert!(matches!(
            select_on_renders(blk, &views, bad, 3.0, &rs_cfg),
            Err(matloc_pipeline::PipelineError::Config(_))
        ));
    }
    assert!(matches!(
        select_on_renders(blk, &[], 5, 3.0, &rs_cfg),
        Err(matloc_pipeline::PipelineError::Config(_))
    ));
    assert!(matches!(
        selection_views(blk, &dataset, &map.partition, &map.config, 9, &rs_cfg),
        Err(matloc_pipeline::PipelineError::Config(_))
    ));

    // An own-encoder row for a set that does not exist is a typed error, not a panic.
    let unknown = matloc_pipeline::table3::Table3Config {
        own_encoder_sets: vec!["greedy N_s=7".into()],
        ..t3cfg
    };
    assert!(matches!(
        matloc_pipeline::table3::evaluate(&map, &dataset, &unknown, &mut |_, _, _| {}),
        Err(matloc_pipeline::PipelineError::Config(_))
    ));

    // An unrelated image (flat grey) is refused, not given a pose.
    let camera = dataset.split(Split::Test).next().unwrap().camera;
    let mut grey = Image::new(camera.width as usize, camera.height as usize, 3);
    grey.data_mut().fill(0.5);
    let r = localize_with(&map, Method::Matloc, "grey", &grey, &camera, &options).unwrap();
    assert!(r.cam_from_world.is_none(), "a grey image was localized");
}
