//! The same data and config give the same map: two builds of `tiny`, each on one thread, run
//! side by side in one process, and every file they write is compared — the NeRF, the ground
//! truth pairs, the query encoder and the place classifier (burn, initialised from the config's
//! seeds, trained with views rendered at virtual viewpoints), the selection, the calibration,
//! the partition and the surface.
//!
//! One thread per build, because rayon's parallel reductions associate floating-point sums in
//! whatever order the work was stolen; on one thread every sum has one order. The builds run
//! at once so that each draw of the CNN backend's process-wide generator is shown to stay its
//! own build's (`matloc_core::backend::seeded_module`).
//!
//! Compared byte for byte, except: safetensors files by parsed header and tensor bytes (their
//! metadata is a map written in a per-process order), the manifest without its stage timings,
//! and training curves without their wall-clock column.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

mod map_sizes;

use matloc_data::read_dataset;
use matloc_pipeline::MapDir;
use matloc_pipeline::build::{MapConfig, build_map};
use matloc_synth::{SynthConfig, synthesize};

/// A short build of every stage, virtual viewpoints on: the point is equality, not accuracy.
fn config() -> MapConfig {
    let mut c = MapConfig::default();
    c.nerf.steps = 120;
    c.nerf.checkpoint_every = 60;
    c.nerf.model_overrides = map_sizes::small_nerf_overrides();
    c.encoder.train.steps = 40;
    c.encoder.train.head_phase.steps = 40;
    c.place.train.epochs = 3;
    c.calibration.max_views = 4;
    c.virtual_views.enabled = true;
    c.virtual_views.per_block = VIRTUAL_PER_BLOCK;
    c
}

/// Virtual viewpoints asked for per block.
const VIRTUAL_PER_BLOCK: usize = 12;

/// A safetensors file as (header, tensor bytes).
fn safetensors_parts(bytes: &[u8]) -> (serde_json::Value, &[u8]) {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    (header, &bytes[8 + n..])
}

/// Removes every object member named `key`, at any depth.
fn strip(value: &mut serde_json::Value, key: &str) {
    match value {
        serde_json::Value::Object(m) => {
            m.remove(key);
            m.values_mut().for_each(|v| strip(v, key));
        }
        serde_json::Value::Array(a) => a.iter_mut().for_each(|v| strip(v, key)),
        _ => {}
    }
}

/// A JSON-lines training curve without its wall-clock column.
fn curve_without_time(bytes: &[u8]) -> Vec<serde_json::Value> {
    std::str::from_utf8(bytes)
        .unwrap()
        .lines()
        .map(|l| {
            let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
            strip(&mut v, "t_s");
            v
        })
        .collect()
}

/// What of a map file must be equal between builds.
#[derive(Debug, PartialEq)]
enum Content {
    Safetensors(serde_json::Value, Vec<u8>),
    Json(serde_json::Value),
    Lines(Vec<serde_json::Value>),
    Bytes(Vec<u8>),
}

fn content(map: &Path, name: &str) -> Content {
    let bytes = std::fs::read(map.join(name)).unwrap();
    if name.ends_with(".safetensors") {
        let (h, d) = safetensors_parts(&bytes);
        Content::Safetensors(h, d.to_vec())
    } else if name.ends_with(".jsonl") {
        Content::Lines(curve_without_time(&bytes))
    } else {
        Content::Bytes(bytes)
    }
}

/// The manifest with what measures the machine rather than the map left out: stage timings
/// and the safetensors checksums (which cover the per-process metadata order).
fn manifest(map: &Path) -> Content {
    let mut v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(map.join("manifest.json")).unwrap()).unwrap();
    for key in [
        "seconds",
        "sha256",
        "created_at",
        "finished_at",
        "started_at",
    ] {
        strip(&mut v, key);
    }
    Content::Json(v)
}

#[test]
fn two_single_thread_builds_of_tiny_write_the_same_map() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("reproducible_tiny");
    let _ = std::fs::remove_dir_all(&dir);
    let data = dir.join("data");
    synthesize(&SynthConfig::preset("tiny").unwrap(), &data, &|_| {}).unwrap();
    let dataset = read_dataset(&data).unwrap();
    let config = config();

    let maps: Vec<PathBuf> = ["a", "b"].iter().map(|n| dir.join(n)).collect();
    std::thread::scope(|s| {
        for map in &maps {
            let (dataset, config) = (&dataset, &config);
            s.spawn(move || {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(1)
                    .build()
                    .unwrap()
                    .install(|| build_map(dataset, map, config, &mut |_| {}))
                    .unwrap()
            });
        }
    });

    let files = |m: &Path| -> Vec<String> {
        MapDir::open(m)
            .unwrap()
            .manifest()
            .files
            .keys()
            .cloned()
            .collect()
    };
    let names = files(&maps[0]);
    assert_eq!(names, files(&maps[1]));
    for must in [
        "blocks/0/model.safetensors",
        "blocks/0/pairs.safetensors",
        "blocks/0/encoder.safetensors",
        "place/place.safetensors",
        "confidence.json",
    ] {
        assert!(names.iter().any(|n| n == must), "{must} not in {names:?}");
    }
    let mut differ = BTreeMap::new();
    for name in &names {
        let (a, b) = (content(&maps[0], name), content(&maps[1], name));
        if a != b {
            differ.insert(name.clone(), ());
        }
    }
    assert!(
        differ.is_empty(),
        "differ between the builds: {:?}",
        differ.keys().collect::<Vec<_>>()
    );
    assert_eq!(manifest(&maps[0]), manifest(&maps[1]), "manifest.json");
    eprintln!("equal in both builds: {names:?} and the manifest");

    // The place classifier trained on virtual views, counted in the place stage's record.
    let map = MapDir::open(&maps[0]).unwrap();
    let place = map
        .manifest()
        .stages
        .iter()
        .find(|s| s.name == "place")
        .unwrap();
    let v = place
        .virtual_views
        .as_ref()
        .expect("virtual views recorded");
    eprintln!("virtual views: {v:?}");
    let blocks = map.manifest().blocks.len();
    assert!(
        v.views > 0 && v.views <= VIRTUAL_PER_BLOCK * blocks,
        "{v:?}"
    );
    assert_eq!(v.views + v.unlabelled, v.candidates - v.rejected.total());
    assert_eq!(v.per_block.len(), blocks);
    assert_eq!(v.per_block.iter().sum::<usize>(), v.views);
    let groups = matloc_place::PlaceModel::load(&maps[0].join("place"))
        .unwrap()
        .groups()
        .len();
    // Counted by label: every label is one of the classifier's groups.
    assert_eq!(v.per_group.len(), groups);
    assert_eq!(v.per_group.iter().sum::<usize>(), v.views);
    assert!(v.seconds > 0.0 && v.survey_height_m > 0.0 && v.cell_m > 0.0);
}
