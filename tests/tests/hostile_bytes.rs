//! Random and mutated bytes as a map's `manifest.json` and as a map build config never make
//! the readers panic: they parse or return an error (the bytes pass of `matloc-data`'s
//! `tests/fuzz.rs`, for the two readers that live in `matloc-pipeline`).

use std::path::Path;

use matloc_pipeline::MapConfig;
use matloc_pipeline::map::MapDir;
use matloc_pipeline::map::manifest::sha256_hex;
use proptest::prelude::*;

/// A manifest of one block with one listed file (`partition.json`, present).
fn manifest_bytes() -> Vec<u8> {
    let partition = b"{\"version\": 1}";
    serde_json::to_vec_pretty(&serde_json::json!({
        "format": "matloc-map",
        "version": 2,
        "created_by": "hostile bytes",
        "config": {},
        "scene": null,
        "blocks": [{"id": 0, "bounds_min": [0.0, 0.0, 0.0], "bounds_max": [1.0, 1.0, 1.0],
                    "num_poses": 3, "selected_dims": []}],
        "stages": [{"name": "partition", "seconds": 1.0}],
        "files": {"partition.json": {"bytes": partition.len(), "sha256": sha256_hex(partition)}},
    }))
    .unwrap()
}

fn config_bytes() -> Vec<u8> {
    serde_json::to_vec_pretty(&MapConfig::default()).unwrap()
}

/// Applies byte edits: (position, new byte, kind) with kind 0 = overwrite, 1 = insert,
/// 2 = delete; positions wrap around the current length.
fn mutate(mut bytes: Vec<u8>, edits: &[(usize, u8, u8)]) -> Vec<u8> {
    for &(at, b, kind) in edits {
        if bytes.is_empty() {
            bytes.push(b);
            continue;
        }
        let i = at % bytes.len();
        match kind % 3 {
            0 => bytes[i] = b,
            1 => bytes.insert(i, b),
            _ => {
                bytes.remove(i);
            }
        }
    }
    bytes
}

/// Opens a map whose manifest is `bytes` and lists its problems.
fn read_manifest(dir: &Path, bytes: &[u8]) {
    std::fs::write(dir.join("manifest.json"), bytes).unwrap();
    if let Ok(map) = MapDir::open_manifest(dir) {
        let _ = map.problems();
    }
    let _ = MapDir::open(dir);
}

fn read_config(bytes: &[u8]) {
    if let Ok(c) = serde_json::from_slice::<MapConfig>(bytes) {
        let _ = c.surface.validate();
        let _ = c.samples.validate();
    }
}

fn map_dir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("partition.json"), b"{\"version\": 1}").unwrap();
    dir
}

#[test]
fn the_unmutated_inputs_are_valid() {
    let dir = map_dir();
    std::fs::write(dir.path().join("manifest.json"), manifest_bytes()).unwrap();
    assert!(MapDir::open_manifest(dir.path()).is_ok());
    assert!(serde_json::from_slice::<MapConfig>(&config_bytes()).is_ok());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        let dir = map_dir();
        read_manifest(dir.path(), &bytes);
        read_config(&bytes);
    }

    #[test]
    fn mutated_manifests_and_configs(
        edits in proptest::collection::vec((any::<usize>(), any::<u8>(), any::<u8>()), 1..12),
    ) {
        let dir = map_dir();
        read_manifest(dir.path(), &mutate(manifest_bytes(), &edits));
        read_config(&mutate(config_bytes(), &edits));
    }

    #[test]
    fn truncated_manifests_and_configs(cut in any::<prop::sample::Index>()) {
        let m = manifest_bytes();
        let dir = map_dir();
        read_manifest(dir.path(), &m[..cut.index(m.len())]);
        let c = config_bytes();
        prop_assert!(serde_json::from_slice::<MapConfig>(&c[..cut.index(c.len())]).is_err());
    }
}
