//! Every surface source on the `tiny` synthetic world, against its exact depth maps.

use std::path::PathBuf;
use std::sync::OnceLock;

use matloc_core::image::Image;
use matloc_data::images::load_frame_depth;
use matloc_data::{Dataset, PointSource, Split, read_dataset};
use matloc_surface::{
    FrameSurfaces, SurfaceChoice, SurfaceConfig, SurfaceError, SurfaceKind, plan, triangulate,
};
use matloc_synth::{SynthConfig, SynthOutput, synthesize_with};

struct Fixture {
    dir: PathBuf,
    dataset: Dataset,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("surface_tiny");
        let _ = std::fs::remove_dir_all(&dir);
        let output = SynthOutput {
            depth: true,
            points: true,
        };
        synthesize_with(
            &SynthConfig::preset("tiny").unwrap(),
            &dir,
            &output,
            &|_| {},
        )
        .unwrap();
        let dataset = read_dataset(&dir).unwrap();
        Fixture { dir, dataset }
    })
}

/// Median over frames of the median relative error of a depth map against the true one,
/// where both have a surface; and the fraction of true-surface cells the map covers. Also
/// prints the 99th percentile and the largest error over all cells (outliers stretch scene
/// boxes).
fn depth_error(dataset: &Dataset, surfaces: &FrameSurfaces) -> (f64, f64) {
    let mut every = Vec::new();
    let mut medians = Vec::new();
    // World bounds of the surface the maps give, and of the true surface.
    let mut bounds = [[f64::INFINITY; 3], [f64::NEG_INFINITY; 3]];
    let mut true_bounds = bounds;
    let grow = |b: &mut [[f64; 3]; 2], p: nalgebra::Point3<f64>| {
        for k in 0..3 {
            b[0][k] = b[0][k].min(p[k]);
            b[1][k] = b[1][k].max(p[k]);
        }
    };
    let mut covered = (0usize, 0usize);
    for i in dataset.split_indices(Split::Train) {
        let truth = load_frame_depth(dataset, &dataset.frames[i], 1)
            .unwrap()
            .unwrap();
        let d = surfaces.depth(dataset, i).unwrap();
        let mut rel = Vec::new();
        for r in 0..d.height() {
            for c in 0..d.width() {
                let tx = ((c as f64 + 0.5) * truth.width() as f64 / d.width() as f64) as usize;
                let ty = ((r as f64 + 0.5) * truth.height() as f64 / d.height() as f64) as usize;
                let t = truth.data()[ty * truth.width() + tx];
                let v = d.data()[r * d.width() + c];
                let fr = &dataset.frames[i];
                let px = nalgebra::Point2::new(
                    (c as f64 + 0.5) * fr.camera.width as f64 / d.width() as f64,
                    (r as f64 + 0.5) * fr.camera.height as f64 / d.height() as f64,
                );
                let b = fr.camera.unproject(px).unwrap();
                let wfc = fr.cam_from_world.inverse();
                if v > 0.0 {
                    grow(
                        &mut bounds,
                        wfc * nalgebra::Point3::from(b / b.z * f64::from(v)),
                    );
                }
                if t > 0.0 {
                    grow(
                        &mut true_bounds,
                        wfc * nalgebra::Point3::from(b / b.z * f64::from(t)),
                    );
                }
                if t > 0.0 {
                    covered.1 += 1;
                    if v > 0.0 {
                        covered.0 += 1;
                        rel.push(f64::from((v - t).abs() / t));
                    }
                }
            }
        }
        medians.push(matloc_core::metrics::median(&rel).unwrap_or(1.0));
        every.extend(rel);
    }
    every.sort_by(f64::total_cmp);
    let gross = every.iter().filter(|e| **e > 1.0).count();
    eprintln!(
        "cells: 99th percentile relative depth error {:.3}, largest {:.3}, {gross} of {} off by more than 100 %",
        every[(every.len() - 1) * 99 / 100],
        every[every.len() - 1],
        every.len()
    );
    assert_eq!(gross, 0, "gross outliers would stretch a block's scene box");
    let worst = (0..3)
        .map(|k| {
            (bounds[0][k] - true_bounds[0][k])
                .abs()
                .max((bounds[1][k] - true_bounds[1][k]).abs())
        })
        .fold(0.0, f64::max);
    eprintln!("surface bounds {bounds:.1?}, true {true_bounds:.1?}: worst face {worst:.1} m off");
    (
        matloc_core::metrics::median(&medians).unwrap(),
        covered.0 as f64 / covered.1.max(1) as f64,
    )
}

fn forced(choice: SurfaceChoice) -> SurfaceConfig {
    SurfaceConfig {
        source: choice,
        ..SurfaceConfig::default()
    }
}

#[test]
fn plan_follows_the_order_of_preference() {
    let f = fixture();
    let train = f.dataset.split_indices(Split::Train);
    assert_eq!(
        plan(&f.dataset, &train, SurfaceChoice::Auto).unwrap().kind,
        SurfaceKind::DepthMaps
    );
    let mut no_depth = f.dataset.clone();
    for fr in &mut no_depth.frames {
        fr.depth_path = None;
    }
    assert_eq!(
        plan(&no_depth, &train, SurfaceChoice::Auto).unwrap().kind,
        SurfaceKind::PlyPoints
    );
    no_depth.points = None;
    assert_eq!(
        plan(&no_depth, &train, SurfaceChoice::Auto).unwrap().kind,
        SurfaceKind::Triangulated
    );
    let e = plan(&no_depth, &train, SurfaceChoice::Depth)
        .unwrap_err()
        .to_string();
    assert!(e.contains("have no depth file"), "{e}");
    let e = plan(&no_depth, &train, SurfaceChoice::Points)
        .unwrap_err()
        .to_string();
    assert!(e.contains("no point cloud"), "{e}");
}

#[test]
fn colmap_points_with_tracks_give_the_true_depth() {
    let f = fixture();
    let colmap = read_dataset(&f.dir.join("sparse/0")).unwrap();
    assert!(matches!(colmap.points, Some(PointSource::Colmap { .. })));
    // Same frame order as the nerfstudio dataset (names sort the same way); splits from it.
    let mut colmap = colmap;
    for (a, b) in colmap.frames.iter_mut().zip(&f.dataset.frames) {
        assert!(b.image_path.ends_with(&a.image_path));
        a.split = b.split;
        a.depth_path = None;
    }
    let train = colmap.split_indices(Split::Train);
    let s =
        FrameSurfaces::prepare(&colmap, &train, &SurfaceConfig::default(), &|_, _, _| {}).unwrap();
    assert_eq!(s.plan().kind, SurfaceKind::ColmapPoints);
    // Depth maps are read beside the nerfstudio copy for the comparison.
    let mut truth = f.dataset.clone();
    truth.points = colmap.points.clone();
    let s_truth = FrameSurfaces::prepare(
        &truth,
        &train,
        &forced(SurfaceChoice::Points),
        &|_, _, _| {},
    )
    .unwrap();
    let (err, cover) = depth_error(&truth, &s_truth);
    eprintln!("COLMAP points: median relative depth error {err:.4}, coverage {cover:.3}");
    assert!(err < 0.02 && cover > 0.9, "{err} {cover}");
}

#[test]
fn ply_points_without_tracks_give_the_true_depth() {
    let f = fixture();
    let s = FrameSurfaces::prepare(
        &f.dataset,
        &f.dataset.split_indices(Split::Train),
        &forced(SurfaceChoice::Points),
        &|_, _, _| {},
    )
    .unwrap();
    assert_eq!(s.plan().kind, SurfaceKind::PlyPoints);
    let (err, cover) = depth_error(&f.dataset, &s);
    eprintln!("PLY points: median relative depth error {err:.4}, coverage {cover:.3}");
    assert!(err < 0.03 && cover > 0.9, "{err} {cover}");
}

/// At `tiny`'s 160×120 one pixel is ~0.4° of view, so points carry a few per cent of depth
/// noise; what matters for a surface is that there are no gross outliers.
#[test]
fn triangulated_points_lie_on_the_surface() {
    let f = fixture();
    let train = f.dataset.split_indices(Split::Train);
    let t = std::time::Instant::now();
    let pts = triangulate(&f.dataset, &train, &Default::default(), &|_, _, _| {}).unwrap();
    let secs = t.elapsed().as_secs_f64();
    let by_frame = pts.by_frame.as_ref().unwrap();
    // Every observation against the true depth at its projection.
    let mut rel = Vec::new();
    let mut per_frame = Vec::new();
    for &i in &train {
        let fr = &f.dataset.frames[i];
        let truth: Image<f32> = load_frame_depth(&f.dataset, fr, 1).unwrap().unwrap();
        per_frame.push(by_frame[i].len() as f64);
        for &k in &by_frame[i] {
            let pc = fr.cam_from_world * pts.xyz[k as usize];
            let px = fr.camera.project(&pc.coords).unwrap();
            let z = f64::from(truth.data()[px.y as usize * truth.width() + px.x as usize]);
            rel.push((pc.z - z).abs() / z);
        }
    }
    rel.sort_by(f64::total_cmp);
    let q = |p: f64| rel[((rel.len() - 1) as f64 * p) as usize];
    let med = matloc_core::metrics::median(&per_frame).unwrap();
    eprintln!(
        "triangulated {} points in {secs:.2} s, median {med} per frame; relative depth error \
         of observations: median {:.4}, 90 % {:.4}, 98 % {:.4}",
        pts.len(),
        q(0.5),
        q(0.9),
        q(0.98)
    );
    assert!(med >= 30.0 && q(0.5) < 0.02 && q(0.9) < 0.06 && q(0.98) < 0.15);
    // And as a surface.
    let mut no_depth = f.dataset.clone();
    no_depth.points = None;
    let s = FrameSurfaces::prepare(
        &no_depth,
        &train,
        &forced(SurfaceChoice::Triangulate),
        &|_, _, _| {},
    )
    .unwrap();
    let (err, cover) = depth_error(&f.dataset, &s);
    eprintln!("triangulated surface: median relative depth error {err:.4}, coverage {cover:.3}");
    assert!(err < 0.05 && cover > 0.8, "{err} {cover}");
}

/// Points refined with the poses fixed (`refine_points`) reproject closer to their
/// keypoints than the rays' least-squares points, and lie on the true surface at least as
/// well.
#[test]
fn points_refined_with_the_poses_fixed_fit_their_keypoints_better() {
    let f = fixture();
    let train = f.dataset.split_indices(Split::Train);
    let run = |refine_points: bool| {
        let config = matloc_surface::TriangulateConfig {
            refine_points,
            ..Default::default()
        };
        let tracks = matloc_surface::triangulate::triangulate_tracks(
            &f.dataset,
            &train,
            &config,
            &|_, _, _| {},
        )
        .unwrap();
        let (mut reprojection, mut depth) = (Vec::new(), Vec::new());
        for (x, obs) in tracks.xyz.iter().zip(&tracks.observations) {
            for &(img, k) in obs {
                let im = &tracks.images[img as usize];
                let fr = &f.dataset.frames[im.frame];
                let px = im.camera.project_world(&fr.cam_from_world, x).unwrap();
                reprojection.push((px - im.pixels[k as usize]).norm());
                let truth: Image<f32> = load_frame_depth(&f.dataset, fr, 1).unwrap().unwrap();
                let pc = fr.cam_from_world * x;
                let at = fr.camera.project(&pc.coords).unwrap();
                let z = f64::from(truth.data()[at.y as usize * truth.width() + at.x as usize]);
                depth.push((pc.z - z).abs() / z);
            }
        }
        let mean = reprojection.iter().sum::<f64>() / reprojection.len() as f64;
        (mean, matloc_core::metrics::median(&depth).unwrap())
    };
    let (plain, refined) = (run(false), run(true));
    eprintln!(
        "mean reprojection error {:.3} → {:.3} px, median relative depth error {:.4} → {:.4}",
        plain.0, refined.0, plain.1, refined.1
    );
    assert!(refined.0 < plain.0, "{plain:?} {refined:?}");
    assert!(refined.1 <= plain.1 * 1.05, "{plain:?} {refined:?}");
}

#[test]
fn too_few_points_names_the_frame_and_image() {
    let f = fixture();
    let cfg = SurfaceConfig {
        min_points: 1_000_000,
        ..forced(SurfaceChoice::Points)
    };
    let train = f.dataset.split_indices(Split::Train);
    let s = FrameSurfaces::prepare(&f.dataset, &train, &cfg, &|_, _, _| {}).unwrap();
    let e = s.depth(&f.dataset, train[0]).unwrap_err();
    assert!(matches!(e, SurfaceError::TooFewPoints { .. }));
    let msg = e.to_string();
    assert!(
        msg.contains("frame_") && msg.contains("min_points"),
        "{msg}"
    );
}

#[test]
fn colmap_track_naming_a_missing_image_is_an_error() {
    let f = fixture();
    let dir = f.dir.join("broken_colmap");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    for name in ["cameras.txt", "images.txt"] {
        std::fs::copy(f.dir.join("sparse/0").join(name), dir.join(name)).unwrap();
    }
    std::fs::write(
        dir.join("points3D.txt"),
        "1 0 0 0 128 128 128 0 1 0 9999 0\n",
    )
    .unwrap();
    let e = read_dataset(&dir).unwrap_err().to_string();
    assert!(e.contains("points3D.txt") && e.contains("9999"), "{e}");
}

#[test]
fn a_depth_map_without_a_usable_value_is_named() {
    let f = fixture();
    let dir = f.dir.join("bad_depth");
    std::fs::create_dir_all(&dir).unwrap();
    let mut ds = f.dataset.clone();
    let i = ds.split_indices(Split::Train)[1];
    let path = dir.join("nan.npy");
    let (w, h) = (
        ds.frames[i].camera.width as usize,
        ds.frames[i].camera.height as usize,
    );
    let mut img = Image::<f32>::new(w, h, 1);
    img.data_mut().fill(f32::NAN);
    img.data_mut()[0] = -1.0;
    // Written by hand: the project's writer refuses such values.
    std::fs::write(&path, matloc_data::images::encode_npy_f32(w, h, img.data())).unwrap();
    ds.frames[i].depth_path = Some(path);
    let s = FrameSurfaces::prepare(&ds, &[i], &SurfaceConfig::default(), &|_, _, _| {}).unwrap();
    let e = s.depth(&ds, i).unwrap_err().to_string();
    assert!(
        e.contains("nan.npy") && e.contains("NaN") && e.contains("1 negative"),
        "{e}"
    );
}

/// The `tiny` survey's poses moved and turned as a GPS/IMU would give them (about 0.3 m and
/// 1°): `refine_poses` brings the points' reprojection error down to a third of a pixel and
/// the attitudes back towards the truth.
#[test]
fn gps_level_poses_are_refined_towards_the_truth() {
    use matloc_core::pose::{Pose, camera_center};
    use matloc_surface::bundle::{BundleConfig, refine_poses};
    use nalgebra::{Rotation3, Translation3, UnitQuaternion, Vector3};

    let f = fixture();
    let train = f.dataset.split_indices(Split::Train);
    let mut noisy = f.dataset.clone();
    noisy.points = None;
    // Each axis uniform in ±0.3 m and ±1° (RMS 0.3 m and 1° over the three axes).
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    for &i in &train {
        let w = noisy.frames[i].cam_from_world.inverse();
        let mut u = || rng.random_range(-1.0..1.0);
        let dt = Vector3::new(u(), u(), u()) * 0.3;
        let dr = Rotation3::new(Vector3::new(u(), u(), u()) * 1f64.to_radians());
        noisy.frames[i].cam_from_world = Pose::from_parts(
            Translation3::from(w.translation.vector + dt),
            UnitQuaternion::from_rotation_matrix(&dr) * w.rotation,
        )
        .inverse();
    }
    let triangulate = matloc_surface::TriangulateConfig {
        max_reprojection_px: 8.0,
        ..Default::default()
    };
    let out = refine_poses(
        &noisy,
        &train,
        &triangulate,
        &BundleConfig::default(),
        &|_, _, _| {},
    )
    .unwrap();
    let err = |p: &Pose, i: usize| {
        let t = &f.dataset.frames[i].cam_from_world;
        (
            (camera_center(p) - camera_center(t)).norm(),
            p.rotation.angle_to(&t.rotation).to_degrees(),
        )
    };
    let mean = |v: &[(f64, f64)], r: bool| {
        v.iter().map(|e| if r { e.1 } else { e.0 }).sum::<f64>() / v.len() as f64
    };
    let before: Vec<(f64, f64)> = out
        .frames
        .iter()
        .map(|&i| err(&noisy.frames[i].cam_from_world, i))
        .collect();
    let after: Vec<(f64, f64)> = out
        .frames
        .iter()
        .zip(&out.poses)
        .map(|(&i, p)| err(p, i))
        .collect();
    eprintln!(
        "{} poses, {} points: reprojection {:.2} → {:.2} px; mean error {:.3} m {:.3}° → {:.3} m \
         {:.3}°",
        out.poses.len(),
        out.points,
        out.median_px.0,
        out.median_px.1,
        mean(&before, false),
        mean(&before, true),
        mean(&after, false),
        mean(&after, true)
    );
    assert_eq!(out.frames.len(), train.len());
    assert!(
        out.median_px.0 > 1.0 && out.median_px.1 < 0.5,
        "{:?}",
        out.median_px
    );
    // 160 × 120 images 30 m up pin a turn and a shift of each camera only together (0.3° is
    // 0.16 m there): the attitudes come closer and the positions stay within that trade.
    assert!(mean(&after, true) < 0.8 * mean(&before, true));
    assert!(mean(&after, false) < 1.5 * mean(&before, false));
}
