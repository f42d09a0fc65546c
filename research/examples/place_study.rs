//! How the map's place predictor holds up on other query sets: for each dataset's test views,
//! the share whose top-1 / top-3 / top-30 hypotheses hold a coarse pose within 15 m of the
//! truth, and the median distance of the nearest of the top 3.
//!
//!     cargo run --release -p matloc-research --example place_study -- MAP DATA [DATA ...]

use matloc_core::metrics::translation_error_m;
use matloc_data::{Split, read_dataset};
use matloc_pipeline::LoadedMap;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 2 {
        eprintln!("usage: place_study MAP DATA [DATA ...]");
        std::process::exit(2);
    }
    let map = LoadedMap::open(std::path::Path::new(&args[0])).expect("map");
    println!("| queries | top-1 ≤ 15 m | top-3 ≤ 15 m | top-30 ≤ 15 m | median nearest of top 3 |");
    println!("|---|---|---|---|---|");
    for data in &args[1..] {
        let dataset = read_dataset(std::path::Path::new(data)).expect("dataset");
        let (mut n, mut hits, mut nearest) = (0, [0usize; 3], Vec::new());
        for f in dataset.split(Split::Test) {
            n += 1;
            let (image, camera) =
                matloc_data::images::load_frame_image(&dataset, f, 1).expect("image");
            let hyps = map.place.predict(&image, &camera, 30).expect("place");
            let d: Vec<f64> = hyps
                .iter()
                .map(|h| translation_error_m(&h.cam_from_world, &f.cam_from_world))
                .collect();
            for (slot, k) in [1usize, 3, 30].iter().enumerate() {
                if d.iter().take(*k).any(|&x| x <= 15.0) {
                    hits[slot] += 1;
                }
            }
            nearest.push(d.iter().take(3).cloned().fold(f64::INFINITY, f64::min));
        }
        nearest.sort_by(f64::total_cmp);
        let pct = |k: usize| 100.0 * k as f64 / n.max(1) as f64;
        println!(
            "| {data} | {:.1} % | {:.1} % | {:.1} % | {:.1} m |",
            pct(hits[0]),
            pct(hits[1]),
            pct(hits[2]),
            nearest.get(n / 2).copied().unwrap_or(f64::NAN)
        );
    }
}
