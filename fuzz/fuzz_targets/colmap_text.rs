//! COLMAP text models: `cameras.txt`, `images.txt`, `points3D.txt`.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use matloc_data::colmap::{parse_cameras_text, parse_images_text, parse_points3d_text};

fuzz_target!(|data: &[u8]| {
    let p = Path::new("model.txt");
    let _ = parse_cameras_text(data, p);
    let _ = parse_images_text(data, p);
    let _ = parse_points3d_text(data, p);
});
