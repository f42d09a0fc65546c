//! Reruns stages of a built map with a changed configuration, in place: the named stages'
//! records are dropped, the manifest's configuration is overlaid with a JSON object, and the
//! build resumes (every other stage is kept). Run it on a copy of the map.
//!
//!     cp -r MAP COPY
//!     cargo run --release -p matloc-research --example rerun_stages -- COPY DATA OVERLAY.json place,calibration

use matloc_pipeline::MapConfig;
use matloc_pipeline::build::{BuildEvent, build_map};
use matloc_pipeline::config::overlay_json;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 5 {
        eprintln!("usage: rerun_stages MAP DATA OVERLAY.json STAGE[,STAGE...]");
        std::process::exit(2);
    }
    let map_path = std::path::Path::new(&args[1]);
    let dataset = matloc_data::read_dataset(std::path::Path::new(&args[2])).expect("dataset");
    let overlay: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&args[3]).expect("overlay")).expect("json");
    let stages: Vec<&str> = args[4].split(',').collect();
    let mut map = matloc_pipeline::MapDir::open(map_path).expect("map");
    let manifest = map.manifest_mut();
    // The stored configuration through the current type first, so that it names every
    // field: an overlay naming a field the stored one lacks would replace its section whole.
    let stored: MapConfig = serde_json::from_value(manifest.config.clone()).expect("config");
    let mut config = serde_json::to_value(&stored).expect("config");
    overlay_json(&mut config, overlay);
    let config: MapConfig = serde_json::from_value(config).expect("config");
    manifest
        .stages
        .retain(|s| !stages.contains(&s.name.as_str()));
    manifest.config = serde_json::to_value(&config).expect("config");
    map.save().expect("save");
    let t = std::time::Instant::now();
    build_map(&dataset, map_path, &config, &mut |e| {
        if let BuildEvent::StageFinished {
            name,
            seconds,
            skipped: false,
        } = e
        {
            eprintln!("{name}: {seconds:.1} s");
        }
    })
    .expect("build");
    eprintln!("rerun in {:.1} s", t.elapsed().as_secs_f64());
}
