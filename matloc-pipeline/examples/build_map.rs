//! Build a map from code and localize with it: synthesise the small `tiny` world, build a map
//! with a reduced training budget (minutes on two cores), open it and localize the test views.
//!
//! `cargo run --release -p matloc-pipeline --example build_map -- OUT_DIR`
//!
//! For your own data, read it with `matloc_data::read_dataset` (a nerfstudio
//! `transforms.json` folder or a COLMAP model) instead of synthesising one.

use std::path::Path;

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_data::{Split, read_dataset};
use matloc_pipeline::build::{BuildEvent, build_map};
use matloc_pipeline::{LoadedMap, MapConfig};
use matloc_synth::{SynthConfig, synthesize};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args().nth(1).ok_or("usage: build_map OUT_DIR")?;
    let out = Path::new(&out);
    let data = out.join("data");
    if !data.join("transforms.json").exists() {
        synthesize(&SynthConfig::preset("tiny")?, &data, &|_| {})?;
    }
    let dataset = read_dataset(&data)?;

    // The default budget suits a real map; a small one keeps this example to minutes.
    let mut config = MapConfig::default();
    config.nerf.steps = 400;
    config.encoder.train.steps = 200;
    config.encoder.train.head_phase.steps = 600;
    config.place.train.epochs = 20;
    let map_dir = out.join("map");
    build_map(&dataset, &map_dir, &config, &mut |e| {
        if let BuildEvent::StageFinished { name, seconds, .. } = e {
            println!("stage {name}: {seconds:.1} s");
        }
    })?;

    let map = LoadedMap::open(&map_dir)?;
    let localizer = map.localizer();
    for f in dataset.split(Split::Test) {
        let (image, camera) = matloc_data::images::load_frame_image(&dataset, f, 1)?;
        let result = localizer.localize(&image, &camera)?;
        match result.cam_from_world {
            Some(p) => println!(
                "{}: {:.2} m, {:.2}°, confidence {:.2}",
                f.image_path.display(),
                translation_error_m(&p, &f.cam_from_world),
                rotation_error_deg(&p, &f.cam_from_world),
                result.confidence
            ),
            None => println!("{}: not localized", f.image_path.display()),
        }
    }
    Ok(())
}
