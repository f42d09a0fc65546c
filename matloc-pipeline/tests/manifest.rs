//! Map directory round trip and corruption handling.

use std::fs;

use matloc_pipeline::map::manifest::{MANIFEST_FILE, MANIFEST_VERSION};
use matloc_pipeline::{BlockEntry, MapDir, MapError};
use serde_json::json;

fn build(root: &std::path::Path) -> MapDir {
    let mut map = MapDir::create_or_resume(root, json!({"steps": 100})).unwrap();
    map.write_file("blocks/0/field.safetensors", &[7u8; 1000])
        .unwrap();
    map.write_json("blocks/0/field.json", &json!({"levels": 16}))
        .unwrap();
    map.manifest_mut().blocks.push(BlockEntry {
        id: 0,
        bounds_min: [-1.0, -2.0, 0.0],
        bounds_max: [1.0, 2.0, 3.0],
        num_poses: 12,
        selected_dims: vec![3, 40],
    });
    map.complete_stage("nerf/0", 1.5).unwrap();
    map
}

#[test]
fn round_trip_and_resume() {
    let dir = tempfile::tempdir().unwrap();
    let map = build(dir.path());
    let opened = MapDir::open(dir.path()).unwrap();
    assert_eq!(opened.manifest(), map.manifest());
    opened.verify().unwrap();
    assert_eq!(
        opened.read_file("blocks/0/field.safetensors").unwrap(),
        vec![7u8; 1000]
    );
    let v: serde_json::Value = opened.read_json("blocks/0/field.json").unwrap();
    assert_eq!(v["levels"], 16);
    assert_eq!(opened.manifest().version, MANIFEST_VERSION);

    // Same config: resumes with the completed stage.
    let resumed = MapDir::create_or_resume(dir.path(), json!({"steps": 100})).unwrap();
    assert!(resumed.stage_done("nerf/0"));
    assert!(!resumed.stage_done("encoder"));
    // Another config: refused, old map untouched.
    let before = fs::read(dir.path().join(MANIFEST_FILE)).unwrap();
    let err = MapDir::create_or_resume(dir.path(), json!({"steps": 5})).unwrap_err();
    assert!(matches!(err, MapError::ConfigMismatch { .. }), "{err}");
    assert_eq!(fs::read(dir.path().join(MANIFEST_FILE)).unwrap(), before);
    // No temporary files are left behind.
    for entry in walk(dir.path()) {
        assert!(!entry.ends_with(".tmp"), "{entry}");
    }
}

fn walk(root: &std::path::Path) -> Vec<String> {
    let mut out = Vec::new();
    for e in fs::read_dir(root).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p.display().to_string());
        }
    }
    out
}

#[test]
fn truncated_file_is_reported_with_its_path() {
    let dir = tempfile::tempdir().unwrap();
    build(dir.path());
    let f = dir.path().join("blocks/0/field.safetensors");
    let bytes = fs::read(&f).unwrap();
    fs::write(&f, &bytes[..500]).unwrap();
    let err = MapDir::open(dir.path()).unwrap_err();
    match &err {
        MapError::SizeMismatch {
            path,
            expected,
            actual,
        } => {
            assert_eq!(path, &f);
            assert_eq!((*expected, *actual), (1000, 500));
        }
        other => panic!("unexpected {other}"),
    }
    assert!(err.to_string().contains("field.safetensors"));
}

#[test]
fn modified_file_fails_its_checksum() {
    let dir = tempfile::tempdir().unwrap();
    build(dir.path());
    let f = dir.path().join("blocks/0/field.safetensors");
    let mut bytes = fs::read(&f).unwrap();
    bytes[10] ^= 1;
    fs::write(&f, &bytes).unwrap();
    let map = MapDir::open(dir.path()).unwrap(); // same size: open's cheap check passes
    let err = map.read_file("blocks/0/field.safetensors").unwrap_err();
    assert!(matches!(err, MapError::Checksum { .. }), "{err}");
    assert!(matches!(map.verify(), Err(MapError::Checksum { .. })));
}

#[test]
fn missing_file_wrong_version_and_garbage_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    build(dir.path());
    fs::remove_file(dir.path().join("blocks/0/field.json")).unwrap();
    let err = MapDir::open(dir.path()).unwrap_err();
    assert!(matches!(err, MapError::MissingFile { .. }), "{err}");

    let dir = tempfile::tempdir().unwrap();
    build(dir.path());
    let mpath = dir.path().join(MANIFEST_FILE);
    let mut v: serde_json::Value = serde_json::from_slice(&fs::read(&mpath).unwrap()).unwrap();
    v["version"] = json!(MANIFEST_VERSION + 1);
    fs::write(&mpath, serde_json::to_vec(&v).unwrap()).unwrap();
    let err = MapDir::open(dir.path()).unwrap_err();
    assert!(
        matches!(err, MapError::Version { found, .. } if found == MANIFEST_VERSION + 1),
        "{err}"
    );

    fs::write(&mpath, b"{ not json").unwrap();
    assert!(matches!(
        MapDir::open(dir.path()),
        Err(MapError::Malformed { .. })
    ));
    fs::write(&mpath, br#"{"format": "something-else", "version": 1}"#).unwrap();
    assert!(matches!(
        MapDir::open(dir.path()),
        Err(MapError::Malformed { .. })
    ));
    let empty = tempfile::tempdir().unwrap();
    assert!(matches!(
        MapDir::open(empty.path()),
        Err(MapError::NotAMap { .. })
    ));
}

#[test]
fn unsafe_names_are_refused_on_write_and_on_load() {
    let dir = tempfile::tempdir().unwrap();
    let mut map = build(dir.path());
    assert!(matches!(
        map.write_file("../escape", b"x"),
        Err(MapError::UnsafePath { .. })
    ));
    let mpath = dir.path().join(MANIFEST_FILE);
    let mut v: serde_json::Value = serde_json::from_slice(&fs::read(&mpath).unwrap()).unwrap();
    v["files"]["../../etc/passwd"] = json!({"bytes": 1, "sha256": "00"});
    fs::write(&mpath, serde_json::to_vec(&v).unwrap()).unwrap();
    assert!(matches!(
        MapDir::open(dir.path()),
        Err(MapError::UnsafePath { .. })
    ));
}
