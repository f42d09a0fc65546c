//! Binary (rotated BRIEF) against gradient-histogram (RootSIFT layout) descriptors on a
//! built map's keypoint structure, measured as HPatches measures a descriptor: for every
//! query of a dataset with ground truth, the query's keypoints (detected as the structure
//! localizer detects them) are matched against the observations of the training images that
//! see most of the query's view at its true pose, and a match is correct when its map point
//! projects within 4 px of the query keypoint at that pose. Both descriptors describe the same
//! keypoints on both sides, so the figures compare descriptors, not detections.
//!
//!     cargo run --release -p matloc-research --example descriptor_study -- MAP QUERIES [IMAGES]
//!
//! Prints per query the matches and correct matches of each descriptor, summed over the
//! `IMAGES` (default 6) best training images, and a summary (with the union of both
//! descriptors' matches). `BINARY_RATIO` / `GRADIENT_RATIO` set each one's Lowe ratio
//! (defaults 0.8 and the gradient matcher's default, 0.8).

use std::path::Path;
use std::time::Instant;

use matloc_data::{Split, read_dataset};
use matloc_keypoints::{
    Descriptor, GradientDescriptor, GrayImage, KeypointConfig, MatchConfig, detect_and_describe,
    detect_and_describe_gradients, match_descriptors,
};
use matloc_pipeline::LoadedMap;
use matloc_structure::StructureImage;
use nalgebra::Point2;

/// A training image's observations re-described both ways: (observation, binary, gradient).
struct Described {
    obs: Vec<usize>,
    binary: Vec<Descriptor>,
    gradient: Vec<GradientDescriptor>,
}

fn keypoint_config() -> KeypointConfig {
    KeypointConfig {
        max_keypoints: 2000,
        upsample: true,
        ..KeypointConfig::default()
    }
}

/// Re-detects a training image's keypoints and keeps those at its observations' pixels.
fn describe_training(im: &StructureImage) -> Option<Described> {
    let app = im.appearance.as_ref()?;
    let (w, h) = (app.camera.width as usize, app.camera.height as usize);
    let gray = GrayImage::from_vec(
        w,
        h,
        app.gray.iter().map(|&v| f32::from(v) / 255.0).collect(),
    )?;
    let (kb, db) = detect_and_describe(&gray, &keypoint_config());
    let (kg, dg) = detect_and_describe_gradients(&gray, &keypoint_config());
    assert_eq!(kb.len(), kg.len());
    let mut out = Described {
        obs: Vec::new(),
        binary: Vec::new(),
        gradient: Vec::new(),
    };
    for (o, px) in im.pixel.iter().enumerate() {
        let nearest = kb
            .iter()
            .enumerate()
            .map(|(i, k)| (i, (k.x - px[0]).powi(2) + (k.y - px[1]).powi(2)))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        if let Some((i, d2)) = nearest
            && d2 < 0.25 * 0.25
        {
            out.obs.push(o);
            out.binary.push(db[i]);
            out.gradient.push(dg[i]);
        }
    }
    Some(out)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: descriptor_study MAP QUERIES [IMAGES]");
        std::process::exit(2);
    }
    let map = LoadedMap::open(Path::new(&args[1])).expect("map");
    let structure = map.structure.as_ref().expect("the map has a structure");
    let dataset = read_dataset(Path::new(&args[2])).expect("queries");
    let per_query: usize = args.get(3).map_or(6, |v| v.parse().expect("IMAGES"));
    let t = Instant::now();
    let described: Vec<Option<Described>> =
        structure.images().iter().map(describe_training).collect();
    let kept: usize = described.iter().flatten().map(|d| d.obs.len()).sum();
    eprintln!(
        "training images re-described in {:.1} s: {kept} of {} observations kept",
        t.elapsed().as_secs_f64(),
        structure.observations()
    );
    let points = structure.points();
    // BINARY_RATIO sets the binary descriptor's ratio test (default 0.8).
    let binary_config = MatchConfig {
        ratio: std::env::var("BINARY_RATIO").map_or(MatchConfig::default().ratio, |v| {
            v.parse().expect("BINARY_RATIO")
        }),
        ..MatchConfig::default()
    };
    // GRADIENT_RATIO sets the gradient descriptor's ratio test (default: the binary's).
    let gradient_config = MatchConfig {
        ratio: std::env::var("GRADIENT_RATIO").map_or(MatchConfig::gradient().ratio, |v| {
            v.parse().expect("GRADIENT_RATIO")
        }),
        ..MatchConfig::gradient()
    };
    println!("query | binary matches correct | gradient matches correct");
    let (mut sums, mut n) = ([0usize; 6], 0usize);
    let (mut ok_b, mut ok_g, mut ok_u) = (0usize, 0usize, 0usize);
    for f in dataset.split(Split::Test) {
        let (image, camera) = matloc_data::images::load_frame_image(&dataset, f, 1).expect("image");
        let truth = f.cam_from_world;
        let gray = GrayImage::from_image(&image).unsharp(1.0, 1.0);
        let (kq, dqb) = detect_and_describe(&gray, &keypoint_config());
        let (_, dqg) = detect_and_describe_gradients(&gray, &keypoint_config());
        // Training images by how many of their points the true pose sees.
        let inside = |p: &nalgebra::Point3<f64>| {
            camera.project_world(&truth, p).is_some_and(|q| {
                q.x >= 0.0 && q.y >= 0.0 && q.x < camera.width as f64 && q.y < camera.height as f64
            })
        };
        let mut ranked: Vec<(usize, usize)> = structure
            .images()
            .iter()
            .enumerate()
            .map(|(i, im)| {
                (
                    im.point
                        .iter()
                        .filter(|&&p| inside(&points[p as usize]))
                        .count(),
                    i,
                )
            })
            .collect();
        ranked.sort_by(|a, b| b.cmp(a));
        let mut row = [0usize; 6];
        for &(_, i) in ranked.iter().take(per_query) {
            let Some(d) = &described[i] else { continue };
            let im = &structure.images()[i];
            let correct = |a: usize, b: usize| {
                let p = points[im.point[d.obs[b]] as usize];
                camera.project_world(&truth, &p).is_some_and(|q| {
                    (q - Point2::new(f64::from(kq[a].x), f64::from(kq[a].y))).norm() <= 4.0
                })
            };
            let mb = match_descriptors(&dqb, &d.binary, &binary_config);
            let mg = match_descriptors(&dqg, &d.gradient, &gradient_config);
            // Union: every query keypoint's match by either descriptor (binary first).
            let mut union: Vec<(usize, usize)> = mb.iter().map(|m| (m.a, m.b)).collect();
            for m in &mg {
                if !mb.iter().any(|x| x.a == m.a) {
                    union.push((m.a, m.b));
                }
            }
            row[4] += union.len();
            row[5] += union.iter().filter(|&&(a, b)| correct(a, b)).count();
            row[0] += mb.len();
            row[1] += mb.iter().filter(|m| correct(m.a, m.b)).count();
            row[2] += mg.len();
            row[3] += mg.iter().filter(|m| correct(m.a, m.b)).count();
        }
        println!(
            "{} | {} {} | {} {}",
            f.image_path.display(),
            row[0],
            row[1],
            row[2],
            row[3]
        );
        for (s, r) in sums.iter_mut().zip(row) {
            *s += r;
        }
        ok_b += usize::from(row[1] >= 15);
        ok_g += usize::from(row[3] >= 15);
        ok_u += usize::from(row[5] >= 15);
        n += 1;
    }
    println!(
        "{n} queries: binary {} matches, {} correct ({:.0} %), {ok_b} queries with >= 15 correct; \
         gradient {} matches, {} correct ({:.0} %), {ok_g} queries with >= 15 correct; \
         union {} matches, {} correct ({:.0} %), {ok_u} queries with >= 15 correct",
        sums[0],
        sums[1],
        100.0 * sums[1] as f64 / sums[0].max(1) as f64,
        sums[2],
        sums[3],
        100.0 * sums[3] as f64 / sums[2].max(1) as f64,
        sums[4],
        sums[5],
        100.0 * sums[5] as f64 / sums[4].max(1) as f64,
    );
}
