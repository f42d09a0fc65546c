//! What a final alignment against the NeRF's rendered colour and depth does to MatLoc's poses:
//! textured patches of a view rendered at MatLoc's pose are found in the query by normalised
//! cross-correlation, lifted by the rendered depth and the pose solved again.
//!
//!     cargo run --release -p matloc-research --example matloc_refine_study -- MAP DATA

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::pose::camera_center;
use matloc_data::{Split, read_dataset};
use matloc_keypoints::GrayImage;
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::{Method, MethodOptions, NerfReferences, localize_with};
use matloc_pnp::{LoRansacPnp, PnpInput, PnpOptions, PoseSolver};
use matloc_structure::ReferenceRenderer;
use nalgebra::{Point2, Point3, Vector3};
use rand::SeedableRng;

fn env<T: std::str::FromStr>(k: &str, d: T) -> T {
    std::env::var(k)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(d)
}

fn patch(img: &GrayImage, cx: isize, cy: isize, half: isize) -> Option<Vec<f32>> {
    let (w, h) = (img.width() as isize, img.height() as isize);
    if cx - half < 0 || cy - half < 0 || cx + half >= w || cy + half >= h {
        return None;
    }
    let mut v = Vec::new();
    for y in cy - half..=cy + half {
        for x in cx - half..=cx + half {
            v.push(img.at(x as usize, y as usize));
        }
    }
    let n = v.len() as f32;
    let mean = v.iter().sum::<f32>() / n;
    v.iter_mut().for_each(|a| *a -= mean);
    let norm = v.iter().map(|a| a * a).sum::<f32>().sqrt();
    (norm / n.sqrt() >= 0.02).then(|| {
        v.iter_mut().for_each(|a| *a /= norm);
        v
    })
}

/// One pass: render at `pose`, correspondences by ZNCC search within `search` px, PnP.
fn pass(
    refs: &NerfReferences<'_>,
    query: &GrayImage,
    camera: &matloc_core::Camera,
    pose: &matloc_core::Pose,
    search: isize,
) -> Option<(matloc_core::Pose, usize, usize)> {
    let step: isize = env("STEP", 6);
    let half: isize = env("HALF", 6);
    let blur: f32 = env("BLUR", 1.0);
    let min_zncc: f32 = env("ZNCC", 0.8);
    let c = camera_center(pose);
    let look = c + pose.inverse().rotation * Vector3::z() * 25.0;
    let reference = refs.render_reference(camera, pose, &look);
    if reference.is_none() && std::env::var("DBG").is_ok() {
        eprintln!("  no render");
    }
    let reference = reference?;
    let render = GrayImage::from_image(&reference.image).gaussian_blur(blur);
    let q = query.gaussian_blur(blur);
    let (w, h) = (render.width() as isize, render.height() as isize);
    let world_from_cam = pose.inverse();
    let mut pixels = Vec::new();
    let mut points = Vec::new();
    let mut scores = Vec::new();
    let mut y = half;
    while y + half < h {
        let mut x = half;
        while x + half < w {
            let i = (y * w + x) as usize;
            let z = reference.z_depth[i];
            let ok_depth = reference.accumulation[i] >= 0.5 && z > 0.0 && {
                let mut ok = true;
                for dy in -1..=1isize {
                    for dx in -1..=1isize {
                        let (xx, yy) = ((x + dx).clamp(0, w - 1), (y + dy).clamp(0, h - 1));
                        let d = reference.z_depth[(yy * w + xx) as usize];
                        ok &= (d - z).abs() <= 0.05 * z;
                    }
                }
                ok
            };
            if let (true, Some(r)) = (ok_depth, patch(&render, x, y, half)) {
                let mut scoresgrid =
                    vec![f32::NEG_INFINITY; ((2 * search + 1) * (2 * search + 1)) as usize];
                let mut best = (f32::NEG_INFINITY, 0isize, 0isize);
                for dy in -search..=search {
                    for dx in -search..=search {
                        if let Some(p) = patch(&q, x + dx, y + dy, half) {
                            let s: f32 = r.iter().zip(&p).map(|(a, b)| a * b).sum();
                            scoresgrid[((dy + search) * (2 * search + 1) + dx + search) as usize] =
                                s;
                            if s > best.0 {
                                best = (s, dx, dy);
                            }
                        }
                    }
                }
                let (s, dx, dy) = best;
                if s >= min_zncc && dx.abs() < search && dy.abs() < search {
                    let at = |ax: isize, ay: isize| {
                        scoresgrid[((ay + search) * (2 * search + 1) + ax + search) as usize]
                    };
                    let sub = |m: f32, c0: f32, p: f32| {
                        let d = m - 2.0 * c0 + p;
                        if d < 0.0 && m.is_finite() && p.is_finite() {
                            (0.5 * (m - p) / d).clamp(-0.5, 0.5)
                        } else {
                            0.0
                        }
                    };
                    let fx = sub(at(dx - 1, dy), s, at(dx + 1, dy));
                    let fy = sub(at(dx, dy - 1), s, at(dx, dy + 1));
                    let (u, v) = (x as f64 + 0.5, y as f64 + 0.5);
                    if let Some(b) = camera.unproject(Point2::new(u, v)) {
                        let p_cam = b * (f64::from(z) / b.z);
                        points.push(world_from_cam * Point3::from(p_cam));
                        pixels.push(Point2::new(
                            u + dx as f64 + f64::from(fx),
                            v + dy as f64 + f64::from(fy),
                        ));
                        scores.push(f64::from(s));
                    }
                }
            }
            x += step;
        }
        y += step;
    }
    let mut o = PnpOptions::default();
    o.ransac.max_error_px = env("PX", 2.0);
    let solver = LoRansacPnp::new(o);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let input = PnpInput::new(camera, &pixels, &points).with_scores(&scores);
    let r = solver.solve(&input, &mut rng);
    if std::env::var("DBG").is_ok() {
        eprintln!("  {} corr, {:?}", pixels.len(), r.as_ref().err());
    }
    let r = r.ok()?;
    Some((r.cam_from_world, pixels.len(), r.stats.num_inliers))
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let map = LoadedMap::open(std::path::Path::new(&args[1])).expect("map");
    let dataset = read_dataset(std::path::Path::new(&args[2])).expect("dataset");
    let refs = NerfReferences::new(&map);
    let options = MethodOptions::default();
    let passes: usize = env("PASSES", 3);
    let (mut good0, mut good1) = (0, 0);
    for f in dataset.split(Split::Test) {
        let (image, camera) = matloc_data::images::load_frame_image(&dataset, f, 1).expect("image");
        let name = f.image_path.display().to_string();
        let r =
            localize_with(&map, &Method::Matloc, &name, &image, &camera, &options).expect("loc");
        let err = |p: &matloc_core::Pose| {
            (
                translation_error_m(p, &f.cam_from_world),
                rotation_error_deg(p, &f.cam_from_world),
            )
        };
        let Some(mut pose) = r.cam_from_world else {
            println!("{name:28} refused");
            continue;
        };
        let e0 = err(&pose);
        good0 += usize::from(e0.0 <= 0.25 && e0.1 <= 2.0);
        let (img, cam) = matloc_pipeline::localizer::options::query_at_working_size(
            &image,
            &camera,
            map.options().max_side,
        );
        let query = GrayImage::from_image(&img);
        let t = std::time::Instant::now();
        let mut row = format!("{name:28} matloc {:6.3} m {:5.2}°", e0.0, e0.1);
        let searches = [env("S1", 12isize), env("S2", 4), env("S2", 4)];
        for &s in searches.iter().take(passes) {
            match pass(&refs, &query, &cam, &pose, s) {
                Some((p, n, k)) => {
                    pose = p;
                    let e = err(&p);
                    row += &format!(" | {:6.3} m {:5.2}° {k}/{n}", e.0, e.1);
                }
                None => {
                    row += " | none";
                    break;
                }
            }
        }
        let e1 = err(&pose);
        good1 += usize::from(e1.0 <= 0.25 && e1.1 <= 2.0);
        println!("{row} {:.2}s", t.elapsed().as_secs_f64());
    }
    println!("within 0.25 m/2°: matloc {good0}, aligned {good1}");
}
