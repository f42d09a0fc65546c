//! A map build refuses bad datasets with errors that name the file and what is wrong, before
//! it writes anything (or, for a problem found mid-build, leaving a map that refuses to load).

use std::path::PathBuf;

use matloc_data::{Split, read_dataset};
use matloc_pipeline::LoadedMap;
use matloc_pipeline::build::{MapConfig, build_map};
use matloc_surface::SurfaceChoice;
use matloc_synth::{SynthConfig, SynthOutput, synthesize_with};

fn tiny(name: &str, output: SynthOutput) -> (PathBuf, matloc_data::Dataset) {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    let _ = std::fs::remove_dir_all(&dir);
    let data = dir.join("data");
    synthesize_with(
        &SynthConfig::preset("tiny").unwrap(),
        &data,
        &output,
        &|_| {},
    )
    .unwrap();
    let dataset = read_dataset(&data).unwrap();
    (dir, dataset)
}

#[test]
fn an_image_whose_size_disagrees_with_its_intrinsics_stops_the_build_before_the_map_exists() {
    let (dir, mut dataset) = tiny("bad_input_size", SynthOutput::default());
    // Intrinsics for a square sensor; the images are 4:3.
    let f = &mut dataset.frames[3];
    f.camera = matloc_core::Camera::pinhole(120, 120, 100.0, 100.0, 60.0, 60.0).unwrap();
    let out = dir.join("map");
    let e = build_map(&dataset, &out, &MapConfig::default(), &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("frame_00003") && e.contains("120x120"), "{e}");
    assert!(!out.exists(), "a map directory was created");
}

#[test]
fn a_surface_source_the_dataset_lacks_stops_the_build_before_the_map_exists() {
    let (dir, mut dataset) = tiny("bad_input_source", SynthOutput::default());
    for f in &mut dataset.frames {
        f.depth_path = None;
    }
    let mut config = MapConfig::default();
    config.surface.source = SurfaceChoice::Points;
    let out = dir.join("map");
    let e = build_map(&dataset, &out, &config, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("no point cloud"), "{e}");
    assert!(!out.exists());
    // A point cloud the dataset names but that is missing is named.
    dataset.points = Some(matloc_data::PointSource::Ply {
        path: dir.join("data/missing.ply"),
    });
    let e = build_map(&dataset, &out, &config, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("missing.ply") && e.contains("does not exist"),
        "{e}"
    );
    assert!(!out.exists());
}

#[test]
fn a_view_with_too_few_surface_points_is_named_and_the_map_does_not_load() {
    let (dir, dataset) = tiny(
        "bad_input_points",
        SynthOutput {
            depth: false,
            points: true,
        },
    );
    let mut config = MapConfig::default();
    config.surface.min_points = 100_000;
    let out = dir.join("map");
    let e = build_map(&dataset, &out, &config, &mut |_| {})
        .unwrap_err()
        .to_string();
    let first = &dataset.frames[dataset.split_indices(Split::Train)[0]];
    assert!(e.contains("min_points") && e.contains("PLY"), "{e}");
    assert!(
        dataset
            .frames
            .iter()
            .any(|f| e.contains(&*f.image_path.to_string_lossy())),
        "no image named in {e} (first train image {})",
        first.image_path.display()
    );
    assert!(LoadedMap::open(&out).is_err(), "an unfinished map loaded");
}

#[test]
fn physically_impossible_intrinsics_or_poses_stop_the_build_before_the_map_exists() {
    let (dir, dataset) = tiny("bad_input_impossible", SynthOutput::default());
    let out = dir.join("map");
    let mut focal = dataset.clone();
    focal.frames[2].camera.fx = 1e-300;
    let e = build_map(&focal, &out, &MapConfig::default(), &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("frame 2") && e.contains("`fx`"), "{e}");
    let mut far = dataset;
    far.frames[7].cam_from_world.translation.vector.x = 1e308;
    let e = build_map(&far, &out, &MapConfig::default(), &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("frame 7") && e.contains("pose"), "{e}");
    assert!(!out.exists(), "a map directory was created");
}
