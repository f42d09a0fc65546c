//! One line of a `localize --queries` list, `NAME MODEL WIDTH HEIGHT PARAMS...`, split and
//! turned into a camera the way `matloc localize` does (COLMAP model by name, parameter count,
//! then the camera's own checks).
#![no_main]

use libfuzzer_sys::fuzz_target;
use matloc_data::colmap::{ColmapCamera, ColmapCameraModel};

fuzz_target!(|data: &[u8]| {
    let Ok(line) = std::str::from_utf8(data) else {
        return;
    };
    let fields: Vec<&str> = line.split_whitespace().collect();
    if fields.len() < 4 {
        return;
    }
    let Ok(model) = ColmapCameraModel::from_name(&fields[1].to_ascii_uppercase()) else {
        return;
    };
    let size = |f: &str| f.parse::<u32>().ok().filter(|&v| v > 0);
    let (Some(width), Some(height)) = (size(fields[2]), size(fields[3])) else {
        return;
    };
    let Ok(params) = fields[4..]
        .iter()
        .map(|p| p.parse::<f64>())
        .collect::<Result<Vec<f64>, _>>()
    else {
        return;
    };
    if params.len() != model.num_params() {
        return;
    }
    let camera = ColmapCamera {
        id: 0,
        model,
        width,
        height,
        params,
    };
    if let Ok(c) = camera.to_camera() {
        // A camera that passed its checks projects and unprojects without panicking.
        let centre = nalgebra::Point2::new(f64::from(c.width) / 2.0, f64::from(c.height) / 2.0);
        if let Some(b) = c.unproject(centre) {
            let _ = c.project(&b);
        }
    }
});
