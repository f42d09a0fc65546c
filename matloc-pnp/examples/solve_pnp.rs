//! matloc-pnp on its own: camera pose from a text file of 2D–3D matches.
//!
//! `cargo run --release -p matloc-pnp --example solve_pnp -- MATCHES W H FX FY CX CY [K1 K2 P1 P2]`
//!
//! `MATCHES` holds one match per line, `u v X Y Z` (pixel with centres at +0.5, world point in
//! metres; `#` starts a comment). Prints `cam_from_world` (OpenCV camera axes), the inliers and
//! the solver statistics. Without arguments it solves a generated aerial scene with 30 %
//! outliers instead.

use matloc_core::{Camera, Distortion, Pose};
use matloc_pnp::{LoRansacPnp, PnpInput, PoseSolver, synthetic};
use nalgebra::{Point2, Point3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Pixels and world points of the matches, in file order.
type Matches = (Vec<Point2<f64>>, Vec<Point3<f64>>);

fn read_matches(path: &str) -> Result<Matches, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{path}: {e}"))?;
    let (mut pixels, mut points) = (Vec::new(), Vec::new());
    for (i, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let v: Vec<f64> = line
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|e| format!("{path}:{}: {e}", i + 1))?;
        if v.len() != 5 {
            return Err(format!("{path}:{}: expected `u v X Y Z`", i + 1));
        }
        pixels.push(Point2::new(v[0], v[1]));
        points.push(Point3::new(v[2], v[3], v[4]));
    }
    Ok((pixels, points))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let (camera, pixels, points, truth): (Camera, _, _, Option<Pose>) = if args.is_empty() {
        let camera = Camera::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0)?;
        let pose = synthetic::aerial_pose(&mut rng);
        let scene = synthetic::make_scene(&mut rng, camera, pose, 300, 0.3, 0.5, false);
        (camera, scene.pixels, scene.points_world, Some(pose))
    } else if args.len() == 7 || args.len() == 11 {
        let n: Vec<f64> = args[1..]
            .iter()
            .map(|a| a.parse())
            .collect::<Result<_, _>>()?;
        let mut camera = Camera::pinhole(n[0] as u32, n[1] as u32, n[2], n[3], n[4], n[5])?;
        if n.len() == 10 {
            camera.distortion = Distortion {
                k1: n[6],
                k2: n[7],
                p1: n[8],
                p2: n[9],
                k3: 0.0,
            };
        }
        let (pixels, points) = read_matches(&args[0])?;
        (camera, pixels, points, None)
    } else {
        eprintln!("usage: solve_pnp [MATCHES W H FX FY CX CY [K1 K2 P1 P2]]");
        std::process::exit(2);
    };
    let result =
        LoRansacPnp::default().solve(&PnpInput::new(&camera, &pixels, &points), &mut rng)?;
    let t = result.cam_from_world.translation.vector;
    let q = result.cam_from_world.rotation.quaternion();
    println!(
        "cam_from_world: t = [{:.4}, {:.4}, {:.4}], q (w, x, y, z) = [{:.6}, {:.6}, {:.6}, {:.6}]",
        t.x, t.y, t.z, q.w, q.i, q.j, q.k
    );
    println!(
        "{} of {} matches are inliers; {:?}",
        result.stats.num_inliers,
        pixels.len(),
        result.stats
    );
    if let Some(truth) = truth {
        let (t_err, r_err) = synthetic::pose_errors(&result.cam_from_world, &truth);
        println!("error against the generated pose: {t_err:.4} m, {r_err:.4}°");
    }
    Ok(())
}
