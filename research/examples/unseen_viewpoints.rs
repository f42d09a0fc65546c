//! The default method on viewpoints the survey never flew, with and without views rendered by
//! the map's NeRFs confirming the poses no training image looks towards.
//!
//! ```sh
//! cargo run --release -p matloc-research --example unseen_viewpoints -- MAP PRESET [CLOSER [TILT]]
//! ```
//!
//! MAP is a map built from `matloc synth --preset PRESET` (seed 0). Each test view is turned
//! about the vertical through the ground point it looks at (45°, 135°, … until no training
//! image looks within the structure method's view angle of it) and brought `CLOSER` (default
//! 0.35) of the way to that point, then pitched `TILT` degrees (default 30) further from the
//! nadir; the view is rendered by the synthetic world and localized
//! with `structure` (every default), then with `structure.rendered.enabled = false`.

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::{Method, MethodOptions, localize_with};
use matloc_synth::SynthConfig;
use matloc_synth::flight::{SecondFlight, render_second_flight, second_flight_frames, turned_view};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let map_dir = args.get(1).expect("MAP");
    let preset = args.get(2).map_or("tiny", String::as_str);
    let closer: f64 = args.get(3).map_or(0.35, |s| s.parse().expect("CLOSER"));
    let tilt: f64 = args.get(4).map_or(30.0, |s| s.parse().expect("TILT"));
    let map = LoadedMap::open(std::path::Path::new(map_dir)).expect("map");
    let structure = map.structure.as_ref().expect("a map with a structure");
    let config = SynthConfig::preset(preset).expect("preset");
    let flight = SecondFlight::same_flight();
    let (world, frames) = second_flight_frames(&config, &flight).expect("frames");
    let with = MethodOptions::default();
    let mut without = MethodOptions::default();
    without.structure.rendered.enabled = false;
    let angle = with.structure.max_view_angle_deg;
    let (mut n, mut ok_with, mut ok_without, mut wrong_with, mut wrong_without) = (0, 0, 0, 0, 0);
    let (mut secs_with, mut secs_without) = (0.0, 0.0);
    for (i, f) in frames.iter().enumerate() {
        let Some(pose) = [45.0, 135.0, 225.0, 315.0, 90.0, 180.0, 270.0]
            .into_iter()
            .filter_map(|yaw| turned_view(&world, &f.cam_from_world, yaw, closer, tilt))
            .find(|p| structure.images_looking_like(p, angle).next().is_none())
        else {
            eprintln!("view {i}: every turn has a training image within {angle}°");
            continue;
        };
        let mut frame = f.clone();
        frame.cam_from_world = pose;
        let image = render_second_flight(&world, &config, &flight, &frame, 500 + i);
        n += 1;
        let mut row = format!("view {i:2}:");
        for (name, options, ok, wrong, secs) in [
            ("with", &with, &mut ok_with, &mut wrong_with, &mut secs_with),
            (
                "without",
                &without,
                &mut ok_without,
                &mut wrong_without,
                &mut secs_without,
            ),
        ] {
            let r = localize_with(&map, &Method::Structure, "q", &image, &f.camera, options)
                .expect("localize");
            *secs += r.total_seconds;
            match r.cam_from_world {
                Some(p) => {
                    let (t, a) = (
                        translation_error_m(&p, &pose),
                        rotation_error_deg(&p, &pose),
                    );
                    *ok += usize::from(t <= 0.25 && a <= 2.0);
                    *wrong += usize::from(t > 5.0 || a > 10.0);
                    row += &format!(" {name} {t:.3} m {a:.2}° ({} inliers);", r.inliers);
                }
                None => row += &format!(" {name} refused ({} inliers);", r.inliers),
            }
        }
        println!("{row}");
    }
    println!(
        "{n} unseen viewpoints: within (0.25 m, 2°) {ok_with} with renders, {ok_without} \
         without; false accepts {wrong_with} / {wrong_without}; {:.3} / {:.3} s per query",
        secs_with / n.max(1) as f64,
        secs_without / n.max(1) as f64
    );
}
