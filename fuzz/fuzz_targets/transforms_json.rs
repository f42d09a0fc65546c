//! nerfstudio `transforms.json`: any bytes parse into a dataset or give an error.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use matloc_data::Split;
use matloc_data::nerfstudio::parse_transforms;

fuzz_target!(|data: &[u8]| {
    let _ = parse_transforms(
        data,
        Path::new("transforms.json"),
        Path::new("/nonexistent-root"),
        Split::Train,
    );
});
