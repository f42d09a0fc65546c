//! How the structure method's render agreement tells a right pose from a wrong one on
//! viewpoints the survey never flew, per blur of the compared images.
//!
//! ```sh
//! cargo run --release -p matloc-research --example render_agreement_study -- MAP PRESET
//! ```
//!
//! MAP is a map built from `matloc synth --preset PRESET` (seed 0). Each test view is turned
//! 45° about the vertical through the ground point it looks at, brought a third closer and
//! pitched 30° towards the horizon (`turned_view`), and drawn by the synthetic world; the map's
//! NeRFs render the view at that true pose and at wrong ones (moved 5, 10 and 25 m over the
//! ground, turned 15° about the vertical); `render_agreement` compares each render with the
//! query at blurs of 0.5, 1, 2 and 3 px.

use matloc_core::pose::camera_center;
use matloc_keypoints::GrayImage;
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::NerfReferences;
use matloc_structure::{ReferenceRenderer, RenderedOptions, render_agreement};
use matloc_synth::SynthConfig;
use matloc_synth::flight::{SecondFlight, render_second_flight, second_flight_frames, turned_view};
use nalgebra::{Translation3, UnitQuaternion, Vector3};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let map = LoadedMap::open(std::path::Path::new(args.get(1).expect("MAP"))).expect("map");
    let preset = args.get(2).map_or("small", String::as_str);
    let config = SynthConfig::preset(preset).expect("preset");
    let flight = SecondFlight::same_flight();
    let (world, frames) = second_flight_frames(&config, &flight).expect("frames");
    let references = NerfReferences::new(&map);
    let blurs = [0.5f32, 1.0, 2.0, 3.0];
    // Per blur: (right, wrong) agreements.
    let mut seen: Vec<(Vec<f64>, Vec<f64>)> = vec![(Vec::new(), Vec::new()); blurs.len()];
    for (i, f) in frames.iter().enumerate() {
        let Some(truth) = turned_view(&world, &f.cam_from_world, 45.0, 0.35, 30.0) else {
            continue;
        };
        let mut frame = f.clone();
        frame.cam_from_world = truth;
        let query = GrayImage::from_image(&render_second_flight(
            &world,
            &config,
            &flight,
            &frame,
            700 + i,
        ));
        let world_from_cam = truth.inverse();
        let c = camera_center(&truth);
        let look = c + (world_from_cam.rotation * Vector3::z()) * 20.0;
        let moved = |dx: f64, dy: f64| {
            matloc_core::Pose::from_parts(
                Translation3::new(dx, dy, 0.0) * world_from_cam.translation,
                world_from_cam.rotation,
            )
            .inverse()
        };
        let turned = {
            let q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 15f64.to_radians());
            matloc_core::Pose::from_parts(world_from_cam.translation, q * world_from_cam.rotation)
                .inverse()
        };
        let poses = [
            (true, truth),
            (false, moved(5.0, 0.0)),
            (false, moved(0.0, 10.0)),
            (false, moved(-25.0, 0.0)),
            (false, turned),
        ];
        let mut row = format!("view {i:2}:");
        for (right, pose) in poses {
            let Some(reference) = references.render_reference(&f.camera, &pose, &look) else {
                continue;
            };
            row += if right { " right" } else { " wrong" };
            for (k, &blur_px) in blurs.iter().enumerate() {
                let options = RenderedOptions {
                    blur_px,
                    ..RenderedOptions::default()
                };
                if let Some(a) = render_agreement(&query, &reference, &options) {
                    row += &format!(" {a:.2}");
                    if right {
                        seen[k].0.push(a);
                    } else {
                        seen[k].1.push(a);
                    }
                }
            }
            row += ";";
        }
        println!("{row}");
    }
    for (k, (right, wrong)) in seen.iter_mut().enumerate() {
        right.sort_by(f64::total_cmp);
        wrong.sort_by(f64::total_cmp);
        let q = |v: &[f64], p: f64| {
            v.get(((v.len() as f64 - 1.0) * p).round() as usize)
                .copied()
        };
        println!(
            "blur {} px: right min {:?} q10 {:?} median {:?}; wrong median {:?} q90 {:?} max {:?}; \
             right ≥ 0.5: {}/{}, wrong ≥ 0.5: {}/{}",
            blurs[k],
            q(right, 0.0),
            q(right, 0.1),
            q(right, 0.5),
            q(wrong, 0.5),
            q(wrong, 0.9),
            q(wrong, 1.0),
            right.iter().filter(|&&a| a >= 0.5).count(),
            right.len(),
            wrong.iter().filter(|&&a| a >= 0.5).count(),
            wrong.len()
        );
    }
}
