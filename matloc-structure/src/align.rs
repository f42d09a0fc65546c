//! Sub-pixel correspondences by patch alignment: a query keypoint matched to a training
//! image's keypoint is moved to where the training image's patch around that keypoint fits
//! the query best (Lucas–Kanade on translation, with gain and bias fitted per patch).
//!
//! Two keypoints detected independently in two images mark the same surface point only to a
//! fraction of a pixel (detector repeatability); that, not the triangulated points, limits a
//! pose from keypoints. Aligning the query to the training image's pixels removes the query
//! side's share. The patch's shape in the query comes from the pose being refined: the
//! training image's pixel grid around the keypoint is laid on the plane through the point
//! facing that image, and that plane is projected into the query (a local affine map).

use matloc_core::Camera;
use matloc_core::pose::{Pose, camera_center};
use matloc_keypoints::GrayImage;
use nalgebra::{Matrix2, Point2, Point3, Vector2};
use serde::{Deserialize, Serialize};

/// Settings of the patch alignment.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AlignOptions {
    /// Align the accepted pose's correspondences and solve again (needs a map that keeps its
    /// training images' gray values).
    pub enabled: bool,
    /// Half side of the square patch, training-image pixels.
    pub half_window: usize,
    /// Gauss–Newton iterations per patch.
    pub iterations: usize,
    /// Largest move of a query keypoint, query pixels: beyond it the patch is taken to have
    /// locked onto something else and the keypoint keeps its detected position.
    pub max_shift_px: f64,
    /// Smallest normalised cross-correlation of an aligned patch: a patch whose shadows or
    /// texture differ from the training image's pulls its point off; 0.95 against 0.8 took
    /// `rubble`'s second flight from 0.032 to 0.022 m (same flight 0.018 → 0.019 m).
    pub min_zncc: f64,
    /// Also align the points that the start's training images see and no descriptor match
    /// reached, each from its projection under the pose: every textured point in view
    /// becomes a correspondence, not only those whose keypoints the query's detector found
    /// again (under a moved sun, a third to a half of them).
    pub track: bool,
}

impl Default for AlignOptions {
    fn default() -> Self {
        AlignOptions {
            enabled: true,
            half_window: 4,
            iterations: 12,
            max_shift_px: 1.5,
            min_zncc: 0.95,
            track: true,
        }
    }
}

/// A query's gray image with its central-difference gradients.
pub(crate) struct QueryPlanes {
    width: usize,
    height: usize,
    gray: Vec<f32>,
    gx: Vec<f32>,
    gy: Vec<f32>,
}

impl QueryPlanes {
    pub(crate) fn new(gray: &GrayImage) -> Self {
        let (w, h) = (gray.width(), gray.height());
        let g = gray.data();
        let mut gx = vec![0.0f32; w * h];
        let mut gy = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let (xl, xr) = (x.saturating_sub(1), (x + 1).min(w.saturating_sub(1)));
                let (yu, yd) = (y.saturating_sub(1), (y + 1).min(h.saturating_sub(1)));
                let span_x = (xr - xl).max(1) as f32;
                let span_y = (yd - yu).max(1) as f32;
                gx[y * w + x] = (g[y * w + xr] - g[y * w + xl]) / span_x;
                gy[y * w + x] = (g[yd * w + x] - g[yu * w + x]) / span_y;
            }
        }
        QueryPlanes {
            width: w,
            height: h,
            gray: g.to_vec(),
            gx,
            gy,
        }
    }
}

/// Bilinear weights and the top-left index at a continuous pixel position (pixel centres at
/// `+0.5`); `None` outside the centres' hull.
#[inline]
fn bilinear_at(width: usize, height: usize, x: f64, y: f64) -> Option<(usize, f32, f32)> {
    let (fx, fy) = (x - 0.5, y - 0.5);
    if !(fx >= 0.0 && fy >= 0.0) {
        return None;
    }
    let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
    if x0 + 1 >= width || y0 + 1 >= height {
        return None;
    }
    Some((
        y0 * width + x0,
        (fx - x0 as f64) as f32,
        (fy - y0 as f64) as f32,
    ))
}

#[inline]
fn lerp4(v: &[f32], i: usize, w: usize, ax: f32, ay: f32) -> f32 {
    let top = v[i] + ax * (v[i + 1] - v[i]);
    let bottom = v[i + w] + ax * (v[i + w + 1] - v[i + w]);
    top + ay * (bottom - top)
}

/// The patch of a training image (`gray`, 8-bit, row-major at its camera's size) around
/// `center`, `(2h + 1)²` samples at whole-pixel offsets, zero mean; `None` when it leaves the
/// image or is flat.
pub(crate) fn template(
    gray: &[u8],
    width: usize,
    height: usize,
    center: Point2<f64>,
    half: usize,
) -> Option<Vec<f32>> {
    let h = half as isize;
    let mut out = Vec::with_capacity((2 * half + 1).pow(2));
    for dy in -h..=h {
        for dx in -h..=h {
            let (i, ax, ay) =
                bilinear_at(width, height, center.x + dx as f64, center.y + dy as f64)?;
            let at = |k: usize| f32::from(gray[k]) / 255.0;
            let top = at(i) + ax * (at(i + 1) - at(i));
            let bottom = at(i + width) + ax * (at(i + width + 1) - at(i + width));
            out.push(top + ay * (bottom - top));
        }
    }
    let mean = out.iter().sum::<f32>() / out.len() as f32;
    out.iter_mut().for_each(|v| *v -= mean);
    let var = out.iter().map(|v| v * v).sum::<f32>() / out.len() as f32;
    (var > 1e-5).then_some(out)
}

/// The local affine map from the training image's pixels around `map_px` to the query's
/// pixels under `query_pose`: the training image's rays near `map_px` meet the plane through
/// `point` that faces the training camera, and those points are projected into the query.
/// Returns the query position of `map_px`'s ray on that plane and the 2×2 map.
pub(crate) fn local_affine(
    map_camera: &Camera,
    map_pose: &Pose,
    map_px: Point2<f64>,
    point: &Point3<f64>,
    query_camera: &Camera,
    query_pose: &Pose,
) -> Option<(Point2<f64>, Matrix2<f64>)> {
    let center = camera_center(map_pose);
    let normal = (point - center).try_normalize(1e-12)?;
    let depth = normal.dot(&(point - center));
    let world_from_cam = map_pose.inverse();
    let on_plane = |px: Point2<f64>| -> Option<Point2<f64>> {
        let ray = world_from_cam.transform_vector(&map_camera.unproject(px)?);
        let along = normal.dot(&ray);
        if along <= 1e-9 {
            return None;
        }
        query_camera.project_world(query_pose, &(center + ray * (depth / along)))
    };
    let c = on_plane(map_px)?;
    let step = 0.5;
    let col = |d: Vector2<f64>| -> Option<Vector2<f64>> {
        let a = on_plane(map_px + d * step)?;
        let b = on_plane(map_px - d * step)?;
        Some((a - b) / (2.0 * step))
    };
    let ax = col(Vector2::x())?;
    let ay = col(Vector2::y())?;
    let a = Matrix2::from_columns(&[ax, ay]);
    a.iter().all(|v| v.is_finite()).then_some((c, a))
}

/// Moves `start` to where `template` (zero mean, from [`template`]) laid through `affine`
/// fits the query best; `None` when the fit leaves the image, drifts beyond
/// `max_shift_px`, inverts the contrast or correlates below `min_zncc`.
pub(crate) fn align(
    query: &QueryPlanes,
    template: &[f32],
    affine: &Matrix2<f64>,
    start: Point2<f64>,
    options: &AlignOptions,
) -> Option<Point2<f64>> {
    let h = options.half_window as isize;
    let n = template.len();
    let offsets: Vec<Vector2<f64>> = (-h..=h)
        .flat_map(|dy| (-h..=h).map(move |dx| Vector2::new(dx as f64, dy as f64)))
        .map(|d| affine * d)
        .collect();
    debug_assert_eq!(offsets.len(), n);
    let mut u = start;
    let mut values = vec![0.0f32; n];
    let mut grads = vec![[0.0f32; 2]; n];
    let t_energy: f32 = template.iter().map(|v| v * v).sum();
    for _ in 0..options.iterations.max(1) {
        for (k, d) in offsets.iter().enumerate() {
            let (i, ax, ay) = bilinear_at(query.width, query.height, u.x + d.x, u.y + d.y)?;
            values[k] = lerp4(&query.gray, i, query.width, ax, ay);
            grads[k] = [
                lerp4(&query.gx, i, query.width, ax, ay),
                lerp4(&query.gy, i, query.width, ax, ay),
            ];
        }
        let mean = values.iter().sum::<f32>() / n as f32;
        let (mut var, mut cov) = (0.0f32, 0.0f32);
        for (v, t) in values.iter().zip(template) {
            var += (v - mean) * (v - mean);
            cov += (v - mean) * t;
        }
        if var <= 1e-9 {
            return None;
        }
        let gain = cov / var;
        if gain <= 0.0 {
            return None;
        }
        // Residual of the gain-and-bias fit, Gauss–Newton step on the translation.
        let (mut h00, mut h01, mut h11, mut b0, mut b1) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
        for k in 0..n {
            let r = f64::from(gain * (values[k] - mean) - template[k]);
            let g = [f64::from(gain * grads[k][0]), f64::from(gain * grads[k][1])];
            h00 += g[0] * g[0];
            h01 += g[0] * g[1];
            h11 += g[1] * g[1];
            b0 += g[0] * r;
            b1 += g[1] * r;
        }
        let det = h00 * h11 - h01 * h01;
        if det.is_nan() || det <= 1e-12 * (h00 + h11).powi(2).max(1e-30) {
            return None;
        }
        let step = Vector2::new(-(h11 * b0 - h01 * b1) / det, -(h00 * b1 - h01 * b0) / det);
        u += step;
        if (u - start).norm() > options.max_shift_px {
            return None;
        }
        if step.norm() < 1e-3 {
            break;
        }
    }
    // Correlation at the final position.
    for (k, d) in offsets.iter().enumerate() {
        let (i, ax, ay) = bilinear_at(query.width, query.height, u.x + d.x, u.y + d.y)?;
        values[k] = lerp4(&query.gray, i, query.width, ax, ay);
    }
    let mean = values.iter().sum::<f32>() / n as f32;
    let (mut var, mut cov) = (0.0f32, 0.0f32);
    for (v, t) in values.iter().zip(template) {
        var += (v - mean) * (v - mean);
        cov += (v - mean) * t;
    }
    let zncc = f64::from(cov) / (f64::from(var) * f64::from(t_energy)).sqrt().max(1e-12);
    (zncc >= options.min_zncc).then_some(u)
}

/// Normalised cross-correlation of `template` (zero mean, from [`template`]) laid through
/// `affine` at `at` in the query, without moving it; `None` when the patch leaves the image
/// or the query is flat there.
pub(crate) fn zncc_at(
    query: &QueryPlanes,
    template: &[f32],
    affine: &Matrix2<f64>,
    at: Point2<f64>,
) -> Option<f64> {
    let n = template.len();
    let h = ((n as f64).sqrt() as isize - 1) / 2;
    let mut values = Vec::with_capacity(n);
    for dy in -h..=h {
        for dx in -h..=h {
            let d = affine * Vector2::new(dx as f64, dy as f64);
            let (i, ax, ay) = bilinear_at(query.width, query.height, at.x + d.x, at.y + d.y)?;
            values.push(lerp4(&query.gray, i, query.width, ax, ay));
        }
    }
    if values.len() != n {
        return None;
    }
    let mean = values.iter().sum::<f32>() / n as f32;
    let (mut var, mut cov) = (0.0f64, 0.0f64);
    let mut t_energy = 0.0f64;
    for (v, t) in values.iter().zip(template) {
        let v = f64::from(v - mean);
        var += v * v;
        cov += v * f64::from(*t);
        t_energy += f64::from(*t) * f64::from(*t);
    }
    (var > 1e-9 && t_energy > 1e-12).then(|| cov / (var * t_energy).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::Camera;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use proptest::prelude::*;

    /// A smooth texture with detail at a few pixels' scale (periods of 5–12 px, as a
    /// lens-blurred photo carries).
    fn texture(x: f64, y: f64) -> f64 {
        0.5 + 0.18 * (0.6 * x + 0.3 * y).sin()
            + 0.12 * (0.4 * x - 0.8 * y + 1.0).sin()
            + 0.08 * (0.9 * x + 0.7 * y + 2.0).cos()
    }

    /// `size × size` values of `f` at pixel centres.
    fn raster(size: usize, f: impl Fn(f64, f64) -> f64) -> Vec<f64> {
        (0..size * size)
            .map(|i| f((i % size) as f64 + 0.5, (i / size) as f64 + 0.5))
            .collect()
    }

    fn planes(size: usize, f: impl Fn(f64, f64) -> f64) -> QueryPlanes {
        let data = raster(size, f).into_iter().map(|v| v as f32).collect();
        QueryPlanes::new(&GrayImage::from_vec(size, size, data).unwrap())
    }

    fn bytes(size: usize, f: impl Fn(f64, f64) -> f64) -> Vec<u8> {
        raster(size, f)
            .into_iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect()
    }

    #[test]
    fn a_shifted_and_relit_patch_is_found_to_a_few_hundredths_of_a_pixel() {
        let (size, center) = (64, Point2::new(30.2, 33.7));
        let shift = Vector2::new(0.37, -0.21);
        let map = bytes(size, texture);
        // The query sees the same surface moved by `shift`, darker and with an offset.
        let query = planes(size, |x, y| 0.1 + 0.7 * texture(x - shift.x, y - shift.y));
        let patch = template(&map, size, size, center, 4).unwrap();
        let options = AlignOptions::default();
        let start = center + shift + Vector2::new(0.6, -0.5);
        let found = align(&query, &patch, &Matrix2::identity(), start, &options).unwrap();
        let err = (found - (center + shift)).norm();
        assert!(err < 0.05, "error {err} px");
    }

    #[test]
    fn a_flat_patch_or_one_beyond_reach_is_refused() {
        let size = 48;
        let flat = vec![128u8; size * size];
        assert!(template(&flat, size, size, Point2::new(20.0, 20.0), 4).is_none());
        let map = bytes(size, texture);
        assert!(template(&map, size, size, Point2::new(2.0, 20.0), 4).is_none());
        // The query holds an unrelated texture: no fit within reach correlates enough.
        let query = planes(size, |x, y| texture(3.0 * y + 11.0, -2.0 * x + 5.0));
        let patch = template(&map, size, size, Point2::new(24.0, 24.0), 4).unwrap();
        let options = AlignOptions::default();
        let got = align(
            &query,
            &patch,
            &Matrix2::identity(),
            Point2::new(24.0, 24.0),
            &options,
        );
        assert!(got.is_none(), "{got:?}");
    }

    fn down_camera(x: f64, y: f64, z: f64, yaw: f64) -> Pose {
        let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        Pose::from_parts(
            Translation3::new(x, y, z),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw) * down,
        )
        .inverse()
    }

    #[test]
    fn the_local_map_of_a_camera_twice_as_high_and_turned_halves_and_rotates() {
        let camera = Camera::pinhole(200, 200, 150.0, 150.0, 100.0, 100.0).unwrap();
        let map_pose = down_camera(0.0, 0.0, 20.0, 0.0);
        let yaw = 0.3f64;
        let query_pose = down_camera(1.0, -2.0, 40.0, yaw);
        // Straight below the map camera, so the plane facing it is the ground.
        let point = Point3::new(0.0, 0.0, 0.0);
        let map_px = camera.project_world(&map_pose, &point).unwrap();
        let (c, a) =
            local_affine(&camera, &map_pose, map_px, &point, &camera, &query_pose).unwrap();
        let expect_c = camera.project_world(&query_pose, &point).unwrap();
        assert!((c - expect_c).norm() < 1e-9);
        // Both look straight down: a rotation by the yaw difference at half the scale.
        let (s, co) = (yaw.sin(), yaw.cos());
        let expect = Matrix2::new(co, -s, s, co) * 0.5;
        assert!((a - expect).norm() < 1e-6, "{a} vs {expect}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(40))]
        #[test]
        fn alignment_undoes_a_subpixel_shift_under_a_known_affine(
            sx in -0.5f64..0.5, sy in -0.5f64..0.5,
            angle in -0.6f64..0.6, scale in 0.8f64..1.25,
            gain in 0.5f64..1.5, bias in -0.1f64..0.1,
        ) {
            let (size, center) = (80, Point2::new(40.3, 39.6));
            let (s, c) = (angle.sin(), angle.cos());
            let a = Matrix2::new(c, -s, s, c) * scale;
            let inv = a.try_inverse().unwrap();
            let target = Point2::new(41.0 + sx, 38.5 + sy);
            // Query pixel q shows the map surface at center + A⁻¹ (q − target).
            let query = planes(size, |x, y| {
                let m = center + inv * (Point2::new(x, y) - target);
                bias + gain * texture(m.x, m.y)
            });
            let map = bytes(size, texture);
            let patch = template(&map, size, size, center, 4).unwrap();
            let start = target + Vector2::new(0.4, 0.3);
            let found = align(&query, &patch, &a, start, &AlignOptions::default());
            let found = found.expect("aligned");
            prop_assert!((found - target).norm() < 0.05, "{} px", (found - target).norm());
        }
    }
}
