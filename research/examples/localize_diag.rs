//! Diagnostics of a built map on a dataset's test views: for each query, the place
//! classifier's coarse pose error and what matching + PnP make of it, next to the same from
//! the true pose (an upper bound: a perfect place stage).
//!
//!     cargo run --release -p matloc-research --example localize_diag -- MAP DATA

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_data::{Split, read_dataset};
use matloc_pipeline::map::load::block_matcher;
use matloc_pipeline::{FixedPlace, LoadedMap};
use matloc_place::PlaceHypothesis;
use matloc_pnp::LoRansacPnp;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: localize_diag MAP DATA");
        std::process::exit(2);
    }
    let mut map = LoadedMap::open(std::path::Path::new(&args[1])).expect("map");
    // DIAG_DIMS=all|a,b,c overrides the selected dims of every block.
    if let Ok(v) = std::env::var("DIAG_DIMS") {
        for b in &mut map.blocks.0 {
            let dims: Vec<usize> = if v == "all" {
                (0..47).collect()
            } else {
                v.split(',').map(|x| x.parse().expect("dim")).collect()
            };
            b.matcher = Box::new(block_matcher(b.encoder.as_ref(), &dims, None).expect("dims"));
            b.dims = dims;
        }
    }
    let dataset = read_dataset(std::path::Path::new(&args[2])).expect("dataset");
    // DIAG_WINDOW=pixels sets a matching window (default: global).
    if let Ok(v) = std::env::var("DIAG_WINDOW") {
        let window: f64 = v.parse().expect("window");
        for b in &mut map.blocks.0 {
            b.matcher =
                Box::new(block_matcher(b.encoder.as_ref(), &b.dims, Some(window)).expect("dims"));
        }
    }
    let solver = LoRansacPnp::default();
    println!(
        "query | coarse err (m, deg) | est err (m, deg) | matches inliers conf | from truth: est err | matches inliers conf"
    );
    // Within 1 m / 5 deg: (place start, accepted), (true-pose start), (oracle from place).
    let (mut ok_place, mut ok_accepted, mut ok_truth, mut ok_oracle, mut n) = (0, 0, 0, 0, 0);
    let mut accept = 0.0;
    let good = |e: Option<(f64, f64)>| e.is_some_and(|(t, r)| t <= 1.0 && r <= 5.0);
    for f in dataset.split(Split::Test) {
        n += 1;
        let (image, camera) = matloc_data::images::load_frame_image(&dataset, f, 1).expect("image");
        let hyps = map.place.predict(&image, &camera, 1).expect("place");
        let h = hyps[0].clone();
        let mut options = map.options();
        // DIAG_CELLS=first,refine sets the PnP thresholds (query cells).
        if let Ok(v) = std::env::var("DIAG_CELLS") {
            let c: Vec<f64> = v.split(',').map(|x| x.parse().expect("cells")).collect();
            options.first_pass_threshold_cells = c[0];
            options.refine_threshold_cells = *c.get(1).unwrap_or(&c[0]);
        }
        accept = options.confidence.accept_threshold;
        options.confidence.accept_threshold = 0.0;
        options.top_k = 1;
        let run = |h: PlaceHypothesis| {
            let fixed = FixedPlace(vec![h]);
            let loc = map.blocks.localizer(&fixed, &solver, options.clone());
            let out = loc.localize(&image, &camera).expect("localize");
            let rep = out.hypotheses[0].clone();
            let err = out.cam_from_world.map(|p| {
                (
                    translation_error_m(&p, &f.cam_from_world),
                    rotation_error_deg(&p, &f.cam_from_world),
                )
            });
            (err, rep)
        };
        let coarse = (
            translation_error_m(&h.cam_from_world, &f.cam_from_world),
            rotation_error_deg(&h.cam_from_world, &f.cam_from_world),
        );
        let (e1, r1) = run(h.clone());
        let truth = PlaceHypothesis {
            cam_from_world: f.cam_from_world,
            ..h
        };
        let (e2, r2) = run(truth);
        // Oracle query features: the block's own NeRF rendered at the true pose (a perfect
        // encoder), from the place hypothesis: isolates NeRF features + depth from the encoder.
        let hb = h.block.unwrap_or(0);
        let oracle = matloc_pipeline::eval::diagnostics::RenderedQueryEncoder {
            renderer: map.blocks.0[hb].renderer.as_ref(),
            camera,
            cam_from_world: f.cam_from_world,
            dims: (0..47).collect(),
            stride: 4,
        };
        let fixed = FixedPlace(vec![h.clone()]);
        let loc = matloc_pipeline::Localizer {
            place: &fixed,
            blocks: map
                .blocks
                .0
                .iter()
                .enumerate()
                .map(|(b, blk)| matloc_pipeline::LocalizerBlock {
                    renderer: blk.renderer.as_ref(),
                    encoder: if b == hb {
                        &oracle
                    } else {
                        blk.encoder.as_ref()
                    },
                    matcher: blk.matcher.as_ref(),
                    dims: blk.dims.clone(),
                    match_dims: blk.match_dims.clone(),
                })
                .collect(),
            solver: &solver,
            options: options.clone(),
        };
        let o = loc.localize(&image, &camera).expect("oracle");
        let oe = o.cam_from_world.map(|p| {
            (
                translation_error_m(&p, &f.cam_from_world),
                rotation_error_deg(&p, &f.cam_from_world),
            )
        });
        // Depth of the NeRF at the true pose vs the dataset's.
        let gt_depth = matloc_data::images::load_frame_depth(&dataset, f, 1)
            .ok()
            .flatten();
        let depth_err_of = |blk: usize| {
            gt_depth.as_ref().map(|g| {
                let r = matloc_match::ViewRenderer::render_view(
                    map.blocks.0[blk].renderer.as_ref(),
                    &camera,
                    &f.cam_from_world,
                    4,
                    &[],
                )
                .expect("render");
                let mut rel = Vec::new();
                for i in 0..r.cols * r.rows {
                    let (x, y) = (i % r.cols * 4 + 2, i / r.cols * 4 + 2);
                    let gd = g.pixel(x, y)[0];
                    if gd > 0.0 && gd.is_finite() && r.accumulation[i] > 0.5 {
                        rel.push(((r.depth_z[i] - gd) / gd).abs() as f64);
                    }
                }
                matloc_core::metrics::median(&rel).unwrap_or(f64::NAN)
            })
        };
        let depth_err = depth_err_of(hb);
        let per_block: Vec<String> = (0..map.blocks.0.len())
            .map(|b| format!("{:.1}", 100.0 * depth_err_of(b).unwrap_or(f64::NAN)))
            .collect();
        println!("  block {hb}; NeRF depth error per block at the true pose (%): {per_block:?}");
        println!(
            "  oracle features from coarse: {} ({} matches, {} inliers); NeRF median depth error {:.1} %",
            oe.map_or("-".to_string(), |e| format!("{:.2} m {:.2}°", e.0, e.1)),
            o.hypotheses[0].matches,
            o.hypotheses[0].inliers,
            100.0 * depth_err.unwrap_or(f64::NAN)
        );
        // Encoder fit at the true pose: correlation of encoder vs rendered features per
        // selected dim over surface cells.
        let blk = &map.blocks.0[hb];
        let all: Vec<usize> = (0..47).collect();
        let target = matloc_match::ViewRenderer::render_view(
            blk.renderer.as_ref(),
            &camera,
            &f.cam_from_world,
            4,
            &all,
        )
        .expect("render");
        let enc = blk.encoder.encode(&image).expect("encode");
        let corr =
            matloc_pipeline::eval::diagnostics::encoder_correlation(&target, &enc, &blk.dims);
        println!(
            "  encoder corr per selected dim {:?}",
            corr.iter()
                .map(|c| c.map_or("-".into(), |c| format!("{c:.2}")))
                .collect::<Vec<_>>()
        );
        ok_place += usize::from(good(e1));
        ok_accepted += usize::from(good(e1) && r1.confidence >= accept);
        ok_truth += usize::from(good(e2));
        ok_oracle += usize::from(good(oe));
        let fmt = |e: Option<(f64, f64)>| {
            e.map_or("-".to_string(), |e| format!("{:.2} m {:.2}°", e.0, e.1))
        };
        println!(
            "{} | {:.1} m {:.1}° | {} | {} {} {:.2} | {} | {} {} {:.2} {}",
            f.image_path.display(),
            coarse.0,
            coarse.1,
            fmt(e1),
            r1.matches,
            r1.inliers,
            r1.confidence,
            fmt(e2),
            r2.matches,
            r2.inliers,
            r2.confidence,
            r2.failure.unwrap_or_default()
        );
    }
    println!(
        "within 1 m / 5 deg of {n}: from the place hypothesis {ok_place} ({ok_accepted} with confidence >= {accept:.2}); from the true pose {ok_truth}; perfect encoder from the place hypothesis {ok_oracle}"
    );
}
