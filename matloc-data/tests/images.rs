//! Image and depth loading: rescaled intrinsics, size mismatch, downscale, .npy and PNG depth.

use std::fs;
use std::path::PathBuf;

use matloc_core::{Camera, Distortion, Image, Pose};
use matloc_data::images::{
    ImageLoadError, PNG_DEPTH_SCALE_M, encode_npy_f32, load_frame_depth, load_frame_image,
    load_rgb, parse_npy, read_depth, read_depth_npy, write_depth_npy, write_depth_png,
    write_png_rgb,
};
use matloc_data::{Dataset, Frame, Split};

fn gradient(w: usize, h: usize) -> Image<f32> {
    let mut img = Image::new(w, h, 3);
    for y in 0..h {
        for x in 0..w {
            let p = img.pixel_mut(x, y);
            p[0] = x as f32 / w as f32;
            p[1] = y as f32 / h as f32;
            p[2] = ((x + y) % 2) as f32;
        }
    }
    img
}

fn one_frame(root: PathBuf, camera: Camera, depth: Option<&str>) -> (Dataset, Frame) {
    let frame = Frame {
        image_path: "img.png".into(),
        depth_path: depth.map(PathBuf::from),
        camera,
        cam_from_world: Pose::identity(),
        split: Split::Train,
    };
    let ds = Dataset {
        root,
        frames: vec![frame.clone()],
        points: None,
        metadata: Default::default(),
    };
    (ds, frame)
}

#[test]
fn png_round_trip_is_exact_on_8bit_values() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a.png");
    let img = gradient(16, 8);
    write_png_rgb(&img, &p).unwrap();
    let back = load_rgb(&p).unwrap();
    assert_eq!(back.shape(), (16, 8, 3));
    for (a, b) in img.data().iter().zip(back.data()) {
        assert!((a - b).abs() <= 0.5 / 255.0 + 1e-6);
    }
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn intrinsics_rescale_when_aspect_matches() {
    let dir = tempfile::tempdir().unwrap();
    write_png_rgb(&gradient(32, 24), &dir.path().join("img.png")).unwrap();
    // Intrinsics stated for 64x48 (twice the file's size): rescaled by 1/2.
    let cam = Camera::opencv(
        64,
        48,
        60.0,
        62.0,
        32.0,
        24.0,
        Distortion {
            k1: -0.1,
            ..Distortion::NONE
        },
    )
    .unwrap();
    let (ds, frame) = one_frame(dir.path().to_path_buf(), cam, None);
    let (img, fitted) = load_frame_image(&ds, &frame, 1).unwrap();
    assert_eq!(img.shape(), (32, 24, 3));
    assert_eq!(
        (
            fitted.width,
            fitted.height,
            fitted.fx,
            fitted.fy,
            fitted.cx,
            fitted.cy
        ),
        (32, 24, 30.0, 31.0, 16.0, 12.0)
    );
    assert_eq!(fitted.distortion, cam.distortion);

    // Downscale by 4 on load: box filter and exactly quartered intrinsics.
    let (small, small_cam) = load_frame_image(&ds, &frame, 4).unwrap();
    assert_eq!(small.shape(), (8, 6, 3));
    assert_eq!(
        (
            small_cam.width,
            small_cam.height,
            small_cam.fx,
            small_cam.cx
        ),
        (8, 6, 7.5, 4.0)
    );
    let expected = matloc_core::image::downscale_box(&img, 4);
    assert_eq!(small.data(), expected.data());
}

#[test]
fn size_mismatch_with_different_aspect_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    write_png_rgb(&gradient(30, 24), &dir.path().join("img.png")).unwrap();
    let cam = Camera::pinhole(64, 48, 60.0, 60.0, 32.0, 24.0).unwrap();
    let (ds, frame) = one_frame(dir.path().to_path_buf(), cam, None);
    let err = load_frame_image(&ds, &frame, 1).unwrap_err();
    match &err {
        ImageLoadError::SizeMismatch {
            path,
            intrinsics_width: 64,
            intrinsics_height: 48,
            image_width: 30,
            image_height: 24,
        } => assert!(path.ends_with("img.png")),
        other => panic!("unexpected {other}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("30x24") && msg.contains("64x48") && msg.contains("img.png"),
        "{msg}"
    );
}

#[test]
fn missing_and_corrupt_images() {
    let dir = tempfile::tempdir().unwrap();
    let err = load_rgb(&dir.path().join("none.png")).unwrap_err();
    assert!(
        matches!(&err, ImageLoadError::NotFound { path } if path.ends_with("none.png")),
        "{err}"
    );
    let bad = dir.path().join("bad.png");
    fs::write(&bad, b"\x89PNG\r\n\x1a\nthis is not a png").unwrap();
    let err = load_rgb(&bad).unwrap_err();
    assert!(
        matches!(&err, ImageLoadError::Codec { path, .. } if path == &bad),
        "{err}"
    );
}

#[test]
fn npy_depth_round_trip_and_numpy_layout() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("d.npy");
    let depth = Image::from_vec(3, 2, 1, vec![0.0f32, 1.5, 70_000.25, 12.0, 65.6, 0.001]).unwrap();
    write_depth_npy(&depth, &p).unwrap();
    let bytes = fs::read(&p).unwrap();
    // numpy.save's layout for a (2, 3) float32 array: version 1.0, the data aligned to 64
    // bytes, a dict header (npyz writes the shape tuple as `(2, 3, )`, which numpy reads as
    // `(2, 3)`).
    assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
    let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    assert_eq!((10 + header_len) % 64, 0);
    let header = std::str::from_utf8(&bytes[10..10 + header_len]).unwrap();
    assert!(
        header.starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3, ), }"),
        "{header}"
    );
    assert!(header.ends_with('\n'));
    assert_eq!(
        &bytes[10 + header_len..10 + header_len + 8],
        &[0, 0, 0, 0, 0, 0, 0xc0, 0x3f]
    );
    let back = read_depth_npy(&p).unwrap();
    assert_eq!(back, depth);
    assert_eq!(read_depth(&p, PNG_DEPTH_SCALE_M).unwrap(), depth);

    // A numpy-style float64 header with extra spaces and a (H, W, 1) shape.
    let mut f8 = b"\x93NUMPY\x01\x00".to_vec();
    let h = "{'descr': '<f8', 'fortran_order': False, 'shape': (1, 2, 1), }          \n";
    f8.extend_from_slice(&(h.len() as u16).to_le_bytes());
    f8.extend_from_slice(h.as_bytes());
    f8.extend_from_slice(&2.5f64.to_le_bytes());
    f8.extend_from_slice(&0.0f64.to_le_bytes());
    assert_eq!(parse_npy(&f8).unwrap().data(), &[2.5, 0.0]);

    // Wrong dtype and wrong length are errors naming the problem.
    let mut wrong = encode_npy_f32(2, 1, &[1.0, 2.0]);
    let at = wrong.windows(3).position(|w| w == b"<f4").unwrap();
    wrong[at..at + 3].copy_from_slice(b"<i4");
    assert!(parse_npy(&wrong).unwrap_err().contains("<i4"));
    let short = encode_npy_f32(2, 1, &[1.0, 2.0]);
    assert!(
        parse_npy(&short[..short.len() - 1])
            .unwrap_err()
            .contains("needs 8")
    );

    // Negative / NaN depth is refused and nothing is written.
    let q = dir.path().join("bad.npy");
    let nan = Image::from_vec(2, 1, 1, vec![1.0f32, f32::NAN]).unwrap();
    assert!(matches!(
        write_depth_npy(&nan, &q).unwrap_err(),
        ImageLoadError::DepthOutOfRange { x: 1, y: 0, .. }
    ));
    assert!(!q.exists());
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn png_depth_millimetres() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("d.png");
    let depth = Image::from_vec(2, 2, 1, vec![0.0f32, 1.234, 65.535, 20.0]).unwrap();
    write_depth_png(&depth, &p, PNG_DEPTH_SCALE_M).unwrap();
    let back = read_depth(&p, PNG_DEPTH_SCALE_M).unwrap();
    for (a, b) in depth.data().iter().zip(back.data()) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
    // 70 m overflows 16-bit millimetres: refused, old file untouched.
    let before = fs::read(&p).unwrap();
    let far = Image::from_vec(1, 1, 1, vec![70.0f32]).unwrap();
    let err = write_depth_png(&far, &p, PNG_DEPTH_SCALE_M).unwrap_err();
    assert!(
        matches!(err, ImageLoadError::DepthOutOfRange { .. }),
        "{err}"
    );
    assert_eq!(fs::read(&p).unwrap(), before);
    // An 8-bit RGB PNG is not a depth map.
    let rgb = dir.path().join("rgb.png");
    write_png_rgb(&gradient(2, 2), &rgb).unwrap();
    assert!(matches!(
        read_depth(&rgb, 1e-3).unwrap_err(),
        ImageLoadError::NotDepthPng { .. }
    ));
}

#[test]
fn frame_depth_is_subsampled_not_averaged() {
    let dir = tempfile::tempdir().unwrap();
    let depth = Image::from_vec(
        4,
        2,
        1,
        vec![10.0f32, 10.0, 0.0, 0.0, 10.0, 10.0, 0.0, 50.0],
    )
    .unwrap();
    write_depth_npy(&depth, &dir.path().join("d.npy")).unwrap();
    let cam = Camera::pinhole(8, 4, 8.0, 8.0, 4.0, 2.0).unwrap();
    let (ds, frame) = one_frame(dir.path().to_path_buf(), cam, Some("d.npy"));
    let full = load_frame_depth(&ds, &frame, 1).unwrap().unwrap();
    assert_eq!(full, depth);
    let half = load_frame_depth(&ds, &frame, 2).unwrap().unwrap();
    assert_eq!(half.shape(), (2, 1, 1));
    // Each value is one of the block's own depths, never a blend of sky and ground.
    assert_eq!(half.data(), &[10.0, 50.0]);
}

#[test]
fn write_into_missing_directory_fails_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("no/such/dir/a.png");
    let err = write_png_rgb(&gradient(2, 2), &p).unwrap_err();
    assert!(
        matches!(
            err,
            ImageLoadError::NotFound { .. } | ImageLoadError::Io { .. }
        ),
        "{err}"
    );
    let err = write_png_rgb(&Image::new(2, 2, 1), &dir.path().join("gray.png")).unwrap_err();
    assert!(matches!(
        err,
        ImageLoadError::Channels {
            expected: 3,
            actual: 1,
            ..
        }
    ));
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[test]
fn working_dataset_fits_file_sizes_then_downscales_every_frame_alike() {
    let dir = tempfile::tempdir().unwrap();
    // A pre-downscaled image (64x48) with intrinsics for the full 128x96 sensor.
    write_png_rgb(&gradient(64, 48), &dir.path().join("img.png")).unwrap();
    let full = Camera::pinhole(128, 96, 100.0, 100.0, 64.0, 48.0).unwrap();
    let (ds, _) = one_frame(dir.path().to_path_buf(), full, None);

    let native = matloc_data::images::working_dataset(&ds, None).unwrap();
    let c = native.frames[0].camera;
    assert_eq!((c.width, c.height, c.fx, c.cx), (64, 48, 50.0, 32.0));

    // Longer side at most 32: factor 2 of the file's size.
    let small = matloc_data::images::working_dataset(&ds, Some(32)).unwrap();
    let c = small.frames[0].camera;
    assert_eq!((c.width, c.height, c.fx, c.cx), (32, 24, 25.0, 16.0));
    let (img, cam) = load_frame_image(&small, &small.frames[0], 1).unwrap();
    assert_eq!((img.width(), img.height()), (32, 24));
    assert_eq!(cam, c);
    // The 8-bit file box-downscaled.
    let file = load_rgb(&dir.path().join("img.png")).unwrap();
    assert!(
        img == matloc_core::image::downscale_box(&file, 2),
        "not the box-downscaled file"
    );
    // A further downscale on top of the working size.
    let (img, cam) = load_frame_image(&small, &small.frames[0], 2).unwrap();
    assert_eq!((img.width(), img.height(), cam.width), (16, 12, 16));
}

#[test]
fn working_dataset_names_an_image_whose_aspect_disagrees_with_its_intrinsics() {
    let dir = tempfile::tempdir().unwrap();
    write_png_rgb(&gradient(64, 64), &dir.path().join("img.png")).unwrap();
    let cam = Camera::pinhole(128, 96, 100.0, 100.0, 64.0, 48.0).unwrap();
    let (ds, _) = one_frame(dir.path().to_path_buf(), cam, None);
    let e = matloc_data::images::working_dataset(&ds, Some(32)).unwrap_err();
    assert!(matches!(e, ImageLoadError::SizeMismatch { .. }));
    let msg = e.to_string();
    assert!(
        msg.contains("img.png") && msg.contains("64x64") && msg.contains("128x96"),
        "{msg}"
    );
    // A missing image is named too.
    std::fs::remove_file(dir.path().join("img.png")).unwrap();
    let e = matloc_data::images::working_dataset(&ds, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("img.png"), "{e}");
}

#[test]
fn depth_dtype_is_checked_from_the_header_and_special_files_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    // An int32 depth map: refused by name by the header check, not only by a full read.
    let p = dir.path().join("d.npy");
    let mut header = String::from("{'descr': '<i4', 'fortran_order': False, 'shape': (2, 3), }");
    header.push_str(&" ".repeat((64 - (10 + header.len() + 1) % 64) % 64));
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    bytes.extend_from_slice(&[0u8; 24]);
    fs::write(&p, &bytes).unwrap();
    for e in [
        matloc_data::images::depth_size(&p).unwrap_err().to_string(),
        read_depth_npy(&p).unwrap_err().to_string(),
    ] {
        assert!(e.contains("<i4") && e.contains("d.npy"), "{e}");
    }
    // A depth "file" that is a link to /dev/zero is not read until memory runs out.
    #[cfg(unix)]
    {
        let link = dir.path().join("zero.npy");
        std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
        let e = read_depth_npy(&link).unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
        let link = dir.path().join("zero.png");
        std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
        let e = load_rgb(&link).unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
    }
}
