//! nerfstudio transforms.json: fixtures, round trips and bad input.

use std::fs;
use std::path::{Path, PathBuf};

use matloc_core::pose::{camera_center, opengl_from_cam_from_world, viewing_direction};
use matloc_core::{Camera, Distortion, Image, Pose, PoseError};
use matloc_data::dataset::SceneMetadata;
use matloc_data::images::write_png_rgb;
use matloc_data::nerfstudio::{NerfstudioError, read_nerfstudio, write_nerfstudio};
use matloc_data::{Dataset, Frame, Split};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn close_pose(a: &Pose, b: &Pose, tol: f64) -> bool {
    (a.translation.vector - b.translation.vector).norm() < tol
        && a.rotation.angle_to(&b.rotation) < tol
}

#[test]
fn global_intrinsics_fixture() {
    let ds = read_nerfstudio(&fixture("ns_global")).unwrap();
    assert_eq!(ds.root, fixture("ns_global"));
    assert_eq!(ds.frames.len(), 3);
    let cam = Camera::pinhole(640, 480, 400.0, 410.0, 320.0, 240.5).unwrap();
    assert!(ds.frames.iter().all(|f| f.camera == cam));

    let f0 = &ds.frames[0];
    assert_eq!(f0.image_path, PathBuf::from("images/frame_00001.png"));
    assert_eq!(
        f0.depth_path.as_deref(),
        Some(Path::new("depth/frame_00001.npy"))
    );
    // OpenGL identity rotation: the camera looks down world -z, centred at the translation.
    assert!((f0.center().coords - Vector3::new(1.0, 2.0, 3.0)).norm() < 1e-12);
    assert!((f0.viewing_direction() - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
    // Image "up" (OpenGL +y) is world +y, so OpenCV "down" (+y) is world -y.
    let down_world = f0.cam_from_world.inverse_transform_vector(&Vector3::y());
    assert!((down_world - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);

    // Splits: "./images/..." in frames matches "images/..." in the list; unlisted = train.
    assert_eq!(f0.split, Split::Train);
    assert_eq!(ds.frames[1].split, Split::Test);
    assert_eq!(ds.frames[2].split, Split::Train);
    // A 3x4 matrix is accepted.
    assert!(ds.frames[2].center().coords.norm() < 1e-12);

    assert_eq!(
        ds.metadata,
        SceneMetadata {
            bounds_min: Some([-100.0, -100.0, 0.0]),
            bounds_max: Some([100.0, 100.0, 40.0]),
            up: Some([0.0, 0.0, 1.0]),
            generator: Some("hand-written fixture".into()),
            preset: Some("tiny".into()),
            seed: Some(7),
            // The fixture's identity `applied_transform`.
            applied_transform: Some([
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0]
            ]),
            ..SceneMetadata::default()
        }
    );
    // The file path itself works too.
    let same = read_nerfstudio(&fixture("ns_global/transforms.json")).unwrap();
    assert_eq!(same, ds);
}

#[test]
fn per_frame_opencv_fixture() {
    let ds = read_nerfstudio(&fixture("ns_per_frame")).unwrap();
    assert_eq!(ds.frames.len(), 3);
    let a = &ds.frames[0].camera;
    assert_eq!(
        (a.width, a.height, a.fx, a.fy, a.cx, a.cy),
        (800, 600, 500.0, 501.0, 400.0, 300.0)
    );
    assert_eq!(
        a.distortion,
        Distortion {
            k1: -0.1,
            k2: 0.01,
            p1: 0.001,
            p2: -0.002,
            k3: 0.0
        }
    );
    let b = &ds.frames[1].camera;
    assert_eq!((b.width, b.height), (400, 300));
    assert_eq!(b.distortion.k3, 0.002);
    assert_eq!(b.distortion.k1, -0.05);
    // Only fl_x and no camera_model: a pinhole camera with fy = fx and the centre defaulted.
    let c = &ds.frames[2].camera;
    assert_eq!((c.fx, c.fy, c.cx, c.cy), (300.0, 300.0, 160.0, 120.0));
    assert!(c.is_pinhole());
    assert!(ds.frames.iter().all(|f| f.split == Split::Train));
}

#[test]
fn blender_split_files_read_sizes_from_images() {
    let dir = tempfile::tempdir().unwrap();
    for name in [
        "transforms_train.json",
        "transforms_val.json",
        "transforms_test.json",
    ] {
        fs::copy(fixture("blender").join(name), dir.path().join(name)).unwrap();
    }
    let img = Image::new(8, 6, 3);
    for p in [
        "train/r_0.png",
        "train/r_1.png",
        "val/r_0.png",
        "test/r_0.png",
    ] {
        let p = dir.path().join(p);
        fs::create_dir_all(p.parent().unwrap()).unwrap();
        write_png_rgb(&img, &p).unwrap();
    }
    let ds = read_nerfstudio(dir.path()).unwrap();
    let splits: Vec<Split> = ds.frames.iter().map(|f| f.split).collect();
    assert_eq!(
        splits,
        [Split::Train, Split::Train, Split::Val, Split::Test]
    );
    assert_eq!(ds.frames[0].image_path, PathBuf::from("./train/r_0.png"));
    let cam = &ds.frames[0].camera;
    assert_eq!((cam.width, cam.height), (8, 6));
    let expected_f = 4.0 / (0.5f64 * 0.6911112070083618).tan();
    assert!((cam.fx - expected_f).abs() < 1e-9 && cam.fy == cam.fx);
    assert_eq!((cam.cx, cam.cy), (4.0, 3.0));
    // The real lego pose is rigid within float32 rounding and looks at the origin.
    let f0 = &ds.frames[0];
    let to_origin = (-f0.center().coords).normalize();
    assert!(f0.viewing_direction().dot(&to_origin) > 0.99);
    // One split file alone takes its split from its name.
    let test_only = read_nerfstudio(&dir.path().join("transforms_test.json")).unwrap();
    assert_eq!(test_only.frames.len(), 1);
    assert_eq!(test_only.frames[0].split, Split::Test);
}

fn sample_dataset(root: &Path, shared_camera: bool) -> Dataset {
    let base = Camera::opencv(
        320,
        240,
        277.7,
        277.9,
        160.25,
        119.75,
        Distortion {
            k1: -0.12,
            k2: 0.03,
            p1: 0.0007,
            p2: -0.0003,
            k3: 0.001,
        },
    )
    .unwrap();
    let frames = (0..7)
        .map(|i| {
            let axis = nalgebra::Unit::new_normalize(Vector3::new(0.3, -0.5 + i as f64 * 0.1, 0.8));
            let rot = UnitQuaternion::from_axis_angle(&axis, 0.3 + 0.77 * i as f64);
            let t = Translation3::new(12.345 * i as f64, -3.21, 31.0 + 0.1 / (i + 1) as f64);
            let camera = if shared_camera {
                base
            } else {
                Camera::pinhole(320 + 2 * i, 240, 250.0 + i as f64, 250.0, 160.0, 120.0).unwrap()
            };
            Frame {
                image_path: PathBuf::from(format!("images/{i:04}.png")),
                depth_path: (i % 2 == 0).then(|| PathBuf::from(format!("depth/{i:04}.npy"))),
                camera,
                cam_from_world: Isometry3::from_parts(t, rot),
                split: [Split::Train, Split::Train, Split::Val, Split::Test][i as usize % 4],
            }
        })
        .collect();
    Dataset {
        root: root.to_path_buf(),
        frames,
        points: None,
        metadata: SceneMetadata {
            bounds_min: Some([-1.5, -2.5, 0.0]),
            bounds_max: Some([300.0, 200.0, 45.5]),
            up: Some([0.0, 0.0, 1.0]),
            generator: Some("test".into()),
            preset: Some("tiny".into()),
            seed: Some(u64::MAX - 1),
            ..SceneMetadata::default()
        },
    }
}

fn assert_same_dataset(a: &Dataset, b: &Dataset) {
    assert_eq!(a.frames.len(), b.frames.len());
    for (fa, fb) in a.frames.iter().zip(&b.frames) {
        assert!(
            close_pose(&fa.cam_from_world, &fb.cam_from_world, 1e-9),
            "{:?} vs {:?}",
            fa.cam_from_world,
            fb.cam_from_world
        );
        assert_eq!(fa.camera, fb.camera);
        assert_eq!(fa.split, fb.split);
        assert_eq!(fa.image_path, fb.image_path);
        assert_eq!(fa.depth_path, fb.depth_path);
    }
    assert_eq!(a.metadata, b.metadata);
}

#[test]
fn round_trip_shared_and_per_frame_intrinsics() {
    for shared in [true, false] {
        let dir = tempfile::tempdir().unwrap();
        let ds = sample_dataset(dir.path(), shared);
        write_nerfstudio(&ds, dir.path()).unwrap();
        let text = fs::read_to_string(dir.path().join("transforms.json")).unwrap();
        let json: serde_json::Value = serde_json::from_str(&text).unwrap();
        // Shared intrinsics go to the top level only.
        assert_eq!(json.get("fl_x").is_some(), shared);
        assert_eq!(json["frames"][0].get("fl_x").is_none(), shared);
        assert_eq!(json["val_filenames"].as_array().unwrap().len(), 2);
        let back = read_nerfstudio(dir.path()).unwrap();
        assert_eq!(back.root, dir.path());
        assert_same_dataset(&ds, &back);
        // The transform matrix written is the OpenGL camera-to-world.
        let m = opengl_from_cam_from_world(&ds.frames[3].cam_from_world);
        let row0 = &json["frames"][3]["transform_matrix"][0];
        assert_eq!(row0[3].as_f64().unwrap(), m[(0, 3)]);
        // No temporary files are left behind.
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}

/// `p` with `.` and `..` resolved lexically.
fn lexical(p: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in p.components() {
        match c {
            std::path::Component::CurDir => {}
            std::path::Component::ParentDir => {
                out.pop();
            }
            c => out.push(c),
        }
    }
    out
}

#[test]
fn writing_elsewhere_keeps_paths_relative_and_resolvable() {
    let tmp = tempfile::tempdir().unwrap();
    let top = tmp.path().join("survey");
    let data = top.join("data");
    let ds = sample_dataset(&data, true);
    let file = top.join("out/nested/my_transforms.json");
    write_nerfstudio(&ds, &file).unwrap();
    let json: serde_json::Value = serde_json::from_slice(&fs::read(&file).unwrap()).unwrap();
    for f in json["frames"].as_array().unwrap() {
        let p = f["file_path"].as_str().unwrap();
        assert!(p.starts_with("../../data/images/"), "{p}");
    }
    // The file and the data move together: the paths still resolve.
    let moved = tmp.path().join("moved");
    fs::rename(&top, &moved).unwrap();
    let back = read_nerfstudio(&moved.join("out/nested/my_transforms.json")).unwrap();
    for (a, b) in ds.frames.iter().zip(&back.frames) {
        let want = |p: PathBuf| moved.join(p.strip_prefix(&top).unwrap());
        assert_eq!(lexical(&back.image_path(b)), want(ds.image_path(a)));
        assert_eq!(
            back.depth_path(b).map(|p| lexical(&p)),
            ds.depth_path(a).map(want)
        );
    }
}

#[test]
fn only_splits_with_frames_are_listed() {
    let dir = tempfile::tempdir().unwrap();
    let mut ds = sample_dataset(dir.path(), true);
    for f in &mut ds.frames {
        f.split = Split::Test;
    }
    write_nerfstudio(&ds, dir.path()).unwrap();
    let json: serde_json::Value =
        serde_json::from_slice(&fs::read(dir.path().join("transforms.json")).unwrap()).unwrap();
    assert!(json.get("train_filenames").is_none() && json.get("val_filenames").is_none());
    assert_eq!(json["test_filenames"].as_array().unwrap().len(), 7);
    let back = read_nerfstudio(dir.path()).unwrap();
    assert!(back.frames.iter().all(|f| f.split == Split::Test));
}

#[test]
fn viewing_direction_survives_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let ds = sample_dataset(dir.path(), true);
    write_nerfstudio(&ds, dir.path()).unwrap();
    let back = read_nerfstudio(dir.path()).unwrap();
    for (a, b) in ds.frames.iter().zip(&back.frames) {
        assert!(
            (viewing_direction(&a.cam_from_world) - viewing_direction(&b.cam_from_world)).norm()
                < 1e-12
        );
        assert!(
            (camera_center(&a.cam_from_world) - camera_center(&b.cam_from_world)).norm() < 1e-9
        );
    }
}

// ----- bad input -----------------------------------------------------------------------------

fn write_json(dir: &Path, text: &str) -> PathBuf {
    let p = dir.join("transforms.json");
    fs::write(&p, text).unwrap();
    p
}

const GOOD_FRAME: &str =
    r#"{"file_path": "a.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#;

fn with_frames(frames: &str, extra: &str) -> String {
    format!(
        r#"{{"fl_x": 100, "cx": 50, "cy": 40, "w": 100, "h": 80{extra}, "frames": [{frames}]}}"#
    )
}

#[test]
fn missing_file_and_directory() {
    let dir = tempfile::tempdir().unwrap();
    let err = read_nerfstudio(&dir.path().join("nope.json")).unwrap_err();
    assert!(
        matches!(&err, NerfstudioError::NotFound { path } if path.ends_with("nope.json")),
        "{err}"
    );
    let err = read_nerfstudio(dir.path()).unwrap_err();
    assert!(
        matches!(&err, NerfstudioError::NotFound { path } if path == dir.path()),
        "{err}"
    );
}

#[test]
fn malformed_json_reports_line_and_column() {
    let dir = tempfile::tempdir().unwrap();
    let p = write_json(
        dir.path(),
        "{\n  \"frames\": [\n    {\"file_path\": \"a.png\",, }\n  ]\n}\n",
    );
    let err = read_nerfstudio(&p).unwrap_err();
    match &err {
        NerfstudioError::Json {
            path, line, column, ..
        } => {
            assert_eq!(path, &p);
            assert_eq!(*line, 3);
            assert!(*column > 20, "column {column}");
        }
        other => panic!("unexpected {other}"),
    }
    assert!(err.to_string().contains("transforms.json"));
    assert!(err.to_string().contains("line 3"));
}

#[test]
fn nan_and_non_rigid_matrices_name_frame_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let nan = r#"{"file_path": "b.png", "transform_matrix": [[1,0,0,0],[0,1,0,NaN],[0,0,1,0],[0,0,0,1]]}"#;
    let p = write_json(
        dir.path(),
        &with_frames(&format!("{GOOD_FRAME}, {nan}"), ""),
    );
    let err = read_nerfstudio(&p).unwrap_err();
    assert!(
        matches!(&err, NerfstudioError::BadTransform { path, frame: 1, source: PoseError::NonFinite { row: 1, col: 3, .. } } if path == &p),
        "{err}"
    );
    assert!(err.to_string().contains("transform_matrix"));

    let scaled =
        r#"{"file_path": "b.png", "transform_matrix": [[2,0,0,0],[0,2,0,0],[0,0,2,0],[0,0,0,1]]}"#;
    let p = write_json(
        dir.path(),
        &with_frames(&format!("{GOOD_FRAME}, {GOOD_FRAME}, {scaled}"), ""),
    );
    let err = read_nerfstudio(&p).unwrap_err();
    assert!(
        matches!(
            &err,
            NerfstudioError::BadTransform {
                frame: 2,
                source: PoseError::NotRigid { .. },
                ..
            }
        ),
        "{err}"
    );

    let short = r#"{"file_path": "b.png", "transform_matrix": [[1,0,0],[0,1,0],[0,0,1]]}"#;
    let p = write_json(dir.path(), &with_frames(short, ""));
    let err = read_nerfstudio(&p).unwrap_err();
    assert!(
        matches!(&err, NerfstudioError::InvalidField { field, at, .. } if field == "transform_matrix" && at.0 == Some(0)),
        "{err}"
    );
}

#[test]
fn unknown_camera_model_and_bad_fields() {
    let dir = tempfile::tempdir().unwrap();
    let p = write_json(
        dir.path(),
        &with_frames(GOOD_FRAME, r#", "camera_model": "OPENCV_FISHEYE""#),
    );
    let err = read_nerfstudio(&p).unwrap_err();
    assert!(
        matches!(&err, NerfstudioError::UnsupportedCameraModel { model, path, .. } if model == "OPENCV_FISHEYE" && path == &p),
        "{err}"
    );

    let p = write_json(dir.path(), &with_frames(GOOD_FRAME, r#", "k4": 0.1"#));
    assert!(
        matches!(read_nerfstudio(&p).unwrap_err(), NerfstudioError::InvalidField { field, .. } if field == "k4")
    );

    let p = write_json(
        dir.path(),
        r#"{"frames": [{"file_path": "a.png", "w": 10, "h": 10, "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
    );
    let err = read_nerfstudio(&p).unwrap_err();
    assert!(
        matches!(&err, NerfstudioError::MissingField { field, .. } if field == "fl_x"),
        "{err}"
    );

    let p = write_json(dir.path(), &with_frames(GOOD_FRAME, r#", "fl_y": -3"#));
    assert!(matches!(
        read_nerfstudio(&p).unwrap_err(),
        NerfstudioError::BadCamera { .. }
    ));

    let p = write_json(
        dir.path(),
        &with_frames(GOOD_FRAME, r#", "test_filenames": ["zzz.png"]"#),
    );
    let err = read_nerfstudio(&p).unwrap_err();
    assert!(
        matches!(&err, NerfstudioError::UnknownSplitEntry { entry, .. } if entry == "zzz.png"),
        "{err}"
    );

    // w/h missing and the image absent: the error names the frame and the image.
    let p = write_json(
        dir.path(),
        r#"{"fl_x": 10, "frames": [{"file_path": "gone.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
    );
    let err = read_nerfstudio(&p).unwrap_err();
    assert!(
        matches!(&err, NerfstudioError::ImageSize { frame: 0, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("gone.png"));
}

#[test]
fn failed_write_leaves_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let mut ds = sample_dataset(dir.path(), true);
    write_nerfstudio(&ds, dir.path()).unwrap();
    let before = fs::read(dir.path().join("transforms.json")).unwrap();
    // A non-finite pose is refused before anything is written; the old file stays intact.
    ds.frames[4].cam_from_world.translation.vector.x = f64::NAN;
    let err = write_nerfstudio(&ds, dir.path()).unwrap_err();
    assert!(
        matches!(err, NerfstudioError::Unwritable { frame: 4, .. }),
        "{err}"
    );
    assert_eq!(
        fs::read(dir.path().join("transforms.json")).unwrap(),
        before
    );
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);

    // A target whose directory cannot be created: an I/O error and nothing written.
    let blocker = dir.path().join("blocker");
    fs::write(&blocker, b"x").unwrap();
    ds.frames[4].cam_from_world = Pose::identity();
    let err = write_nerfstudio(&ds, &blocker.join("sub")).unwrap_err();
    assert!(matches!(err, NerfstudioError::Io { .. }), "{err}");
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 2);
}

mod random_round_trip {
    use super::*;
    use proptest::prelude::*;

    fn frame_strategy() -> impl Strategy<Value = Frame> {
        (
            prop::array::uniform3(-1.0..1.0f64),
            0.0..std::f64::consts::PI,
            prop::array::uniform3(-1000.0..1000.0f64),
            (16u32..4000, 16u32..3000, 0.3..3.0f64, 0.9..1.1f64),
            prop::array::uniform5(-0.2..0.2f64),
            any::<bool>(),
            0usize..3,
        )
            .prop_filter_map(
                "non-zero axis",
                |(axis, angle, t, (w, h, ff, aspect), d, distorted, split)| {
                    let axis = nalgebra::Unit::try_new(Vector3::from(axis), 1e-3)?;
                    let f = w as f64 * ff;
                    let distortion = if distorted {
                        Distortion {
                            k1: d[0],
                            k2: d[1],
                            p1: d[2] * 0.01,
                            p2: d[3] * 0.01,
                            k3: d[4],
                        }
                    } else {
                        Distortion::NONE
                    };
                    let camera = Camera::opencv(
                        w,
                        h,
                        f,
                        f * aspect,
                        w as f64 * 0.49,
                        h as f64 * 0.51,
                        distortion,
                    )
                    .ok()?;
                    Some(Frame {
                        image_path: PathBuf::from(format!("img/{w}_{h}.jpg")),
                        depth_path: None,
                        camera,
                        cam_from_world: Isometry3::from_parts(
                            Translation3::from(Vector3::from(t)),
                            UnitQuaternion::from_axis_angle(&axis, angle),
                        ),
                        split: [Split::Train, Split::Val, Split::Test][split],
                    })
                },
            )
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

        #[test]
        fn write_then_read_is_identity(frames in prop::collection::vec(frame_strategy(), 1..6)) {
            let dir = tempfile::tempdir().unwrap();
            let ds = Dataset { root: dir.path().to_path_buf(), frames, metadata: SceneMetadata::default(), points: None };
            write_nerfstudio(&ds, dir.path()).unwrap();
            let back = read_nerfstudio(dir.path()).unwrap();
            prop_assert_eq!(back.frames.len(), ds.frames.len());
            for (a, b) in ds.frames.iter().zip(&back.frames) {
                prop_assert!(close_pose(&a.cam_from_world, &b.cam_from_world, 1e-9));
                prop_assert_eq!(a.camera, b.camera);
                prop_assert_eq!(a.split, b.split);
            }
        }
    }
}

/// A Blender `camera_angle_x` that is no field of view is blamed by name (it used to surface
/// as a bad `fx`).
#[test]
fn camera_angle_x_out_of_range_is_named() {
    for angle in ["3.2", "0", "-1", "3.141592653589793"] {
        let text = format!(
            r#"{{"camera_angle_x": {angle}, "w": 8, "h": 6, "frames": [{{"file_path": "a.png",
               "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}]}}"#
        );
        let e = matloc_data::nerfstudio::parse_transforms(
            text.as_bytes(),
            Path::new("transforms.json"),
            Path::new("."),
            Split::Train,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("camera_angle_x") && !e.contains("fx"),
            "{angle}: {e}"
        );
    }
}
