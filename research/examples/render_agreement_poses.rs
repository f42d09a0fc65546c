//! How the structure method's render agreement scores the consensuses an evaluation found:
//! every place hypothesis of `matloc eval`'s `results.jsonl` with a solved pose and at least
//! `MIN_INLIERS` (15) inliers is rendered by the map's NeRFs at that pose and compared with
//! the query (`render_agreement`) at blurs of 1, 2 and 3 px, at the query's size and at half
//! of it; each row gives the pose's distance from the truth.
//!
//! ```sh
//! cargo run --release -p matloc-research --example render_agreement_poses -- MAP DATA RESULTS
//! ```
//!
//! DATA is the dataset the evaluation localized (its test split), RESULTS its
//! `results.jsonl`.

use matloc_core::Image;
use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::pose::{Pose, cam_from_world_from_colmap, camera_center, viewing_direction};
use matloc_data::{Split, read_dataset};
use matloc_keypoints::GrayImage;
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::NerfReferences;
use matloc_structure::{ReferenceRenderer, RenderedOptions, RenderedReference, render_agreement};

/// Half the size of `reference`: colour and opacity averaged over 2 × 2 pixels.
fn halved(reference: &RenderedReference) -> RenderedReference {
    let (w, h, c) = reference.image.shape();
    let (hw, hh) = (w / 2, h / 2);
    let mut image = Image::new(hw, hh, c);
    let mut accumulation = vec![0f32; hw * hh];
    for y in 0..hh {
        for x in 0..hw {
            for ch in 0..c {
                let mut v = 0.0;
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    v += reference.image.pixel(2 * x + dx, 2 * y + dy)[ch];
                }
                image.pixel_mut(x, y)[ch] = v / 4.0;
            }
            accumulation[y * hw + x] = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .iter()
                .map(|(dx, dy)| reference.accumulation[(2 * y + dy) * w + 2 * x + dx])
                .sum::<f32>()
                / 4.0;
        }
    }
    RenderedReference {
        image,
        z_depth: vec![0.0; hw * hh],
        accumulation,
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        eprintln!("usage: render_agreement_poses MAP DATA RESULTS");
        std::process::exit(2);
    }
    let map = LoadedMap::open(std::path::Path::new(&args[1])).expect("map");
    let dataset = read_dataset(std::path::Path::new(&args[2])).expect("dataset");
    let min_inliers: usize = std::env::var("MIN_INLIERS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(15);
    let references = NerfReferences::new(&map);
    let blurs = [1.0f32, 2.0, 3.0];
    println!("query | inliers | error m / deg | agreement at blur 1 2 3 px | half size 1 2 3 px");
    let text = std::fs::read_to_string(&args[3]).expect("results");
    for line in text.lines() {
        let r: serde_json::Value = serde_json::from_str(line).expect("json");
        let name = r["name"].as_str().expect("name");
        let Some(frame) = dataset
            .split(Split::Test)
            .find(|f| f.image_path.to_string_lossy().ends_with(name))
        else {
            continue;
        };
        let (image, camera) =
            matloc_data::images::load_frame_image(&dataset, frame, 1).expect("image");
        let query = GrayImage::from_image(&image);
        let half_query = query.resized(query.width() / 2, query.height() / 2);
        let mut seen: Vec<Pose> = Vec::new();
        for h in r["hypotheses"].as_array().into_iter().flatten() {
            let inliers = h["inliers"].as_u64().unwrap_or(0) as usize;
            let (Some(q), Some(t)) = (h.get("refined_qvec_wxyz"), h.get("refined_tvec")) else {
                continue;
            };
            if inliers < min_inliers {
                continue;
            }
            let q: [f64; 4] = serde_json::from_value(q.clone()).expect("qvec");
            let t: [f64; 3] = serde_json::from_value(t.clone()).expect("tvec");
            let pose = cam_from_world_from_colmap(q, t).expect("pose");
            if seen
                .iter()
                .any(|p| (camera_center(p) - camera_center(&pose)).norm() < 0.05)
            {
                continue;
            }
            seen.push(pose);
            let look = camera_center(&pose) + viewing_direction(&pose) * 15.0;
            let Some(reference) = references.render_reference(&camera, &pose, &look) else {
                continue;
            };
            let half = halved(&reference);
            let score = |q: &GrayImage, r: &RenderedReference, blur_px: f32| {
                let options = RenderedOptions {
                    blur_px,
                    ..RenderedOptions::default()
                };
                render_agreement(q, r, &options).map_or("  -  ".to_string(), |a| format!("{a:.2}"))
            };
            let full: Vec<String> = blurs
                .iter()
                .map(|&b| score(&query, &reference, b))
                .collect();
            let small: Vec<String> = blurs
                .iter()
                .map(|&b| score(&half_query, &half, b / 2.0))
                .collect();
            println!(
                "{name} | {inliers} | {:.2} / {:.1} | {} | {}",
                translation_error_m(&pose, &frame.cam_from_world),
                rotation_error_deg(&pose, &frame.cam_from_world),
                full.join(" "),
                small.join(" ")
            );
        }
    }
}
