//! Tests of the synthetic world: determinism, geometric consistency, survey layout, texture.

use matloc_core::pose::{camera_center, viewing_direction};
use matloc_core::{Camera, Distortion, Image, Pose};
use nalgebra::{Point2, Point3, Vector3};

use super::*;
use matloc_data::Split;

fn tiny() -> (World, SurveyPlan, SynthConfig) {
    let cfg = SynthConfig::preset("tiny").unwrap();
    let (w, p) = generate(&cfg).unwrap();
    (w, p, cfg)
}

#[test]
fn same_seed_same_images_and_poses_other_seed_other_world() {
    let (wa, pa, cfg) = tiny();
    let (wb, pb) = generate(&cfg).unwrap();
    assert_eq!(pa, pb);
    for i in [0, pa.frames.len() - 1] {
        let f = &pa.frames[i];
        let ra = wa.render(&f.camera, &f.cam_from_world, &cfg.render);
        let rb = wb.render(&f.camera, &f.cam_from_world, &cfg.render);
        assert_eq!(ra, rb, "frame {i} differs between two generations");
    }

    let (wc, pc) = generate(&cfg.clone().with_seed(1)).unwrap();
    assert_ne!(pa.frames[0].cam_from_world, pc.frames[0].cam_from_world);
    let f = &pa.frames[pa.frames.len() / 2];
    let ra = wa.render(&f.camera, &f.cam_from_world, &cfg.render);
    let rc = wc.render(&f.camera, &f.cam_from_world, &cfg.render);
    let differing = ra
        .depth
        .data()
        .iter()
        .zip(rc.depth.data())
        .filter(|(a, c)| (*a - *c).abs() > 0.01 * a.max(1.0))
        .count();
    assert!(
        differing > ra.depth.data().len() / 20,
        "seed 1 world looks like seed 0 ({differing} depth pixels differ)"
    );
    let centers = |w: &World| w.buildings.iter().map(|b| b.center).collect::<Vec<_>>();
    assert_ne!(centers(&wa), centers(&wc));
}

/// Depth of `depth` at continuous pixel `(x, y)`: bilinear where the four neighbours agree
/// within 2 % (a smooth surface), else the nearest pixel (at a depth edge).
fn lookup_depth(depth: &Image<f32>, x: f64, y: f64) -> Option<f64> {
    let (w, h) = (depth.width() as i64, depth.height() as i64);
    let nx = x.floor() as i64;
    let ny = y.floor() as i64;
    if nx < 0 || ny < 0 || nx >= w || ny >= h {
        return None;
    }
    let at = |i: i64, j: i64| {
        depth.pixel(i.clamp(0, w - 1) as usize, j.clamp(0, h - 1) as usize)[0] as f64
    };
    let nearest = at(nx, ny);
    let (gx, gy) = (x - 0.5, y - 0.5);
    let (i0, j0) = (gx.floor() as i64, gy.floor() as i64);
    let (fx, fy) = (gx - i0 as f64, gy - j0 as f64);
    let q = [
        at(i0, j0),
        at(i0 + 1, j0),
        at(i0, j0 + 1),
        at(i0 + 1, j0 + 1),
    ];
    let lo = q.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = q.iter().copied().fold(0.0, f64::max);
    if lo > 0.0 && hi - lo < 0.02 * lo {
        Some((q[0] * (1.0 - fx) + q[1] * fx) * (1.0 - fy) + (q[2] * (1.0 - fx) + q[3] * fx) * fy)
    } else {
        Some(nearest)
    }
}

/// Outcome of lifting pixels of view A with their depth and projecting them into view B.
#[derive(Default, Debug)]
struct Agreement {
    /// B's depth agrees within 1 %.
    agree: usize,
    /// B sees something clearly in front of the point (occlusion).
    occluded: usize,
    /// B sees clearly behind the point: a real inconsistency (or a depth-edge pixel).
    behind: usize,
}

/// Lifts every pixel of A with its depth, projects it into B and compares with B's depth.
fn depth_agreement(
    world: &World,
    cam: &Camera,
    a: &Pose,
    b: &Pose,
    opts: &RenderOptions,
) -> Agreement {
    let ra = world.render(cam, a, opts);
    let rb = world.render(cam, b, opts);
    let a_world_from_cam = a.inverse();
    let mut out = Agreement::default();
    for y in 0..cam.height as usize {
        for x in 0..cam.width as usize {
            let z = ra.depth.pixel(x, y)[0] as f64;
            if z <= 0.0 {
                continue;
            }
            let bearing = cam
                .unproject(Point2::new(x as f64 + 0.5, y as f64 + 0.5))
                .unwrap();
            let p_world = a_world_from_cam * Point3::from(bearing * (z / bearing.z));
            let p_b = b * p_world;
            let Some(px) = cam.project(&p_b.coords) else {
                continue;
            };
            if !cam.contains(px) {
                continue;
            }
            let Some(zb) = lookup_depth(&rb.depth, px.x, px.y) else {
                continue;
            };
            if (zb - p_b.z).abs() <= 0.01 * p_b.z {
                out.agree += 1;
            } else if zb < p_b.z {
                out.occluded += 1;
            } else {
                out.behind += 1;
            }
        }
    }
    out
}

#[test]
fn depth_is_consistent_across_views() {
    let (world, plan, cfg) = tiny();
    let cam = plan.frames[0].camera;
    let train = plan
        .frames
        .iter()
        .filter(|f| f.split == Split::Train)
        .count();
    // Consecutive frames on a line, frames two apart, a query view and its neighbour, and two
    // frames of the crossing passes that look at the same ground.
    let nearest_train = |q: usize| {
        (0..train)
            .min_by(|&i, &j| {
                let d = |k: usize| (plan.frames[k].center() - plan.frames[q].center()).norm();
                d(i).total_cmp(&d(j))
            })
            .unwrap()
    };
    let mut pairs = vec![
        (3, 4),
        (10, 11),
        (13, 15),
        (train, nearest_train(train)),
        (train + 5, nearest_train(train + 5)),
    ];
    let look = |k: usize| {
        world
            .raycast(
                &plan.frames[k].center(),
                &plan.frames[k].viewing_direction(),
            )
            .unwrap()
            .point
    };
    let cross = (0..train)
        .filter(|&j| {
            plan.frames[j]
                .viewing_direction()
                .dot(&plan.frames[5].viewing_direction())
                < 0.9
        })
        .min_by(|&i, &j| {
            (look(i) - look(5))
                .norm()
                .total_cmp(&(look(j) - look(5)).norm())
        })
        .unwrap();
    pairs.push((5, cross));
    let mut total = Agreement::default();
    for (i, j) in pairs {
        let r = depth_agreement(
            &world,
            &cam,
            &plan.frames[i].cam_from_world,
            &plan.frames[j].cam_from_world,
            &cfg.render,
        );
        let seen = r.agree + r.occluded + r.behind;
        eprintln!("pair ({i}, {j}): {r:?} of {seen}");
        assert!(
            seen > 2000,
            "pair ({i}, {j}) overlaps in only {seen} pixels"
        );
        // Points not occluded in B must agree; the few that do not are depth-edge pixels.
        assert!(
            r.agree as f64 >= 0.98 * (r.agree + r.behind) as f64,
            "pair ({i}, {j}): {r:?}"
        );
        assert!(
            r.agree as f64 >= 0.6 * seen as f64,
            "pair ({i}, {j}): {r:?}"
        );
        total.agree += r.agree;
        total.occluded += r.occluded;
        total.behind += r.behind;
    }
    let visible = (total.agree + total.behind) as f64;
    let frac = total.agree as f64 / visible;
    let all = total.agree as f64 / (visible + total.occluded as f64);
    eprintln!("overall: {total:?}: {frac:.4} of visible, {all:.4} of all in view agree");
    assert!(
        frac > 0.99,
        "only {frac:.4} of visible lifted pixels agree within 1 %"
    );
    assert!(
        all > 0.85,
        "only {all:.4} of in-view lifted pixels agree within 1 %"
    );
}

#[test]
fn depth_matches_raycast_under_lens_distortion() {
    let (world, plan, cfg) = tiny();
    let f = &plan.frames[7];
    let d = Distortion {
        k1: -0.12,
        k2: 0.03,
        p1: 0.001,
        p2: -0.0005,
        k3: 0.0,
    };
    let cam = Camera::opencv(96, 72, 80.0, 80.0, 48.0, 36.0, d).unwrap();
    let r = world.render(&cam, &f.cam_from_world, &cfg.render);
    let wfc = f.cam_from_world.inverse();
    let origin = camera_center(&f.cam_from_world);
    for y in (0..72).step_by(7) {
        for x in (0..96).step_by(5) {
            let b = cam
                .unproject(Point2::new(x as f64 + 0.5, y as f64 + 0.5))
                .unwrap();
            let hit = world
                .raycast(&origin, &(wfc.rotation * b))
                .expect("oblique view sees ground");
            let z = r.depth.pixel(x, y)[0] as f64;
            assert!(
                (hit.t * b.z - z).abs() < 1e-3 * z,
                "({x}, {y}): {} vs {z}",
                hit.t * b.z
            );
        }
    }
}

#[test]
fn degenerate_cameras_and_poses_do_not_panic() {
    let (world, plan, cfg) = tiny();
    let f = &plan.frames[0];
    let mut cam = f.camera;
    cam.width = 0;
    let r = world.render(&cam, &f.cam_from_world, &cfg.render);
    assert_eq!(r.rgb.data().len(), 0);
    let mut cam = f.camera;
    cam.fx = f64::NAN;
    let r = world.render(&cam, &f.cam_from_world, &cfg.render);
    assert!(r.depth.data().iter().all(|&z| z == 0.0));
    let mut pose = f.cam_from_world;
    pose.translation.vector.x = f64::INFINITY;
    let r = world.render(&f.camera, &pose, &cfg.render);
    assert!(r.depth.data().iter().all(|&z| z == 0.0));
    // Strong distortion: pixels that cannot be undistorted become sky, the rest render.
    let d = Distortion {
        k1: -0.6,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    };
    let wide = Camera::opencv(64, 48, 20.0, 20.0, 32.0, 24.0, d).unwrap();
    let r = world.render(&wide, &f.cam_from_world, &cfg.render);
    assert!(r.rgb.data().iter().all(|v| v.is_finite()));
    assert!(
        world
            .raycast(&Point3::new(f64::NAN, 0.0, 0.0), &Vector3::z())
            .is_none()
    );
}

#[test]
fn raycast_and_height_agree_on_open_ground() {
    let (world, _, _) = tiny();
    let mut checked = 0;
    for k in 0..400 {
        let x = -60.0 + 120.0 * ((k * 37 % 400) as f64 / 400.0);
        let y = -60.0 + 120.0 * ((k * 91 % 400) as f64 / 400.0);
        let o = Point3::new(x, y, 200.0);
        let hit = world.raycast(&o, &Vector3::new(0.0, 0.0, -3.0)).unwrap();
        if matches!(hit.material, Material::Ground | Material::Road) {
            assert!((hit.point.z - world.height_at(x, y)).abs() < 1e-6);
            assert!((hit.t - (200.0 - world.height_at(x, y))).abs() < 1e-6);
            assert!(hit.normal.z > 0.9);
            checked += 1;
        } else {
            assert!(hit.point.z > world.height_at(x, y) - 0.6);
        }
    }
    assert!(checked > 200);
    assert!(
        world
            .raycast(&Point3::new(0.0, 0.0, 50.0), &Vector3::z())
            .is_none()
    );
    assert!(
        world
            .raycast(&Point3::new(0.0, 0.0, 50.0), &Vector3::zeros())
            .is_none()
    );
    let (lo, hi) = world.bounds();
    assert!(lo.x < -40.0 && hi.x > 40.0 && lo.z < hi.z && hi.z > 5.0);
}

#[test]
fn query_views_never_coincide_with_training_views() {
    for name in ["tiny", "small"] {
        let cfg = SynthConfig::preset(name).unwrap();
        let (_, plan) = generate(&cfg).unwrap();
        let train: Vec<_> = plan
            .frames
            .iter()
            .filter(|f| f.split == Split::Train)
            .collect();
        let test: Vec<_> = plan
            .frames
            .iter()
            .filter(|f| f.split == Split::Test)
            .collect();
        assert_eq!(test.len(), cfg.survey.test_views, "{name}");
        for q in &test {
            let closest = train
                .iter()
                .map(|t| (t.center() - q.center()).norm())
                .fold(f64::INFINITY, f64::min);
            assert!(
                closest >= cfg.survey.min_test_train_distance_m,
                "{name}: query {closest} m from a training view"
            );
        }
    }
}

#[test]
fn every_camera_looks_at_the_ground() {
    let (world, plan, cfg) = tiny();
    let alt = cfg.survey.altitude_m;
    for (i, f) in plan.frames.iter().enumerate() {
        let hit = world
            .raycast(&f.center(), &f.viewing_direction())
            .unwrap_or_else(|| panic!("frame {i} looks at the sky"));
        assert!(
            hit.t > 0.3 * alt && hit.t < 2.0 * alt,
            "frame {i}: centre ray hits at {} m",
            hit.t
        );
        let down = -f.viewing_direction().z;
        assert!(down > 0.7, "frame {i} is not looking down ({down})");
    }
    // Two passes, lines alternating: four distinct headings.
    let mut headings: Vec<i64> = plan
        .frames
        .iter()
        .map(|f| {
            let d = f.viewing_direction();
            (d.y.atan2(d.x).to_degrees() / 90.0).round() as i64 & 3
        })
        .collect();
    headings.sort();
    headings.dedup();
    assert_eq!(headings.len(), 4);
}

/// Interval of the footprint of a frame along `axis`, on the plane `z = ground`, using the image's
/// centre column (`column = true`) or centre row.
fn footprint_interval(
    f: &matloc_data::Frame,
    axis: &Vector3<f64>,
    ground: f64,
    column: bool,
) -> (f64, f64) {
    let c = f.camera;
    let (w, h) = (c.width as f64, c.height as f64);
    let ends = if column {
        [(0.5 * w, 0.0), (0.5 * w, h)]
    } else {
        [(0.0, 0.5 * h), (w, 0.5 * h)]
    };
    let wfc = f.cam_from_world.inverse();
    let o = f.center();
    let v: Vec<f64> = ends
        .iter()
        .map(|&(x, y)| {
            let d = wfc.rotation * c.unproject(Point2::new(x, y)).unwrap();
            let p = o + d * ((ground - o.z) / d.z);
            p.coords.dot(axis)
        })
        .collect();
    (v[0].min(v[1]), v[0].max(v[1]))
}

fn overlap((a0, a1): (f64, f64), (b0, b1): (f64, f64)) -> f64 {
    (a1.min(b1) - a0.max(b0)).max(0.0) / (0.5 * ((a1 - a0) + (b1 - b0)))
}

#[test]
fn consecutive_frames_overlap_as_configured() {
    for name in ["tiny", "small"] {
        let cfg = SynthConfig::preset(name).unwrap();
        let (world, plan) = generate(&cfg).unwrap();
        let train: Vec<usize> = (0..plan.frames.len())
            .filter(|&i| plan.frames[i].split == Split::Train)
            .collect();
        let ground = 0.5 * (world.terrain.hmin + world.terrain.hmax);
        let mut forward = Vec::new();
        let mut side = Vec::new();
        for w in train.windows(2) {
            let (a, b) = (&plan.frames[w[0]], &plan.frames[w[1]]);
            let dir = viewing_direction(&a.cam_from_world);
            let heading = Vector3::new(dir.x, dir.y, 0.0).normalize();
            if plan.line[w[0]] == plan.line[w[1]] {
                forward.push(overlap(
                    footprint_interval(a, &heading, ground, true),
                    footprint_interval(b, &heading, ground, true),
                ));
            }
        }
        // Side overlap: the frame of the next line nearest across the track.
        for &i in &train {
            let a = &plan.frames[i];
            let dir = a.viewing_direction();
            let heading = Vector3::new(dir.x, dir.y, 0.0).normalize();
            let across = Vector3::new(heading.y, -heading.x, 0.0);
            let next = train
                .iter()
                .filter(|&&j| plan.line[j] == plan.line[i] + 1)
                .filter(|&&j| plan.frames[j].viewing_direction().dot(&across).abs() < 0.2)
                .min_by(|&&j, &&k| {
                    let d =
                        |f: &matloc_data::Frame| ((f.center() - a.center()).dot(&heading)).abs();
                    d(&plan.frames[j]).total_cmp(&d(&plan.frames[k]))
                });
            if let Some(&j) = next {
                side.push(overlap(
                    footprint_interval(a, &across, ground, false),
                    footprint_interval(&plan.frames[j], &across, ground, false),
                ));
            }
        }
        assert!(forward.len() > 10 && side.len() > 10, "{name}");
        for (what, list, want) in [
            ("forward", &forward, cfg.survey.forward_overlap),
            ("side", &side, cfg.survey.side_overlap),
        ] {
            let (lo, hi) = list
                .iter()
                .fold((1.0f64, 0.0f64), |(l, h), &v| (l.min(v), h.max(v)));
            eprintln!("{name} {what} overlap: {lo:.3}..{hi:.3} (configured {want})");
            assert!(
                lo > want - 0.08 && hi < want + 0.08,
                "{name} {what} overlap {lo:.3}..{hi:.3} vs {want}"
            );
        }
    }
}

#[test]
fn images_are_richly_textured() {
    let (world, plan, cfg) = tiny();
    for i in [0, 9, 17, 30, plan.frames.len() - 1] {
        let f = &plan.frames[i];
        let r = world.render(&f.camera, &f.cam_from_world, &cfg.render);
        let (w, h) = (r.rgb.width(), r.rgb.height());
        let lum = |x: usize, y: usize| {
            let p = r.rgb.pixel(x, y);
            0.3 * p[0] + 0.59 * p[1] + 0.11 * p[2]
        };
        let mut grad = 0.0;
        for y in 0..h - 1 {
            for x in 0..w - 1 {
                grad += (lum(x + 1, y) - lum(x, y)).abs() + (lum(x, y + 1) - lum(x, y)).abs();
            }
        }
        let grad = grad / ((w - 1) * (h - 1)) as f32;
        let sky = r.depth.data().iter().filter(|&&z| z == 0.0).count();
        // Flat blocks: 8×8 pixel blocks whose luminance barely varies.
        let (mut flat, mut blocks) = (0, 0);
        for by in (0..h - 7).step_by(8) {
            for bx in (0..w - 7).step_by(8) {
                let v: Vec<f32> = (0..64).map(|k| lum(bx + k % 8, by + k / 8)).collect();
                let m = v.iter().sum::<f32>() / 64.0;
                let sd = (v.iter().map(|x| (x - m) * (x - m)).sum::<f32>() / 64.0).sqrt();
                blocks += 1;
                if sd < 0.01 {
                    flat += 1;
                }
            }
        }
        eprintln!("frame {i}: mean |grad| {grad:.4}, sky {sky}, flat blocks {flat}/{blocks}");
        assert!(grad > 0.02, "frame {i}: mean gradient {grad}");
        assert_eq!(sky, 0, "frame {i} sees sky");
        assert!(
            flat * 10 < blocks,
            "frame {i}: {flat}/{blocks} flat 8x8 blocks"
        );
    }
}

#[test]
fn preset_sizes_match_their_purpose() {
    for (name, train_range, tests, size) in [
        ("tiny", 40..=60, 10, (160, 120)),
        ("small", 150..=250, 30, (320, 240)),
        ("rubble", 200..=600, 40, (320, 240)),
        ("building", 200..=600, 40, (320, 240)),
    ] {
        let cfg = SynthConfig::preset(name).unwrap();
        let (world, plan) = generate(&cfg).unwrap();
        let train = plan
            .frames
            .iter()
            .filter(|f| f.split == Split::Train)
            .count();
        assert!(
            train_range.contains(&train),
            "{name}: {train} training views"
        );
        assert_eq!(plan.frames.len() - train, tests, "{name}");
        let c = plan.frames[0].camera;
        assert_eq!((c.width, c.height), size, "{name}");
        let (lo, hi) = world.bounds();
        assert!(hi.x - lo.x >= cfg.world.extent_m, "{name}");
        assert!(world.building_count() > 0, "{name}");
    }
}

#[test]
fn presets_and_config_errors() {
    for name in PRESET_NAMES {
        let cfg = SynthConfig::preset(name).unwrap();
        cfg.validate().unwrap();
        assert_eq!(cfg.preset, name);
        let json = serde_json::to_string(&cfg).unwrap();
        assert_eq!(serde_json::from_str::<SynthConfig>(&json).unwrap(), cfg);
    }
    let err = SynthConfig::preset("huge").unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, SynthError::UnknownPreset { .. }));
    assert!(
        msg.contains("huge") && msg.contains("tiny") && msg.contains("building"),
        "{msg}"
    );
    let partial: SynthConfig =
        serde_json::from_str(r#"{"seed": 5, "survey": {"width": 64}}"#).unwrap();
    assert_eq!(
        (partial.seed, partial.survey.width, partial.survey.height),
        (5, 64, 240)
    );

    let mut bad = SynthConfig::preset("tiny").unwrap();
    bad.survey.pitch_deg = 70.0;
    assert!(matches!(
        generate(&bad),
        Err(SynthError::InvalidConfig {
            field: "survey.pitch_deg",
            ..
        })
    ));
    let mut bad = SynthConfig::preset("tiny").unwrap();
    bad.world.extent_m = f64::NAN;
    assert!(matches!(
        generate(&bad),
        Err(SynthError::InvalidConfig {
            field: "world.extent_m",
            ..
        })
    ));
    let mut bad = SynthConfig::preset("tiny").unwrap();
    bad.survey.altitude_m = 4.0;
    bad.world.building_height_m = [10.0, 12.0];
    assert!(matches!(
        generate(&bad),
        Err(SynthError::CameraInsideScene { .. })
    ));
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
                .filter(|f| f.split == Split::Test)
                .count(),
            t.elapsed(),
            plan.geometry
        );
        let n = plan.frames.len();
        for (k, i) in [0, n / 3, n / 2, 2 * n / 3, 9].into_iter().enumerate() {
            let f = &plan.frames[i];
            let t = std::time::Instant::now();
            let r = world.render(&f.camera, &f.cam_from_world, &cfg.render);
            eprintln!("  render {i}: {:?}", t.elapsed());
            let path = std::path::PathBuf::from(format!("/tmp/synth_{name}_{k}.png"));
            write::write_png(&r.rgb, &path).unwrap();
        }
    }
}

/// Timing breakdown of the renderer (`cargo test -- --ignored perf_breakdown --nocapture`).
#[test]
#[ignore]
fn perf_breakdown() {
    for name in ["small", "rubble", "building"] {
        let cfg = SynthConfig::preset(name).unwrap();
        let (world, plan) = generate(&cfg).unwrap();
        let views: Vec<_> = plan
            .frames
            .iter()
            .step_by(plan.frames.len() / 16)
            .take(16)
            .collect();
        for (label, opts) in [
            ("full", cfg.render.clone()),
            (
                "aa2",
                RenderOptions {
                    edge_samples: 2,
                    ..cfg.render.clone()
                },
            ),
            (
                "no-aa",
                RenderOptions {
                    edge_samples: 1,
                    ..cfg.render.clone()
                },
            ),
            (
                "no-aa-no-shadow",
                RenderOptions {
                    edge_samples: 1,
                    shadows: false,
                    ..cfg.render.clone()
                },
            ),
        ] {
            let t = std::time::Instant::now();
            for f in &views {
                std::hint::black_box(world.render(&f.camera, &f.cam_from_world, &opts));
            }
            let s = t.elapsed().as_secs_f64();
            eprintln!("{name} {label}: {:.1} images/s", views.len() as f64 / s);
        }
    }
}

/// Cost split between ray tracing and shading (`--ignored perf_split --nocapture`).
#[test]
#[ignore]
fn perf_split() {
    let cfg = SynthConfig::preset("small").unwrap();
    let (world, plan) = generate(&cfg).unwrap();
    let f = &plan.frames[plan.frames.len() / 3];
    let wfc = f.cam_from_world.inverse();
    let o = wfc.translation.vector;
    let dirs: Vec<Vector3<f64>> = (0..240)
        .flat_map(|y| (0..320).map(move |x| (x, y)))
        .map(|(x, y)| {
            wfc.rotation
                * f.camera
                    .unproject(Point2::new(x as f64 + 0.5, y as f64 + 0.5))
                    .unwrap()
        })
        .collect();
    let t = std::time::Instant::now();
    let mut hits = Vec::new();
    for d in &dirs {
        hits.push(world.trace(&o, d));
    }
    let trace = t.elapsed();
    let t = std::time::Instant::now();
    let mut terr = 0.0;
    for d in &dirs {
        terr += world
            .terrain
            .intersect(&o, d, f64::INFINITY)
            .map_or(0.0, |h| h.0);
    }
    let terrain = t.elapsed();
    let t = std::time::Instant::now();
    let mut acc = 0.0f32;
    for (d, h) in dirs.iter().zip(&hits) {
        if let Some(h) = h {
            let p = o + d * h.t;
            acc += world.albedo(&p, &h.normal, h.prim, (h.t / f.camera.fx) as f32)[0];
        }
    }
    let albedo = t.elapsed();
    let t = std::time::Instant::now();
    let mut occ = 0;
    for (d, h) in dirs.iter().zip(&hits) {
        if let Some(h) = h {
            let p = o + d * h.t + h.normal * 1e-3;
            let t1 = ((world.top_z + 0.01 - p.z) / world.sun.z).max(0.0);
            occ += usize::from(world.occluded(&p, &world.sun, 1e-6, t1));
        }
    }
    let shadow = t.elapsed();
    eprintln!(
        "76800 rays single-threaded: trace {trace:?} (terrain {terrain:?}), albedo {albedo:?}, shadow {shadow:?} [{terr:.0} {acc:.0} {occ}]"
    );
}

/// Renders 48 views of a preset at 320×240 (`SYNTH_PRESET`, default `small`); run under
/// `/usr/bin/time` to turn CPU seconds into an unloaded-machine throughput estimate.
#[test]
#[ignore]
fn perf_throughput() {
    let name = std::env::var("SYNTH_PRESET").unwrap_or_else(|_| "small".into());
    let cfg = SynthConfig::preset(&name).unwrap();
    let (world, plan) = generate(&cfg).unwrap();
    let views: Vec<_> = plan
        .frames
        .iter()
        .step_by(plan.frames.len() / 48)
        .take(48)
        .collect();
    let t = std::time::Instant::now();
    for f in &views {
        std::hint::black_box(world.render(&f.camera, &f.cam_from_world, &cfg.render));
    }
    let s = t.elapsed().as_secs_f64();
    eprintln!(
        "{name}: {} images in {s:.2} s wall = {:.1} images/s",
        views.len(),
        views.len() as f64 / s
    );
}

/// A turned view keeps looking at the terrain point the survey view looked at (without tilt),
/// from `closer` of the way nearer, at the turned heading; tilt lifts it towards the horizon.
#[test]
fn a_turned_view_looks_at_the_same_ground_point_from_nearer() {
    let (world, plan, _) = tiny();
    let pose = plan.frames[0].cam_from_world;
    let c = camera_center(&pose);
    let dir = viewing_direction(&pose);
    let ground = world.height_at(c.x, c.y);
    let look = c + dir * ((ground - c.z) / dir.z);
    let t = crate::flight::turned_view(&world, &pose, 90.0, 0.25, 0.0).unwrap();
    let (c2, d2) = (camera_center(&t), viewing_direction(&t));
    assert!(((look - c2).norm() - 0.75 * (look - c).norm()).abs() < 1e-9);
    assert!((look - c2).normalize().dot(&d2) > 1.0 - 1e-9);
    // A quarter turn about the vertical: the horizontal heading turns by 90°.
    let (h1, h2) = (
        Vector3::new(dir.x, dir.y, 0.0).normalize(),
        Vector3::new(d2.x, d2.y, 0.0).normalize(),
    );
    assert!(h1.dot(&h2).abs() < 1e-9 && h1.cross(&h2).z > 0.0);
    let tilted = crate::flight::turned_view(&world, &pose, 0.0, 0.0, 20.0).unwrap();
    let d3 = viewing_direction(&tilted);
    assert!(d3.z > dir.z, "tilted {d3:?} vs {dir:?}");
    assert!((d3.angle(&dir).to_degrees() - 20.0).abs() < 1e-6);
}
