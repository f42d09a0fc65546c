//! COLMAP binary models: `cameras.bin`, `images.bin`, `points3D.bin`.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use matloc_data::colmap::{parse_cameras_binary, parse_images_binary, parse_points3d_binary};

fuzz_target!(|data: &[u8]| {
    let p = Path::new("model.bin");
    let _ = parse_cameras_binary(data, p);
    let _ = parse_images_binary(data, p);
    let _ = parse_points3d_binary(data, p);
});
