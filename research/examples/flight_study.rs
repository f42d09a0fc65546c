//! How a map's learned query encoders hold up on other query sets (a second flight, a lens):
//! for each dataset's test views, the encoder of the block that renders most of the view
//! against that block's NeRF features rendered at the true pose — MNN matches, correct ones
//! (≤ 2 px and ≤ 8 px) and the PnP pose they give — and the whole MatLoc pipeline
//! (`Method::Matloc`, the map's calibration): within 1 m, refused, false accepts (returned
//! beyond 5 m or 10°). `FLIGHT_DIMS=A-B` matches on block dims A..=B only.
//!
//!     cargo run --release -p matloc-research --example flight_study -- MAP DATA [DATA ...]
//!
//! Counts of correct matches vary far less from build to build than the ten `tiny` test views'
//! within-1-m counts, so encoder variants are compared on them.

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_data::{Split, read_dataset};
use matloc_match::QueryFeatures;
use matloc_match::localize::{correct_matches, render_map_points, solve_pose, timed_match};
use matloc_pipeline::map::LoadedMap;
use matloc_pipeline::methods::{Method, MethodOptions, localize_with};
use matloc_pnp::LoRansacPnp;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::path::PathBuf;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}

fn main() {
    let args: Vec<PathBuf> = std::env::args().skip(1).map(PathBuf::from).collect();
    if args.len() < 2 {
        eprintln!("usage: flight_study MAP DATA [DATA ...]");
        std::process::exit(2);
    }
    let map = LoadedMap::open(&args[0]).expect("map");
    for blk in &map.blocks.0 {
        assert_eq!(
            blk.encoder.dims(),
            blk.dims.as_slice(),
            "the study needs encoders of their blocks' rendered dims"
        );
    }
    // `FLIGHT_DIMS=A-B` matches on the block dims A..=B only (the pipeline keeps all).
    let selection: Option<Vec<usize>> = std::env::var("FLIGHT_DIMS").ok().map(|v| {
        let (a, b) = v.split_once('-').expect("FLIGHT_DIMS=A-B");
        (a.parse().expect("A")..=b.parse().expect("B")).collect()
    });
    let solver = LoRansacPnp::default();
    let options = MethodOptions::default();
    println!(
        "| queries | matches | correct ≤ 2 px | ≤ 8 px | PnP from the true render: median t | MatLoc within 1 m | refused | false |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for data in &args[1..] {
        let dataset = read_dataset(data).expect("dataset");
        let frames: Vec<_> = dataset.split(Split::Test).collect();
        let (mut matches, mut c2, mut c8) = (0.0, 0.0, 0.0);
        let mut pnp = Vec::new();
        let (mut within, mut refused, mut wrong) = (0, 0, 0);
        for f in &frames {
            let (image, camera) =
                matloc_data::images::load_frame_image(&dataset, f, 1).expect("image");
            // The block whose NeRF renders the most of the view.
            let (blk, points) = map
                .blocks
                .0
                .iter()
                .filter_map(|blk| {
                    render_map_points(
                        blk.renderer.as_ref(),
                        &camera,
                        &f.cam_from_world,
                        blk.encoder.stride(),
                        &blk.dims,
                        0.5,
                    )
                    .ok()
                    .map(|p| (blk, p))
                })
                .max_by_key(|(_, p)| p.valid().iter().filter(|v| **v).count())
                .expect("no block renders the view");
            let encoded = blk.encoder.encode(&image).expect("encode");
            let query = QueryFeatures::new(encoded, blk.encoder.stride() as f64);
            let tm = timed_match(blk.matcher.as_ref(), &query, &points, selection.as_deref())
                .unwrap_or_else(|_| matloc_match::localize::TimedMatches {
                    matches: Vec::new(),
                    elapsed: std::time::Duration::ZERO,
                });
            matches += tm.matches.len() as f64;
            c2 += correct_matches(&tm.matches, &camera, &f.cam_from_world, 2.0) as f64;
            c8 += correct_matches(&tm.matches, &camera, &f.cam_from_world, 8.0) as f64;
            let mut rng = ChaCha8Rng::seed_from_u64(7);
            pnp.push(
                solve_pose(&tm.matches, &camera, &solver, &mut rng).map_or(f64::INFINITY, |r| {
                    translation_error_m(&r.cam_from_world, &f.cam_from_world)
                }),
            );
            let r = localize_with(&map, &Method::Matloc, "q", &image, &camera, &options)
                .expect("localize");
            match r.cam_from_world {
                None => refused += 1,
                Some(p)
                    if translation_error_m(&p, &f.cam_from_world) > 5.0
                        || rotation_error_deg(&p, &f.cam_from_world) > 10.0 =>
                {
                    wrong += 1
                }
                Some(p) if translation_error_m(&p, &f.cam_from_world) <= 1.0 => within += 1,
                Some(_) => {}
            }
        }
        let n = frames.len().max(1) as f64;
        println!(
            "| {} | {:.0} | {:.1} | {:.1} | {:.3} m | {within}/{} | {refused} | {wrong} |",
            data.display(),
            matches / n,
            c2 / n,
            c8 / n,
            median(&mut pnp),
            frames.len()
        );
    }
}
