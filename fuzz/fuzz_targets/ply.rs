//! PLY point clouds (ASCII and binary).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use matloc_data::ply::parse_ply;

fuzz_target!(|data: &[u8]| {
    let _ = parse_ply(data, Path::new("points.ply"));
});
