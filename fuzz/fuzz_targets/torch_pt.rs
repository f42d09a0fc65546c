//! torch `.pt` files (Mega-NeRF metadata and coordinates).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use matloc_data::torch_pt::parse_pt;

fuzz_target!(|data: &[u8]| {
    let _ = parse_pt(data, Path::new("metadata.pt"));
});
