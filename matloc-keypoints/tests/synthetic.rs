//! Keypoint matches on the synthetic aerial world are geometrically correct, and descriptors
//! survive rotation.

use matloc_core::Image;
use matloc_data::Split;
use matloc_keypoints::{
    GrayImage, KeypointConfig, MatchConfig, detect_and_describe, match_descriptors,
};
use matloc_synth::{SynthConfig, World, plan_survey};
use nalgebra::Point2;

/// Two neighbouring training views of the `tiny` world at 320×240: ≥ 80 % of the mutual
/// matches (Lowe ratio 0.8, Hamming ≤ 64) land within 3 px of the true correspondence (lifted with the true depth).
#[test]
fn matches_between_neighbouring_views_are_correct() {
    let mut cfg = SynthConfig::preset("tiny").unwrap();
    cfg.survey.width = 320;
    cfg.survey.height = 240;
    let world = World::generate(&cfg.world, cfg.seed).unwrap();
    let plan = plan_survey(&world, &cfg.survey, cfg.seed).unwrap();
    let train: Vec<_> = plan
        .frames
        .iter()
        .filter(|f| f.split == Split::Train)
        .collect();
    let (a, b) = (train[4], train[5]);
    let ra = world.render(&a.camera, &a.cam_from_world, &cfg.render);
    let rb = world.render(&b.camera, &b.cam_from_world, &cfg.render);
    let ga = GrayImage::from_image(&ra.rgb);
    let gb = GrayImage::from_image(&rb.rgb);
    let kcfg = KeypointConfig::default();
    let (ka, da) = detect_and_describe(&ga, &kcfg);
    let (kb, db) = detect_and_describe(&gb, &kcfg);
    assert!(
        ka.len() > 200 && kb.len() > 200,
        "{} {}",
        ka.len(),
        kb.len()
    );
    let matches = match_descriptors(&da, &db, &MatchConfig::default());
    let mut correct = 0;
    let mut checked = 0;
    for m in &matches {
        let k = ka[m.a];
        let z = depth_at(&ra.depth, k.x, k.y);
        if z <= 0.0 {
            continue;
        }
        let bearing = a
            .camera
            .unproject(Point2::new(k.x as f64, k.y as f64))
            .unwrap();
        let p_cam = bearing * (z as f64 / bearing.z);
        let p_world = a
            .cam_from_world
            .inverse_transform_point(&nalgebra::Point3::from(p_cam));
        let Some(px) = b.camera.project_world(&b.cam_from_world, &p_world) else {
            continue;
        };
        checked += 1;
        let kb = kb[m.b];
        let err = ((px.x - kb.x as f64).powi(2) + (px.y - kb.y as f64).powi(2)).sqrt();
        if err <= 3.0 {
            correct += 1;
        }
    }
    let precision = correct as f64 / checked.max(1) as f64;
    println!(
        "keypoints {} / {}, matches {}, checked {checked}, precision {precision:.3}",
        ka.len(),
        kb.len(),
        matches.len()
    );
    assert!(checked >= 60, "only {checked} matches with depth");
    assert!(precision >= 0.8, "precision {precision}");
}

fn depth_at(depth: &Image<f32>, x: f32, y: f32) -> f32 {
    let (c, r) = (x.floor() as usize, y.floor() as usize);
    if c >= depth.width() || r >= depth.height() {
        return 0.0;
    }
    depth.pixel(c, r)[0]
}

/// A 90° rotation of a textured view: rotated-BRIEF matches map through the rotation.
#[test]
fn descriptors_are_rotation_invariant() {
    let cfg = SynthConfig::preset("tiny").unwrap();
    let world = World::generate(&cfg.world, cfg.seed).unwrap();
    let plan = plan_survey(&world, &cfg.survey, cfg.seed).unwrap();
    let f = &plan.frames[3];
    let img = GrayImage::from_image(&world.render(&f.camera, &f.cam_from_world, &cfg.render).rgb);
    let (w, h) = (img.width(), img.height());
    // Rotate 90° clockwise: (x, y) → (h − 1 − y, x) in pixel indices.
    let mut rot = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            rot[x * h + (h - 1 - y)] = img.at(x, y);
        }
    }
    let rotated = GrayImage::from_vec(h, w, rot).unwrap();
    let kcfg = KeypointConfig::default();
    let (ka, da) = detect_and_describe(&img, &kcfg);
    let (kb, db) = detect_and_describe(&rotated, &kcfg);
    let matches = match_descriptors(&da, &db, &MatchConfig::default());
    let correct = matches
        .iter()
        .filter(|m| {
            let (a, b) = (ka[m.a], kb[m.b]);
            let (ex, ey) = (h as f32 - a.y, a.x);
            ((b.x - ex).powi(2) + (b.y - ey).powi(2)).sqrt() <= 2.5
        })
        .count();
    println!("rotation: {} matches, {correct} correct", matches.len());
    assert!(correct >= 30, "{correct} of {}", matches.len());
    assert!(correct as f64 >= 0.7 * matches.len() as f64);
}
