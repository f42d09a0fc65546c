//! Map build configs (`map build --config`): parse, then the checks a build makes first.
#![no_main]

use libfuzzer_sys::fuzz_target;
use matloc_pipeline::MapConfig;

fuzz_target!(|data: &[u8]| {
    if let Ok(config) = serde_json::from_slice::<MapConfig>(data) {
        let _ = config.surface.validate();
        let _ = config.samples.validate();
        let _ = serde_json::to_vec(&config);
    }
});
