//! Points from posed images alone, the surface of last resort: ORB keypoints of every image are
//! matched with its nearest neighbours (by camera centre, among images looking the same way
//! within `max_view_angle_deg`); each match is triangulated from the known poses (midpoint of
//! the two rays) and kept when both rays meet at `min_angle_deg` or more in front of both
//! cameras and reproject within `max_reprojection_px`. Matches sharing a keypoint join into
//! tracks (union-find); each track is re-solved over all its rays (least squares), its
//! outlying observations dropped, then (`refine_points`) moved to minimise its reprojection
//! errors with the poses fixed (structure-only bundle adjustment), the observations it then
//! leaves beyond the gate dropped, and kept with `min_track_len` or more views. This is
//! COLMAP's `point_triangulator` idea on the project's own keypoints.

use matloc_core::Camera;
use matloc_core::pose::{Pose, camera_center, viewing_direction};
use matloc_data::Dataset;
use matloc_data::images::load_frame_image;
use matloc_data::points::SparsePoints;
use matloc_keypoints::{
    Descriptor, DescriptorKind, GradientDescriptor, GrayImage, KeypointConfig, MatchConfig,
    detect_and_describe_both, match_descriptors,
};
use nalgebra::{Matrix3, Point2, Point3, Vector3};
use rayon::prelude::*;

use crate::config::TriangulateConfig;
use crate::reprojection::{PointView, refine_point};

/// Huber width of the points' structure-only refinement, pixels.
const REFINE_HUBER_PX: f64 = 1.0;
/// Most Levenberg–Marquardt steps of a point's refinement.
const REFINE_ITERATIONS: usize = 10;
use crate::error::SurfaceError;

/// One image's keypoints, ready to triangulate.
struct Features {
    frame: usize,
    camera: Camera,
    cam_from_world: Pose,
    center: Point3<f64>,
    pixels: Vec<Point2<f64>>,
    /// Unit ray directions, world frame.
    rays: Vec<Vector3<f64>>,
    descriptors: Vec<Descriptor>,
    gradients: Vec<GradientDescriptor>,
    /// Gray values at the detection size, 8-bit, row-major.
    gray: Vec<u8>,
}

/// Progress of triangulation: `(phase, done, total)` with phase `"detect"` or `"match"`.
pub type TriangulateProgress<'a> = &'a (dyn Fn(&str, usize, usize) + Sync);

/// One image's keypoints as triangulation saw them (at the detection size).
#[derive(Clone, Debug)]
pub struct ImageKeypoints {
    /// Dataset frame.
    pub frame: usize,
    /// The camera at the detection size.
    pub camera: Camera,
    /// Keypoint positions, pixels.
    pub pixels: Vec<Point2<f64>>,
    /// Their binary descriptors (what pairs of training images are matched with).
    pub descriptors: Vec<Descriptor>,
    /// Their gradient-histogram descriptors (what a query from another day or viewpoint is
    /// matched with).
    pub gradients: Vec<GradientDescriptor>,
    /// The image's gray values at the detection size (`camera`'s), 8-bit, row-major: what a
    /// localizer aligns patches to.
    pub gray: Vec<u8>,
}

/// Triangulated points with the keypoints that observe them.
#[derive(Clone, Debug, Default)]
pub struct TrackedPoints {
    /// Positions, world frame.
    pub xyz: Vec<Point3<f64>>,
    /// Per point, its observations as (index into `images`, keypoint index).
    pub observations: Vec<Vec<(u32, u32)>>,
    /// The keypoints of every triangulated image, in the order of the `frames` given.
    pub images: Vec<ImageKeypoints>,
}

impl TrackedPoints {
    /// The points with per-frame visibility (tracks indexed by dataset frame).
    pub fn to_sparse_points(&self, num_frames: usize) -> SparsePoints {
        let mut by_frame = vec![Vec::new(); num_frames];
        for (id, obs) in self.observations.iter().enumerate() {
            for &(img, _) in obs {
                by_frame[self.images[img as usize].frame].push(id as u32);
            }
        }
        SparsePoints {
            xyz: self.xyz.clone(),
            by_frame: Some(by_frame),
        }
    }
}

/// Triangulates points seen by the frames `frames` of `dataset`; tracks are indexed by dataset
/// frame.
pub fn triangulate(
    dataset: &Dataset,
    frames: &[usize],
    config: &TriangulateConfig,
    progress: TriangulateProgress<'_>,
) -> Result<SparsePoints, SurfaceError> {
    Ok(triangulate_tracks(dataset, frames, config, progress)?
        .to_sparse_points(dataset.frames.len()))
}

/// Triangulates points seen by the frames `frames` of `dataset`, keeping each track's
/// keypoints (the structure a keypoint localizer matches against).
pub fn triangulate_tracks(
    dataset: &Dataset,
    frames: &[usize],
    config: &TriangulateConfig,
    progress: TriangulateProgress<'_>,
) -> Result<TrackedPoints, SurfaceError> {
    let done = std::sync::atomic::AtomicUsize::new(0);
    let features = frames
        .par_iter()
        .map(|&i| {
            let f = features_of(dataset, i, config);
            let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress("detect", n, frames.len());
            f
        })
        .collect::<Result<Vec<_>, SurfaceError>>()?;
    let pairs = neighbour_pairs(&features, config);
    let done = std::sync::atomic::AtomicUsize::new(0);
    let matches: Vec<(usize, usize, usize, usize)> = pairs
        .par_iter()
        .flat_map_iter(|&(a, b)| {
            let m = pair_matches(&features[a], &features[b], config);
            let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress("match", n, pairs.len());
            m.into_iter().map(move |(ka, kb)| (a, ka, b, kb))
        })
        .collect();
    let mut tracks = merge_tracks(&features, &matches, config);
    tracks.images = features
        .into_iter()
        .map(|f| ImageKeypoints {
            frame: f.frame,
            camera: f.camera,
            pixels: f.pixels,
            descriptors: f.descriptors,
            gradients: f.gradients,
            gray: f.gray,
        })
        .collect();
    Ok(tracks)
}

fn features_of(
    dataset: &Dataset,
    index: usize,
    config: &TriangulateConfig,
) -> Result<Features, SurfaceError> {
    let frame = dataset
        .frames
        .get(index)
        .ok_or(SurfaceError::NoFrame(index))?;
    let long = frame.camera.width.max(frame.camera.height);
    let factor = long.div_ceil(config.max_side).max(1);
    let (image, camera) = load_frame_image(dataset, frame, factor)?;
    let kp_config = KeypointConfig {
        max_keypoints: config.max_keypoints,
        upsample: config.upsample,
        ..KeypointConfig::default()
    };
    let gray = GrayImage::from_image(&image);
    let (keypoints, descriptors, gradients) = detect_and_describe_both(&gray, &kp_config);
    let world_from_cam = frame.cam_from_world.inverse();
    let mut out = Features {
        frame: index,
        camera,
        cam_from_world: frame.cam_from_world,
        center: camera_center(&frame.cam_from_world),
        pixels: Vec::with_capacity(keypoints.len()),
        rays: Vec::with_capacity(keypoints.len()),
        descriptors: Vec::with_capacity(keypoints.len()),
        gradients: Vec::with_capacity(keypoints.len()),
        gray: gray
            .data()
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect(),
    };
    for ((k, d), g) in keypoints.iter().zip(descriptors).zip(gradients) {
        let px = Point2::new(f64::from(k.x), f64::from(k.y));
        if let Some(b) = camera.unproject(px) {
            out.pixels.push(px);
            out.rays
                .push(world_from_cam.transform_vector(&b).normalize());
            out.descriptors.push(d);
            out.gradients.push(g);
        }
    }
    Ok(out)
}

/// Each image with its `neighbours` nearest images looking the same way; pairs `(a < b)`.
fn neighbour_pairs(features: &[Features], config: &TriangulateConfig) -> Vec<(usize, usize)> {
    let cos_max = config.max_view_angle_deg.to_radians().cos();
    let dirs: Vec<Vector3<f64>> = features
        .iter()
        .map(|f| viewing_direction(&f.cam_from_world))
        .collect();
    let mut pairs = std::collections::BTreeSet::new();
    for a in 0..features.len() {
        let mut near: Vec<(f64, usize)> = (0..features.len())
            .filter(|&b| b != a && dirs[a].dot(&dirs[b]) >= cos_max)
            .map(|b| ((features[a].center - features[b].center).norm(), b))
            .filter(|(d, _)| *d > 1e-9)
            .collect();
        near.sort_by(|x, y| x.0.total_cmp(&y.0));
        for &(_, b) in near.iter().take(config.neighbours) {
            pairs.insert((a.min(b), a.max(b)));
        }
    }
    pairs.into_iter().collect()
}

/// Reprojection error of a world point in an image, pixels (`None` behind the camera).
fn reprojection(f: &Features, x: &Point3<f64>, observed: Point2<f64>) -> Option<f64> {
    let p = f.camera.project_world(&f.cam_from_world, x)?;
    Some((p - observed).norm())
}

/// Matches of one image pair that triangulate consistently.
fn pair_matches(a: &Features, b: &Features, config: &TriangulateConfig) -> Vec<(usize, usize)> {
    let min_sin = config.min_angle_deg.to_radians().sin();
    let found = match config.pair_descriptor {
        DescriptorKind::Binary => {
            match_descriptors(&a.descriptors, &b.descriptors, &MatchConfig::default())
        }
        DescriptorKind::Gradient => {
            match_descriptors(&a.gradients, &b.gradients, &MatchConfig::gradient())
        }
    };
    found
        .into_iter()
        .filter(|m| {
            let (da, db) = (a.rays[m.a], b.rays[m.b]);
            let Some(x) = midpoint(&a.center, &da, &b.center, &db, min_sin) else {
                return false;
            };
            [(a, m.a), (b, m.b)].iter().all(|(f, k)| {
                reprojection(f, &x, f.pixels[*k]).is_some_and(|e| e <= config.max_reprojection_px)
            })
        })
        .map(|m| (m.a, m.b))
        .collect()
}

/// Midpoint of the closest points of two rays, when they meet in front of both origins at an
/// angle whose sine is at least `min_sin`.
fn midpoint(
    ca: &Point3<f64>,
    da: &Vector3<f64>,
    cb: &Point3<f64>,
    db: &Vector3<f64>,
    min_sin: f64,
) -> Option<Point3<f64>> {
    let b = da.dot(db);
    let denom = 1.0 - b * b;
    if denom < min_sin * min_sin {
        return None;
    }
    let w = ca - cb;
    let (d, e) = (da.dot(&w), db.dot(&w));
    let s = (b * e - d) / denom;
    let t = (e - b * d) / denom;
    if s <= 0.0 || t <= 0.0 {
        return None;
    }
    Some(Point3::from(
        (ca.coords + da * s + cb.coords + db * t) * 0.5,
    ))
}

/// Least-squares point nearest to a set of rays.
fn nearest_to_rays(rays: &[(Point3<f64>, Vector3<f64>)]) -> Option<Point3<f64>> {
    let mut a = Matrix3::zeros();
    let mut rhs = Vector3::zeros();
    for (c, d) in rays {
        let m = Matrix3::identity() - d * d.transpose();
        a += m;
        rhs += m * c.coords;
    }
    a.lu().solve(&rhs).map(Point3::from)
}

fn find(parent: &mut [usize], mut x: usize) -> usize {
    while parent[x] != x {
        parent[x] = parent[parent[x]];
        x = parent[x];
    }
    x
}

/// Joins pairwise matches into tracks and solves each track's point (`images` left empty).
fn merge_tracks(
    features: &[Features],
    matches: &[(usize, usize, usize, usize)],
    config: &TriangulateConfig,
) -> TrackedPoints {
    let mut offset = Vec::with_capacity(features.len() + 1);
    offset.push(0);
    for f in features {
        offset.push(offset.last().unwrap() + f.pixels.len());
    }
    let total = *offset.last().unwrap();
    let mut parent: Vec<usize> = (0..total).collect();
    let mut matched = vec![false; total];
    for &(a, ka, b, kb) in matches {
        let (ia, ib) = (offset[a] + ka, offset[b] + kb);
        matched[ia] = true;
        matched[ib] = true;
        let (x, y) = (find(&mut parent, ia), find(&mut parent, ib));
        if x != y {
            parent[x.max(y)] = x.min(y);
        }
    }
    // Observations per root, as (feature image, keypoint), for every matched keypoint.
    let mut members: std::collections::BTreeMap<usize, Vec<(usize, usize)>> = Default::default();
    for (img, f) in features.iter().enumerate() {
        for k in 0..f.pixels.len() {
            let id = offset[img] + k;
            if matched[id] {
                let r = find(&mut parent, id);
                members.entry(r).or_default().push((img, k));
            }
        }
    }
    let min_sin = config.min_angle_deg.to_radians().sin();
    let mut out = TrackedPoints::default();
    for mut obs in members.into_values() {
        // One observation per image (a track through two keypoints of one image is a chain
        // of wrong matches; the first keypoint stays, the reprojection test judges the rest).
        obs.sort();
        obs.dedup_by_key(|o| o.0);
        if obs.len() < config.min_track_len {
            continue;
        }
        let rays = |obs: &[(usize, usize)]| -> Vec<(Point3<f64>, Vector3<f64>)> {
            obs.iter()
                .map(|&(i, k)| (features[i].center, features[i].rays[k]))
                .collect()
        };
        let Some(mut x) = nearest_to_rays(&rays(&obs)) else {
            continue;
        };
        let keep = |x: &Point3<f64>, &(i, k): &(usize, usize)| {
            reprojection(&features[i], x, features[i].pixels[k])
                .is_some_and(|e| e <= config.max_reprojection_px)
        };
        if !obs.iter().all(|o| keep(&x, o)) {
            obs.retain(|o| keep(&x, o));
            if obs.len() < config.min_track_len {
                continue;
            }
            let Some(y) = nearest_to_rays(&rays(&obs)) else {
                continue;
            };
            x = y;
            if !obs.iter().all(|o| keep(&x, o)) {
                continue;
            }
        }
        if config.refine_points {
            let views: Vec<PointView<'_>> = obs
                .iter()
                .map(|&(i, k)| PointView {
                    camera: &features[i].camera,
                    cam_from_world: &features[i].cam_from_world,
                    pixel: features[i].pixels[k],
                })
                .collect();
            let Some(y) = refine_point(&views, x, REFINE_HUBER_PX, REFINE_ITERATIONS) else {
                continue;
            };
            x = y;
            if !obs.iter().all(|o| keep(&x, o)) {
                obs.retain(|o| keep(&x, o));
                if obs.len() < config.min_track_len {
                    continue;
                }
            }
        }
        // Enough parallax between some pair of rays.
        let dirs: Vec<Vector3<f64>> = obs
            .iter()
            .map(|&(i, _)| (x - features[i].center).normalize())
            .collect();
        let wide = dirs.iter().enumerate().any(|(p, u)| {
            dirs[p + 1..]
                .iter()
                .any(|v| u.cross(v).norm() >= min_sin && u.dot(v) > 0.0)
        });
        if !wide {
            continue;
        }
        out.xyz.push(x);
        out.observations
            .push(obs.iter().map(|&(i, k)| (i as u32, k as u32)).collect());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn midpoint_of_crossing_rays_and_rejections() {
        let ca = Point3::new(0.0, 0.0, 10.0);
        let cb = Point3::new(4.0, 0.0, 10.0);
        let x = Point3::new(2.0, 1.0, 0.0);
        let (da, db) = ((x - ca).normalize(), (x - cb).normalize());
        let m = midpoint(&ca, &da, &cb, &db, 0.01).unwrap();
        assert!((m - x).norm() < 1e-9);
        // Behind one origin.
        assert!(midpoint(&ca, &-da, &cb, &db, 0.01).is_none());
        // Too narrow an angle.
        assert!(midpoint(&ca, &da, &cb, &db, 0.9).is_none());
        let y = nearest_to_rays(&[
            (ca, da),
            (cb, db),
            (
                Point3::new(0.0, 5.0, 8.0),
                (x - Point3::new(0.0, 5.0, 8.0)).normalize(),
            ),
        ])
        .unwrap();
        assert!((y - x).norm() < 1e-9);
    }
}
