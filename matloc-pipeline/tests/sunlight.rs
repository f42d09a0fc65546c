//! The sunlight stage on the `tiny` world: the sun estimated when the data does not give it,
//! and clear errors when the shadows it would lift cannot be trusted.

use std::path::PathBuf;

use matloc_data::{Dataset, read_dataset};
use matloc_pipeline::MapConfig;
use matloc_pipeline::build::sunlight::SunlightRecord;
use matloc_pipeline::build::{JobCommands, plan_map};
use matloc_pipeline::map::layout::SUNLIGHT_FILE;
use matloc_synth::{SynthConfig, SynthOutput, synthesize_with};
use nalgebra::Vector3;

/// A fresh `tiny` world in `name`, with or without its depth files.
fn tiny(name: &str, depth: bool) -> (Dataset, PathBuf) {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    let _ = std::fs::remove_dir_all(&dir);
    let output = SynthOutput {
        depth,
        points: false,
    };
    synthesize_with(
        &SynthConfig::preset("tiny").unwrap(),
        &dir.join("data"),
        &output,
        &|_| {},
    )
    .unwrap();
    (read_dataset(&dir.join("data")).unwrap(), dir.join("map"))
}

/// The jobs of a plan (the commands are written, not run).
fn jobs() -> JobCommands {
    JobCommands {
        program: PathBuf::from("matloc"),
        data: PathBuf::from("data"),
    }
}

fn lifting() -> MapConfig {
    let mut config = MapConfig::default();
    config.sunlight.enabled = true;
    config
}

/// Without a sun in the config or the metadata, the stage finds it from the images; a
/// direction pointing away from the sun is refused.
#[test]
fn the_sun_is_estimated_when_the_data_does_not_give_it() {
    let (mut dataset, map) = tiny("sunlight_estimated", true);
    let truth = Vector3::from(dataset.metadata.sun_direction.take().expect("synth sun"));
    let t = std::time::Instant::now();
    let planned = plan_map(&dataset, &map, &lifting(), &jobs(), &mut |_| {}).unwrap();
    let record: SunlightRecord = planned.map.read_json(SUNLIGHT_FILE).unwrap();
    let off = Vector3::from(record.sun_direction)
        .angle(&truth)
        .to_degrees();
    let check = record.check.clone().expect("checked");
    eprintln!(
        "estimated {off:.2}° off in a {:.1} s plan; {check:?}; gain {:?}",
        t.elapsed().as_secs_f64(),
        record.gain
    );
    assert_eq!(record.sun_source, "estimated from the images");
    assert!(off < 5.0, "{off:.2}° off");
    assert!(check.contrast > 0.4 && check.rival.is_some_and(|r| r < 0.8));
    assert_eq!(
        record.images.len(),
        planned
            .dataset
            .split_indices(matloc_data::Split::Train)
            .len()
    );

    // The direction of the light instead of towards the sun.
    let mut flipped = lifting();
    flipped.sunlight.sun_direction = Some((-truth).into());
    let e = plan_map(
        &dataset,
        &map.with_extension("flipped"),
        &flipped,
        &jobs(),
        &mut |_| {},
    )
    .err()
    .expect("refused")
    .to_string();
    assert!(
        e.contains("towards the sun") && e.contains("(config)"),
        "{e}"
    );
}

/// Shadows are traced only on depth files: on triangulated points the stage stops and says so.
#[test]
fn a_surface_without_depth_files_is_refused() {
    let (dataset, map) = tiny("sunlight_no_depth", false);
    assert!(dataset.metadata.sun_direction.is_some());
    let e = plan_map(&dataset, &map, &lifting(), &jobs(), &mut |_| {})
        .err()
        .expect("refused")
        .to_string();
    assert!(
        e.contains("triangulated") && e.contains("depth files") && e.contains("dataset metadata"),
        "{e}"
    );
}
