//! Localize one image against a built map through the library, with the default method
//! (`structure`; the paper's pipeline is `Method::Matloc`).
//!
//! `cargo run --release -p matloc-pipeline --example localize_image -- MAP IMAGE [FX FY CX CY]`
//!
//! Without intrinsics the image is taken to come from the map's own camera (scaled to the
//! image's size). Prints the pose as `cam_from_world` (OpenCV camera axes, metres), or why the
//! query was refused.

use std::path::Path;

use matloc_core::Camera;
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::{Method, MethodOptions, localize_with};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 3 && args.len() != 7 {
        eprintln!("usage: localize_image MAP IMAGE [FX FY CX CY]");
        std::process::exit(2);
    }
    let map = LoadedMap::open(Path::new(&args[1]))?;
    let image = matloc_data::images::load_rgb(Path::new(&args[2]))?;
    let (w, h) = (image.width() as u32, image.height() as u32);
    let camera = if args.len() == 7 {
        let v: Vec<f64> = args[3..7]
            .iter()
            .map(|a| a.parse())
            .collect::<Result<_, _>>()?;
        Camera::pinhole(w, h, v[0], v[1], v[2], v[3])?
    } else {
        map.camera()
            .ok_or("the map records no camera: pass FX FY CX CY")?
            .rescaled(w, h)?
    };
    // The map was built at its own resolution: bring the query to it.
    let (image, camera) = match map.camera() {
        Some(c) if (c.width, c.height) != (w, h) => (
            matloc_core::image::resize_area(&image, c.width as usize, c.height as usize),
            camera.rescaled(c.width, c.height)?,
        ),
        _ => (image, camera),
    };
    let options = MethodOptions::default();
    let result = localize_with(&map, &Method::DEFAULT, &args[2], &image, &camera, &options)?;
    let confidence = result.confidence.unwrap_or(f64::NAN);
    match result.cam_from_world {
        Some(pose) => {
            let t = pose.translation.vector;
            let q = pose.rotation.quaternion();
            println!(
                "cam_from_world: t = [{:.4}, {:.4}, {:.4}] m, q (w, x, y, z) = [{:.6}, {:.6}, {:.6}, {:.6}]",
                t.x, t.y, t.z, q.w, q.i, q.j, q.k
            );
            println!(
                "confidence {confidence:.3}, {} inliers, {:.3} s",
                result.inliers, result.total_seconds
            );
        }
        None => println!(
            "not localized (confidence {confidence:.3} after {} hypotheses)",
            result.hypotheses.len()
        ),
    }
    Ok(())
}
