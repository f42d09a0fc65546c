//! A map's `manifest.json`: opening the map and listing its problems never panics.
#![no_main]

use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use matloc_pipeline::map::MapDir;

fuzz_target!(|data: &[u8]| {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    let dir = DIR.get_or_init(|| tempfile::tempdir().expect("temporary directory"));
    std::fs::write(dir.path().join("manifest.json"), data).expect("write manifest");
    if let Ok(map) = MapDir::open_manifest(dir.path()) {
        let _ = map.problems();
        let _ = MapDir::open(dir.path());
    }
});
