//! The structure localizer (`matloc_structure`) alone: triangulates the training split of a
//! dataset as the map build's structure stage does, then localizes every test view from one
//! start pose (the true pose moved by OFFSET metres in a fixed direction per view, and 2°),
//! so that the figures measure matching and PnP without the place predictor. With
//! `QUERIES=DIR` the queries are that dataset's test split instead (e.g. the second flight
//! from `matloc synth --second-flight`, same poses, other light and lens). With
//! `STRUCTURE_OPTIONS='{"neighbours": 10}'` (JSON, fields of `StructureOptions`) the
//! localizer's settings differ from the defaults in those fields.
//!
//! `cargo run --release -p matloc-research --example structure_study -- DATA [OFFSET_M]`

use std::path::Path;
use std::time::Instant;

use matloc_core::Pose;
use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_data::Split;
use matloc_structure::{StructureMap, StructureOptions};
use matloc_surface::TriangulateConfig;
use matloc_surface::triangulate::triangulate_tracks;
use nalgebra::{Translation3, Unit, UnitQuaternion, Vector3};
use rand::SeedableRng;

/// The true pose's camera moved by `offset` m and turned by 2°, in a direction set by `i`.
fn start_of(truth: &Pose, i: usize, offset: f64) -> Pose {
    let a = i as f64 * 2.399_963;
    let t = Vector3::new(a.cos(), a.sin(), 0.3 * (2.0 * a).sin()).normalize() * offset;
    let axis = Unit::new_normalize(Vector3::new(a.sin(), 0.5, a.cos()));
    let r = UnitQuaternion::from_axis_angle(&axis, 2f64.to_radians());
    let world_from_cam = truth.inverse();
    Pose::from_parts(
        Translation3::from(world_from_cam.translation.vector + t),
        world_from_cam.rotation * r,
    )
    .inverse()
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let data = Path::new(args.get(1).expect("usage: structure_study DATA [OFFSET_M]"));
    let offset: f64 = args.get(2).map_or(1.5, |s| s.parse().unwrap());
    let dataset = matloc_data::read_dataset(data).unwrap();
    let queries = std::env::var("QUERIES")
        .ok()
        .map(|q| matloc_data::read_dataset(Path::new(&q)).unwrap());
    let queries = queries.as_ref().unwrap_or(&dataset);

    let train = dataset.split_indices(Split::Train);
    let config = TriangulateConfig {
        upsample: true,
        max_side: dataset
            .frames
            .iter()
            .map(|f| f.camera.width.max(f.camera.height))
            .max()
            .unwrap_or(1),
        ..TriangulateConfig::default()
    };
    let t = Instant::now();
    let tracks = triangulate_tracks(&dataset, &train, &config, &|_, _, _| {}).unwrap();
    let map = StructureMap::from_tracks(&tracks, |f| dataset.frames[f].cam_from_world);
    println!(
        "triangulated {} points, {} observations, {} images in {:.1} s",
        map.points().len(),
        map.observations(),
        map.images().len(),
        t.elapsed().as_secs_f64()
    );

    let options: StructureOptions = std::env::var("STRUCTURE_OPTIONS").map_or_else(
        |_| StructureOptions::default(),
        |json| serde_json::from_str(&json).expect("STRUCTURE_OPTIONS: StructureOptions JSON"),
    );
    let (mut dt, mut dr, mut seconds) = (Vec::new(), Vec::new(), 0.0);
    let (mut within_25cm, mut within_1m, mut refused) = (0, 0, 0);
    let (mut align_s, mut aligned_inliers) = (0.0, 0usize);
    for (i, f) in queries.split(Split::Test).enumerate() {
        let (image, camera) = matloc_data::images::load_frame_image(queries, f, 1).unwrap();
        let start = start_of(&f.cam_from_world, i, offset);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let t = Instant::now();
        let r = matloc_structure::localize(&map, &image, &camera, &[start], &options, &mut rng)
            .unwrap();
        seconds += t.elapsed().as_secs_f64();
        align_s += r
            .stage_seconds
            .iter()
            .find(|(n, _)| n == "align")
            .map_or(0.0, |(_, s)| *s);
        aligned_inliers += r.aligned_inliers;
        match r.cam_from_world {
            Some(p) => {
                let (t, a) = (
                    translation_error_m(&p, &f.cam_from_world),
                    rotation_error_deg(&p, &f.cam_from_world),
                );
                within_25cm += usize::from(t <= 0.25 && a <= 2.0);
                within_1m += usize::from(t <= 1.0 && a <= 5.0);
                println!(
                    "{}: {t:.3} m {a:.3}° ({} inliers of {} matches)",
                    f.image_path.display(),
                    r.inliers,
                    r.matches
                );
                dt.push(t);
                dr.push(a);
            }
            None => {
                refused += 1;
                println!("{}: refused", f.image_path.display());
                dt.push(f64::INFINITY);
                dr.push(f64::INFINITY);
            }
        }
    }
    let n = dt.len();
    let near: Vec<f64> = dt.iter().copied().filter(|t| *t <= 0.25).collect();
    println!(
        "{n} queries: median {:.3} m / {:.3}° (mean within 0.25 m: {:.4} m), within (0.25 m, \
         2°) {within_25cm}, (1 m, 5°) {within_1m}, refused {refused}; {:.3} s per query \
         (alignment {:.3} s, {:.0} aligned inliers)",
        median(&mut dt),
        median(&mut dr),
        near.iter().sum::<f64>() / near.len().max(1) as f64,
        seconds / n.max(1) as f64,
        align_s / n.max(1) as f64,
        aligned_inliers as f64 / n.max(1) as f64
    );
}
