//! Mega-NeRF / Mill-19 layout: a file written by real torch in the script's convention, round
//! trips through `write_mega_nerf`, format detection, and bad input.

use std::fs;
use std::path::{Path, PathBuf};

use matloc_core::pose::{cam_from_world_from_mega_nerf, camera_center};
use matloc_core::{Camera, Distortion, Image, Pose};
use matloc_data::dataset::SceneMetadata;
use matloc_data::images::write_png_rgb;
use matloc_data::meganerf::{
    COORDINATES_FILE, DRB_FROM_COLMAP, MegaNerfError, MegaNerfOptions, read_mega_nerf,
    read_mega_nerf_with, write_mega_nerf,
};
use matloc_data::summary::{DatasetFormat, detect_format, validate};
use matloc_data::torch_pt::{PtValue, Tensor, read_pt, write_pt};
use matloc_data::{DataError, Dataset, Frame, Split, read_dataset};
use nalgebra::{Isometry3, Matrix3x4, Point3, Translation3, UnitQuaternion, Vector3};
use proptest::prelude::*;

fn torch_fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/torch")
        .join(name)
}

fn png(path: &Path, w: usize, h: usize) {
    fs::create_dir_all(path.parent().unwrap()).unwrap();
    write_png_rgb(&Image::new(w, h, 3), path).unwrap();
}

fn close_pose(a: &Pose, b: &Pose, tol: f64) -> bool {
    (a.translation.vector - b.translation.vector).norm() < tol
        && a.rotation.angle_to(&b.rotation) < tol
}

/// `coordinates.pt` and one `train/metadata/000000.pt` exactly as `torch.save` wrote them in
/// the conventions of `colmap_to_mega_nerf.py` (see `tests/fixtures/torch`), with a 4×3 image.
fn torch_written_dataset() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    fs::copy(
        torch_fixture("coordinates.pt"),
        dir.path().join(COORDINATES_FILE),
    )
    .unwrap();
    fs::create_dir_all(dir.path().join("train/metadata")).unwrap();
    fs::copy(
        torch_fixture("metadata.pt"),
        dir.path().join("train/metadata/000000.pt"),
    )
    .unwrap();
    png(&dir.path().join("train/rgbs/000000.png"), 4, 3);
    dir
}

#[test]
fn reads_torch_written_files_into_metric_opencv_poses() {
    let dir = torch_written_dataset();
    let ds = read_mega_nerf(dir.path()).unwrap();
    assert_eq!(ds.root, dir.path());
    assert_eq!(ds.frames.len(), 1);
    let f = &ds.frames[0];
    assert_eq!(f.image_path, PathBuf::from("train/rgbs/000000.png"));
    assert_eq!(f.split, Split::Train);
    // The rgbs are undistorted: a pinhole camera from `intrinsics` = [fx, fy, cx, cy].
    assert_eq!(f.camera, Camera::pinhole(4, 3, 5.0, 6.0, 2.0, 1.5).unwrap());
    // camera_in_drb = [down (0,1,0), right (1,0,0), back (0,0,-1) | (0.25, -0.5, 0.125)]:
    // the OpenCV axes (right, down, forward) are the world axes, so R = I, and the centre is
    // origin_drb + pose_scale_factor * t = (10.5, -3.25, 7) + 123.5 * (0.25, -0.5, 0.125).
    let centre = Point3::new(41.375, -65.0, 22.4375);
    let expected = Isometry3::from_parts(
        Translation3::from(-centre.coords),
        UnitQuaternion::identity(),
    );
    assert!(
        close_pose(&f.cam_from_world, &expected, 1e-12),
        "{:?}",
        f.cam_from_world
    );
    // The same pose as the core conversion of the (down, right, back) matrix before the
    // script's column swap.
    let camera_in_drb = Matrix3x4::new(
        0.0, 1.0, 0.0, centre.x, //
        1.0, 0.0, 0.0, centre.y, //
        0.0, 0.0, -1.0, centre.z,
    );
    assert!(close_pose(
        &f.cam_from_world,
        &cam_from_world_from_mega_nerf(&camera_in_drb).unwrap(),
        1e-12
    ));
    // What was undone is recorded.
    let m = ds.metadata.mega_nerf.unwrap();
    assert_eq!(m.origin_drb, [10.5, -3.25, 7.0]);
    assert_eq!(m.pose_scale_factor, 123.5);
    assert_eq!(ds.metadata.applied_transform, Some(DRB_FROM_COLMAP));
    assert_eq!(ds.metadata.up, Some([-1.0, 0.0, 0.0]));

    // With distorted rgbs the camera takes the file's `distortion` ([k1, 0, 0, 0]).
    let ds = read_mega_nerf_with(
        dir.path(),
        &MegaNerfOptions {
            images_distorted: true,
        },
    )
    .unwrap();
    let d = ds.frames[0].camera.distortion;
    assert!((d.k1 - 0.1).abs() < 1e-7 && d.k2 == 0.0 && d.p1 == 0.0 && d.p2 == 0.0);
}

#[test]
fn read_dataset_recognises_the_layout() {
    let dir = torch_written_dataset();
    assert_eq!(detect_format(dir.path()).unwrap(), DatasetFormat::MegaNerf);
    assert_eq!(
        detect_format(&dir.path().join(COORDINATES_FILE)).unwrap(),
        DatasetFormat::MegaNerf
    );
    let ds = read_dataset(dir.path()).unwrap();
    assert_eq!(ds.frames.len(), 1);
    assert!(validate(&ds).is_empty(), "{:?}", validate(&ds));
    // Without coordinates.pt it is no dataset at all.
    fs::remove_file(dir.path().join(COORDINATES_FILE)).unwrap();
    assert!(matches!(
        read_dataset(dir.path()),
        Err(DataError::UnknownFormat { .. })
    ));
    let e = read_mega_nerf(dir.path()).unwrap_err();
    assert!(matches!(e, MegaNerfError::NotMegaNerf { .. }), "{e}");
    assert!(e.to_string().contains(COORDINATES_FILE), "{e}");
}

fn frame(i: usize, split: Split, camera: Camera) -> Frame {
    let axis = nalgebra::Unit::new_normalize(Vector3::new(0.3, -0.5 + i as f64 * 0.1, 0.8));
    Frame {
        image_path: PathBuf::from(format!("images/{i:04}.png")),
        depth_path: None,
        camera,
        cam_from_world: Isometry3::from_parts(
            Translation3::new(12.345 * i as f64, -3.21, 31.0 + 0.1 / (i + 1) as f64),
            UnitQuaternion::from_axis_angle(&axis, 0.3 + 0.77 * i as f64),
        ),
        split,
    }
}

/// A nerfstudio-like dataset in `root` with tiny generated images of each camera's size.
fn source_dataset(root: &Path, frames: Vec<Frame>) -> Dataset {
    for f in &frames {
        png(
            &root.join(&f.image_path),
            f.camera.width as usize,
            f.camera.height as usize,
        );
    }
    Dataset {
        root: root.to_path_buf(),
        frames,
        metadata: SceneMetadata::default(),
        points: None,
    }
}

/// A Mega-NeRF dataset written from a handful of frames: `(dataset dir, source dataset)`.
fn written_fixture() -> (tempfile::TempDir, tempfile::TempDir, Dataset) {
    let src = tempfile::tempdir().unwrap();
    let cam = Camera::pinhole(6, 4, 5.0, 5.5, 3.0, 2.0).unwrap();
    let splits = [Split::Train, Split::Test, Split::Train, Split::Val];
    let frames = (0..4).map(|i| frame(i, splits[i], cam)).collect();
    let ds = source_dataset(src.path(), frames);
    let out = tempfile::tempdir().unwrap();
    write_mega_nerf(&ds, out.path()).unwrap();
    (out, src, ds)
}

#[test]
fn write_then_read_keeps_poses_intrinsics_and_splits() {
    let (out, _src, ds) = written_fixture();
    for p in [
        "coordinates.pt",
        "train/metadata/000000.pt",
        "train/rgbs/000000.png",
        "val/metadata/000001.pt",
        "val/rgbs/000003.png",
    ] {
        assert!(out.path().join(p).is_file(), "{p}");
    }
    let back = read_mega_nerf(out.path()).unwrap();
    // train files first, then val, each sorted by name.
    let order = [0, 2, 1, 3];
    assert_eq!(back.frames.len(), 4);
    for (b, &i) in back.frames.iter().zip(&order) {
        let a = &ds.frames[i];
        assert!(close_pose(&a.cam_from_world, &b.cam_from_world, 1e-9));
        assert_eq!(a.camera, b.camera);
        assert_eq!(
            b.split,
            if a.split == Split::Train {
                Split::Train
            } else {
                Split::Test
            }
        );
    }
    // Every written position is normalised into [-1, 1], as Mega-NeRF expects.
    let m = back.metadata.mega_nerf.unwrap();
    for f in &back.frames {
        let c = (camera_center(&f.cam_from_world).coords - Vector3::from(m.origin_drb))
            / m.pose_scale_factor;
        assert!(c.amax() <= 1.0 + 1e-12);
    }
    // Writing again into a dataset is refused; writing the read dataset elsewhere keeps its
    // normalisation.
    assert!(matches!(
        write_mega_nerf(&back, out.path()),
        Err(MegaNerfError::Unwritable { .. })
    ));
    let again = tempfile::tempdir().unwrap();
    assert_eq!(write_mega_nerf(&back, again.path()).unwrap(), m);
}

/// Rewrites one key of a `.pt` dict (`None` removes it).
fn edit_pt(file: &Path, key: &str, value: Option<PtValue>) {
    let PtValue::Dict(mut items) = read_pt(file).unwrap() else {
        panic!("not a dict")
    };
    items.retain(|(k, _)| k != key);
    if let Some(v) = value {
        items.push((key.to_string(), v));
    }
    write_pt(file, &PtValue::Dict(items)).unwrap();
}

fn read_err(dir: &Path) -> MegaNerfError {
    read_mega_nerf(dir).unwrap_err()
}

#[test]
fn bad_coordinates_are_typed_errors_naming_file_and_key() {
    let (out, _src, _) = written_fixture();
    let coords = out.path().join(COORDINATES_FILE);
    let good = fs::read(&coords).unwrap();

    fs::write(&coords, b"not a torch file").unwrap();
    let e = read_err(out.path());
    assert!(matches!(e, MegaNerfError::Torch(_)), "{e}");
    assert!(e.to_string().contains("coordinates.pt"), "{e}");

    fs::write(&coords, &good).unwrap();
    edit_pt(&coords, "pose_scale_factor", None);
    let e = read_err(out.path());
    assert!(
        matches!(&e, MegaNerfError::MissingKey { key, .. } if key == "pose_scale_factor"),
        "{e}"
    );
    assert!(e.to_string().contains("coordinates.pt"), "{e}");

    fs::write(&coords, &good).unwrap();
    edit_pt(&coords, "pose_scale_factor", Some(PtValue::Float(-2.0)));
    let e = read_err(out.path());
    assert!(
        matches!(&e, MegaNerfError::BadField { key, .. } if key == "pose_scale_factor"),
        "{e}"
    );

    fs::write(&coords, &good).unwrap();
    edit_pt(
        &coords,
        "origin_drb",
        Some(PtValue::Tensor(Tensor::f64(vec![2], vec![1.0, 2.0]))),
    );
    let e = read_err(out.path());
    assert!(
        matches!(&e, MegaNerfError::BadField { key, .. } if key == "origin_drb"),
        "{e}"
    );
}

#[test]
fn bad_metadata_is_a_typed_error_naming_file_and_key() {
    let cases: Vec<(&str, Option<PtValue>)> = vec![
        ("c2w", None),
        (
            "c2w",
            Some(PtValue::Tensor(Tensor::f64(vec![2, 4], vec![0.0; 8]))),
        ),
        ("intrinsics", None),
        (
            "intrinsics",
            Some(PtValue::Tensor(Tensor::f64(vec![3], vec![1.0; 3]))),
        ),
        ("W", None),
        ("W", Some(PtValue::Str("six".into()))),
        ("H", Some(PtValue::Float(3.5))),
        (
            "distortion",
            Some(PtValue::Tensor(Tensor::f64(vec![3], vec![0.1; 3]))),
        ),
    ];
    for (key, value) in cases {
        let (out, _src, _) = written_fixture();
        let file = out.path().join("train/metadata/000002.pt");
        let missing = value.is_none();
        edit_pt(&file, key, value);
        let e = read_err(out.path());
        let msg = e.to_string();
        assert!(
            msg.contains("000002.pt") && msg.contains(key),
            "{key}: {msg}"
        );
        if missing {
            assert!(matches!(e, MegaNerfError::MissingKey { .. }), "{msg}");
        } else {
            assert!(matches!(e, MegaNerfError::BadField { .. }), "{msg}");
        }
    }
}

#[test]
fn non_rigid_pose_bad_intrinsics_missing_and_wrong_images_are_errors() {
    let (out, _src, _) = written_fixture();
    let file = out.path().join("val/metadata/000001.pt");
    let mut m = vec![0.0; 12];
    m[0] = 2.0;
    m[5] = 1.0;
    m[10] = 1.0;
    edit_pt(
        &file,
        "c2w",
        Some(PtValue::Tensor(Tensor::f64(vec![3, 4], m))),
    );
    let e = read_err(out.path());
    assert!(matches!(e, MegaNerfError::BadPose { .. }), "{e}");
    assert!(e.to_string().contains("000001.pt"), "{e}");

    let (out, _src, _) = written_fixture();
    let file = out.path().join("val/metadata/000001.pt");
    edit_pt(
        &file,
        "intrinsics",
        Some(PtValue::Tensor(Tensor::f64(
            vec![4],
            vec![-5.0, 5.0, 3.0, 2.0],
        ))),
    );
    let e = read_err(out.path());
    assert!(matches!(e, MegaNerfError::BadCamera { .. }), "{e}");

    let (out, _src, _) = written_fixture();
    fs::remove_file(out.path().join("val/rgbs/000003.png")).unwrap();
    let e = read_err(out.path());
    assert!(matches!(e, MegaNerfError::MissingImage { .. }), "{e}");
    assert!(e.to_string().contains("000003.pt"), "{e}");

    let (out, _src, _) = written_fixture();
    png(&out.path().join("train/rgbs/000000.png"), 12, 8);
    let e = read_err(out.path());
    assert!(
        matches!(
            e,
            MegaNerfError::ImageSize {
                width: 12,
                height: 8,
                expected_width: 6,
                expected_height: 4,
                ..
            }
        ),
        "{e}"
    );
    let msg = e.to_string();
    assert!(
        msg.contains("000000.png") && msg.contains("000000.pt"),
        "{msg}"
    );

    // A corrupt metadata file names itself.
    let (out, _src, _) = written_fixture();
    let file = out.path().join("train/metadata/000000.pt");
    let bytes = fs::read(&file).unwrap();
    fs::write(&file, &bytes[..bytes.len() / 2]).unwrap();
    let e = read_err(out.path());
    assert!(e.to_string().contains("000000.pt"), "{e}");
}

fn pose_strategy() -> impl Strategy<Value = Pose> {
    (
        prop::array::uniform3(-1.0..1.0f64),
        0.0..3.1f64,
        prop::array::uniform3(-500.0..500.0f64),
    )
        .prop_filter_map("non-zero axis", |(axis, angle, t)| {
            let axis = nalgebra::Unit::try_new(Vector3::from(axis), 1e-3)?;
            Some(Isometry3::from_parts(
                Translation3::from(Vector3::from(t)),
                UnitQuaternion::from_axis_angle(&axis, angle),
            ))
        })
}

fn camera_strategy() -> impl Strategy<Value = Camera> {
    (
        2u32..7,
        2u32..7,
        1.0..900.0f64,
        1.0..900.0f64,
        -2.0..8.0f64,
        -2.0..8.0f64,
        prop::option::of(prop::array::uniform5(-0.2..0.2f64)),
    )
        .prop_map(|(w, h, fx, fy, cx, cy, d)| {
            let distortion = d.map_or(Distortion::NONE, |d| Distortion {
                k1: d[0],
                k2: d[1],
                p1: d[2],
                p2: d[3],
                k3: d[4],
            });
            Camera::opencv(w, h, fx, fy, cx, cy, distortion).unwrap()
        })
}

fn frames_strategy() -> impl Strategy<Value = Vec<Frame>> {
    prop::collection::vec((pose_strategy(), camera_strategy(), any::<bool>()), 1..5).prop_map(|v| {
        v.into_iter()
            .enumerate()
            .map(|(i, (cam_from_world, camera, test))| Frame {
                image_path: PathBuf::from(format!("img/{i}.png")),
                depth_path: None,
                camera,
                cam_from_world,
                split: if test { Split::Test } else { Split::Train },
            })
            .collect()
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn any_dataset_round_trips_within_1e9(frames in frames_strategy()) {
        let src = tempfile::tempdir().unwrap();
        let ds = source_dataset(src.path(), frames);
        let out = tempfile::tempdir().unwrap();
        write_mega_nerf(&ds, out.path()).unwrap();
        let back = read_mega_nerf_with(out.path(), &MegaNerfOptions { images_distorted: true }).unwrap();
        prop_assert_eq!(back.frames.len(), ds.frames.len());
        // Files are named by frame index: train first, then val.
        let mut order: Vec<usize> = (0..ds.frames.len()).filter(|&i| ds.frames[i].split == Split::Train).collect();
        order.extend((0..ds.frames.len()).filter(|&i| ds.frames[i].split != Split::Train));
        for (b, &i) in back.frames.iter().zip(&order) {
            let a = &ds.frames[i];
            prop_assert!(close_pose(&a.cam_from_world, &b.cam_from_world, 1e-9),
                "{:?} vs {:?}", a.cam_from_world, b.cam_from_world);
            let (ca, cb) = (&a.camera, &b.camera);
            prop_assert_eq!((ca.width, ca.height), (cb.width, cb.height));
            for (x, y) in [(ca.fx, cb.fx), (ca.fy, cb.fy), (ca.cx, cb.cx), (ca.cy, cb.cy),
                (ca.distortion.k1, cb.distortion.k1), (ca.distortion.k2, cb.distortion.k2),
                (ca.distortion.p1, cb.distortion.p1), (ca.distortion.p2, cb.distortion.p2),
                (ca.distortion.k3, cb.distortion.k3)] {
                prop_assert!((x - y).abs() <= 1e-9);
            }
            prop_assert_eq!(a.split, b.split);
        }
    }
}
