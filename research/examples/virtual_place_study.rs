//! Whether virtual viewpoints in the place classifier's training set bring its hypotheses
//! closer for queries from where the survey never flew: one `tiny` map is built without them,
//! copied, and its place stage rerun on the copy with `virtual` on (same NeRFs, same groups);
//! both classifiers then answer the same queries, rendered by the synthetic world's ray caster
//! at half the survey's height above the terrain, 40° below the horizon, random headings, and
//! the survey's own test views.
//!
//! Distances: `target` is between the points where the query's and the hypothesis's optical
//! axes meet the scene (the ground each looks at), `centre` between the camera centres.
//!
//!     cargo run --release -p matloc-research --example virtual_place_study -- OUT [QUERIES [PER_BLOCK]]
//!
//! `QUERIES` never-flown queries (40), `PER_BLOCK` virtual views asked for per block (the
//! default of `virtual.per_block`); a map already built in `OUT/off` is reused.

use std::path::{Path, PathBuf};

use matloc_core::metrics::translation_error_m;
use matloc_core::{Camera, Image, Pose};
use matloc_data::{Split, read_dataset};
use matloc_pipeline::MapDir;
use matloc_pipeline::build::{BuildEvent, MapConfig, build_map};
use matloc_pipeline::map::layout::PARTITION_FILE;
use matloc_place::{PlaceModel, PlacePredictor};
use matloc_surface::viewpoints::{GroundFrame, heading_pitch_pose};
use matloc_synth::{RenderOptions, SynthConfig, World};
use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The end-to-end tests' tiny map sizes (`tests/tests/end_to_end.rs`), with a shorter encoder
/// (the place stage does not use it).
fn config() -> MapConfig {
    let mut c = MapConfig::default();
    c.nerf.steps = 300;
    c.nerf.checkpoint_every = 100;
    c.nerf.model_overrides = serde_json::json!({
        "field": {"log2_table_size": 15, "max_resolution": 512},
        "train": {"batch_rays": 1024, "march": {"steps": 128, "max_samples": 24},
                  "occupancy_warmup_steps": 32},
        "render": {"march": {"steps": 128}},
    });
    c.encoder.train.steps = 100;
    c.place.train.epochs = 20;
    c.calibration.max_views = 4;
    c
}

/// Where the optical axis of `pose` first meets the world.
fn target(world: &World, pose: &Pose) -> Option<Point3<f64>> {
    let inv = pose.inverse();
    let eye = Point3::from(inv.translation.vector);
    world
        .raycast(&eye, &inv.transform_vector(&Vector3::z()))
        .map(|h| h.point)
}

/// Per query: top-1 target and centre distances, nearest target of the top 3.
struct Scores {
    top1_target: Vec<f64>,
    top1_centre: Vec<f64>,
    top3_target: Vec<f64>,
    /// The nearest target of any group's coarse pose: the best a top-1 answer can do.
    best_target: Vec<f64>,
}

fn score(model: &PlaceModel, world: &World, queries: &[(Image<f32>, Camera, Pose)]) -> Scores {
    let mut s = Scores {
        top1_target: Vec::new(),
        top1_centre: Vec::new(),
        top3_target: Vec::new(),
        best_target: Vec::new(),
    };
    for (image, camera, truth) in queries {
        let hyps = model.predict(image, camera, 3).expect("place prediction");
        let t = target(world, truth).expect("query looks at the scene");
        let d: Vec<f64> = hyps
            .iter()
            .map(|h| target(world, &h.cam_from_world).map_or(f64::INFINITY, |p| (p - t).norm()))
            .collect();
        s.top1_target.push(d[0]);
        s.top1_centre
            .push(translation_error_m(&hyps[0].cam_from_world, truth));
        s.top3_target
            .push(d.iter().copied().fold(f64::INFINITY, f64::min));
        s.best_target.push(
            model
                .groups()
                .groups
                .iter()
                .filter_map(|g| target(world, &g.coarse_pose))
                .map(|p| (p - t).norm())
                .fold(f64::INFINITY, f64::min),
        );
    }
    s
}

fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn share(v: &[f64], within: f64) -> f64 {
    v.iter().filter(|&&d| d <= within).count() as f64 / v.len().max(1) as f64
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(out) = args.first().map(PathBuf::from) else {
        eprintln!("usage: virtual_place_study OUT [QUERIES [PER_BLOCK]]");
        std::process::exit(2);
    };
    let n_queries: usize = args.get(1).map_or(40, |s| s.parse().expect("QUERIES"));
    let synth = SynthConfig::preset("tiny").expect("tiny preset");
    let data = out.join("data");
    if !data.join("transforms.json").is_file() {
        matloc_synth::synthesize(&synth, &data, &|_| {}).expect("synthesize");
    }
    let dataset = read_dataset(&data).expect("dataset");
    let off_dir = out.join("off");
    let on_dir = out.join("on");
    let config = config();
    let t = std::time::Instant::now();
    build_map(&dataset, &off_dir, &config, &mut |_| {}).expect("map build");
    eprintln!(
        "map without virtual views: {:.0} s",
        t.elapsed().as_secs_f64()
    );

    // The same map, its place stage rerun with virtual views.
    let _ = std::fs::remove_dir_all(&on_dir);
    copy_dir(&off_dir, &on_dir);
    let mut on = MapDir::open(&on_dir).expect("copied map");
    on.manifest_mut()
        .stages
        .retain(|s| s.name != "place" && s.name != "calibration");
    let mut on_config = config.clone();
    on_config.virtual_views.enabled = true;
    if let Some(n) = args.get(2) {
        on_config.virtual_views.per_block = n.parse().expect("PER_BLOCK");
    }
    let working =
        matloc_data::images::working_dataset(&dataset, on_config.images.max_side).expect("working");
    let partition = on.read_json(PARTITION_FILE).expect("partition");
    matloc_pipeline::build::place::run(&working, &partition, &mut on, &on_config, &mut |e| {
        if let BuildEvent::StageFinished { name, seconds, .. } = e {
            eprintln!("{name} (virtual on): {seconds:.1} s");
        }
    })
    .expect("place stage with virtual views");
    let record = on
        .manifest()
        .stages
        .iter()
        .find(|s| s.name == "place")
        .and_then(|s| s.virtual_views.clone())
        .expect("virtual views recorded");
    eprintln!("{record:?}");
    let off_secs = MapDir::open(&off_dir)
        .expect("map")
        .manifest()
        .stages
        .iter()
        .find(|s| s.name == "place")
        .map_or(f64::NAN, |s| s.seconds);
    let on_secs = on
        .manifest()
        .stages
        .iter()
        .find(|s| s.name == "place")
        .map_or(f64::NAN, |s| s.seconds);

    let model_off = PlaceModel::load(&off_dir.join("place")).expect("place off");
    let model_on = PlaceModel::load(&on_dir.join("place")).expect("place on");

    // Queries from half the survey's height, 40° below the horizon, any heading, over the
    // middle of the world.
    let (world, plan) = matloc_synth::generate(&synth).expect("world");
    let test: Vec<_> = dataset.split(Split::Test).collect();
    let camera = test[0].camera;
    let heights: Vec<f64> = dataset
        .frames
        .iter()
        .map(|f| {
            let c = f.center();
            c.z - world.height_at(c.x, c.y)
        })
        .collect();
    let survey_h = median(&heights);
    let _ = plan;
    let (lo, hi) = world.content_bounds();
    let frame = GroundFrame::new(Vector3::z()).expect("frame");
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut novel = Vec::new();
    while novel.len() < n_queries {
        let x = lo.x + (hi.x - lo.x) * rng.random_range(0.25..0.75);
        let y = lo.y + (hi.y - lo.y) * rng.random_range(0.25..0.75);
        let eye = Point3::new(x, y, world.height_at(x, y) + 0.5 * survey_h);
        let heading = rng.random_range(0.0..std::f64::consts::TAU);
        let pose = heading_pitch_pose(&frame, &eye, heading, 40_f64.to_radians());
        // Looking at the scene's content, and not from inside an object.
        let Some(t) = target(&world, &pose) else {
            continue;
        };
        if !(lo.x..=hi.x).contains(&t.x) || !(lo.y..=hi.y).contains(&t.y) {
            continue;
        }
        if world
            .raycast(&eye, &Vector3::new(0.0, 0.0, -1.0))
            .is_none_or(|h| h.t < 3.0)
        {
            continue;
        }
        let r = world.render(&camera, &pose, &RenderOptions::default());
        novel.push((r.rgb, camera, pose));
    }
    let same: Vec<_> = test
        .iter()
        .map(|f| {
            let (image, camera) = matloc_data::images::load_frame_image(&dataset, f, 1).unwrap();
            (image, camera, f.cam_from_world)
        })
        .collect();
    println!(
        "tiny: survey {survey_h:.1} m above the terrain; queries {:.1} m up, 40° pitch, any heading",
        0.5 * survey_h
    );
    println!(
        "virtual views: {} ({} candidates), place stage {off_secs:.1} s without, {on_secs:.1} s with ({:.1} s of it the virtual views)",
        record.views, record.candidates, record.seconds
    );
    println!(
        "| queries | virtual | top-1 target median | top-1 target ≤ 10 m | top-3 nearest target median | top-1 centre median | nearest group target median |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (name, qs) in [("never flown", &novel), ("survey test views", &same)] {
        for (label, model) in [("off", &model_off), ("on", &model_on)] {
            let s = score(model, &world, qs);
            println!(
                "| {name} ({}) | {label} | {:.1} m | {:.0} % | {:.1} m | {:.1} m | {:.1} m |",
                qs.len(),
                median(&s.top1_target),
                100.0 * share(&s.top1_target, 10.0),
                median(&s.top3_target),
                median(&s.top1_centre),
                median(&s.best_target)
            );
        }
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("mkdir");
    for e in std::fs::read_dir(from).expect("read dir") {
        let e = e.expect("entry");
        let dst = to.join(e.file_name());
        if e.file_type().expect("type").is_dir() {
            copy_dir(&e.path(), &dst);
        } else {
            std::fs::copy(e.path(), &dst).expect("copy");
        }
    }
}
