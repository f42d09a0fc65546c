//! Dataset summary and validation.

use std::fs;
use std::path::{Path, PathBuf};

use matloc_core::pose::look_at;
use matloc_core::{Camera, Image};
use matloc_data::dataset::SceneMetadata;
use matloc_data::images::{write_depth_npy, write_png_rgb};
use matloc_data::nerfstudio::write_nerfstudio;
use matloc_data::summary::{Problem, inspect, summarize, validate};
use matloc_data::{Dataset, Frame, Split, read_dataset};
use nalgebra::{Point3, Vector3};

/// A 4 × 3 grid of nadir cameras at 30 m, 10 m apart, plus one oblique camera at 40 m.
fn grid(root: &Path) -> Dataset {
    let cam = Camera::pinhole(64, 48, 50.0, 50.0, 32.0, 24.0).unwrap();
    let mut frames = Vec::new();
    for j in 0..3 {
        for i in 0..4 {
            let eye = Point3::new(10.0 * i as f64, 10.0 * j as f64, 30.0);
            let target = Point3::new(eye.x, eye.y, 0.0);
            frames.push(Frame {
                image_path: PathBuf::from(format!("images/{j}_{i}.png")),
                depth_path: None,
                camera: cam,
                cam_from_world: look_at(&eye, &target, &Vector3::y()).unwrap(),
                split: if i == 3 { Split::Test } else { Split::Train },
            });
        }
    }
    let eye = Point3::new(15.0, -20.0, 40.0);
    frames.push(Frame {
        image_path: "images/oblique.png".into(),
        depth_path: Some("depth/oblique.npy".into()),
        camera: Camera::pinhole(128, 96, 100.0, 100.0, 64.0, 48.0).unwrap(),
        cam_from_world: look_at(&eye, &Point3::new(15.0, 10.0, 0.0), &Vector3::z()).unwrap(),
        split: Split::Val,
    });
    Dataset {
        root: root.to_path_buf(),
        frames,
        points: None,
        metadata: SceneMetadata {
            bounds_min: Some([-50.0, -50.0, 0.0]),
            bounds_max: Some([80.0, 70.0, 25.0]),
            up: Some([0.0, 0.0, 2.0]),
            generator: Some("test".into()),
            preset: None,
            seed: Some(3),
            ..SceneMetadata::default()
        },
    }
}

#[test]
fn summary_numbers() {
    let ds = grid(Path::new("/nowhere"));
    let s = summarize(&ds);
    assert_eq!(s.num_frames, 13);
    assert_eq!((s.splits.train, s.splits.val, s.splits.test), (9, 1, 3));
    assert_eq!(s.with_depth, 1);
    assert_eq!(s.resolutions[0].count, 12);
    assert_eq!((s.resolutions[0].width, s.resolutions[0].height), (64, 48));
    assert_eq!(s.cameras.len(), 2);
    assert!(!s.cameras[0].distorted);
    assert!((s.cameras[0].hfov_deg - 2.0 * (32.0f64 / 50.0).atan().to_degrees()).abs() < 1e-9);

    let c = s.centers.unwrap();
    assert!((c.min[0] - 0.0).abs() < 1e-9 && (c.max[0] - 30.0).abs() < 1e-9);
    assert!((c.min[1] + 20.0).abs() < 1e-9 && (c.max[2] - 40.0).abs() < 1e-9);
    assert!((c.extent_m[1] - 40.0).abs() < 1e-9);
    assert!((s.median_nn_spacing_m.unwrap() - 10.0).abs() < 1e-9);

    let a = s.altitude.unwrap();
    assert!(a.from_metadata);
    assert_eq!(a.up, [0.0, 0.0, 1.0]);
    assert!((a.min_m - 30.0).abs() < 1e-9 && (a.max_m - 40.0).abs() < 1e-9);

    let v = s.viewing.unwrap();
    assert!(v.mean_direction[2] < -0.9);
    assert!(v.max_angle_deg > 20.0 && v.mean_angle_deg < v.max_angle_deg);

    let text = s.to_string();
    for needle in [
        "frames: 13 (train 9, val 1, test 3)",
        "64x48 ×12",
        "median nearest-neighbour",
        "seed: 3",
        "scene bounds",
    ] {
        assert!(text.contains(needle), "missing `{needle}` in\n{text}");
    }
    let json = serde_json::to_value(&s).unwrap();
    assert_eq!(json["splits"]["test"], 3);
    assert_eq!(json["metadata"]["seed"], 3);
}

#[test]
fn empty_dataset_summary_and_validation() {
    let ds = Dataset {
        root: PathBuf::from("x"),
        frames: vec![],
        points: None,
        metadata: SceneMetadata::default(),
    };
    let s = summarize(&ds);
    assert_eq!(s.num_frames, 0);
    assert!(s.centers.is_none() && s.median_nn_spacing_m.is_none() && s.viewing.is_none());
    assert!(!s.to_string().is_empty());
    assert_eq!(validate(&ds), vec![Problem::NoFrames]);
}

#[test]
fn validation_finds_missing_and_mismatched_files() {
    let dir = tempfile::tempdir().unwrap();
    let mut ds = grid(dir.path());
    ds.frames.truncate(4);
    ds.frames.push(grid(dir.path()).frames.pop().unwrap());
    fs::create_dir_all(dir.path().join("images")).unwrap();
    fs::create_dir_all(dir.path().join("depth")).unwrap();
    // 0: exact size; 1: half size (rescalable); 2: wrong aspect; 3: missing; 4: depth aspect wrong.
    write_png_rgb(&Image::new(64, 48, 3), &dir.path().join("images/0_0.png")).unwrap();
    write_png_rgb(&Image::new(32, 24, 3), &dir.path().join("images/0_1.png")).unwrap();
    write_png_rgb(&Image::new(50, 48, 3), &dir.path().join("images/0_2.png")).unwrap();
    write_png_rgb(
        &Image::new(128, 96, 3),
        &dir.path().join("images/oblique.png"),
    )
    .unwrap();
    write_depth_npy(
        &Image::new(10, 10, 1),
        &dir.path().join("depth/oblique.npy"),
    )
    .unwrap();

    let problems = validate(&ds);
    assert_eq!(problems.len(), 3, "{problems:?}");
    assert!(matches!(
        &problems[0],
        Problem::ImageSizeMismatch {
            frame: 2,
            intrinsics: (64, 48),
            image: (50, 48),
            ..
        }
    ));
    assert!(
        matches!(&problems[1], Problem::MissingImage { frame: 3, path } if path.ends_with("images/0_3.png"))
    );
    assert!(matches!(
        &problems[2],
        Problem::DepthSizeMismatch {
            frame: 4,
            depth: (10, 10),
            ..
        }
    ));
    assert!(problems[0].to_string().contains("50x48"));

    // Through the nerfstudio writer and format detection, the same problems come back.
    write_nerfstudio(&ds, dir.path()).unwrap();
    let (summary, again) = inspect(dir.path()).unwrap();
    assert_eq!(summary.num_frames, 5);
    assert_eq!(again.len(), 3);
    assert_eq!(read_dataset(dir.path()).unwrap().frames.len(), 5);
}

#[test]
fn read_dataset_propagates_format_errors() {
    use matloc_data::DataError;
    use matloc_data::nerfstudio::NerfstudioError;
    let dir = tempfile::tempdir().unwrap();
    fs::write(dir.path().join("transforms.json"), "{\"frames\": [}").unwrap();
    let err = read_dataset(dir.path()).unwrap_err();
    assert!(
        matches!(
            &err,
            DataError::Nerfstudio(NerfstudioError::Json { line: 1, .. })
        ),
        "{err}"
    );
    assert!(err.to_string().contains("transforms.json"));
}

/// Each physically impossible frame is named with the field and the bound it breaks; the
/// Camera constructor's own checks are bypassed (readers build cameras field by field).
#[test]
fn impossible_intrinsics_and_poses_are_problems() {
    use matloc_data::summary::plausibility;
    let base = grid(Path::new("/nowhere"));
    assert!(plausibility(&base).is_empty(), "{:?}", plausibility(&base));
    type Breaker = Box<dyn Fn(&mut Frame)>;
    let cases: Vec<(&str, Breaker, &str)> = vec![
        ("tiny focal", Box::new(|f| f.camera.fx = 1e-300), "`fx`"),
        ("huge focal", Box::new(|f| f.camera.fy = 1e308), "`fy`"),
        ("pp outside", Box::new(|f| f.camera.cx = 1e4), "`cx`"),
        ("nan pp", Box::new(|f| f.camera.cy = f64::NAN), "`cy`"),
        (
            "huge side",
            Box::new(|f| f.camera.width = 1_000_000_000),
            "`width`",
        ),
        (
            // camera_angle_x = π: the focal length from it is ~0.
            "180° field of view",
            Box::new(|f| f.camera.fx = 64.0 / (2.0 * (std::f64::consts::PI / 2.0).tan())),
            "`fx`",
        ),
        (
            "k1 +1e6",
            Box::new(|f| f.camera.distortion.k1 = 1e6),
            "`distortion`",
        ),
        (
            "k1 -1e6",
            Box::new(|f| f.camera.distortion.k1 = -1e6),
            "`distortion`",
        ),
        (
            "far translation",
            Box::new(|f| f.cam_from_world.translation.vector.x = 1e308),
            "pose",
        ),
        (
            "nan translation",
            Box::new(|f| f.cam_from_world.translation.vector.z = f64::NAN),
            "not finite",
        ),
    ];
    for (name, break_it, want) in cases {
        let mut ds = base.clone();
        break_it(&mut ds.frames[2]);
        let problems = plausibility(&ds);
        assert_eq!(problems.len(), 1, "{name}: {problems:?}");
        let msg = problems[0].to_string();
        assert!(
            msg.starts_with("frame 2:") && msg.contains(want),
            "{name}: {msg}"
        );
        // validate reports it too (with the missing files of this fixture).
        assert!(validate(&ds).iter().any(|p| p.to_string() == msg), "{name}");
    }
}

/// A truncated PNG passes the header check and fails the deep one, named.
#[test]
fn deep_validation_decodes_every_image() {
    let dir = tempfile::tempdir().unwrap();
    let ds = grid(dir.path());
    for f in &ds.frames {
        let p = ds.image_path(f);
        fs::create_dir_all(p.parent().unwrap()).unwrap();
        write_png_rgb(
            &Image::new(f.camera.width as usize, f.camera.height as usize, 3),
            &p,
        )
        .unwrap();
        if let Some(d) = ds.depth_path(f) {
            fs::create_dir_all(d.parent().unwrap()).unwrap();
            write_depth_npy(
                &Image::new(f.camera.width as usize, f.camera.height as usize, 1),
                &d,
            )
            .unwrap();
        }
    }
    assert!(matloc_data::summary::validate_deep(&ds, &|| {}).is_empty());
    let victim = ds.image_path(&ds.frames[5]);
    let bytes = fs::read(&victim).unwrap();
    fs::write(&victim, &bytes[..bytes.len() - 20]).unwrap();
    assert!(validate(&ds).is_empty(), "the header is intact");
    let deep = matloc_data::summary::validate_deep(&ds, &|| {});
    assert_eq!(deep.len(), 1, "{deep:?}");
    assert!(
        deep[0].to_string().contains("5_") || deep[0].to_string().contains("1_1"),
        "{}",
        deep[0]
    );
}
