//! The pipeline end to end on input it was never tuned on: a path-traced survey (Blender
//! Cycles: other geometry, materials, soft shadows and indirect light) of 18 posed 320×240
//! images without depth, and four queries between its frames. The fixture is the outside
//! benchmark's smoke set (`bench/outside/outside.py smoke --out tests/fixtures/outside-smoke`);
//! the full benchmark and its table are `bench/outside/run.sh`.
//!
//! This asserts only that every stage runs on such input: the map builds from triangulated
//! points, loads, and each method answers each query with a pose or a refusal, never an error;
//! accuracy is measured by the benchmark, not here.

use std::path::{Path, PathBuf};

mod map_sizes;

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_data::{Split, read_dataset};
use matloc_pipeline::LoadedMap;
use matloc_pipeline::build::{BuildEvent, MapConfig, build_map};
use matloc_pipeline::methods::{Method, MethodOptions, localize_with};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/outside-smoke")
}

/// Short training lengths: the run, not the accuracy, is under test.
fn smoke_config() -> MapConfig {
    let mut c = MapConfig::default();
    c.nerf.steps = 200;
    c.nerf.checkpoint_every = 100;
    c.nerf.model_overrides = map_sizes::small_nerf_overrides();
    c.encoder.train.steps = 100;
    c.encoder.train.head_phase.steps = 200;
    c.place.train.epochs = 10;
    c.calibration.max_views = 4;
    c
}

#[test]
fn a_path_traced_survey_without_depth_builds_and_localizes() {
    let survey = read_dataset(&fixture().join("survey")).expect("the smoke survey");
    assert_eq!(survey.split(Split::Train).count(), 18);
    assert!(
        survey.frames.iter().all(|f| f.depth_path.is_none()),
        "the survey must carry no depth"
    );
    let queries = read_dataset(&fixture().join("queries")).expect("the smoke queries");
    let test: Vec<_> = queries.split(Split::Test).collect();
    assert_eq!(test.len(), 4);

    let map_dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("outside_smoke_map");
    let _ = std::fs::remove_dir_all(&map_dir);
    let t = std::time::Instant::now();
    let mut finished = Vec::new();
    build_map(&survey, &map_dir, &smoke_config(), &mut |e| {
        if let BuildEvent::StageFinished { name, .. } = e {
            finished.push(name.clone());
        }
    })
    .expect("map build");
    eprintln!("map built in {:.0} s", t.elapsed().as_secs_f64());
    // A fresh build reports each stage once (never also as "done earlier").
    let mut unique = finished.clone();
    unique.sort();
    unique.dedup();
    assert_eq!(unique.len(), finished.len(), "{finished:?}");
    let surface: serde_json::Value =
        serde_json::from_slice(&std::fs::read(map_dir.join("surface.json")).unwrap()).unwrap();
    assert_eq!(surface["plan"]["kind"], "triangulated", "{surface}");

    // The triangulated points fit the survey's poses to a fraction of a pixel at the median.
    let dir = matloc_pipeline::MapDir::open(&map_dir).unwrap();
    let s = matloc_pipeline::map::check::structure_summary(&dir).expect("a structure");
    let r = s
        .reprojection
        .clone()
        .expect("the images' cameras are kept");
    eprintln!("structure: {s:?}");
    assert!(s.points > 0 && r.observations == s.observations, "{s:?}");
    assert!(
        r.median_px < 1.0 && r.median_px <= r.p95_px && r.p95_px <= r.max_px,
        "{r:?}"
    );

    let map = LoadedMap::open(&map_dir).expect("the map loads");
    let options = MethodOptions::default();
    for method in [Method::Structure, Method::Matloc, Method::RgbKeypoints] {
        for f in &test {
            let (image, camera) = matloc_data::images::load_frame_image(&queries, f, 1).unwrap();
            let name = f.image_path.display().to_string();
            let r = localize_with(&map, &method, &name, &image, &camera, &options)
                .unwrap_or_else(|e| panic!("{method} on {name}: {e}"));
            match r.cam_from_world {
                Some(p) => {
                    let c = matloc_core::pose::camera_center(&p);
                    assert!(c.iter().all(|v| v.is_finite()), "{method} on {name}: {c:?}");
                    eprintln!(
                        "{method} {name}: {:.3} m / {:.2}°, {} inliers, {:.2} s",
                        translation_error_m(&p, &f.cam_from_world),
                        rotation_error_deg(&p, &f.cam_from_world),
                        r.inliers,
                        r.total_seconds
                    );
                }
                None => eprintln!("{method} {name}: refused"),
            }
        }
    }
}
