//! `matloc dataset import mega-nerf` and the split flags, run as a user would.

use std::path::{Path, PathBuf};

use matloc_core::{Camera, Image, Pose};
use matloc_data::dataset::SceneMetadata;
use matloc_data::images::write_png_rgb;
use matloc_data::meganerf::{read_mega_nerf, write_mega_nerf};
use matloc_data::nerfstudio::read_nerfstudio;
use matloc_data::{Dataset, Frame, Split};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

mod common;

use common::{matloc, text};

/// A Mega-NeRF dataset of five frames (three train, two val) with 6×4 images, in `dir/mega`.
fn mega_fixture(dir: &Path) -> PathBuf {
    let src = dir.join("src");
    let camera = Camera::pinhole(6, 4, 5.0, 5.5, 3.0, 2.0).unwrap();
    let frames: Vec<Frame> = (0..5)
        .map(|i| {
            let image_path = PathBuf::from(format!("img/{i}.png"));
            std::fs::create_dir_all(src.join("img")).unwrap();
            write_png_rgb(&Image::new(6, 4, 3), &src.join(&image_path)).unwrap();
            let axis = nalgebra::Unit::new_normalize(Vector3::new(0.2, 0.1 * i as f64, 1.0));
            Frame {
                image_path,
                depth_path: None,
                camera,
                cam_from_world: Isometry3::from_parts(
                    Translation3::new(100.0 * i as f64, -40.0, 250.0),
                    UnitQuaternion::from_axis_angle(&axis, 0.4 * i as f64),
                ),
                split: if i % 3 == 1 {
                    Split::Test
                } else {
                    Split::Train
                },
            }
        })
        .collect();
    let ds = Dataset {
        root: src,
        frames,
        metadata: SceneMetadata::default(),
        points: None,
    };
    let mega = dir.join("mega");
    write_mega_nerf(&ds, &mega).unwrap();
    mega
}

fn close_pose(a: &Pose, b: &Pose, tol: f64) -> bool {
    (a.translation.vector - b.translation.vector).norm() < tol
        && a.rotation.angle_to(&b.rotation) < tol
}

fn same_frames(a: &Dataset, b: &Dataset) {
    assert_eq!(a.frames.len(), b.frames.len());
    for (fa, fb) in a.frames.iter().zip(&b.frames) {
        assert!(close_pose(&fa.cam_from_world, &fb.cam_from_world, 1e-9));
        assert_eq!(fa.camera, fb.camera);
        assert_eq!(fa.split, fb.split);
        let (ia, ib) = (a.image_path(fa), b.image_path(fb));
        assert_eq!(
            std::fs::read(&ia).unwrap(),
            std::fs::read(&ib).unwrap(),
            "{} vs {}",
            ia.display(),
            ib.display()
        );
    }
}

#[test]
fn import_mega_nerf_references_or_copies_the_images() {
    let dir = tempfile::tempdir().unwrap();
    let mega = mega_fixture(dir.path());
    let original = read_mega_nerf(&mega).unwrap();

    // `dataset info` reads the layout directly.
    let o = matloc(&["dataset", "info", mega.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));

    let out = dir.path().join("ns");
    let o = matloc(&[
        "dataset",
        "import",
        "mega-nerf",
        mega.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("5 frames (3 train, 2 test)"),
        "{}",
        text(&o)
    );
    let json = std::fs::read_to_string(out.join("transforms.json")).unwrap();
    assert!(json.contains("../mega/train/rgbs/000000.png"), "{json}");
    assert!(json.contains("\"applied_transform\""), "{json}");
    let imported = read_nerfstudio(&out).unwrap();
    same_frames(&original, &imported);
    // What was undone travels along, so poses can be given back.
    assert_eq!(imported.metadata.mega_nerf, original.metadata.mega_nerf);
    assert_eq!(
        imported.metadata.applied_transform,
        original.metadata.applied_transform
    );

    let copied = dir.path().join("ns_copy");
    let o = matloc(&[
        "dataset",
        "import",
        "mega-nerf",
        mega.to_str().unwrap(),
        "--out",
        copied.to_str().unwrap(),
        "--copy",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(copied.join("images/val/000001.png").is_file());
    let imported = read_nerfstudio(&copied).unwrap();
    same_frames(&original, &imported);
}

#[test]
fn import_of_a_broken_dataset_fails_and_writes_no_transforms() {
    let dir = tempfile::tempdir().unwrap();
    let mega = mega_fixture(dir.path());
    std::fs::remove_file(mega.join("val/rgbs/000004.png")).unwrap();
    let out = dir.path().join("ns");
    let o = matloc(&[
        "dataset",
        "import",
        "mega-nerf",
        mega.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("000004.pt"), "{}", text(&o));
    assert!(!out.join("transforms.json").exists());

    let o = matloc(&[
        "dataset",
        "import",
        "mega-nerf",
        dir.path().join("nothing").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("coordinates.pt"), "{}", text(&o));
}

#[test]
fn split_flags_are_checked_applied_and_recorded_by_map_build() {
    let dir = tempfile::tempdir().unwrap();
    let mega = mega_fixture(dir.path());
    let data = mega.to_str().unwrap();
    let map = dir.path().join("map");
    let map_s = map.to_str().unwrap();
    let build = |extra: &[&str]| {
        let mut args = vec!["map", "build", "--data", data, "--out", map_s];
        args.extend_from_slice(extra);
        matloc(&args)
    };

    let o = build(&["--test-every", "2", "--test-list", "x.txt"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("cannot be used with"), "{}", text(&o));

    let o = build(&["--resplit"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("--resplit needs"), "{}", text(&o));

    // The Mega-NeRF data has its val frames as test frames: a rule needs --resplit.
    let o = build(&["--test-every", "2"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("already has 2 test"), "{}", text(&o));

    let list = dir.path().join("test.txt");
    std::fs::write(&list, "# held out\ntrain/rgbs/000002.png\nnot/there.png\n").unwrap();
    let o = build(&["--test-list", list.to_str().unwrap(), "--resplit"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("not/there.png"), "{}", text(&o));
    assert!(
        !map.join("manifest.json").exists()
            || !std::fs::read_to_string(map.join("manifest.json"))
                .unwrap()
                .contains("\"split\"")
    );

    // Five blank 6×4 frames are too little for a map: the plan step refuses them, and a
    // refused build leaves nothing behind.
    let o = build(&["--test-every", "2", "--resplit"]);
    assert!(!o.status.success());
    assert!(!map.exists(), "{}", text(&o));

    // On a map that exists (created here as a build interrupted in its first stage leaves it),
    // the split is recorded before the first stage runs, and kept when the build stops.
    let config = serde_json::to_value(matloc_pipeline::build::MapConfig::default()).unwrap();
    matloc_pipeline::MapDir::create_or_resume(&map, config).unwrap();
    let o = build(&["--test-every", "2", "--resplit"]);
    assert!(!o.status.success());
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(map.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(
        manifest["split"],
        serde_json::json!({"rule": {"every": 2}, "resplit": true}),
        "{}",
        text(&o)
    );
    // Another rule on the same map is refused.
    let o = build(&["--test-every", "3", "--resplit"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("built with split"), "{}", text(&o));
}
