//! `.npy` depth maps.
#![no_main]

use libfuzzer_sys::fuzz_target;
use matloc_data::images::parse_npy;

fuzz_target!(|data: &[u8]| {
    let _ = parse_npy(data);
});
