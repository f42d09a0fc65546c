//! End to end on the `tiny` synthetic world, one map built once for all the tests here: the
//! build is interrupted mid-stage and resumed; the map localizes the test views with the
//! learned query encoder and with a perfect one (which checks everything but the CNN), refuses
//! an unrelated image, and runs the paper's Table 3 and the selection on held-out renders; maps
//! of the same world built without depth files localize nearly as well.
//!
//! The maps here are built on one thread, where the same data and config give the same map
//! (`reproducible.rs`): rayon's parallel reductions would associate the training's sums in
//! whatever order the work was stolen, and every floor below would then be a draw.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

mod bin_path;
use bin_path::matloc_bin;
mod fs_tree;
use fs_tree::copy_tree;
mod map_sizes;

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::{Image, Pose};
use matloc_data::{Dataset, PointSource, Split, read_dataset};
use matloc_pipeline::LoadedMap;
use matloc_pipeline::build::select::{select_on_renders, selection_views};
use matloc_pipeline::build::{BuildEvent, MapConfig, build_map};
use matloc_pipeline::config::{RenderScore, RenderSelectConfig};
use matloc_pipeline::eval::diagnostics::RenderedQueryEncoder;
use matloc_pipeline::eval::table3::{Table3Config, evaluate, markdown, paired_markdown};
use matloc_pipeline::methods::{
    LocalizationMethod, Method, MethodOptions, QueryResult, localize_with,
};
use matloc_pipeline::{LocalizeOptions, Localizer, LocalizerBlock, PipelineError};
use matloc_place::{PlaceHypothesis, PlacePredictor};
use matloc_pnp::LoRansacPnp;
use matloc_surface::SurfaceKind;
use matloc_synth::{SynthConfig, SynthOutput, synthesize, synthesize_with};

fn tiny_config() -> MapConfig {
    tiny_sized(MapConfig::default())
}

/// `c` with the end-to-end map's training sizes.
fn tiny_sized(mut c: MapConfig) -> MapConfig {
    c.nerf.steps = 300;
    c.nerf.checkpoint_every = 100;
    c.nerf.model_overrides = map_sizes::small_nerf_overrides();
    // 600 encoder steps (about 30 s): at 150 the encoder found a fifth as many correct
    // matches, and ten queries could not tell a lens or a second flight from chance.
    c.encoder.train.steps = 600;
    c.place.train.epochs = 20;
    c.calibration.max_views = 8;
    c
}

/// The map built once: its dataset, directory, and what the interrupted build showed.
struct Built {
    dataset: Dataset,
    map_dir: PathBuf,
    /// Whether the simulated crash happened.
    crashed: bool,
    /// Whether the unfinished map refused to load.
    unfinished_refused: bool,
    /// Stages the resumed build skipped.
    skipped: Vec<String>,
}

/// The tiny world synthesised afresh into the test directory `name` (its `data`), and where
/// its map goes (`map`).
fn fresh_tiny(name: &str) -> (Dataset, PathBuf) {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    let _ = std::fs::remove_dir_all(&dir);
    let data = dir.join("data");
    synthesize(&SynthConfig::preset("tiny").unwrap(), &data, &|_| {}).unwrap();
    (read_dataset(&data).unwrap(), dir.join("map"))
}

/// `build_map` in a one-thread pool: a reproducible map.
fn build_one_thread(
    dataset: &Dataset,
    map_dir: &Path,
    config: &MapConfig,
    on_event: &mut (dyn FnMut(&BuildEvent) + Send),
) -> Result<(), PipelineError> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| build_map(dataset, map_dir, config, on_event))
        .map(|_| ())
}

fn built() -> &'static Built {
    static BUILT: OnceLock<Built> = OnceLock::new();
    BUILT.get_or_init(|| {
        let (dataset, map_dir) = fresh_tiny("end_to_end_tiny");
        let config = tiny_config();

        // A build that dies in the middle of training the first encoder.
        let crashed = catch_unwind(AssertUnwindSafe(|| {
            build_one_thread(&dataset, &map_dir, &config, &mut |e| {
                if let BuildEvent::StageFinished { name, seconds, .. } = e {
                    eprintln!("stage {name}: {seconds:.1} s");
                }
                if let BuildEvent::StageProgress { done, .. } = e
                    && *done >= 10
                    && !map_dir.join("blocks/0/encoder.safetensors").exists()
                    && map_dir.join("blocks/0/pairs.safetensors").exists()
                {
                    panic!("simulated crash");
                }
            })
        }))
        .is_err();
        let unfinished_refused = LoadedMap::open(&map_dir).is_err();

        // Resume: finished stages are skipped.
        let mut skipped = Vec::new();
        build_one_thread(&dataset, &map_dir, &config, &mut |e| {
            if let BuildEvent::StageFinished {
                name,
                skipped: s,
                seconds,
            } = e
            {
                eprintln!(
                    "stage {name}: {seconds:.1} s{}",
                    if *s { " (skipped)" } else { "" }
                );
                if *s {
                    skipped.push(name.clone());
                }
            }
        })
        .unwrap();
        Built {
            dataset,
            map_dir,
            crashed,
            unfinished_refused,
            skipped,
        }
    })
}

/// The pose MatLoc finds for test view `f` when the query's features are block 0's NeRF
/// features rendered at the true pose (a perfect encoder): hypotheses from `place`, the
/// uncalibrated prior confidence, matching on `match_dims` of the block's dims.
fn perfect_encoder_pose(
    map: &LoadedMap,
    place: &dyn PlacePredictor,
    image: &Image<f32>,
    camera: matloc_core::Camera,
    f: &matloc_data::Frame,
    match_dims: Option<Vec<usize>>,
) -> Option<Pose> {
    let blk = &map.blocks.0[0];
    let oracle = RenderedQueryEncoder {
        renderer: blk.renderer.as_ref(),
        camera,
        cam_from_world: f.cam_from_world,
        dims: (0..47).collect(),
        stride: 4,
    };
    let solver = LoRansacPnp::default();
    let localizer = Localizer {
        place,
        blocks: vec![LocalizerBlock {
            renderer: blk.renderer.as_ref(),
            encoder: &oracle,
            matcher: blk.matcher.as_ref(),
            dims: blk.dims.clone(),
            match_dims,
        }],
        solver: &solver,
        options: LocalizeOptions::default(),
    };
    localizer.localize(image, &camera).unwrap().cam_from_world
}

/// Method options that stop MatLoc after its NeRF-feature passes (no keypoint finish): the
/// learned-encoder floors below measure the paper's pipeline itself.
fn features_only() -> MethodOptions {
    let mut o = MethodOptions::default();
    o.matloc.keypoint_finish = false;
    o
}

fn within(p: &Pose, gt: &Pose, t: f64, r: f64) -> bool {
    translation_error_m(p, gt) <= t && rotation_error_deg(p, gt) <= r
}

#[test]
fn an_interrupted_build_resumes_without_redoing_finished_stages() {
    let b = built();
    assert!(b.crashed, "the simulated crash did not happen");
    assert!(b.unfinished_refused, "an unfinished map must not load");
    for s in ["partition", "nerf/0", "pairs/0"] {
        assert!(
            b.skipped.iter().any(|x| x == s),
            "{s} was redone: {:?}",
            b.skipped
        );
    }
    assert!(
        !b.skipped.iter().any(|x| x == "encoder/0"),
        "the interrupted stage was skipped"
    );
}

#[test]
fn matloc_localizes_test_views_with_the_learned_encoder() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let options = features_only();
    let tests: Vec<_> = b.dataset.split(Split::Test).collect();
    let (mut ok, mut wrong, mut errors) = (0, 0, Vec::new());
    for f in &tests {
        let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
        // The full pipeline: place → encoder → selected features → MNN → PnP → refinement.
        let r = localize_with(&map, &Method::Matloc, "q", &image, &camera, &options).unwrap();
        if let Some(p) = r.cam_from_world {
            errors.push(translation_error_m(&p, &f.cam_from_world));
            ok += usize::from(within(&p, &f.cam_from_world, 1.0, 5.0));
            wrong += usize::from(!within(&p, &f.cam_from_world, 5.0, 10.0));
        }
    }
    eprintln!(
        "tiny end to end, learned encoder: {ok}/{} within 1 m / 5 deg, {wrong} false accepts, \
         accepted errors {errors:?}",
        tests.len()
    );
    // Measured across builds: 3–7 of 10 within 1 m. The calibrated confidence and the
    // a-contrario floor must refuse rather than return wrong poses.
    assert!(
        ok >= 3,
        "learned encoder: only {ok} of {} within 1 m / 5°",
        tests.len()
    );
    assert!(wrong <= 1, "{wrong} wrong poses returned");
}

/// The calibration stage rerun on a copy of the map with `calibration.queries = rendered`:
/// views rendered halfway between neighbouring training views, which neither the encoder nor
/// the place predictor saw. The record says so, some attempts are correct, and MatLoc with
/// that confidence keeps the learned-encoder floors.
#[test]
fn calibration_on_rendered_views_keeps_matloc_s_floors() {
    use matloc_pipeline::config::CalibrationQueries;
    use matloc_pipeline::map::layout::{CONFIDENCE_FILE, CalibrationRecord};
    let b = built();
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("end_to_end_rendered_calibration");
    let _ = std::fs::remove_dir_all(&dir);
    copy_tree(&b.map_dir, &dir);
    let mut config = tiny_config();
    config.calibration.queries = CalibrationQueries::Rendered;
    let mut map = matloc_pipeline::MapDir::open(&dir).unwrap();
    let manifest = map.manifest_mut();
    manifest.stages.retain(|s| s.name != "calibration");
    manifest.config = serde_json::to_value(&config).unwrap();
    map.save().unwrap();
    let mut rerun = Vec::new();
    build_one_thread(&b.dataset, &dir, &config, &mut |e| {
        if let BuildEvent::StageFinished {
            name,
            skipped: false,
            ..
        } = e
        {
            rerun.push(name.clone());
        }
    })
    .unwrap();
    assert_eq!(rerun, ["calibration"]);

    let map = LoadedMap::open(&dir).unwrap();
    let record: CalibrationRecord = map.dir.read_json(CONFIDENCE_FILE).unwrap();
    assert_eq!(record.queries, CalibrationQueries::Rendered);
    assert_eq!(map.calibrated_on, CalibrationQueries::Rendered);
    let correct = record.samples.iter().filter(|s| s.1).count();
    assert!(
        correct > 0,
        "no correct attempt among {}",
        record.samples.len()
    );
    let options = features_only();
    let (mut ok, mut wrong) = (0, 0);
    for f in b.dataset.split(Split::Test) {
        let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
        let r = localize_with(&map, &Method::Matloc, "q", &image, &camera, &options).unwrap();
        if let Some(p) = r.cam_from_world {
            ok += usize::from(within(&p, &f.cam_from_world, 1.0, 5.0));
            wrong += usize::from(!within(&p, &f.cam_from_world, 5.0, 10.0));
        }
    }
    eprintln!(
        "rendered calibration: {correct} of {} attempts correct; MatLoc {ok}/10 within 1 m, \
         {wrong} false accepts",
        record.samples.len()
    );
    assert!(ok >= 3, "only {ok} of 10 within 1 m / 5°");
    assert!(wrong <= 1, "{wrong} wrong poses returned");
}

/// Bound on the default method's median translation error on the `tiny` test views (160×120,
/// ≈ 0.22 m per pixel on the ground): measured 0.038–0.059 m from the place hypotheses with
/// patch alignment (correlation floors 0.9–0.96), 0.100 m without; the bound leaves most of
/// that again for build-to-build spread.
const MEDIAN_BOUND_M: f64 = 0.10;

/// The default localizer (`Method::Structure`: the query's keypoints against the points
/// triangulated from the training images, starting from the learned place predictor's
/// hypotheses) on the test views.
#[test]
fn the_default_method_localizes_test_views_to_centimetres() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    assert_eq!(Method::DEFAULT, Method::Structure);
    let options = MethodOptions::default();
    let tests: Vec<_> = b.dataset.split(Split::Test).collect();
    let (mut ok, mut wrong, mut errors) = (0, 0, Vec::new());
    for f in &tests {
        let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
        let r = localize_with(&map, &Method::DEFAULT, "q", &image, &camera, &options).unwrap();
        match r.cam_from_world {
            Some(p) => {
                errors.push(translation_error_m(&p, &f.cam_from_world));
                ok += usize::from(within(&p, &f.cam_from_world, 0.25, 2.0));
                wrong += usize::from(!within(&p, &f.cam_from_world, 5.0, 10.0));
            }
            None => errors.push(f64::INFINITY),
        }
    }
    errors.sort_by(f64::total_cmp);
    eprintln!(
        "tiny end to end, default method: {ok}/{} within 0.25 m / 2 deg, {wrong} false \
         accepts, errors {errors:.3?}",
        tests.len()
    );
    assert!(
        ok >= 8,
        "default method: only {ok} of {} within 0.25 m / 2°",
        tests.len()
    );
    assert_eq!(wrong, 0, "wrong poses returned");
    assert!(
        median(&errors) <= MEDIAN_BOUND_M,
        "median {:.3} m",
        median(&errors)
    );
}

/// `matloc --quiet eval` of the tiny map on its data with `args`, into `name` next to the
/// map; the report directory. Fails the test with the command's output when it fails.
/// MatLoc with its keypoint finish (the default): the poses its NeRF-feature passes reach start
/// the structure localizer, whose confirmed pose replaces MatLoc's. On the test views it
/// reaches (0.25 m, 2°) where the feature passes alone reach about a metre, and returns
/// nothing wrong.
#[test]
fn matloc_s_keypoint_finish_brings_its_poses_to_centimetres() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let tests: Vec<_> = b.dataset.split(Split::Test).collect();
    let count = |options: &MethodOptions| {
        let (mut ok, mut wrong, mut errors) = (0, 0, Vec::new());
        for f in &tests {
            let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
            let r = localize_with(&map, &Method::Matloc, "q", &image, &camera, options).unwrap();
            if let Some(p) = r.cam_from_world {
                // The answer names the hypothesis whose feature pose started it.
                assert_eq!(r.hypotheses.iter().filter(|h| h.accepted).count(), 1);
                errors.push(translation_error_m(&p, &f.cam_from_world));
                ok += usize::from(within(&p, &f.cam_from_world, 0.25, 2.0));
                wrong += usize::from(!within(&p, &f.cam_from_world, 5.0, 10.0));
            }
        }
        (ok, wrong, errors)
    };
    let (finished, finished_wrong, e1) = count(&MethodOptions::default());
    let (features, _, e0) = count(&features_only());
    eprintln!(
        "tiny, MatLoc within 0.25 m / 2 deg: {finished}/{n} with the keypoint finish \
         ({finished_wrong} wrong, errors {e1:.3?}), {features}/{n} without (errors {e0:.3?})",
        n = tests.len()
    );
    assert!(
        finished >= 6 && finished > features,
        "keypoint finish: {finished} of {} within 0.25 m / 2°, {features} without",
        tests.len()
    );
    assert_eq!(finished_wrong, 0, "wrong poses returned");
}

fn eval_tiny(b: &Built, name: &str, args: &[&str]) -> PathBuf {
    let dir = b.map_dir.parent().unwrap();
    let out = dir.join(name);
    let _ = std::fs::remove_dir_all(&out);
    let o = std::process::Command::new(matloc_bin())
        .args(["--quiet", "eval", "--map"])
        .arg(&b.map_dir)
        .arg("--data")
        .arg(dir.join("data"))
        .args(args)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

/// `matloc eval` as a user runs it: the report has the accuracy and time tables, the
/// confidence reliability of the methods that have a confidence (on the test views, which
/// nothing in the build fitted on), and what each row's method was given.
#[test]
fn eval_reports_confidence_reliability_and_what_differs_between_rows() {
    let b = built();
    let out = eval_tiny(b, "eval", &["--methods", "structure,matloc,rgb-keypoints"]);
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    eprintln!("{report}");
    for needle in [
        "## Table 1",
        "## Table 2",
        "## Confidence reliability",
        "| structure | 10 |",
        "| matloc | 10 |",
        "## What differs between the rows",
        "- `structure` (10 queries): the place predictor's top 30 hypotheses (MatLoc gets the first 3)",
        "- `rgb-keypoints` (10 queries): the top-1 hypothesis only (as the paper's comparison), 2 passes, each after the first rendering at the pose the last one solved; refuses when PnP finds no consensus of 6 inliers in any pass, when a pass moves the pose further than the one before, or no training image looks within 37° of the pose's direction; confidence 1 − NFA",
        "(fitted at build time on held-out training views",
    ] {
        assert!(
            report.contains(needle),
            "{needle:?} missing from the report"
        );
    }
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    for m in summary.as_array().unwrap() {
        let r = &m["reliability"];
        let ece = r["ece"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&ece), "{m}");
        let binned: u64 = r["bins"]
            .as_array()
            .unwrap()
            .iter()
            .map(|b| b["queries"].as_u64().unwrap())
            .sum();
        assert_eq!(binned, 10, "{m}");
    }
}

/// rgb-keypoints' second pass, which renders again at the pose the first solved, against the
/// paper's single render (`matloc eval --method-options` with `{"keypoints": {"passes": 1}}`):
/// every returned pose comes from the passes asked for, the report says what the row was
/// given, and two passes return no more wrong poses and no fewer within 1 m, give or take one
/// query (the map's place predictor differs build to build; two runs: one pass 2 and 2 wrong,
/// 0 and 1 within 1 m; two passes 0 and 1 wrong, 1 and 1 within 1 m).
#[test]
fn rgb_keypoints_renders_again_at_the_pose_it_solved() {
    let b = built();
    let options = b.map_dir.parent().unwrap().join("one_pass.json");
    std::fs::write(&options, r#"{"keypoints": {"passes": 1}}"#).unwrap();
    let options = options.to_str().unwrap();
    let out = eval_tiny(
        b,
        "eval_one_pass",
        &["--methods", "rgb-keypoints", "--method-options", options],
    );
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    for needle in [
        "Method options from `",
        "the top-1 hypothesis only (as the paper's comparison), one render at it (the paper's)",
    ] {
        assert!(report.contains(needle), "{needle:?} missing:\n{report}");
    }
    let (mut one, mut wrong_one) = (Vec::new(), 0);
    for line in std::fs::read_to_string(out.join("results.jsonl"))
        .unwrap()
        .lines()
    {
        let r: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!(r["iterations"], 1, "{r}");
        if r["localized"] == true {
            let (t, rot) = (
                r["error_translation_m"].as_f64().unwrap(),
                r["error_rotation_deg"].as_f64().unwrap(),
            );
            one.push(t);
            wrong_one += usize::from(t > 5.0 || rot > 10.0);
        } else {
            one.push(f64::INFINITY);
        }
    }
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let options = MethodOptions::default();
    assert_eq!(options.keypoints.passes, 2);
    let (mut two, mut wrong_two) = (Vec::new(), 0);
    for f in b.dataset.split(Split::Test) {
        let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
        let r = localize_with(&map, &Method::RgbKeypoints, "q", &image, &camera, &options).unwrap();
        match r.cam_from_world {
            Some(p) => {
                assert_eq!(r.iterations, 2);
                two.push(translation_error_m(&p, &f.cam_from_world));
                wrong_two += usize::from(!within(&p, &f.cam_from_world, 5.0, 10.0));
            }
            None => two.push(f64::INFINITY),
        }
    }
    assert_eq!(two.len(), one.len());
    eprintln!(
        "tiny, rgb-keypoints: one pass {one:.3?} ({wrong_one} wrong), two passes {two:.3?} \
         ({wrong_two} wrong)"
    );
    assert!(
        wrong_two <= wrong_one.max(1),
        "two passes: {wrong_two} wrong, one pass {wrong_one}"
    );
    assert!(
        count_within(&two, 1.0) + 1 >= count_within(&one, 1.0),
        "fewer within 1 m with two passes"
    );
}

/// `truth` moved by `metres` and turned by `degrees`, in a direction that differs per `i`.
fn offset_start(truth: &Pose, i: usize, metres: f64, degrees: f64) -> Pose {
    let a = i as f64 * 2.399_963;
    let t = nalgebra::Vector3::new(a.cos(), a.sin(), 0.3 * (2.0 * a).sin()).normalize() * metres;
    let axis = nalgebra::Unit::new_normalize(nalgebra::Vector3::new(a.sin(), 0.5, a.cos()));
    let r = nalgebra::UnitQuaternion::from_axis_angle(&axis, degrees.to_radians());
    let wfc = truth.inverse();
    Pose::from_parts(
        nalgebra::Translation3::from(wfc.translation.vector + t),
        wfc.rotation * r,
    )
    .inverse()
}

/// The paper's photometric baselines on the built map: iNeRF (300 iterations) and curriculum
/// iNeRF (200, coarse to fine) from starts 0.4 m / 2° off four test views lower the
/// photometric error they minimise and stay near the truth; through `localize_with`, from the
/// place predictor's first hypothesis, each returns a pose (never a refusal).
#[test]
fn inerf_and_curriculum_inerf_lower_the_photometric_error_from_a_near_start() {
    use matloc_pipeline::baselines::{InerfOptions, inerf, photometric_error};
    use rand::SeedableRng;
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let model = map.nerf(0).unwrap();
    let frames: Vec<_> = b.dataset.split(Split::Test).take(4).collect();
    for (name, options) in [
        ("iNeRF", InerfOptions::inerf()),
        ("curriculum iNeRF", InerfOptions::curriculum()),
    ] {
        let mut report = Vec::new();
        for (i, f) in frames.iter().enumerate() {
            let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
            let start = offset_start(&f.cam_from_world, i, 0.4, 2.0);
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(i as u64);
            let out = inerf(model, &camera, &image, &start, &options, &mut rng).unwrap();
            assert_eq!(out.iterations, options.iterations);
            let p = out.cam_from_world.expect("iNeRF always returns a pose");
            let loss = |p: &Pose| photometric_error(model, &camera, &image, p, 2).unwrap();
            report.push((
                loss(&start),
                loss(&p),
                translation_error_m(&p, &f.cam_from_world),
                rotation_error_deg(&p, &f.cam_from_world),
            ));
        }
        eprintln!("tiny, {name} from 0.4 m / 2° (error before, after; m, deg after): {report:.4?}");
        for &(before, after, t, r) in &report {
            assert!(
                after < before,
                "{name}: photometric error {before} -> {after}"
            );
            assert!(t < 1.0 && r < 5.0, "{name}: ended {t:.3} m / {r:.2}° off");
        }
    }
    let f = frames[0];
    let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
    for method in [Method::Inerf, Method::CurriculumInerf] {
        let r = localize_with(
            &map,
            &method,
            "q",
            &image,
            &camera,
            &MethodOptions::default(),
        )
        .unwrap();
        assert!(r.cam_from_world.is_some(), "{method} refused");
        assert_eq!(
            r.iterations,
            if method == Method::Inerf { 300 } else { 200 }
        );
    }
}

#[test]
fn a_perfect_encoder_bounds_what_matching_pnp_and_refinement_reach() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let (mut ok, mut errors) = (0, Vec::new());
    for f in b.dataset.split(Split::Test) {
        let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
        // From the place classifier's hypotheses, matching on the selected dims.
        let blk = &map.blocks.0[0];
        let place = map.place.as_ref();
        let est = perfect_encoder_pose(&map, place, &image, camera, f, blk.match_dims.clone());
        match est {
            Some(p) => {
                errors.push(translation_error_m(&p, &f.cam_from_world));
                ok += usize::from(within(&p, &f.cam_from_world, 1.0, 2.0));
            }
            None => errors.push(f64::INFINITY),
        }
    }
    eprintln!("tiny end to end, perfect encoder: {ok} within 1 m / 2 deg, errors {errors:?}");
    // Measured across builds: 10 of 10 within 1 m, medians 0.12–0.30 m; the median bound is
    // twice the worse.
    assert!(ok >= 3, "perfect encoder: only {ok} of 10 localized");
    errors.sort_by(f64::total_cmp);
    let median = 0.5 * (errors[errors.len() / 2 - 1] + errors[errors.len() / 2]);
    assert!(
        median <= 0.6,
        "perfect encoder: median translation error {median:.3} m (refusals count as ∞)"
    );
}

#[test]
fn an_unrelated_image_is_refused() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let camera = b.dataset.split(Split::Test).next().unwrap().camera;
    let mut grey = Image::new(camera.width as usize, camera.height as usize, 3);
    grey.data_mut().fill(0.5);
    let options = MethodOptions::default();
    for method in [Method::Matloc, Method::Structure] {
        let r = localize_with(&map, &method, "grey", &grey, &camera, &options).unwrap();
        assert!(
            r.cam_from_world.is_none(),
            "{method}: a grey image was localized"
        );
    }
}

/// A method that answers every query with one fixed pose (a plug-in, not a built-in).
struct FixedAnswer {
    pose: Pose,
    calls: std::sync::atomic::AtomicUsize,
}

impl LocalizationMethod for FixedAnswer {
    fn name(&self) -> &str {
        "fixed-answer"
    }

    fn localize(
        &self,
        _map: &LoadedMap,
        name: &str,
        _image: &Image<f32>,
        _camera: &matloc_core::Camera,
        _options: &MethodOptions,
    ) -> Result<QueryResult, PipelineError> {
        self.calls.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        Ok(QueryResult {
            name: name.to_string(),
            method: self.name().to_string(),
            localized: true,
            cam_from_world: Some(self.pose),
            camera_center: Some(matloc_core::pose::camera_center(&self.pose).coords.into()),
            confidence: None,
            inliers: 0,
            iterations: 0,
            hypotheses: Vec::new(),
            stage_seconds: Vec::new(),
            total_seconds: 0.0,
        })
    }
}

/// A method registered by name runs through the same entry points as the built-in ones, with
/// the checks they share: intrinsics no camera has are refused before it runs, and a pose
/// outside the mapped volume is refused whichever method gave it; a batch of query specs and
/// its JSON records take it as they take `structure`.
#[test]
fn a_registered_method_runs_through_the_shared_checks() {
    use matloc_pipeline::methods::{MethodRegistry, MethodRegistryError};
    use std::sync::Arc;
    use std::sync::atomic::Ordering;

    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let f = b.dataset.split(Split::Test).next().unwrap();
    let image = matloc_data::images::load_rgb(&b.dataset.image_path(f)).unwrap();
    let options = MethodOptions::default();
    let inside = Arc::new(FixedAnswer {
        pose: f.cam_from_world,
        calls: Default::default(),
    });
    let mut registry = MethodRegistry::builtin();
    registry.register(inside.clone()).unwrap();
    assert_eq!(
        registry.register(inside.clone()),
        Err(MethodRegistryError::Duplicate("fixed-answer".into()))
    );
    assert_eq!(registry.names()[..2], ["structure", "matloc"]);
    let e = registry.get("nope").unwrap_err().to_string();
    assert!(e.contains("fixed-answer") && e.contains("structure"), "{e}");
    let method = registry.get("fixed-answer").unwrap();

    let r = localize_with(&map, method.as_ref(), "q", &image, &f.camera, &options).unwrap();
    assert_eq!(r.cam_from_world, Some(f.cam_from_world));
    assert_eq!(r.method, "fixed-answer");
    let bad = matloc_core::Camera {
        cx: -5000.0,
        ..f.camera
    };
    let calls = inside.calls.load(Ordering::SeqCst);
    assert!(matches!(
        localize_with(&map, method.as_ref(), "q", &image, &bad, &options),
        Err(PipelineError::ImplausibleCamera(_))
    ));
    assert_eq!(
        inside.calls.load(Ordering::SeqCst),
        calls,
        "ran on a bad camera"
    );

    // 5 km above the survey: outside the mapped volume, refused with the reason.
    let far = FixedAnswer {
        // x_cam = R (x + (0, 0, −5000)) + t: the same camera 5 km higher.
        pose: f.cam_from_world * Pose::translation(0.0, 0.0, -5000.0),
        calls: Default::default(),
    };
    let r = localize_with(&map, &far, "q", &image, &f.camera, &options).unwrap();
    assert!(!r.localized && r.cam_from_world.is_none(), "{r:?}");

    // The query path: specs → records, the plug-in's name in each.
    let spec = matloc_data::query::QuerySpec {
        name: "q.png".into(),
        path: b.dataset.image_path(f),
        camera: Ok(f.camera),
        cam_from_world_gt: Some(f.cam_from_world),
    };
    let records = matloc_pipeline::query::localize_batch(
        &map,
        method.as_ref(),
        &options,
        std::slice::from_ref(&spec),
        |_| Ok::<(), ()>(()),
    )
    .unwrap();
    let world =
        matloc_pipeline::query::OutputWorld::new(matloc_pipeline::query::WorldKind::Data, None)
            .unwrap();
    let v = matloc_pipeline::query::poses::jsonl_record(&records[0], &world).unwrap();
    assert_eq!(v["method"], "fixed-answer");
    assert_eq!(v["error_translation_m"].as_f64(), Some(0.0));
}

#[test]
fn table3_runs_every_feature_set_on_the_built_map() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    // Every feature set matches and localizes from perturbed true poses with the map's own
    // encoder and localizer.
    let t3cfg = Table3Config {
        max_queries: 4,
        render_scores: vec![RenderScore::MatchF1 { tol_px: 4.0 }],
        ..Default::default()
    };
    let t3 = evaluate(&map, &b.dataset, &t3cfg, &mut |_, _, _| {}).unwrap();
    eprint!("{}", markdown(&t3));
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
    let paired = paired_markdown(&t3);
    eprint!("{paired}");
    assert_eq!(paired.lines().count(), 2 + t3.rows.len());
    assert!(paired.contains("| all-47 |") && paired.contains("+0.000 m [+0.000, +0.000]"));

    // An own-encoder row for a set that does not exist is a typed error, not a panic.
    let unknown = Table3Config {
        own_encoder_sets: vec!["greedy N_s=7".into()],
        ..t3cfg
    };
    assert!(matches!(
        evaluate(&map, &b.dataset, &unknown, &mut |_, _, _| {}),
        Err(PipelineError::Config(_))
    ));
}

#[test]
fn selection_on_held_out_renders_picks_distinct_dims_and_types_its_errors() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let solver = LoRansacPnp::default();
    // Sorted distinct dims, a positive F1 (the encoder matches some cells within a cell of
    // the truth), bad budgets are typed errors.
    let rs_cfg = RenderSelectConfig::default();
    let blk = &map.blocks.0[0];
    let views = selection_views(blk, &b.dataset, &map.partition, &map.config, 0, &rs_cfg).unwrap();
    assert!(!views.is_empty());
    let sel = select_on_renders(blk, &views, 3, 3.0, &rs_cfg, &solver).unwrap();
    assert_eq!(sel.dims.len(), 3);
    assert!(sel.dims.windows(2).all(|w| w[0] < w[1]) && sel.dims[2] < 47);
    assert!(sel.report.objective > 0.0, "{:?}", sel.report);
    for bad in [0, 48] {
        assert!(matches!(
            select_on_renders(blk, &views, bad, 3.0, &rs_cfg, &solver),
            Err(PipelineError::Config(_))
        ));
    }
    assert!(matches!(
        select_on_renders(blk, &[], 5, 3.0, &rs_cfg, &solver),
        Err(PipelineError::Config(_))
    ));
    assert!(matches!(
        selection_views(blk, &b.dataset, &map.partition, &map.config, 9, &rs_cfg),
        Err(PipelineError::Config(_))
    ));
}

/// A map's surface source and its perfect-encoder errors on the test views.
struct Outcome {
    surface: String,
    /// Perfect-encoder translation errors from fixed starts (refusals as ∞), sorted.
    perfect: Vec<f64>,
    /// Test views whose top place hypothesis is within 5 m of the truth.
    place_within_5m: usize,
}

fn median(v: &[f64]) -> f64 {
    0.5 * (v[v.len() / 2 - 1] + v[v.len() / 2])
}

/// A place predictor that answers one fixed coarse pose (block 0).
struct FixedStart(Pose);

impl PlacePredictor for FixedStart {
    fn predict(
        &self,
        _: &Image<f32>,
        _: &matloc_core::Camera,
        _: usize,
    ) -> Result<Vec<PlaceHypothesis>, matloc_place::PlaceError> {
        Ok(vec![PlaceHypothesis {
            group: 0,
            score: 1.0,
            cam_from_world: self.0,
            block: Some(0),
        }])
    }
}

/// The true pose moved by 1.5 m and turned by 2°, in a direction fixed per view index.
fn start_of(truth: &Pose, i: usize) -> Pose {
    offset_start(truth, i, 1.5, 2.0)
}

/// Fixed starts per test view in the surface comparison.
const STARTS_PER_VIEW: usize = 3;

/// Builds a map of `dataset` (unless `config` is `None`: the map exists) and localizes the
/// test views with the perfect encoder, from fixed starts near the truth; also counts how
/// often the map's place predictor puts its first hypothesis within 5 m.
fn build_and_localize(dataset: &Dataset, map_dir: &Path, config: Option<&MapConfig>) -> Outcome {
    let t = std::time::Instant::now();
    if let Some(config) = config {
        let _ = std::fs::remove_dir_all(map_dir);
        build_map(dataset, map_dir, config, &mut |_| {}).unwrap();
    }
    let build_s = t.elapsed().as_secs_f64();
    let surface: serde_json::Value =
        serde_json::from_slice(&std::fs::read(map_dir.join("surface.json")).unwrap()).unwrap();
    let map = LoadedMap::open(map_dir).unwrap();
    let mut perfect = Vec::new();
    let mut place_within_5m = 0;
    for (i, f) in dataset.split(Split::Test).enumerate() {
        let (image, camera) = matloc_data::images::load_frame_image(dataset, f, 1).unwrap();
        let top = map.place.predict(&image, &camera, 1).unwrap();
        place_within_5m += usize::from(
            top.first()
                .is_some_and(|h| translation_error_m(&h.cam_from_world, &f.cam_from_world) <= 5.0),
        );
        // Three starts per view, in different directions: a median over 30 runs rather than
        // 10, so that one view's luck does not decide the comparison.
        for k in 0..STARTS_PER_VIEW {
            let start = FixedStart(start_of(&f.cam_from_world, i + 10 * k));
            perfect.push(
                match perfect_encoder_pose(&map, &start, &image, camera, f, None) {
                    Some(p) => translation_error_m(&p, &f.cam_from_world),
                    None => f64::INFINITY,
                },
            );
        }
    }
    perfect.sort_by(f64::total_cmp);
    let o = Outcome {
        surface: surface["plan"]["kind"].as_str().unwrap_or("?").to_string(),
        perfect,
        place_within_5m,
    };
    eprintln!(
        "{}: surface {}, build {build_s:.0} s, perfect encoder from fixed starts: median {:.3} m \
         (errors {:.3?}); place top-1 within 5 m: {}/10",
        map_dir.display(),
        o.surface,
        median(&o.perfect),
        o.perfect,
        o.place_within_5m
    );
    o
}

fn without_depth(mut d: Dataset) -> Dataset {
    for f in &mut d.frames {
        f.depth_path = None;
    }
    d
}

/// Maps built without depth files — from points triangulated from the posed images alone,
/// from the world exported as a COLMAP model (points3D with tracks), from a nerfstudio folder
/// with a `sparse_pc.ply` — against the depth-supplied build above.
///
/// The comparison localizes the test views with the block's NeRF features rendered at the
/// true pose as the query's (the perfect encoder), matching on every rendered dim, from fixed
/// starts 1.5 m / 2° off the truth: it measures what the surface source changes — the
/// partition, the block's scene box, the NeRF — without the run-to-run noise of CNN training
/// (NeRF training is reproducible; the place classifier and encoder are not). The variants
/// train their encoders for a few steps only (nothing here uses them); their place predictors
/// (trained on NeRF-rendered depth instead of depth files) must put the first hypothesis
/// within 5 m for most test views.
#[test]
fn maps_without_depth_localize_within_1_5x_of_the_depth_build() {
    let b = built();
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("no_depth_tiny");
    let _ = std::fs::remove_dir_all(&dir);
    let data = b.map_dir.parent().unwrap().join("data");
    // The same world's sparse points, written beside the reference dataset.
    let output = SynthOutput {
        depth: true,
        points: true,
    };
    let copy = dir.join("data");
    synthesize_with(
        &SynthConfig::preset("tiny").unwrap(),
        &copy,
        &output,
        &|_| {},
    )
    .unwrap();
    let with_depth = read_dataset(&copy).unwrap();
    assert!(matches!(with_depth.points, Some(PointSource::Ply { .. })));
    assert_eq!(
        with_depth.frames,
        read_dataset(&data).unwrap().frames,
        "not the same world"
    );
    let data = copy;

    // nerfstudio folder with sparse_pc.ply, no depth.
    let ply = without_depth(with_depth.clone());
    // No depth and no points: triangulation.
    let mut bare = without_depth(with_depth.clone());
    bare.points = None;
    // The COLMAP model (images named relative to images/), with the synthetic test split.
    let mut colmap = read_dataset(&data.join("sparse/0")).unwrap();
    assert!(matches!(colmap.points, Some(PointSource::Colmap { .. })));
    for (c, n) in colmap.frames.iter_mut().zip(&with_depth.frames) {
        assert!(n.image_path.ends_with(&c.image_path));
        c.split = n.split;
    }

    let reference = build_and_localize(&b.dataset, &b.map_dir, None);
    assert_eq!(reference.surface, "depth_maps");
    let mut config = tiny_config();
    config.encoder.train.steps = 5;
    config.encoder.train.head_phase.steps = 0;
    let runs = [
        (
            bare,
            "map_triangulated",
            SurfaceKind::Triangulated,
            "triangulated",
        ),
        (
            colmap,
            "map_colmap",
            SurfaceKind::ColmapPoints,
            "colmap_points",
        ),
        (ply, "map_ply", SurfaceKind::PlyPoints, "ply_points"),
    ];
    let bound = 1.5 * median(&reference.perfect);
    let mut failures = Vec::new();
    for (dataset, name, kind, tag) in runs {
        let surface = matloc_surface::plan(
            &dataset,
            &dataset.split_indices(Split::Train),
            matloc_surface::SurfaceChoice::Auto,
        )
        .unwrap();
        assert_eq!(surface.kind, kind);
        // One variant without the structure stage: the default method then fails with an
        // error naming the map, the NeRF methods still localize.
        let mut config = config.clone();
        config.structure.enabled = name != "map_ply";
        let o = build_and_localize(&dataset, &dir.join(name), Some(&config));
        assert_eq!(o.surface, tag);
        if !config.structure.enabled {
            let map = LoadedMap::open(&dir.join(name)).unwrap();
            assert!(map.structure.is_none());
            let f = dataset.split(Split::Test).next().unwrap();
            let (image, camera) = matloc_data::images::load_frame_image(&dataset, f, 1).unwrap();
            let e = localize_with(
                &map,
                &Method::DEFAULT,
                "q",
                &image,
                &camera,
                &Default::default(),
            )
            .unwrap_err()
            .to_string();
            assert!(
                e.contains("no keypoint structure") && e.contains(name),
                "{e}"
            );
        }
        let m = median(&o.perfect);
        if m > bound {
            failures.push(format!(
                "{name}: median {m:.3} m > 1.5 × {:.3} m",
                median(&reference.perfect)
            ));
        }
        if o.place_within_5m + 2 < reference.place_within_5m {
            failures.push(format!(
                "{name}: place top-1 within 5 m for {}/10, the depth build {}/10",
                o.place_within_5m, reference.place_within_5m
            ));
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// Errors of the learned-encoder pipeline (`Method::Matloc`) on `frames` of `dataset`:
/// translation error per query (∞ when refused) and the number of false accepts (returned
/// and > 5 m or > 10°).
fn learned_errors(
    map: &LoadedMap,
    dataset: &Dataset,
    frames: &[&matloc_data::Frame],
) -> (Vec<f64>, usize) {
    method_errors(map, Method::Matloc, dataset, frames)
}

/// [`learned_errors`] for any method.
fn method_errors(
    map: &LoadedMap,
    method: Method,
    dataset: &Dataset,
    frames: &[&matloc_data::Frame],
) -> (Vec<f64>, usize) {
    let options = features_only();
    let mut errors = Vec::new();
    let mut wrong = 0;
    for f in frames {
        let (image, camera) = matloc_data::images::load_frame_image(dataset, f, 1).unwrap();
        let r = localize_with(map, &method, "q", &image, &camera, &options).unwrap();
        errors.push(error_or_wrong(
            r.cam_from_world,
            &f.cam_from_world,
            &mut wrong,
        ));
    }
    (errors, wrong)
}

/// Translation error of a returned pose; ∞ when refused, and ∞ counted in `wrong` when
/// returned outside 5 m / 10° (a false accept).
fn error_or_wrong(est: Option<Pose>, truth: &Pose, wrong: &mut usize) -> f64 {
    match est {
        Some(p) if within(&p, truth, 5.0, 10.0) => translation_error_m(&p, truth),
        Some(p) => {
            eprintln!(
                "false accept: {:.2} m, {:.2}°",
                translation_error_m(&p, truth),
                rotation_error_deg(&p, truth)
            );
            *wrong += 1;
            f64::INFINITY
        }
        None => f64::INFINITY,
    }
}

fn count_within(errors: &[f64], t: f64) -> usize {
    errors.iter().filter(|e| **e <= t).count()
}

/// Two more query poses per test view, near it (each moved 1.5 m and 2° like a fixed start),
/// with `flight`'s camera: thirty queries rather than ten for the learned-encoder
/// comparisons, whose ten-view counts moved by up to three between builds.
fn nearby_queries(
    config: &SynthConfig,
    flight: &matloc_synth::SecondFlight,
) -> (matloc_synth::World, Vec<matloc_data::Frame>) {
    let (world, frames) = matloc_synth::flight::second_flight_frames(config, flight).unwrap();
    let nearby = frames
        .iter()
        .enumerate()
        .flat_map(|(i, f)| {
            (1..3).map(move |k| {
                let mut g = f.clone();
                g.cam_from_world = start_of(&f.cam_from_world, i + 10 * k);
                g
            })
        })
        .collect();
    (world, nearby)
}

/// The queries near the test views ([`nearby_queries`]), rendered in memory as `flight`
/// shoots them.
fn nearby_renders(
    config: &SynthConfig,
    flight: &matloc_synth::SecondFlight,
) -> Vec<(matloc_data::Frame, Image<f32>)> {
    let (world, frames) = nearby_queries(config, flight);
    frames
        .into_iter()
        .enumerate()
        .map(|(j, f)| {
            let image =
                matloc_synth::flight::render_second_flight(&world, config, flight, &f, 100 + j);
            (f, image)
        })
        .collect()
}

/// MatLoc's error on one image with the learned encoder ([`error_or_wrong`]).
fn learned_error(
    map: &LoadedMap,
    image: &Image<f32>,
    camera: &matloc_core::Camera,
    truth: &Pose,
    wrong: &mut usize,
) -> f64 {
    let options = features_only();
    let r = localize_with(map, &Method::Matloc, "q", image, camera, &options).unwrap();
    error_or_wrong(r.cam_from_world, truth, wrong)
}

/// [`learned_errors`] on [`nearby_renders`].
fn learned_errors_rendered(
    map: &LoadedMap,
    config: &SynthConfig,
    flight: &matloc_synth::SecondFlight,
) -> (Vec<f64>, usize) {
    let mut wrong = 0;
    let errors = nearby_renders(config, flight)
        .iter()
        .map(|(f, image)| learned_error(map, image, &f.camera, &f.cam_from_world, &mut wrong))
        .collect();
    (errors, wrong)
}

/// [`thirty_errors`] of the same flight: `b`'s test views and the queries rendered near them.
fn same_flight_errors(b: &Built, map: &LoadedMap) -> (Vec<f64>, usize) {
    let same: Vec<_> = b.dataset.split(Split::Test).collect();
    let config = SynthConfig::preset("tiny").unwrap();
    thirty_errors(
        map,
        &b.dataset,
        &same,
        &config,
        &matloc_synth::SecondFlight::same_flight(),
    )
}

/// MatLoc's errors with the learned encoder on `frames` of `dataset` and on the twenty queries
/// rendered near them as `flight` shoots them ([`nearby_renders`]), and how many were wrong.
fn thirty_errors(
    map: &LoadedMap,
    dataset: &Dataset,
    frames: &[&matloc_data::Frame],
    config: &SynthConfig,
    flight: &matloc_synth::SecondFlight,
) -> (Vec<f64>, usize) {
    let (mut err, wrong) = learned_errors(map, dataset, frames);
    let (near, near_wrong) = learned_errors_rendered(map, config, flight);
    err.extend(near);
    (err, wrong + near_wrong)
}

/// The test views re-shot as a later flight, written to disk and read back as a dataset with
/// `camera_model` OPENCV. With the map's sun (+0.4 EV, warmer white balance, a k1 = −0.05 lens,
/// 0.5 px blur, sensor noise) the learned encoder localizes them about as well as the same
/// flight's views at the same poses: over the ten views and two rendered near each, at most a
/// fifth fewer within 1 m and at most one of the thirty returned wrong.
#[test]
fn a_second_flight_localizes_close_to_the_same_flight() {
    let same_sun = matloc_synth::SecondFlight {
        sun_azimuth_shift_deg: 0.0,
        sun_elevation_deg: None,
        ..matloc_synth::SecondFlight::default()
    };
    against_the_same_flight("second flight, same sun", same_sun, true);
}

/// The full second flight (the sun also turned 55° and lowered to 22°): most queries are
/// refused, and at most one of the thirty may be returned wrong.
#[test]
#[ignore = "not met: one build returned 4 of 30 wrong; on three other tiny worlds under four suns 7 of 45 accepted poses were 5.1-7.5 m off, the tail of MatLoc's metre-level poses crossing the 5 m line (docs/BENCHMARKS.md); with the shadow-invariant place predictor one build gave 0 wrong, 0/30 within 1 m (accepted 1.1-2.7 m), and tiny worlds 101-103 returned 2 of their 30 test views wrong, 1 within 1 m: the encoder is the limit"]
fn a_second_flight_with_the_sun_moved_returns_nothing_wrong() {
    against_the_same_flight(
        "second flight, sun moved",
        matloc_synth::SecondFlight::default(),
        false,
    );
}

/// MatLoc with the learned encoder on `flight` (the ten test views written to disk and read
/// back, and two rendered near each) against the same flight at the same poses: at most one of
/// the thirty wrong and, when `bounded`, at most a fifth fewer within 1 m.
fn against_the_same_flight(name: &str, flight: matloc_synth::SecondFlight, bounded: bool) {
    let b = built();
    let config = SynthConfig::preset("tiny").unwrap();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let (same_err, same_wrong) = same_flight_errors(b, &map);
    let n_same = count_within(&same_err, 1.0);
    let n = same_err.len();
    assert_eq!(n, 30);
    let flown = fly(b, &name.replace([' ', ','], "_"), &flight);
    let second: Vec<_> = flown.split(Split::Test).collect();
    let same: Vec<_> = b.dataset.split(Split::Test).collect();
    assert_eq!(second.len(), same.len());
    for (s, f) in second.iter().zip(&same) {
        assert_eq!(s.cam_from_world, f.cam_from_world);
        assert!(
            (s.camera.distortion.k1 + 0.05).abs() < 1e-12,
            "lens not read back"
        );
    }
    let (err, wrong) = thirty_errors(&map, &flown, &second, &config, &flight);
    let k = count_within(&err, 1.0);
    eprintln!(
        "tiny, learned encoder: same flight {n_same}/{n} within 1 m ({same_wrong} false), \
         {name} {k}/{n} ({wrong} false); errors {same_err:.3?} vs {err:.3?}"
    );
    assert!(wrong <= 1, "{name}: {wrong} false accepts");
    if bounded {
        assert!(
            k + n / 5 >= n_same,
            "{name}: {k}/{n} within 1 m, same flight {n_same}/{n}"
        );
    }
}

/// The tiny world's map built with `configs/another-day.json` (the sun's shadows lifted out of
/// the training images before the NeRF is fitted; the encoder trained towards its features on
/// shadow-augmented, shadow-invariant input), at the end-to-end sizes.
fn built_another_day() -> &'static Built {
    static BUILT: OnceLock<Built> = OnceLock::new();
    BUILT.get_or_init(|| {
        let (dataset, map_dir) = fresh_tiny("end_to_end_tiny_another_day");
        let partial: serde_json::Value =
            serde_json::from_str(include_str!("../../configs/another-day.json")).unwrap();
        let config = MapConfig::from_partial(partial, "configs/another-day.json").unwrap();
        assert!(config.sunlight.enabled && config.encoder.train.net.shadow_invariant);
        build_one_thread(&dataset, &map_dir, &tiny_sized(config), &mut |e| {
            if let BuildEvent::StageFinished { name, seconds, .. } = e {
                eprintln!("another-day map, stage {name}: {seconds:.1} s");
            }
        })
        .unwrap();
        Built {
            dataset,
            map_dir,
            crashed: false,
            unfinished_refused: false,
            skipped: Vec::new(),
        }
    })
}

/// MatLoc's errors on the another-day map, the same flight and the full second flight (sun
/// turned 55° and lowered to 22°, exposure, white balance, lens, blur, noise), thirty queries
/// each, and how many of each were returned wrong; computed once per test run.
struct LiftedRun {
    same: Vec<f64>,
    same_wrong: usize,
    second: Vec<f64>,
    second_wrong: usize,
}

fn lifted_run() -> &'static LiftedRun {
    static RUN: OnceLock<LiftedRun> = OnceLock::new();
    RUN.get_or_init(|| {
        let b = built_another_day();
        let config = SynthConfig::preset("tiny").unwrap();
        let map = LoadedMap::open(&b.map_dir).unwrap();
        let lifted: serde_json::Value =
            serde_json::from_slice(&std::fs::read(b.map_dir.join("sunlight.json")).unwrap())
                .unwrap();
        assert_eq!(lifted["sun_source"], "dataset metadata");
        let (same, same_wrong) = same_flight_errors(b, &map);
        let flight = matloc_synth::SecondFlight::default();
        let flown = fly(b, "second_flight_lifted", &flight);
        let frames: Vec<_> = flown.split(Split::Test).collect();
        let (second, second_wrong) = thirty_errors(&map, &flown, &frames, &config, &flight);
        assert_eq!((same.len(), second.len()), (30, 30));
        let n = same.len();
        eprintln!(
            "tiny, lifted shadows: same flight {}/{n} within 1 m, median {:.3} m ({same_wrong} \
             false); sun moved {}/{n}, median {:.3} m ({second_wrong} false); gain {}",
            count_within(&same, 1.0),
            upper_median(&same),
            count_within(&second, 1.0),
            upper_median(&second),
            lifted["gain"]
        );
        LiftedRun {
            same,
            same_wrong,
            second,
            second_wrong,
        }
    })
}

/// The middle value of `v` (the upper one of an even count), ∞ counted as any other value.
fn upper_median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The full second flight against a map built for queries from another day: MatLoc with the
/// learned encoder localizes it about as well as the same flight (thirty queries each: within
/// 1 m at most a fifth fewer, the median error at most 1.5 times). Measured over six builds:
/// within 1 m 3 / 6 / 5 / 5 / 3 / 4 against 9 / 10 / 2 / 6 / 5 / 10 on the same flight (the
/// first and last at the bound), medians 1.03–1.26×.
#[test]
fn a_second_flight_with_the_sun_moved_localizes_against_a_map_with_its_shadows_lifted() {
    let r = lifted_run();
    let n = r.second.len();
    let (n_same, k) = (count_within(&r.same, 1.0), count_within(&r.second, 1.0));
    assert!(
        k + n / 5 >= n_same,
        "{k}/{n} within 1 m, same flight {n_same}/{n}"
    );
    let (m_same, m) = (upper_median(&r.same), upper_median(&r.second));
    assert!(
        m <= 1.5 * m_same,
        "median {m:.3} m, same flight {m_same:.3} m"
    );
}

/// The same run returns at most one of the thirty second-flight queries wrong (outside 5 m /
/// 10°).
#[test]
#[ignore = "not met reliably: over six builds of the tiny another-day map the moved sun gave 0, 1, 0, 2, 0 and 0 false accepts of 30 (the same flight 3, 0, 0, 0, 0 and 1, that one 5.02 m off), the tail of MatLoc's metre-level poses on this 160x120 world crossing the 5 m line; on `small` and `rubble` 0 of 30 and 0 of 40 (docs/BENCHMARKS.md)"]
fn a_second_flight_with_the_sun_moved_returns_at_most_one_wrong_against_a_map_with_its_shadows_lifted()
 {
    let r = lifted_run();
    assert!(
        r.second_wrong <= 1,
        "{} false accepts (same flight {})",
        r.second_wrong,
        r.same_wrong
    );
}

/// The tiny world's test views re-shot as `flight`, written next to the map into `name` (one
/// directory per test, so tests running at once never share one).
fn fly(b: &Built, name: &str, flight: &matloc_synth::SecondFlight) -> Dataset {
    let config = SynthConfig::preset("tiny").unwrap();
    let dir = b.map_dir.parent().unwrap().join(name);
    let _ = std::fs::remove_dir_all(&dir);
    matloc_synth::synthesize_second_flight(&config, flight, &dir, &|_| {}).unwrap();
    read_dataset(&dir).unwrap()
}

/// The place predictor under the full second flight's sun, exposure and white balance: its
/// top hypothesis is within 15 m of the truth as often as on the same flight, give or take
/// one view (it sees the shadow-invariant channels). Measured on three other tiny worlds
/// under four suns: 100, 100 and 90 % against the same flight's 100, 100 and 90 %; on RGB
/// 70–90 % against 90–100 %.
#[test]
fn the_place_predictor_holds_up_on_a_second_flight() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let flown = fly(
        b,
        "second_flight_place",
        &matloc_synth::SecondFlight::default(),
    );
    let near = |dataset: &Dataset| {
        dataset
            .split(Split::Test)
            .filter(|f| {
                let (image, camera) = matloc_data::images::load_frame_image(dataset, f, 1).unwrap();
                let top = map.place.predict(&image, &camera, 1).unwrap();
                translation_error_m(&top[0].cam_from_world, &f.cam_from_world) <= 15.0
            })
            .count()
    };
    let (same, second) = (near(&b.dataset), near(&flown));
    eprintln!("tiny, place: top hypothesis within 15 m, same flight {same}/10, second {second}/10");
    assert!(same >= 8, "same flight: {same}/10");
    assert!(
        second + 1 >= same,
        "second flight {second}/10, same flight {same}/10"
    );
}

/// The default method on the full second flight (sun turned 55° and lowered to 22°, exposure,
/// white balance, a k1 = −0.05 lens, blur, noise) against the same flight's views at the same
/// poses: the goal of a second-flight median within 1.5× of the same flight's, nothing wrong,
/// and at most two views fewer within 0.5 m. Measured with patch alignment and tracking:
/// 0.072 against 0.052 m (1.38×), 9/10 against 10/10 within 0.5 m; without them
/// the moved sun doubled the median (0.205 against 0.095 m).
#[test]
fn the_default_method_holds_up_on_a_second_flight() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let same: Vec<_> = b.dataset.split(Split::Test).collect();
    let (mut same_err, same_wrong) = method_errors(&map, Method::DEFAULT, &b.dataset, &same);
    let flown = fly(
        b,
        "second_flight_default",
        &matloc_synth::SecondFlight::default(),
    );
    let second: Vec<_> = flown.split(Split::Test).collect();
    let (mut err, wrong) = method_errors(&map, Method::DEFAULT, &flown, &second);
    same_err.sort_by(f64::total_cmp);
    err.sort_by(f64::total_cmp);
    eprintln!(
        "tiny, default method: same flight median {:.3} m, {}/10 within 0.25 m ({same_wrong} \
         false); second flight median {:.3} m, {}/10 ({wrong} false); errors {same_err:.3?} vs \
         {err:.3?}",
        median(&same_err),
        count_within(&same_err, 0.25),
        median(&err),
        count_within(&err, 0.25)
    );
    assert_eq!(same_wrong + wrong, 0, "false accepts");
    assert!(
        median(&err) <= 1.5 * median(&same_err),
        "second flight median {:.3} m > 1.5 × {:.3} m",
        median(&err),
        median(&same_err)
    );
    // Recall at 0.5 m: at most two of the ten views lost to the other day.
    assert!(
        count_within(&err, 0.5) + 2 >= count_within(&same_err, 0.5),
        "second flight {}/10 within 0.5 m, same flight {}/10",
        count_within(&err, 0.5),
        count_within(&same_err, 0.5)
    );
}

/// A query through a distorting lens (k1 = −0.05, same pose and light) localizes as well as
/// its undistorted twin: with the perfect encoder from the same fixed starts, three per query,
/// on the ten views and two twins near each (the geometry: rendering, matching and PnP through
/// the lens model; a median over 90 runs, bound 1.25× + 2 cm), and with the learned encoder on
/// the same thirty (at most a fifth fewer within 1 m). Over the ten views alone (30 runs) the
/// distorted median exceeded the bound in one build of ten.
#[test]
fn a_distorted_query_localizes_as_well_as_its_undistorted_twin() {
    let b = built();
    let config = SynthConfig::preset("tiny").unwrap();
    let lens = matloc_synth::SecondFlight::lens_only(-0.05);
    let (world, frames) = matloc_synth::flight::second_flight_frames(&config, &lens).unwrap();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let same: Vec<_> = b.dataset.split(Split::Test).collect();
    let (mut plain, mut bent) = (Vec::new(), Vec::new());
    let (mut plain_learned, mut bent_learned) = (Vec::new(), Vec::new());
    for (i, (twin, f)) in frames.iter().zip(&same).enumerate() {
        // The planned pose and the one read back from transforms.json (float round trip).
        assert!(within(&twin.cam_from_world, &f.cam_from_world, 1e-6, 1e-6));
        let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
        let distorted = matloc_synth::flight::render_second_flight(&world, &config, &lens, twin, i);
        let err = |p: Option<Pose>| {
            p.map_or(f64::INFINITY, |p| {
                translation_error_m(&p, &f.cam_from_world)
            })
        };
        // Three starts per view, as in the surface comparison, so that a few views' luck with
        // the matches does not decide the median.
        for k in 0..STARTS_PER_VIEW {
            let start = FixedStart(start_of(&f.cam_from_world, i + 10 * k));
            plain.push(err(perfect_encoder_pose(
                &map, &start, &image, camera, f, None,
            )));
            bent.push(err(perfect_encoder_pose(
                &map,
                &start,
                &distorted,
                twin.camera,
                f,
                None,
            )));
        }
        let truth = &f.cam_from_world;
        plain_learned.push(learned_error(&map, &image, &camera, truth, &mut 0));
        bent_learned.push(learned_error(&map, &distorted, &twin.camera, truth, &mut 0));
    }
    // The two twins near each view, rendered in memory through a pinhole and the lens: the
    // perfect encoder from three starts each (90 runs per twin) and the learned encoder.
    let near_plain = nearby_renders(&config, &matloc_synth::SecondFlight::same_flight());
    let near_bent = nearby_renders(&config, &lens);
    for (j, ((p, pi), (d, di))) in near_plain.iter().zip(&near_bent).enumerate() {
        assert!(within(&p.cam_from_world, &d.cam_from_world, 1e-9, 1e-9));
        let truth = &p.cam_from_world;
        let err = |q: Option<Pose>| q.map_or(f64::INFINITY, |q| translation_error_m(&q, truth));
        for k in 0..STARTS_PER_VIEW {
            let start = FixedStart(start_of(truth, 100 + j + 100 * k));
            plain.push(err(perfect_encoder_pose(
                &map, &start, pi, p.camera, p, None,
            )));
            bent.push(err(perfect_encoder_pose(
                &map, &start, di, d.camera, d, None,
            )));
        }
        plain_learned.push(learned_error(&map, pi, &p.camera, truth, &mut 0));
        bent_learned.push(learned_error(&map, di, &d.camera, truth, &mut 0));
    }
    for v in [&mut plain, &mut bent] {
        v.sort_by(f64::total_cmp);
    }
    assert_eq!((plain.len(), bent.len()), (90, 90));
    let n = plain_learned.len();
    assert_eq!((n, bent_learned.len()), (30, 30));
    eprintln!(
        "twins, perfect encoder: undistorted median {:.3} m, distorted {:.3} m; learned: \
         {}/{n} vs {}/{n} within 1 m ({plain_learned:.3?} vs {bent_learned:.3?})",
        median(&plain),
        median(&bent),
        count_within(&plain_learned, 1.0),
        count_within(&bent_learned, 1.0)
    );
    assert!(
        median(&bent) <= 1.25 * median(&plain) + 0.02,
        "distorted median {:.3} m, undistorted {:.3} m",
        median(&bent),
        median(&plain)
    );
    assert!(
        count_within(&bent_learned, 1.0) + n / 5 >= count_within(&plain_learned, 1.0),
        "learned encoder: distorted {:?}, undistorted {:?}",
        bent_learned,
        plain_learned
    );
}

/// The default method through a distorting lens: each test view rendered twice at its pose and
/// in the map's light, through a pinhole and through a k1 = −0.05 lens, the same way (no 8-bit
/// file in between). The distorted twins localize as well as the undistorted ones, nothing
/// returned wrong: the solver's camera model handles the lens (matches stay in distorted
/// pixels).
#[test]
fn the_default_method_localizes_a_distorted_query_as_well_as_its_twin() {
    let b = built();
    let config = SynthConfig::preset("tiny").unwrap();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let same: Vec<_> = b.dataset.split(Split::Test).collect();
    let options = MethodOptions::default();
    let mut wrong = 0;
    let mut errors = |k1: f64| {
        let lens = matloc_synth::SecondFlight::lens_only(k1);
        let (world, frames) = matloc_synth::flight::second_flight_frames(&config, &lens).unwrap();
        let mut out = Vec::new();
        for (i, (twin, f)) in frames.iter().zip(&same).enumerate() {
            assert!(within(&twin.cam_from_world, &f.cam_from_world, 1e-6, 1e-6));
            assert!((twin.camera.distortion.k1 - k1).abs() < 1e-12);
            let image = matloc_synth::flight::render_second_flight(&world, &config, &lens, twin, i);
            let r =
                localize_with(&map, &Method::DEFAULT, "q", &image, &twin.camera, &options).unwrap();
            out.push(error_or_wrong(
                r.cam_from_world,
                &f.cam_from_world,
                &mut wrong,
            ));
        }
        out
    };
    let (mut plain, mut bent) = (errors(0.0), errors(-0.05));
    let (n_plain, n_bent) = (count_within(&plain, 0.25), count_within(&bent, 0.25));
    plain.sort_by(f64::total_cmp);
    bent.sort_by(f64::total_cmp);
    eprintln!(
        "twins, default method: undistorted median {:.3} m ({n_plain}/10 within 0.25 m), \
         distorted {:.3} m ({n_bent}/10); {plain:.3?} vs {bent:.3?}",
        median(&plain),
        median(&bent)
    );
    assert_eq!(wrong, 0, "false accepts");
    assert!(
        median(&bent) <= 1.25 * median(&plain) + 0.02,
        "distorted median {:.3} m, undistorted {:.3} m",
        median(&bent),
        median(&plain)
    );
    assert!(n_bent + 1 >= n_plain, "{n_bent}/10 against {n_plain}/10");
}

/// A start that looks elsewhere (the training pose farthest from the query, as a place
/// predictor gives for a viewpoint the survey never flew) leaves the structure method too few
/// points to match; with retrieval it matches the training images that share the most with
/// the query and localizes it (measured: 9 of 10 within 0.25 m / 2° with it, 1 without).
#[test]
fn structure_retrieval_localizes_from_a_start_that_looks_elsewhere() {
    use rand::SeedableRng;
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let structure = map.structure.as_ref().expect("the map has a structure");
    let train: Vec<_> = b.dataset.split(Split::Train).collect();
    let mut options = matloc_structure::StructureOptions::default();
    let (mut without, mut with, mut wrong) = (0, 0, 0);
    let test: Vec<_> = b.dataset.split(Split::Test).collect();
    for f in &test {
        let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
        let center = matloc_core::pose::camera_center(&f.cam_from_world);
        let far = train
            .iter()
            .max_by(|a, c| {
                let da = (matloc_core::pose::camera_center(&a.cam_from_world) - center).norm();
                let dc = (matloc_core::pose::camera_center(&c.cam_from_world) - center).norm();
                da.total_cmp(&dc)
            })
            .unwrap()
            .cam_from_world;
        let mut run = |retrieval: usize| {
            options.retrieval = retrieval;
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
            let r =
                matloc_structure::localize(structure, &image, &camera, &[far], &options, &mut rng)
                    .unwrap();
            r.cam_from_world.map(|p| {
                (
                    translation_error_m(&p, &f.cam_from_world),
                    rotation_error_deg(&p, &f.cam_from_world),
                )
            })
        };
        let ok = |e: Option<(f64, f64)>| e.is_some_and(|(t, r)| t <= 0.25 && r <= 2.0);
        let (a, c) = (run(0), run(2));
        eprintln!(
            "{}: without retrieval {a:?}, with {c:?}",
            f.image_path.display()
        );
        without += usize::from(ok(a));
        with += usize::from(ok(c));
        // Only the poses retrieval gave (a start's own accepted pose is returned before it).
        wrong += usize::from(a.is_none() && c.is_some_and(|(t, r)| t > 5.0 || r > 10.0));
    }
    eprintln!(
        "within 0.25 m / 2°: {without} without retrieval, {with} with, of {}",
        test.len()
    );
    assert!(with * 10 >= test.len() * 8, "{with} of {}", test.len());
    assert!(with > without, "{with} vs {without}");
    assert_eq!(wrong, 0);
}

/// A test view mirrored (top to bottom, or left to right) is an image no camera takes: the
/// default method returns no pose for any of them. Intrinsics no camera has are rejected before
/// localizing, naming the field; with a focal length 10× too long, any pose returned lies in
/// the mapped volume.
#[test]
fn mirrored_views_and_impossible_intrinsics_get_no_pose() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let options = MethodOptions::default();
    let volume =
        matloc_pipeline::volume::MappedVolume::of_map(&map.partition, map.structure.as_ref())
            .expect("the map has a volume");
    let (mut mirrored_accepted, mut straight_ok) = (Vec::new(), 0);
    for f in b.dataset.split(Split::Test) {
        let (image, camera) = matloc_data::images::load_frame_image(&b.dataset, f, 1).unwrap();
        let (w, h, c) = image.shape();
        for vertical in [true, false] {
            let mut m = Image::new(w, h, c);
            for y in 0..h {
                for x in 0..w {
                    let (sx, sy) = if vertical {
                        (x, h - 1 - y)
                    } else {
                        (w - 1 - x, y)
                    };
                    m.pixel_mut(x, y).copy_from_slice(image.pixel(sx, sy));
                }
            }
            let r = localize_with(&map, &Method::DEFAULT, "mirror", &m, &camera, &options).unwrap();
            if let Some(p) = r.cam_from_world {
                mirrored_accepted.push((vertical, r.inliers, matloc_core::pose::camera_center(&p)));
            }
        }
        let r = localize_with(&map, &Method::DEFAULT, "q", &image, &camera, &options).unwrap();
        straight_ok += usize::from(
            r.cam_from_world
                .is_some_and(|p| within(&p, &f.cam_from_world, 0.25, 2.0)),
        );
        let far = matloc_core::Camera {
            fx: camera.fx * 10.0,
            fy: camera.fy * 10.0,
            ..camera
        };
        let r = localize_with(&map, &Method::DEFAULT, "long", &image, &far, &options).unwrap();
        if let Some(p) = r.cam_from_world {
            let centre = matloc_core::pose::camera_center(&p);
            assert!(
                volume.contains(&centre),
                "a 10× focal gave a camera at {centre}"
            );
        }
        for (field, bad) in [
            (
                "cx",
                matloc_core::Camera {
                    cx: -5000.0,
                    ..camera
                },
            ),
            (
                "p1",
                matloc_core::Camera {
                    distortion: matloc_core::Distortion {
                        p1: 10.0,
                        ..camera.distortion
                    },
                    ..camera
                },
            ),
        ] {
            match localize_with(&map, &Method::DEFAULT, "bad", &image, &bad, &options) {
                Err(PipelineError::ImplausibleCamera(e)) => assert_eq!(e.field(), field, "{e}"),
                other => panic!("{field}: expected an implausible camera, got {other:?}"),
            }
        }
    }
    eprintln!(
        "mirrored views accepted: {mirrored_accepted:?}; straight views within 0.25 m: {straight_ok}"
    );
    assert!(mirrored_accepted.is_empty(), "{mirrored_accepted:?}");
    assert!(straight_ok >= 8, "{straight_ok}");
}

/// Viewpoints the survey never flew: each test view turned about the vertical through the
/// ground point it looks at until no training image looks within the structure method's view
/// angle of it, brought a third of the way closer and pitched 30° nearer the horizon
/// (`matloc_synth::flight::turned_view`). The default method accepts such a pose only when a
/// view rendered there by the block's NeRF agrees with the query: with the renders it
/// localizes some within 0.5 m / 2°, without them none (every consensus is refused as
/// unseen), and neither accepts a wrong pose (measured: 3 of 10 within 0.5 m / 2°, one more
/// at 0.96 m / 2.1°, against 0; `research/examples/unseen_viewpoints.rs`).
#[test]
fn renders_confirm_viewpoints_the_survey_never_flew() {
    let b = built();
    let map = LoadedMap::open(&b.map_dir).unwrap();
    let structure = map.structure.as_ref().expect("the map has a structure");
    let config = SynthConfig::preset("tiny").unwrap();
    let flight = matloc_synth::SecondFlight::same_flight();
    let (world, frames) = matloc_synth::flight::second_flight_frames(&config, &flight).unwrap();
    let with = MethodOptions::default();
    let mut without = MethodOptions::default();
    without.structure.rendered.enabled = false;
    let angle = with.structure.max_view_angle_deg;
    let (mut unseen, mut ok_with, mut ok_without, mut wrong) = (0, 0, 0, 0);
    for (i, f) in frames.iter().enumerate() {
        let Some(pose) = [45.0, 135.0, 225.0, 315.0, 90.0, 180.0, 270.0]
            .into_iter()
            .filter_map(|yaw| {
                matloc_synth::flight::turned_view(&world, &f.cam_from_world, yaw, 0.35, 30.0)
            })
            .find(|p| structure.images_looking_like(p, angle).next().is_none())
        else {
            continue;
        };
        unseen += 1;
        let mut frame = f.clone();
        frame.cam_from_world = pose;
        let image =
            matloc_synth::flight::render_second_flight(&world, &config, &flight, &frame, 500 + i);
        for (options, ok) in [(&with, &mut ok_with), (&without, &mut ok_without)] {
            let r =
                localize_with(&map, &Method::Structure, "q", &image, &f.camera, options).unwrap();
            if let Some(p) = r.cam_from_world {
                let (t, a) = (
                    translation_error_m(&p, &pose),
                    rotation_error_deg(&p, &pose),
                );
                eprintln!("view {i}: {t:.3} m {a:.2}° ({} inliers)", r.inliers);
                *ok += usize::from(t <= 0.5 && a <= 2.0);
                wrong += usize::from(t > 5.0 || a > 10.0);
            }
        }
    }
    eprintln!("{unseen} unseen viewpoints: {ok_with} with renders, {ok_without} without");
    assert!(
        unseen >= 8,
        "only {unseen} of the test views could be turned out of sight"
    );
    assert!(ok_with >= 2, "{ok_with} within 0.5 m / 2° with renders");
    assert_eq!(ok_without, 0);
    assert_eq!(wrong, 0);
}
