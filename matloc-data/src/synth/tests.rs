//! Tests of the synthetic world that need its internals.

use matloc_core::pose::camera_center;
use nalgebra::{Point2, Point3, Vector3};

use super::*;

fn tiny() -> (World, SurveyPlan, SynthConfig) {
    let cfg = SynthConfig::preset("tiny").unwrap();
    let (w, p) = generate(&cfg).unwrap();
    (w, p, cfg)
}

/// Writes a few views of each preset to /tmp for looking at (`cargo test -- --ignored preview`).
#[test]
#[ignore]
fn preview() {
    for name in PRESET_NAMES {
        let cfg = SynthConfig::preset(name).unwrap();
        let t = std::time::Instant::now();
        let (world, plan) = generate(&cfg).unwrap();
        eprintln!(
            "{name}: {} prims, {} buildings, {} frames ({} test), gen {:?}, geom {:?}",
            world.primitive_count(),
            world.building_count(),
            plan.frames.len(),
            plan.frames
                .iter()
                .filter(|f| f.split == crate::Split::Test)
                .count(),
            t.elapsed(),
            plan.geometry
        );
        let n = plan.frames.len();
        for (k, i) in [0, n / 3, n / 2, 2 * n / 3].into_iter().enumerate() {
            let f = &plan.frames[i];
            let t = std::time::Instant::now();
            let r = world.render(&f.camera, &f.cam_from_world, &cfg.render);
            eprintln!("  render {i}: {:?}", t.elapsed());
            let path = std::path::PathBuf::from(format!("/tmp/synth_{name}_{k}.png"));
            write::write_png(&r.rgb, &path).unwrap();
        }
    }
}
