//! The synthetic dataset written to disk reads back through the nerfstudio reader.

use std::sync::Mutex;

use matloc_data::Split;
use matloc_data::images::{load_rgb, read_depth_npy};
use matloc_data::nerfstudio::read_nerfstudio;
use matloc_synth::{Progress, SynthConfig, World, synthesize};

#[test]
fn synth_dataset_reads_back_with_identical_poses_and_depth() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = SynthConfig::preset("tiny").unwrap().with_seed(3);
    // Fewer, smaller frames keep this CI-sized; the layout logic is the same.
    cfg.survey.width = 96;
    cfg.survey.height = 72;
    cfg.survey.test_views = 4;
    let seen = Mutex::new(Vec::new());
    let written = synthesize(&cfg, dir.path(), &|p: Progress| {
        seen.lock().unwrap().push(p)
    })
    .unwrap();
    let seen = seen.into_inner().unwrap();
    let total = written.frames.len();
    assert_eq!(seen.len(), total + 1);
    assert!(seen.iter().any(|p| p.done == total && p.total == total));

    let read = read_nerfstudio(dir.path()).unwrap();
    assert_eq!(read.frames.len(), total);
    assert_eq!(read.metadata, written.metadata);
    assert_eq!(read.metadata.seed, Some(3));
    assert_eq!(read.metadata.preset.as_deref(), Some("tiny"));
    assert_eq!(read.metadata.up, Some([0.0, 0.0, 1.0]));
    // The sun, towards it: the world's default azimuth 150° (clockwise from north, +y), 50° up.
    let sun = read.metadata.sun_direction.expect("sun written");
    let (az, el) = (150f64.to_radians(), 50f64.to_radians());
    let expected = [az.sin() * el.cos(), az.cos() * el.cos(), el.sin()];
    assert!(
        sun.iter().zip(expected).all(|(a, b)| (a - b).abs() < 1e-12),
        "{sun:?}"
    );
    assert_eq!(read.split(Split::Test).count(), 4);

    let world = World::generate(&cfg.world, cfg.seed).unwrap();
    for (i, (a, b)) in written.frames.iter().zip(&read.frames).enumerate() {
        assert_eq!(a.image_path, b.image_path);
        assert_eq!(a.depth_path, b.depth_path);
        assert_eq!(a.split, b.split);
        assert_eq!(a.camera.width, b.camera.width);
        assert!(
            (a.camera.fx - b.camera.fx).abs() < 1e-9 && (a.camera.cx - b.camera.cx).abs() < 1e-9
        );
        let (ma, mb) = (
            a.cam_from_world.to_homogeneous(),
            b.cam_from_world.to_homogeneous(),
        );
        assert!(
            (ma - mb).abs().max() < 1e-9,
            "frame {i} pose changed: {ma} vs {mb}"
        );

        let depth = read_depth_npy(&read.depth_path(b).unwrap()).unwrap();
        let rgb = load_rgb(&read.image_path(b)).unwrap();
        assert_eq!((rgb.width(), rgb.height()), (96, 72));
        if i % 9 == 0 {
            let r = world.render(&a.camera, &a.cam_from_world, &cfg.render);
            assert_eq!(
                depth, r.depth,
                "frame {i}: depth file differs from the render"
            );
            let max_err = rgb
                .data()
                .iter()
                .zip(r.rgb.data())
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max);
            assert!(
                max_err <= 0.5 / 255.0 + 1e-6,
                "frame {i}: 8-bit quantisation error {max_err}"
            );
        }
    }
    // Nothing but the dataset: no temporary files left behind.
    for sub in ["images", "depth"] {
        let n = std::fs::read_dir(dir.path().join(sub)).unwrap().count();
        assert_eq!(n, total, "{sub}");
    }
}

#[test]
fn synth_unknown_preset_names_the_valid_ones() {
    let err = SynthConfig::preset("mill19").unwrap_err().to_string();
    assert!(
        err.contains("mill19") && err.contains("tiny, small, rubble, building"),
        "{err}"
    );
}
