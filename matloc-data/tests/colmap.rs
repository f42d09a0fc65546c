//! COLMAP sparse models: text fixtures for every supported model, text ↔ binary, bad input.

use std::fs;
use std::path::{Path, PathBuf};

use matloc_core::{Distortion, PoseError};
use matloc_data::colmap::{
    ColmapCameraModel, ColmapError, ColmapFormat, ColmapModel, default_image_dir, find_model_dir,
    parse_cameras_binary, parse_images_binary, read_colmap, read_colmap_dataset, read_colmap_dir,
    write_colmap,
};
use matloc_data::summary::{DatasetFormat, detect_format};
use matloc_data::{DataError, read_dataset};
use nalgebra::Vector3;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn close_models(a: &ColmapModel, b: &ColmapModel) {
    assert_eq!(a.cameras, b.cameras);
    assert_eq!(a.points3d, b.points3d);
    assert_eq!(a.images.len(), b.images.len());
    for (ia, ib) in a.images.values().zip(b.images.values()) {
        assert_eq!(
            (ia.id, &ia.name, ia.camera_id),
            (ib.id, &ib.name, ib.camera_id)
        );
        assert_eq!(ia.points2d, ib.points2d);
        assert!(
            (ia.cam_from_world.translation.vector - ib.cam_from_world.translation.vector).norm()
                < 1e-12
        );
        assert!(
            ia.cam_from_world
                .rotation
                .angle_to(&ib.cam_from_world.rotation)
                < 1e-12
        );
    }
}

#[test]
fn text_fixture_maps_all_five_models() {
    let model = read_colmap(&fixture("colmap_text")).unwrap();
    assert_eq!(model.cameras.len(), 5);
    let cam = |id: u32| model.cameras[&id].to_camera().unwrap();

    assert_eq!(model.cameras[&1].model, ColmapCameraModel::SimplePinhole);
    let c = cam(1);
    assert_eq!(
        (c.width, c.height, c.fx, c.fy, c.cx, c.cy),
        (640, 480, 500.0, 500.0, 320.0, 240.0)
    );
    assert!(c.is_pinhole());

    let c = cam(2);
    assert_eq!((c.fx, c.fy, c.cx, c.cy), (500.0, 510.0, 321.0, 239.0));
    assert!(c.is_pinhole());

    let c = cam(3);
    assert_eq!(
        (c.width, c.height, c.fx, c.fy, c.cx, c.cy),
        (800, 600, 700.0, 700.0, 400.0, 300.0)
    );
    assert_eq!(
        c.distortion,
        Distortion {
            k1: -0.02,
            ..Distortion::NONE
        }
    );

    let c = cam(4);
    assert_eq!((c.cx, c.cy), (401.0, 299.0));
    assert_eq!(
        c.distortion,
        Distortion {
            k1: -0.02,
            k2: 0.003,
            ..Distortion::NONE
        }
    );

    let c = cam(5);
    assert_eq!((c.fx, c.fy, c.cx, c.cy), (900.0, 905.0, 512.0, 384.0));
    assert_eq!(
        c.distortion,
        Distortion {
            k1: -0.1,
            k2: 0.02,
            p1: 0.001,
            p2: -0.0005,
            k3: 0.0
        }
    );

    // Images: ids unordered in the file, a blank keypoint line, a last image without one.
    assert_eq!(model.images.len(), 5);
    let e = &model.images[&5];
    assert_eq!((e.name.as_str(), e.camera_id), ("img_e.jpg", 5));
    assert_eq!(e.points2d.len(), 3);
    assert_eq!(e.points2d[0].xy, [10.5, 20.25]);
    assert_eq!(e.points2d[0].point3d_id, Some(100));
    assert_eq!(e.points2d[2].point3d_id, None);
    // Identity rotation with t = (1, 2, 3): the centre is -t.
    assert!(
        (e.cam_from_world.inverse().translation.vector - Vector3::new(-1.0, -2.0, -3.0)).norm()
            < 1e-12
    );
    assert!(model.images[&2].points2d.is_empty());
    assert!(model.images[&4].points2d.is_empty());
    // 90° about z: camera x axis is world y.
    let a = &model.images[&1];
    let x_world = a.cam_from_world.inverse_transform_vector(&Vector3::x());
    assert!(
        (x_world - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12
            || (x_world - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12
    );
    assert!(
        (a.cam_from_world * nalgebra::Point3::new(1.0, 0.0, 0.0)
            - nalgebra::Point3::new(0.0, 1.0, 10.0))
        .norm()
            < 1e-12
    );

    assert_eq!(model.points3d.len(), 2);
    let p = &model.points3d[&101];
    assert_eq!(p.xyz, [-4.0, 5.5, 6.0]);
    assert_eq!(p.rgb, [10, 20, 30]);
    assert_eq!(p.error, 1.25);
    assert_eq!(p.track.len(), 3);
    assert_eq!((p.track[2].image_id, p.track[2].point2d_idx), (5, 1));
}

#[test]
fn dataset_conversion_and_detection() {
    let root = fixture("colmap_text");
    let ds = read_colmap_dataset(&root).unwrap();
    // Frames sorted by name; the image directory defaults to `images/` beside `sparse/`.
    let names: Vec<_> = ds
        .frames
        .iter()
        .map(|f| f.image_path.to_str().unwrap().to_string())
        .collect();
    assert_eq!(
        names,
        [
            "img_a.jpg",
            "img_b.jpg",
            "img_c.jpg",
            "img_d.jpg",
            "img_e.jpg"
        ]
    );
    assert_eq!(ds.root, root.join("images"));
    assert_eq!(
        default_image_dir(&root.join("sparse/0")),
        root.join("images")
    );
    assert_eq!(ds.frames[4].camera.fx, 900.0);

    assert_eq!(detect_format(&root).unwrap(), DatasetFormat::Colmap);
    assert_eq!(
        detect_format(&root.join("sparse/0")).unwrap(),
        DatasetFormat::Colmap
    );
    assert_eq!(read_dataset(&root).unwrap(), ds);
    assert_eq!(
        detect_format(&fixture("ns_global")).unwrap(),
        DatasetFormat::Nerfstudio
    );
    let (dir, format) = find_model_dir(&root).unwrap();
    assert_eq!((dir, format), (root.join("sparse/0"), ColmapFormat::Text));
}

#[test]
fn text_binary_round_trip() {
    let text_model = read_colmap(&fixture("colmap_text")).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let bin_dir = tmp.path().join("bin/sparse/0");
    write_colmap(&text_model, &bin_dir, ColmapFormat::Binary).unwrap();
    assert_eq!(
        find_model_dir(&tmp.path().join("bin")).unwrap().1,
        ColmapFormat::Binary
    );
    let bin_model = read_colmap(&tmp.path().join("bin")).unwrap();
    close_models(&text_model, &bin_model);

    let txt_dir = tmp.path().join("txt");
    write_colmap(&bin_model, &txt_dir, ColmapFormat::Text).unwrap();
    let again = read_colmap_dir(&txt_dir, ColmapFormat::Text).unwrap();
    close_models(&text_model, &again);

    // Binary again from the re-read text: byte-identical files.
    let bin2 = tmp.path().join("bin2");
    write_colmap(&again, &bin2, ColmapFormat::Binary).unwrap();
    for name in ["cameras.bin", "points3D.bin"] {
        assert_eq!(
            fs::read(bin_dir.join(name)).unwrap(),
            fs::read(bin2.join(name)).unwrap()
        );
    }
}

#[test]
fn hand_packed_binary_matches_documented_layout() {
    // cameras.bin: one PINHOLE camera, packed by hand from COLMAP's documented layout.
    let mut cams = Vec::new();
    cams.extend_from_slice(&1u64.to_le_bytes());
    cams.extend_from_slice(&3u32.to_le_bytes()); // camera_id
    cams.extend_from_slice(&1i32.to_le_bytes()); // PINHOLE
    cams.extend_from_slice(&640u64.to_le_bytes());
    cams.extend_from_slice(&480u64.to_le_bytes());
    for v in [500.0f64, 501.0, 320.0, 240.0] {
        cams.extend_from_slice(&v.to_le_bytes());
    }
    let cameras = parse_cameras_binary(&cams, Path::new("cameras.bin")).unwrap();
    let c = cameras[&3].to_camera().unwrap();
    assert_eq!(
        (c.width, c.height, c.fx, c.fy, c.cx, c.cy),
        (640, 480, 500.0, 501.0, 320.0, 240.0)
    );

    // images.bin: one image with two keypoints, one unmatched (u64::MAX).
    let mut imgs = Vec::new();
    imgs.extend_from_slice(&1u64.to_le_bytes());
    imgs.extend_from_slice(&9u32.to_le_bytes());
    for v in [1.0f64, 0.0, 0.0, 0.0, 4.0, 5.0, 6.0] {
        imgs.extend_from_slice(&v.to_le_bytes());
    }
    imgs.extend_from_slice(&3u32.to_le_bytes());
    imgs.extend_from_slice(b"dir/x.png\0");
    imgs.extend_from_slice(&2u64.to_le_bytes());
    for (x, y, id) in [(1.5f64, 2.5f64, 42u64), (3.0, 4.0, u64::MAX)] {
        imgs.extend_from_slice(&x.to_le_bytes());
        imgs.extend_from_slice(&y.to_le_bytes());
        imgs.extend_from_slice(&id.to_le_bytes());
    }
    let images = parse_images_binary(&imgs, Path::new("images.bin")).unwrap();
    let im = &images[&9];
    assert_eq!((im.name.as_str(), im.camera_id), ("dir/x.png", 3));
    assert_eq!(im.points2d[0].point3d_id, Some(42));
    assert_eq!(im.points2d[1].point3d_id, None);
    assert_eq!(
        im.cam_from_world.translation.vector,
        Vector3::new(4.0, 5.0, 6.0)
    );

    // Our writer produces exactly the hand-packed bytes.
    let tmp = tempfile::tempdir().unwrap();
    let model = ColmapModel {
        cameras: cameras.clone(),
        images: images.clone(),
        points3d: Default::default(),
    };
    write_colmap(&model, tmp.path(), ColmapFormat::Binary).unwrap();
    assert_eq!(fs::read(tmp.path().join("cameras.bin")).unwrap(), cams);
    assert_eq!(fs::read(tmp.path().join("images.bin")).unwrap(), imgs);
    assert_eq!(
        fs::read(tmp.path().join("points3D.bin")).unwrap(),
        0u64.to_le_bytes()
    );

    // Truncation anywhere names the record and field.
    let err = parse_images_binary(&imgs[..imgs.len() - 3], Path::new("images.bin")).unwrap_err();
    match &err {
        ColmapError::Truncated { record, path, .. } => {
            assert!(
                record.contains("image #0") && record.contains("point3D_id"),
                "{record}"
            );
            assert_eq!(path, Path::new("images.bin"));
        }
        other => panic!("unexpected {other}"),
    }
    let err = parse_images_binary(&imgs[..60], Path::new("images.bin")).unwrap_err();
    assert!(
        matches!(&err, ColmapError::Truncated { record, .. } if record.contains("tvec")),
        "{err}"
    );

    // An unsupported model id in binary: FULL_OPENCV (6).
    let mut full = cams.clone();
    full[12..16].copy_from_slice(&6i32.to_le_bytes());
    let err = parse_cameras_binary(&full, Path::new("cameras.bin")).unwrap_err();
    assert!(
        matches!(&err, ColmapError::UnsupportedCameraModel { model, camera_id: 3, .. } if model.contains("FULL_OPENCV")),
        "{err}"
    );
    assert!(err.to_string().contains("cameras.bin"));
}

#[test]
fn unsupported_model_in_text_names_model_and_file() {
    let err = read_colmap(&fixture("colmap_fisheye")).unwrap_err();
    match &err {
        ColmapError::UnsupportedCameraModel {
            path,
            camera_id,
            model,
        } => {
            assert!(path.ends_with("colmap_fisheye/cameras.txt"));
            assert_eq!(*camera_id, 7);
            assert!(
                model.contains("OPENCV_FISHEYE") && model.contains("id 5"),
                "{model}"
            );
        }
        other => panic!("unexpected {other}"),
    }
    assert!(err.to_string().contains("OPENCV_FISHEYE"));
}

#[test]
fn bad_text_input_is_typed() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    // No model at all.
    let err = read_colmap(d).unwrap_err();
    assert!(matches!(err, ColmapError::NotFound { .. }), "{err}");
    let err = read_dataset(d).unwrap_err();
    assert!(matches!(err, DataError::UnknownFormat { .. }), "{err}");
    let err = read_dataset(&d.join("missing")).unwrap_err();
    assert!(matches!(err, DataError::NotFound { .. }), "{err}");

    // cameras without images.
    fs::write(d.join("cameras.txt"), "1 PINHOLE 10 10 5 5 5 5\n").unwrap();
    let err = read_colmap(d).unwrap_err();
    assert!(
        matches!(&err, ColmapError::MissingFile { path } if path.ends_with("images.txt")),
        "{err}"
    );

    // A bad number names the line and field.
    fs::write(d.join("images.txt"), "# c\n1 1 0 0 0 0 0 zero 1 a.png\n\n").unwrap();
    let err = read_colmap(d).unwrap_err();
    assert!(
        matches!(
            &err,
            ColmapError::Parse {
                line: 2,
                field: "TZ",
                ..
            }
        ),
        "{err}"
    );

    // A zero quaternion.
    fs::write(d.join("images.txt"), "1 0 0 0 0 0 0 0 1 a.png\n\n").unwrap();
    let err = read_colmap(d).unwrap_err();
    assert!(
        matches!(
            &err,
            ColmapError::BadPose {
                image_id: 1,
                source: PoseError::BadQuaternion { .. },
                ..
            }
        ),
        "{err}"
    );

    // An image referring to a missing camera.
    fs::write(d.join("images.txt"), "1 1 0 0 0 0 0 0 2 a.png\n\n").unwrap();
    let err = read_colmap(d).unwrap_err();
    assert!(
        matches!(&err, ColmapError::UnknownCamera { camera_id: 2, .. }),
        "{err}"
    );

    // Too few parameters for the model.
    fs::write(d.join("cameras.txt"), "1 OPENCV 10 10 5 5 5 5\n").unwrap();
    let err = read_colmap(d).unwrap_err();
    assert!(
        matches!(
            &err,
            ColmapError::Parse {
                field: "PARAMS",
                line: 1,
                ..
            }
        ),
        "{err}"
    );

    // Negative focal length.
    fs::write(d.join("cameras.txt"), "1 PINHOLE 10 10 -5 5 5 5\n").unwrap();
    let err = read_colmap(d).unwrap_err();
    assert!(
        matches!(&err, ColmapError::BadCamera { camera_id: 1, .. }),
        "{err}"
    );
}

#[test]
fn dataset_to_colmap_and_back() {
    let ds = matloc_data::nerfstudio::read_nerfstudio(&fixture("ns_global")).unwrap();
    let model = ColmapModel::from_dataset(&ds).unwrap();
    assert_eq!(model.cameras.len(), 1);
    let tmp = tempfile::tempdir().unwrap();
    write_colmap(&model, &tmp.path().join("sparse/0"), ColmapFormat::Text).unwrap();
    let back = read_colmap_dataset(tmp.path()).unwrap();
    // Names sort in the same order as the fixture's frames.
    for (a, b) in ds.frames.iter().zip(&back.frames) {
        assert_eq!(a.camera, b.camera);
        assert!((a.center() - b.center()).norm() < 1e-9);
        assert!(
            a.cam_from_world
                .rotation
                .angle_to(&b.cam_from_world.rotation)
                < 1e-9
        );
    }
}

#[test]
fn names_with_spaces_and_short_params() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    fs::write(d.join("cameras.txt"), "1 PINHOLE 10 10 5 5 5 5\n").unwrap();
    fs::write(d.join("images.txt"), "1 1 0 0 0 0 0 0 1 my photo 1.png\n\n").unwrap();
    let model = read_colmap(d).unwrap();
    assert_eq!(model.images[&1].name, "my photo 1.png");
    let out = d.join("bin");
    write_colmap(&model, &out, ColmapFormat::Binary).unwrap();
    assert_eq!(read_colmap(&out).unwrap().images[&1].name, "my photo 1.png");

    // A hand-built camera with too few parameters is an error, not a panic.
    let mut cam = model.cameras[&1].clone();
    cam.params.truncate(2);
    assert!(cam.to_camera().is_err());
}

/// `images.txt` written without the POINTS2D lines (some exporters do) reads as images
/// without keypoints, with or without the blank line between them.
#[test]
fn images_text_without_points2d_lines() {
    let compact =
        "1 1 0 0 0 0 0 -2.0 1 a.png\n2 1 0 0 0 1 0 -2.0 1 b.png\n3 1 0 0 0 2 0 -2.0 1 img 3.png\n";
    let images =
        matloc_data::colmap::parse_images_text(compact.as_bytes(), Path::new("images.txt"))
            .unwrap();
    assert_eq!(images.len(), 3);
    assert_eq!(images[&3].name, "img 3.png");
    assert!(images.values().all(|i| i.points2d.is_empty()));
    // Mixed: one image with keypoints, one without.
    let mixed = "1 1 0 0 0 0 0 -2.0 1 a.png\n10.5 20.5 -1 11 12 7\n2 1 0 0 0 1 0 -2.0 1 b.png\n";
    let images =
        matloc_data::colmap::parse_images_text(mixed.as_bytes(), Path::new("images.txt")).unwrap();
    assert_eq!(images[&1].points2d.len(), 2);
    assert_eq!(images[&1].points2d[1].point3d_id, Some(7));
    assert!(images[&2].points2d.is_empty());
}
