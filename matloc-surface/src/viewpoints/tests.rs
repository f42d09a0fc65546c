use matloc_core::pose::{camera_center, viewing_direction};
use proptest::prelude::*;

use super::*;

/// Flat ground at height 0 over `[0, 100]²` with a 20 m tall building over `[40, 60]²`.
fn true_height(x: f64, y: f64) -> f64 {
    if (40.0..=60.0).contains(&x) && (40.0..=60.0).contains(&y) {
        20.0
    } else {
        0.0
    }
}

/// A nadir survey at 30 m on a 10 m grid over `[10, 90]²`; each camera sees the surface on a
/// 1 m lattice within 20 m (horizontally) of the point under it, clipped to `[0, 100]²`.
fn survey() -> (Vec<Point3<f64>>, Vec<Vec<Point3<f64>>>) {
    let mut centres = Vec::new();
    let mut seen = Vec::new();
    for i in 0..9 {
        for j in 0..9 {
            let (cx, cy) = (10.0 + 10.0 * i as f64, 10.0 + 10.0 * j as f64);
            centres.push(Point3::new(cx, cy, 30.0));
            let mut pts = Vec::new();
            for dx in -20..=20 {
                for dy in -20..=20 {
                    let (x, y) = (cx + dx as f64 + 0.5, cy + dy as f64 + 0.5);
                    if (0.0..100.0).contains(&x) && (0.0..100.0).contains(&y) {
                        pts.push(Point3::new(x, y, true_height(x, y)));
                    }
                }
            }
            seen.push(pts);
        }
    }
    (centres, seen)
}

fn camera() -> Camera {
    Camera::from_hfov(64, 48, 60.0).unwrap()
}

/// The surveyed square up to 45 m, split in two blocks.
fn blocks() -> Vec<SceneBox> {
    vec![
        SceneBox {
            min: [0.0, 0.0, 0.0],
            max: [50.0, 100.0, 45.0],
        },
        SceneBox {
            min: [50.0, 0.0, 0.0],
            max: [100.0, 100.0, 45.0],
        },
    ]
}

fn config(seed: u64, per_block: usize) -> VirtualViewsConfig {
    VirtualViewsConfig {
        enabled: true,
        per_block,
        seed,
        ..VirtualViewsConfig::default()
    }
}

fn sample(config: &VirtualViewsConfig, blocks: &[SceneBox]) -> VirtualViews {
    let (centres, seen) = survey();
    let cam = camera();
    let scene = ViewpointScene {
        up: Vector3::z(),
        camera: &cam,
        training_centres: &centres,
        seen: &seen,
        blocks,
    };
    sample_viewpoints(config, &scene).unwrap()
}

fn grid_of(v: &VirtualViews) -> SurfaceGrid {
    let (_, seen) = survey();
    SurfaceGrid::build(GroundFrame::new(Vector3::z()).unwrap(), v.cell_m, &seen).unwrap()
}

/// Every invariant of an accepted pose, as a list of violations.
fn violations(c: &VirtualViewsConfig, v: &VirtualViews, blocks: &[SceneBox]) -> Vec<String> {
    let grid = grid_of(v);
    let mut bad = Vec::new();
    for (k, p) in v.poses.iter().enumerate() {
        let eye = camera_center(&p.cam_from_world);
        let b = &blocks[p.block];
        // Inside the sampled volume: over the block's box, height above the surface under it
        // within the band.
        if !(b.min[0] <= eye.x && eye.x <= b.max[0] && b.min[1] <= eye.y && eye.y <= b.max[1]) {
            bad.push(format!("{k}: centre {eye} outside block {}", p.block));
        }
        // The surface under the camera: its cell, or the cells around it at the grid's edge.
        let under = grid
            .height(eye.x, eye.y)
            .or_else(|| grid.max_height_within(eye.x, eye.y, v.cell_m))
            .unwrap_or(f64::NAN);
        let rel = (eye.z - under) / v.survey_height_m;
        if !(c.altitude_band[0] - 1e-9 <= rel && rel <= c.altitude_band[1] + 1e-9) {
            bad.push(format!(
                "{k}: height {rel:.3}× the survey's, outside the band"
            ));
        }
        // Attitude: the optical axis is +z of the camera, pitched as drawn.
        let d = viewing_direction(&p.cam_from_world);
        let pitch = (-d.z).asin().to_degrees();
        if (pitch - p.pitch_deg).abs() > 1e-6
            || pitch < c.pitch_deg[0] - 1e-6
            || pitch > c.pitch_deg[1] + 1e-6
        {
            bad.push(format!("{k}: pitch {pitch} vs drawn {}", p.pitch_deg));
        }
        // Not inside geometry: the true surface within the clearance radius stays that far
        // below the camera.
        for dx in [-1.0, -0.5, 0.0, 0.5, 1.0] {
            for dy in [-1.0, -0.5, 0.0, 0.5, 1.0] {
                let (x, y) = (
                    eye.x + dx * c.min_clearance_m,
                    eye.y + dy * c.min_clearance_m,
                );
                if eye.z - true_height(x, y) < c.min_clearance_m - 1e-9 {
                    bad.push(format!("{k}: camera {eye} within clearance of ({x}, {y})"));
                }
            }
        }
        // The optical axis meets the true surface at the target, over covered ground.
        let t = p.target;
        // (Cells are marched every half cell and hold their highest point: the target lies
        // at most half a cell below the ground, and no higher than the surface a cell away.)
        let r = v.cell_m;
        let top = [-r, 0.0, r]
            .iter()
            .flat_map(|&dx| [-r, 0.0, r].map(|dy| true_height(t.x + dx, t.y + dy)))
            .fold(f64::MIN, f64::max);
        if t.z > top + 1e-6 || t.z < -0.5 * r - 1e-6 {
            bad.push(format!("{k}: target {t} off the surface"));
        }
        let along = (t - eye).normalize();
        if (along - d).norm() > 1e-6 {
            bad.push(format!("{k}: target {t} not on the optical axis"));
        }
        if grid.views(t.x, t.y) < c.min_views {
            bad.push(format!("{k}: target {t} on ground fewer cameras saw"));
        }
        if p.coverage < c.min_coverage {
            bad.push(format!("{k}: coverage {}", p.coverage));
        }
        // The target projects to the image centre.
        let px = camera().project_world(&p.cam_from_world, &t);
        if px.is_none_or(|px| (px.x - 32.0).abs() > 1e-6 || (px.y - 24.0).abs() > 1e-6) {
            bad.push(format!("{k}: target projects to {px:?}"));
        }
    }
    if v.poses.len() + v.rejected.total() != v.candidates {
        bad.push(format!(
            "{} accepted + {} rejected ≠ {} candidates",
            v.poses.len(),
            v.rejected.total(),
            v.candidates
        ));
    }
    bad
}

#[test]
fn accepted_poses_lie_in_their_block_and_band_clear_of_geometry_over_covered_ground() {
    let c = config(7, 40);
    let v = sample(&c, &blocks());
    assert_eq!(v.poses.len(), 80, "{:?}", v.rejected);
    assert!((v.survey_height_m - 30.0).abs() < 1e-9);
    let bad = violations(&c, &v, &blocks());
    assert!(bad.is_empty(), "{bad:#?}");
}

#[test]
fn the_building_column_holds_no_camera_below_its_roof_plus_clearance() {
    let c = config(3, 200);
    let v = sample(&c, &blocks());
    let over_roof: Vec<_> = v
        .poses
        .iter()
        .map(|p| camera_center(&p.cam_from_world))
        .filter(|e| (38.0..=62.0).contains(&e.x) && (38.0..=62.0).contains(&e.y))
        .collect();
    assert!(
        !over_roof.is_empty(),
        "some cameras are drawn over the roof"
    );
    // Cameras drawn low beside the building are dropped.
    assert!(v.rejected.clearance > 0, "{:?}", v.rejected);
    for e in over_roof {
        assert!(e.z >= 20.0 + c.min_clearance_m, "{e}");
    }
}

#[test]
fn ground_no_training_camera_saw_gives_no_pose_and_counts_why() {
    let c = config(1, 10);
    // A block beside the surveyed square.
    let away = [SceneBox {
        min: [200.0, 200.0, 0.0],
        max: [300.0, 300.0, 45.0],
    }];
    let v = sample(&c, &away);
    assert!(v.poses.is_empty());
    assert_eq!(v.candidates, 10 * c.max_candidates_per_pose);
    assert_eq!(v.rejected.no_ground_below, v.candidates, "{:?}", v.rejected);
    // Seen by one camera only: with two required, the axis or the footprint is uncovered.
    let (centres, seen) = survey();
    let cam = camera();
    let one = [seen[0].clone()];
    let scene = ViewpointScene {
        up: Vector3::z(),
        camera: &cam,
        training_centres: &centres[..1],
        seen: &one,
        blocks: &blocks()[..1],
    };
    let v = sample_viewpoints(&c, &scene).unwrap();
    assert!(v.poses.is_empty());
    assert!(v.rejected.axis_not_covered > 0, "{:?}", v.rejected);
    assert_eq!(v.rejected.total(), v.candidates);
    // Required by one camera, the same scene gives poses.
    let v = sample_viewpoints(
        &VirtualViewsConfig {
            min_views: 1,
            ..c.clone()
        },
        &scene,
    )
    .unwrap();
    assert!(!v.poses.is_empty(), "{:?}", v.rejected);
}

#[test]
fn coverage_is_the_fraction_of_footprint_rays_on_ground_enough_cameras_saw() {
    let c = VirtualViewsConfig {
        min_coverage: 0.9,
        ..config(5, 30)
    };
    let v = sample(&c, &blocks());
    assert!(!v.poses.is_empty(), "{:?}", v.rejected);
    let grid = grid_of(&v);
    let cam = camera();
    let bearings = footprint_bearings(&cam);
    for p in &v.poses {
        let eye = camera_center(&p.cam_from_world);
        let w = p.cam_from_world.inverse();
        let covered = bearings
            .0
            .iter()
            .filter(|b| {
                grid.cast(&eye, &w.transform_vector(b), 1e4)
                    .is_some_and(|q| grid.views(q.x, q.y) >= c.min_views)
            })
            .count();
        let f = covered as f64 / 64.0;
        assert!((f - p.coverage).abs() < 1e-12);
        assert!(f >= 0.9, "{f}");
    }
    // The stricter rule drops footprints the default keeps.
    assert!(v.rejected.low_coverage > 0, "{:?}", v.rejected);
}

#[test]
fn headings_cover_every_quadrant_and_heights_and_pitches_span_their_bands() {
    let c = config(11, 100);
    let v = sample(&c, &blocks());
    let mut quadrants = [0; 4];
    for p in &v.poses {
        quadrants[(p.heading_deg / 90.0) as usize % 4] += 1;
    }
    assert!(quadrants.iter().all(|&n| n >= 10), "{quadrants:?}");
    let rel: Vec<f64> = v.poses.iter().map(|p| p.height_m / 30.0).collect();
    let (lo, hi) = rel
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &r| (a.min(r), b.max(r)));
    assert!(lo < 0.5 && hi > 1.2, "{lo} … {hi}");
    let pitches: Vec<f64> = v.poses.iter().map(|p| p.pitch_deg).collect();
    let (lo, hi) = pitches
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &r| (a.min(r), b.max(r)));
    assert!(lo < 45.0 && hi > 85.0, "{lo} … {hi}");
}

#[test]
fn draws_are_deterministic_from_the_seed() {
    let a = sample(&config(9, 10), &blocks());
    let b = sample(&config(9, 10), &blocks());
    let c = sample(&config(10, 10), &blocks());
    assert_eq!(a, b);
    assert_ne!(a.poses, c.poses);
}

#[test]
fn nadir_poses_keep_the_image_top_towards_the_heading() {
    let frame = GroundFrame::new(Vector3::z()).unwrap();
    let eye = Point3::new(1.0, 2.0, 30.0);
    let pose = heading_pitch_pose(&frame, &eye, 90f64.to_radians(), 90f64.to_radians());
    assert!((viewing_direction(&pose) + Vector3::z()).norm() < 1e-12);
    // A ground point north (+y, heading 90°) of the point under the camera is in the upper half.
    let px = camera()
        .project_world(&pose, &Point3::new(1.0, 12.0, 0.0))
        .unwrap();
    assert!(px.y < 24.0 && (px.x - 32.0).abs() < 1e-9, "{px}");
    assert!((camera_center(&pose) - eye).norm() < 1e-9);
    // Level (pitch → 0) towards +x: image right is −y, image down is −z.
    let pose = heading_pitch_pose(&frame, &eye, 0.0, 1e-9);
    let r = pose.rotation.to_rotation_matrix();
    assert!((r.matrix().row(0).transpose() + Vector3::y()).norm() < 1e-6);
    assert!((r.matrix().row(1).transpose() + Vector3::z()).norm() < 1e-6);
}

fn bounding_box<'a>(points: impl Iterator<Item = &'a Point3<f64>>) -> SceneBox {
    let mut b = SceneBox {
        min: [f64::MAX; 3],
        max: [f64::MIN; 3],
    };
    for p in points {
        for a in 0..3 {
            b.min[a] = b.min[a].min(p[a]);
            b.max[a] = b.max[a].max(p[a]);
        }
    }
    b
}

#[test]
fn a_tilted_up_axis_gives_the_same_sampler() {
    // The survey seen in a world rotated 30° about x: poses come back rotated the same way.
    let rot = Rotation3::from_axis_angle(&Vector3::x_axis(), 30f64.to_radians());
    let (centres, seen) = survey();
    let centres_r: Vec<_> = centres.iter().map(|p| rot * p).collect();
    let seen_r: Vec<Vec<_>> = seen
        .iter()
        .map(|s| s.iter().map(|p| rot * p).collect())
        .collect();
    let cam = camera();
    let scene = ViewpointScene {
        up: rot * Vector3::z(),
        camera: &cam,
        training_centres: &centres_r,
        seen: &seen_r,
        blocks: &[bounding_box(seen_r.iter().flatten().chain(&centres_r))],
    };
    let v = sample_viewpoints(&config(2, 20), &scene).unwrap();
    assert_eq!(v.poses.len(), 20, "{:?}", v.rejected);
    for p in &v.poses {
        let eye = rot.inverse() * camera_center(&p.cam_from_world);
        let d = rot.inverse() * viewing_direction(&p.cam_from_world);
        assert!(eye.z - true_height(eye.x, eye.y) >= 2.0, "{eye}");
        assert!(((-d.z).asin().to_degrees() - p.pitch_deg).abs() < 1e-6);
    }
}

#[test]
fn the_default_is_off_and_bad_fields_are_named() {
    let d = VirtualViewsConfig::default();
    assert!(!d.enabled);
    assert!(d.is_default());
    assert!(d.problems().is_empty());
    let bad = VirtualViewsConfig {
        altitude_band: [1.3, 0.4],
        pitch_deg: [20.0, 120.0],
        min_clearance_m: f64::NAN,
        min_views: 0,
        min_coverage: 1.5,
        cell_m: -1.0,
        max_candidates_per_pose: 0,
        ..d.clone()
    };
    let fields: Vec<&str> = bad.problems().iter().map(|p| p.field).collect();
    assert_eq!(
        fields,
        [
            "virtual.altitude_band",
            "virtual.pitch_deg",
            "virtual.min_clearance_m",
            "virtual.min_views",
            "virtual.min_coverage",
            "virtual.cell_m",
            "virtual.max_candidates_per_pose",
        ]
    );
    let e = bad.validate().unwrap_err().to_string();
    assert!(e.contains("virtual.altitude_band"), "{e}");
    // The sampler refuses it instead of drawing.
    let (centres, seen) = survey();
    let cam = camera();
    let scene = ViewpointScene {
        up: Vector3::z(),
        camera: &cam,
        training_centres: &centres,
        seen: &seen,
        blocks: &blocks(),
    };
    assert!(sample_viewpoints(&bad, &scene).is_err());
    let no_up = ViewpointScene {
        up: Vector3::zeros(),
        ..scene
    };
    assert!(sample_viewpoints(&d, &no_up).is_err());
    let nothing: Vec<Vec<Point3<f64>>> = vec![Vec::new(); centres.len()];
    let blind = ViewpointScene {
        up: Vector3::z(),
        camera: &cam,
        training_centres: &centres,
        seen: &nothing,
        blocks: &blocks(),
    };
    assert!(matches!(
        sample_viewpoints(&d, &blind),
        Err(SurfaceError::NoSurfaceSeen)
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]

    /// Any seed and band give poses that obey every invariant.
    #[test]
    fn any_seed_gives_poses_that_obey_the_invariants(
        seed in any::<u64>(),
        lo in 0.2f64..1.0,
        extra in 0.0f64..1.0,
        pitch_lo in 10.0f64..80.0,
    ) {
        let c = VirtualViewsConfig {
            altitude_band: [lo, lo + extra],
            pitch_deg: [pitch_lo, 90.0],
            ..config(seed, 8)
        };
        let v = sample(&c, &blocks());
        let bad = violations(&c, &v, &blocks());
        prop_assert!(bad.is_empty(), "{:#?}", bad);
    }
}

/// On the `tiny` synthetic world, with the surface each training camera sees (exact ray casts
/// on a grid of every 8th pixel): the accepted cameras are clear of the true geometry (nothing
/// within the clearance below them, nothing above them) and their optical axis first meets the
/// world near the sampler's target.
#[test]
fn on_the_tiny_world_cameras_are_clear_of_the_true_geometry() {
    use matloc_data::Split;
    let (world, plan) =
        matloc_synth::generate(&matloc_synth::SynthConfig::preset("tiny").unwrap()).unwrap();
    let train: Vec<_> = plan
        .frames
        .iter()
        .filter(|f| f.split == Split::Train)
        .collect();
    let seen: Vec<Vec<Point3<f64>>> = train
        .iter()
        .map(|f| {
            let w = f.cam_from_world.inverse();
            let eye = f.center();
            let mut pts = Vec::new();
            for r in (4..f.camera.height).step_by(8) {
                for c in (4..f.camera.width).step_by(8) {
                    let b = f.camera.unproject(Point2::new(c as f64, r as f64)).unwrap();
                    if let Some(h) = world.raycast(&eye, &w.transform_vector(&b)) {
                        pts.push(h.point);
                    }
                }
            }
            pts
        })
        .collect();
    let centres: Vec<_> = train.iter().map(|f| f.center()).collect();
    let boxed = bounding_box(seen.iter().flatten().chain(&centres));
    let cam = train[0].camera;
    let scene = ViewpointScene {
        up: Vector3::z(),
        camera: &cam,
        training_centres: &centres,
        seen: &seen,
        blocks: &[boxed],
    };
    let c = config(0, 64);
    let v = sample_viewpoints(&c, &scene).unwrap();
    eprintln!(
        "tiny: {} training views, survey height {:.1} m, cell {:.1} m: {} candidates, {} accepted, \
         rejected {:?}",
        train.len(),
        v.survey_height_m,
        v.cell_m,
        v.candidates,
        v.poses.len(),
        v.rejected
    );
    assert!(v.poses.len() >= 48, "{:?}", v.rejected);
    let mut near = 0;
    for p in &v.poses {
        let eye = camera_center(&p.cam_from_world);
        for d in [-Vector3::z(), Vector3::z()] {
            if let Some(h) = world.raycast(&eye, &d) {
                assert!(
                    d.z < 0.0 && h.t >= c.min_clearance_m,
                    "camera {eye}: surface {:.2} m along {d}",
                    h.t
                );
            }
        }
        // The height field holds each cell's highest point, so the axis may stop on it short
        // of the true surface (a roof edge or crown the exact ray passes), never beyond it.
        let hit = world
            .raycast(&eye, &viewing_direction(&p.cam_from_world))
            .expect("the optical axis meets the world");
        let to_target = (p.target - eye).norm();
        assert!(
            hit.t >= to_target - v.cell_m,
            "camera {eye}: axis meets the world at {} before {}",
            hit.point,
            p.target
        );
        near += usize::from((hit.point - p.target).norm() <= 2.0 * v.cell_m);
    }
    eprintln!(
        "tiny: {near} of {} targets within two cells of the true hit",
        v.poses.len()
    );
    assert!(near * 10 >= v.poses.len() * 8, "{near}");
}

#[test]
fn depth_maps_lift_to_the_surface_and_a_looking_down_survey_gives_up() {
    let frame = GroundFrame::new(Vector3::z()).unwrap();
    let eye = Point3::new(5.0, -3.0, 30.0);
    let pose = heading_pitch_pose(&frame, &eye, 0.3, 90f64.to_radians());
    // A 16 × 12 map (a quarter of the 64 × 48 image) of flat ground 30 m below, one hole.
    let mut depth = vec![30.0f32; 16 * 12];
    depth[5] = 0.0;
    let depth = matloc_core::Image::from_vec(16, 12, 1, depth).unwrap();
    let pts = points_from_depth(&camera(), &pose, &depth, 1);
    assert_eq!(pts.len(), 16 * 12 - 1);
    for p in &pts {
        assert!(p.z.abs() < 1e-9, "{p}");
        // Each point projects back inside the image.
        let px = camera().project_world(&pose, p).unwrap();
        assert!(camera().contains(px), "{px}");
    }
    assert_eq!(points_from_depth(&camera(), &pose, &depth, 4).len(), 4 * 3);
    // Nadir and 30° oblique views at four headings: up is +z.
    let poses: Vec<Pose> = (0..4)
        .flat_map(|k| {
            let h = f64::from(k) * std::f64::consts::FRAC_PI_2;
            [90.0f64, 60.0].map(|p| heading_pitch_pose(&frame, &eye, h, p.to_radians()))
        })
        .collect();
    let up = up_from_views(&poses).unwrap();
    assert!((up - Vector3::z()).norm() < 1e-9, "{up}");
    assert!(up_from_views(&[]).is_none());
}

#[test]
fn a_nadir_footprint_lands_on_the_cells_under_the_camera() {
    let (_, seen) = survey();
    let frame = GroundFrame::new(Vector3::z()).unwrap();
    let grid = SurfaceGrid::build(frame, 2.0, &seen).unwrap();
    let cam = camera();
    // 20 m above flat ground at (20, 20), nadir: a 60° field of view spans ±11.5 m in x.
    let pose = heading_pitch_pose(
        &frame,
        &Point3::new(20.0, 20.0, 20.0),
        0.0,
        90_f64.to_radians(),
    );
    let cells = footprint_cells(&grid, &cam, &pose);
    assert_eq!(cells.len(), 64, "every ray meets the ground");
    // The grid starts at the lowest point, (0.5, 0.5); 50 cells a row.
    let (o, _) = grid.extent();
    for &c in &cells {
        let u = o[0] + (c % 50) as f64 * 2.0 + 1.0;
        let v = o[1] + (c / 50) as f64 * 2.0 + 1.0;
        assert!(
            (u - 20.0).abs() <= 13.0 && (v - 20.0).abs() <= 13.0,
            "cell at ({u}, {v})"
        );
    }
    // The cells a camera saw: sorted, unique, and the footprint's own cells among the camera's
    // under the same spot.
    // Camera (i, j) = (1, 1) of the survey stands over (20, 20).
    let under = grid.cells_of(&seen[10]);
    assert!(under.windows(2).all(|w| w[0] < w[1]));
    assert!(cells.iter().all(|c| under.binary_search(c).is_ok()));
    // Looking at the sky: the axis leaves the grid and no ray meets anything.
    let up = heading_pitch_pose(
        &frame,
        &Point3::new(20.0, 20.0, 20.0),
        0.0,
        -60_f64.to_radians(),
    );
    assert!(footprint_cells(&grid, &cam, &up).is_empty());
    assert!(grid.reach(&Point3::new(20.0, 20.0, 20.0)) >= 80_f64.hypot(80.0) + 20.0);
}
