//! The map's sun taken out of its training images: which pixels lie in a cast shadow of the
//! sun (decided from the per-frame surfaces), and the images with those shadows lifted to
//! sunlight. A NeRF fitted to the lifted images carries the surfaces' colours instead of one
//! day's shadows, so the query encoder, trained towards its features with shadow augmentation,
//! can answer the same under another sun (docs/DECISIONS.md, "The map's shadows are lifted
//! before its NeRFs are fitted").
//!
//! - [`shadow_mask`]: from each pixel's surface point a ray is marched towards the sun; a
//!   step that lies behind the surface of the view and of at least one neighbouring view, and
//!   that no view sees in front of its surface, is inside the scene, so the pixel is shadowed.
//! - [`ShadowEdges`]: the light a shadow takes away, per channel, from pairs of pixels across
//!   the masks' edges: their ratios pile up at 1 (pairs on one side of a true edge) and at the
//!   sun-to-sky ratio (pairs across it); the second pile's peak is the gain.
//! - [`lift_shadows`]: the image with its shadowed pixels multiplied by that gain in linear
//!   light, the mask's edge softened.
//! - [`estimate_sun`]: the sun's direction, when the data does not give it, as the direction
//!   whose masks' edges the images darken across most.

use matloc_core::shadow::{to_display, to_linear};
use matloc_core::{Camera, Image, Pose};
use nalgebra::{Point2, Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::SurfaceError;

mod estimate;
pub use estimate::{SunEstimate, SunView, estimate_sun, sun_edges, sun_views};

/// Settings of the shadow lifting (the map's `sunlight` section).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SunlightConfig {
    /// Lift the cast shadows of the training images before the NeRFs are fitted. Off by
    /// default: it pays for queries under another sun with fewer correct matches under the
    /// map's own (docs/DECISIONS.md).
    pub enabled: bool,
    /// Direction towards the sun in the dataset's world frame (normalised when used); `None`
    /// takes the dataset's `sun_direction` metadata, else estimates it from the images
    /// ([`estimate_sun`]).
    pub sun_direction: Option<[f64; 3]>,
    /// Nearest training views (by camera centre) whose surfaces also vote on whether a point
    /// along a sun ray is inside the scene.
    pub neighbours: usize,
    /// Longest side of the grid a mask is computed on (bilinear up to the image).
    pub max_side: usize,
    /// Gaussian softening of the mask's edge, image pixels.
    pub edge_blur_px: f32,
}

impl Default for SunlightConfig {
    fn default() -> Self {
        SunlightConfig {
            enabled: false,
            sun_direction: None,
            neighbours: 6,
            max_side: 640,
            edge_blur_px: 0.7,
        }
    }
}

impl SunlightConfig {
    /// Whether this is the default (off) configuration.
    pub fn is_default(&self) -> bool {
        *self == SunlightConfig::default()
    }

    /// Checks every field.
    pub fn validate(&self) -> Result<(), SurfaceError> {
        let bad =
            |field: &'static str, reason: String| SurfaceError::InvalidConfig { field, reason };
        if let Some(d) = self.sun_direction {
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if !(n.is_finite() && n > 1e-9) {
                return Err(bad(
                    "sunlight.sun_direction",
                    format!("must be a finite non-zero vector, got {d:?}"),
                ));
            }
        }
        if self.max_side < 8 {
            return Err(bad(
                "sunlight.max_side",
                format!("must be at least 8, got {}", self.max_side),
            ));
        }
        if !(self.edge_blur_px.is_finite() && (0.0..=10.0).contains(&self.edge_blur_px)) {
            return Err(bad(
                "sunlight.edge_blur_px",
                format!("must be in [0, 10], got {}", self.edge_blur_px),
            ));
        }
        Ok(())
    }
}

/// A view and its surface: z-depth in metres (0 or non-finite where unknown), at the camera's
/// size or smaller (a densified grid), read at the nearest cell.
#[derive(Clone, Copy, Debug)]
pub struct DepthView<'a> {
    /// The view's camera.
    pub camera: &'a Camera,
    /// World → camera.
    pub cam_from_world: &'a Pose,
    /// Z-depth map.
    pub depth: &'a Image<f32>,
}

impl<'a> DepthView<'a> {
    /// A dataset frame's view with its depth map.
    pub fn of(frame: &'a matloc_data::Frame, depth: &'a Image<f32>) -> Self {
        DepthView {
            camera: &frame.camera,
            cam_from_world: &frame.cam_from_world,
            depth,
        }
    }

    /// Depth at image pixel coordinates `(x, y)` of the camera.
    fn depth_at(&self, x: f64, y: f64) -> Option<f64> {
        let (dw, dh, _) = self.depth.shape();
        let sx = dw as f64 / f64::from(self.camera.width.max(1));
        let sy = dh as f64 / f64::from(self.camera.height.max(1));
        let (u, v) = ((x * sx).floor(), (y * sy).floor());
        if !(u >= 0.0 && v >= 0.0 && u < dw as f64 && v < dh as f64) {
            return None;
        }
        let d = self.depth.data()[v as usize * dw + u as usize];
        (d.is_finite() && d > 0.0).then_some(f64::from(d))
    }

    /// Where the world point `p` stands against this view's surface: `Some(true)` behind it
    /// by more than 0.3 % of the depth and 5 cm, `Some(false)` in front of it (the view sees
    /// through `p`), `None` outside the view. (A wider margin loses the shadows of low objects
    /// seen from 50 m and more: docs/DECISIONS.md.)
    fn behind_surface(&self, p: &Point3<f64>) -> Option<bool> {
        let pc = self.cam_from_world * p;
        if pc.z <= 1e-6 {
            return None;
        }
        let q = self.camera.project(&pc.coords)?;
        let d = self.depth_at(q.x, q.y)?;
        Some(pc.z > d * 1.003 + 0.05)
    }
}

/// For each camera centre, the `k` nearest other centres (indices, nearest first): the views
/// whose surfaces vote on its shadows.
pub fn nearest_views(centres: &[Point3<f64>], k: usize) -> Vec<Vec<usize>> {
    (0..centres.len())
        .map(|v| {
            let c = centres[v];
            let mut order: Vec<usize> = (0..centres.len()).filter(|&o| o != v).collect();
            order.sort_by(|&a, &b| (centres[a] - c).norm().total_cmp(&(centres[b] - c).norm()));
            order.truncate(k);
            order
        })
        .collect()
}

/// Size of the grid [`shadow_mask`] works on for `camera`: its image scaled down so the longer
/// side is at most `max_side` (never up).
pub fn grid_size(camera: &Camera, max_side: usize) -> (usize, usize) {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let scale = (max_side.max(1) as f64 / w.max(h).max(1) as f64).min(1.0);
    (
        ((w as f64 * scale).round() as usize).max(1),
        ((h as f64 * scale).round() as usize).max(1),
    )
}

/// Steps of the march towards the sun (growing geometrically from 0.4 % of the depth to about
/// 20 times it): coarser steps skip corners and thin occluders, and cut shadows short
/// (docs/DECISIONS.md, "The sun is estimated from the images").
const MARCH_STEPS: usize = 90;
/// Growth of each step over the last.
const MARCH_GROWTH: f64 = 1.1;
/// Steps in a row outside every view (none could vote) before a march stops.
const UNSEEN_STEPS: usize = 8;

/// Cast-shadow mask of `view` under a sun in direction `sun_world` (towards the sun), on a grid
/// of at most `max_side` cells a side (1 = shadowed, 0 = lit or unknown). A point along a
/// pixel's sun ray is inside the scene when no view (`view` and `others`) sees in front of
/// it and at least two see it behind their surface (one when there are no `others`).
pub fn shadow_mask(
    view: &DepthView,
    others: &[DepthView],
    sun_world: &Vector3<f64>,
    max_side: usize,
) -> Image<f32> {
    let (w, h) = (view.camera.width as usize, view.camera.height as usize);
    let (gw, gh) = grid_size(view.camera, max_side);
    let mut mask = Image::<f32>::new(gw, gh, 1);
    let sun = sun_world.normalize();
    if !sun.iter().all(|v| v.is_finite()) || w == 0 || h == 0 {
        return mask;
    }
    let world_from_cam = view.cam_from_world.inverse();
    let votes_needed = if others.is_empty() { 1 } else { 2 };
    let data = mask.data_mut();
    for gy in 0..gh {
        for gx in 0..gw {
            let px = (gx as f64 + 0.5) * w as f64 / gw as f64;
            let py = (gy as f64 + 0.5) * h as f64 / gh as f64;
            let (Some(z), Some(b)) = (
                view.depth_at(px, py),
                view.camera.unproject(Point2::new(px, py)),
            ) else {
                continue;
            };
            if b.z <= 1e-6 {
                continue;
            }
            let surface = world_from_cam * Point3::from(b * (z / b.z));
            let mut t = 0.004 * z;
            let mut unseen = 0;
            'march: for _ in 0..MARCH_STEPS {
                let p = surface + sun * t;
                t *= MARCH_GROWTH;
                let mut votes = 0;
                for v in std::iter::once(view).chain(others) {
                    match v.behind_surface(&p) {
                        Some(true) => votes += 1,
                        Some(false) => {
                            unseen = 0;
                            continue 'march;
                        }
                        None => {}
                    }
                }
                if votes >= votes_needed {
                    data[gy * gw + gx] = 1.0;
                    break;
                }
                // A ray that has left every view stays out of them (nearly always): nothing
                // further along it can vote.
                unseen = if votes > 0 { 0 } else { unseen + 1 };
                if unseen == UNSEEN_STEPS {
                    break;
                }
            }
        }
    }
    mask
}

/// The mask resampled to `w × h` (bilinear, cell centres).
fn resample(mask: &Image<f32>, w: usize, h: usize) -> Vec<f32> {
    let (mw, mh, _) = mask.shape();
    if (mw, mh) == (w, h) {
        return mask.data().to_vec();
    }
    let m = mask.data();
    let mut out = vec![0.0f32; w * h];
    for y in 0..h {
        let fy = ((y as f64 + 0.5) * mh as f64 / h as f64 - 0.5).clamp(0.0, (mh - 1) as f64);
        let (y0, ay) = (fy.floor() as usize, (fy - fy.floor()) as f32);
        let y1 = (y0 + 1).min(mh - 1);
        for x in 0..w {
            let fx = ((x as f64 + 0.5) * mw as f64 / w as f64 - 0.5).clamp(0.0, (mw - 1) as f64);
            let (x0, ax) = (fx.floor() as usize, (fx - fx.floor()) as f32);
            let x1 = (x0 + 1).min(mw - 1);
            let top = m[y0 * mw + x0] * (1.0 - ax) + m[y0 * mw + x1] * ax;
            let bottom = m[y1 * mw + x0] * (1.0 - ax) + m[y1 * mw + x1] * ax;
            out[y * w + x] = top * (1.0 - ay) + bottom * ay;
        }
    }
    out
}

/// Histogram resolution of the log ratios, natural-log units per bin.
const BIN: f32 = 0.05;
/// Lowest log ratio kept (ratios below `e^-1` are not shadow edges).
const LOG_MIN: f32 = -1.0;
/// Number of bins (log ratios up to `LOG_MIN + BINS · BIN` = 3, a ratio of 20).
const BINS: usize = 80;
/// The gain is searched above this ratio (the first pile sits at 1).
const MIN_GAIN: f32 = 1.5;
/// Pixels between the two pixels of a pair.
const PAIR_SPAN: isize = 3;
/// Pairs at the gain's peak needed to trust it.
const MIN_PEAK_PAIRS: u64 = 30;

/// Ratios of linear light across the edges of shadow masks, per channel, collected over
/// images: a lit pixel `PAIR_SPAN` pixels from a pixel inside the mask (the inside eroded and
/// the outside kept one pixel clear of the edge, so a mask a pixel off still pairs across).
#[derive(Clone, Debug)]
pub struct ShadowEdges {
    hist: [[u64; BINS]; 3],
    /// Sum and count of every pair's `ln(lit / shadowed)` of the channels' mean linear light,
    /// clamped to ±[`MAX_LOG_RATIO`] (how strongly the masks' edges darken the images, which
    /// the sun search scores).
    log_sum: f64,
    log_pairs: u64,
}

/// Clamp of a pair's log ratio in [`ShadowEdges::contrast`].
const MAX_LOG_RATIO: f64 = 3.0;

impl Default for ShadowEdges {
    fn default() -> Self {
        ShadowEdges {
            hist: [[0; BINS]; 3],
            log_sum: 0.0,
            log_pairs: 0,
        }
    }
}

impl ShadowEdges {
    /// Adds the pairs of `img` (RGB in `[0, 1]`) across `mask` (any size; resampled, > 0.5 is
    /// shadow).
    pub fn add(&mut self, img: &Image<f32>, mask: &Image<f32>) {
        let (w, h, c) = img.shape();
        if c != 3 || w == 0 || h == 0 {
            return;
        }
        let m: Vec<bool> = resample(mask, w, h).iter().map(|&v| v > 0.5).collect();
        let at = |x: isize, y: isize| -> Option<bool> {
            (x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h)
                .then(|| m[y as usize * w + x as usize])
        };
        // Inside: the pixel and its 8 neighbours in the mask; outside: none of them.
        let all = |x: isize, y: isize, v: bool| {
            (-1..=1).all(|dy| (-1..=1).all(|dx| at(x + dx, y + dy) == Some(v)))
        };
        let px = img.data();
        for y in 0..h as isize {
            for x in 0..w as isize {
                if !all(x, y, true) {
                    continue;
                }
                let i = y as usize * w + x as usize;
                for (dx, dy) in [
                    (PAIR_SPAN, 0),
                    (-PAIR_SPAN, 0),
                    (0, PAIR_SPAN),
                    (0, -PAIR_SPAN),
                ] {
                    let (ox, oy) = (x + dx, y + dy);
                    if !all(ox, oy, false) {
                        continue;
                    }
                    let j = oy as usize * w + ox as usize;
                    let lit: [f32; 3] = std::array::from_fn(|k| to_linear(px[3 * j + k]));
                    let dark: [f32; 3] = std::array::from_fn(|k| to_linear(px[3 * i + k]));
                    let mean = |v: &[f32; 3]| v.iter().sum::<f32>() / 3.0;
                    let r = f64::from((mean(&lit).max(1e-4) / mean(&dark).max(1e-4)).ln())
                        .clamp(-MAX_LOG_RATIO, MAX_LOG_RATIO);
                    self.log_sum += r;
                    self.log_pairs += 1;
                    for k in 0..3 {
                        let b = ((lit[k].max(1e-4) / dark[k].max(1e-4)).ln() - LOG_MIN) / BIN;
                        if b >= 0.0 && (b as usize) < BINS {
                            self.hist[k][b as usize] += 1;
                        }
                    }
                }
            }
        }
    }

    /// Adds the pairs another collection holds.
    pub fn merge(&mut self, other: &ShadowEdges) {
        for (a, b) in self.hist.iter_mut().zip(&other.hist) {
            for (x, y) in a.iter_mut().zip(b) {
                *x += y;
            }
        }
        self.log_sum += other.log_sum;
        self.log_pairs += other.log_pairs;
    }

    /// Mean `ln(lit / shadowed)` over every pair (brightness, clamped to ±3) and the number of
    /// pairs; `None` without pairs.
    pub fn contrast(&self) -> Option<(f64, u64)> {
        (self.log_pairs > 0).then(|| (self.log_sum / self.log_pairs as f64, self.log_pairs))
    }

    /// Pairs collected (of the first channel, inside the histogram's range).
    pub fn pairs(&self) -> u64 {
        self.hist[0].iter().sum()
    }

    /// Per channel, the ratio at the peak of the pairs above [`MIN_GAIN`] (three bins
    /// summed); `None` when a channel's peak holds fewer than [`MIN_PEAK_PAIRS`] pairs.
    pub fn gain(&self) -> Option<[f32; 3]> {
        let first = (((MIN_GAIN.ln() - LOG_MIN) / BIN).ceil() as usize).max(1);
        let mut gain = [1.0f32; 3];
        for (k, g) in gain.iter_mut().enumerate() {
            let h = &self.hist[k];
            let (mut best, mut count) = (0, 0);
            for c in first..BINS - 1 {
                let v = h[c - 1] + h[c] + h[c + 1];
                if v > count {
                    (best, count) = (c, v);
                }
            }
            if count < MIN_PEAK_PAIRS {
                return None;
            }
            *g = (LOG_MIN + (best as f32 + 0.5) * BIN).exp();
        }
        Some(gain)
    }
}

/// A lifted pixel may come out at most this many times as bright as the mean of the lit
/// pixels around it: where a mask is wrong (a lit surface marked shadowed) the gain would
/// paint a bright patch, a true shadow comes out near its surroundings.
const MAX_OVER_LIT: f32 = 1.5;

/// Mean of `values` over the pixels where `keep` holds in the `(2r + 1)²` window around each
/// pixel (NaN where the window has none); summed-area tables, O(pixels).
fn local_mean(values: &[f32], keep: &[bool], w: usize, h: usize, r: usize) -> Vec<f32> {
    let stride = w + 1;
    let mut sum = vec![0.0f64; stride * (h + 1)];
    let mut cnt = vec![0u32; stride * (h + 1)];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let (v, c) = if keep[i] {
                (f64::from(values[i]), 1)
            } else {
                (0.0, 0)
            };
            let o = (y + 1) * stride + x + 1;
            sum[o] = v + sum[o - 1] + sum[o - stride] - sum[o - stride - 1];
            cnt[o] = c + cnt[o - 1] + cnt[o - stride] - cnt[o - stride - 1];
        }
    }
    let mut out = vec![f32::NAN; w * h];
    for y in 0..h {
        let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
        for x in 0..w {
            let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
            let at = |yy: usize, xx: usize| yy * stride + xx;
            let n = cnt[at(y1, x1)] + cnt[at(y0, x0)] - cnt[at(y0, x1)] - cnt[at(y1, x0)];
            if n > 0 {
                let s = sum[at(y1, x1)] + sum[at(y0, x0)] - sum[at(y0, x1)] - sum[at(y1, x0)];
                out[y * w + x] = (s / f64::from(n)) as f32;
            }
        }
    }
    out
}

/// `img` (RGB in `[0, 1]`) with the pixels under `mask` (any size, resampled) multiplied by
/// `gain` in linear light, the mask softened by a Gaussian of `edge_blur_px`. The factor is
/// capped so a pixel's lifted brightness stays within [`MAX_OVER_LIT`] of the lit pixels
/// around it (a window of a fortieth of the image's longer side, at least 15 pixels).
pub fn lift_shadows(
    img: &Image<f32>,
    mask: &Image<f32>,
    gain: [f32; 3],
    edge_blur_px: f32,
) -> Image<f32> {
    let (w, h, c) = img.shape();
    let mut out = img.clone();
    if c != 3 || w == 0 || h == 0 {
        return out;
    }
    let full = Image::from_vec(w, h, 1, resample(mask, w, h)).expect("w*h mask values");
    let lit: Vec<bool> = full.data().iter().map(|&v| v < 0.5).collect();
    let soft = if edge_blur_px > 0.0 {
        full.gaussian_blur(edge_blur_px)
    } else {
        full
    };
    let brightness: Vec<f32> = img
        .data()
        .chunks_exact(3)
        .map(|p| (to_linear(p[0]) + to_linear(p[1]) + to_linear(p[2])) / 3.0)
        .collect();
    let reference = local_mean(&brightness, &lit, w, h, (w.max(h) / 80).max(7));
    let mean_gain = (gain[0] + gain[1] + gain[2]) / 3.0;
    for (i, (p, &a)) in out
        .data_mut()
        .chunks_exact_mut(3)
        .zip(soft.data())
        .enumerate()
    {
        if a <= 0.0 {
            continue;
        }
        // Scale of the whole gain this pixel may take (1: all of it).
        let room = if reference[i].is_finite() && mean_gain > 1.0 {
            let most = MAX_OVER_LIT * reference[i] / brightness[i].max(1e-6);
            ((most - 1.0) / (mean_gain - 1.0)).clamp(0.0, 1.0)
        } else {
            1.0
        };
        let a = a.min(1.0) * room;
        for k in 0..3 {
            p[k] = to_display(to_linear(p[k]) * (1.0 + a * (gain[k] - 1.0)));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A camera looking straight down from `height` metres above `(x, y)`, over a ground
    /// plane z = 0 with a box of top `top` over `[−2, 2]²`.
    fn nadir(x: f64, y: f64, height: f64) -> (Camera, Pose) {
        let camera = Camera::pinhole(80, 80, 60.0, 60.0, 40.0, 40.0).unwrap();
        // Camera z looks down (−world z), camera x along world x, camera y along −world y.
        let r = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        let centre = Vector3::new(x, y, height);
        let t = -(r * centre);
        (camera, Pose::from_parts(Translation3::from(t), r))
    }

    fn box_depth(camera: &Camera, pose: &Pose, top: f64) -> Image<f32> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let inv = pose.inverse();
        let centre = inv.translation.vector;
        let mut d = Image::<f32>::new(w, h, 1);
        for y in 0..h {
            for x in 0..w {
                let b = camera
                    .unproject(Point2::new(x as f64 + 0.5, y as f64 + 0.5))
                    .unwrap();
                let dir = inv.rotation * b;
                // Hit the box top, else the ground.
                let t_top = (top - centre.z) / dir.z;
                let p = centre + dir * t_top;
                let t = if p.x.abs() <= 2.0 && p.y.abs() <= 2.0 {
                    t_top
                } else {
                    -centre.z / dir.z
                };
                d.data_mut()[y * w + x] = (t * b.z) as f32;
            }
        }
        d
    }

    #[test]
    fn a_box_shadows_the_ground_away_from_the_sun() {
        let views: Vec<(Camera, Pose)> = vec![nadir(0.0, 0.0, 20.0), nadir(3.0, 1.0, 20.0)];
        let depths: Vec<Image<f32>> = views.iter().map(|(c, p)| box_depth(c, p, 3.0)).collect();
        let dv: Vec<DepthView> = views
            .iter()
            .zip(&depths)
            .map(|((c, p), d)| DepthView {
                camera: c,
                cam_from_world: p,
                depth: d,
            })
            .collect();
        // Sun from +x, 45° up: the shadow lies on the −x side of the box, about 3 m long.
        let sun = Vector3::new(1.0, 0.0, 1.0);
        let mask = shadow_mask(&dv[0], &dv[1..], &sun, 80);
        let at = |wx: f64, wy: f64| {
            let q = dv[0]
                .camera
                .project(&(dv[0].cam_from_world * Point3::new(wx, wy, 0.0)).coords)
                .unwrap();
            mask.data()[q.y as usize * 80 + q.x as usize]
        };
        assert_eq!(at(-3.5, 0.0), 1.0, "beside the box, away from the sun");
        assert_eq!(at(3.5, 0.0), 0.0, "beside the box, towards the sun");
        assert_eq!(at(-7.0, 0.0), 0.0, "beyond the shadow's length");
        assert_eq!(at(0.0, 0.0), 0.0, "the box top is lit");
        assert_eq!(at(-3.5, 4.0), 0.0, "to the side of the shadow");
    }

    /// Whether the ground point `(x, y, 0)` lies in the shadow of the box `[−2, 2]² × [0, top]`
    /// under a sun in direction `sun` (slab test along the sun ray).
    fn box_shadows(x: f64, y: f64, top: f64, sun: &Vector3<f64>) -> bool {
        let (p, lo, hi) = ([x, y, 0.0], [-2.0, -2.0, 0.0], [2.0, 2.0, top]);
        let (mut t0, mut t1) = (1e-9f64, f64::INFINITY);
        for k in 0..3 {
            if sun[k].abs() < 1e-12 {
                if p[k] < lo[k] || p[k] > hi[k] {
                    return false;
                }
                continue;
            }
            let (a, b) = ((lo[k] - p[k]) / sun[k], (hi[k] - p[k]) / sun[k]);
            t0 = t0.max(a.min(b));
            t1 = t1.min(a.max(b));
        }
        t0 <= t1
    }

    /// The image a nadir view sees of the box scene: a textured ground and box top under
    /// sky light 1 and a sun of strength 4, the ground dark where the box shadows it.
    fn box_image(camera: &Camera, pose: &Pose, top: f64, sun: &Vector3<f64>) -> Image<f32> {
        let depth = box_depth(camera, pose, top);
        let (w, h) = (camera.width as usize, camera.height as usize);
        let inv = pose.inverse();
        let mut img = Image::<f32>::new(w, h, 3);
        for y in 0..h {
            for x in 0..w {
                let b = camera
                    .unproject(Point2::new(x as f64 + 0.5, y as f64 + 0.5))
                    .unwrap();
                let z = f64::from(depth.data()[y * w + x]);
                let p = inv * Point3::from(b * (z / b.z));
                let albedo = 0.25
                    + 0.2 * ((p.x * 3.1).sin() * (p.y * 2.3).cos()).abs()
                    + 0.1 * ((p.x * 0.7 + p.y * 1.3).sin() + 1.0) / 2.0;
                let lit = p.z > 0.5 || !box_shadows(p.x, p.y, top, sun);
                let light = 1.0 + if lit { 4.0 * sun.z.max(0.0) } else { 0.0 };
                for k in 0..3 {
                    img.data_mut()[3 * (y * w + x) + k] = to_display((albedo * light / 5.0) as f32);
                }
            }
        }
        img
    }

    #[test]
    fn the_sun_is_found_from_where_the_images_darken() {
        let sun = Vector3::new(
            40f64.to_radians().cos() * (-30f64).to_radians().cos(),
            40f64.to_radians().cos() * (-30f64).to_radians().sin(),
            40f64.to_radians().sin(),
        );
        let top = 3.0;
        let camera = Camera::pinhole(160, 160, 120.0, 120.0, 80.0, 80.0).unwrap();
        let poses: Vec<Pose> = [(0.0, 0.0), (3.0, 1.0), (-2.0, -3.0)]
            .iter()
            .map(|&(x, y)| nadir(x, y, 15.0).1)
            .collect();
        let depths: Vec<Image<f32>> = poses.iter().map(|p| box_depth(&camera, p, top)).collect();
        let images: Vec<Image<f32>> = poses
            .iter()
            .map(|p| box_image(&camera, p, top, &sun))
            .collect();
        let dv: Vec<DepthView> = poses
            .iter()
            .zip(&depths)
            .map(|(p, d)| DepthView {
                camera: &camera,
                cam_from_world: p,
                depth: d,
            })
            .collect();
        let views: Vec<SunView> = (0..3)
            .map(|i| SunView {
                view: dv[i],
                others: (0..3).filter(|&o| o != i).map(|o| dv[o]).collect(),
                image: &images[i],
            })
            .collect();
        let est = estimate_sun(&views, 160).expect("an estimate");
        // A ground pixel here is 1/8 m, and the shadow's length moves by a pixel per degree
        // of elevation: the search resolves a pixel or two.
        let off = est.direction.angle(&sun).to_degrees();
        assert!(off < 3.0, "{off:.2}° off: {est:?}");
        // What the lifting uses: the shadows it casts cover those of the true sun.
        let (mut both, mut either) = (0, 0);
        for v in &views {
            let a = shadow_mask(&v.view, &v.others, &sun, 160);
            let b = shadow_mask(&v.view, &v.others, &est.direction, 160);
            for (x, y) in a.data().iter().zip(b.data()) {
                both += usize::from(*x > 0.5 && *y > 0.5);
                either += usize::from(*x > 0.5 || *y > 0.5);
            }
        }
        let iou = both as f64 / either as f64;
        eprintln!("box scene: sun {off:.2}° off, masks IoU {iou:.3}: {est:?}");
        assert!(iou > 0.85, "shadows overlap the true sun's by {iou:.3}");
        // Sun 4× the sky at 40°: lit / shadowed = 1 + 4 sin 40° ≈ 3.6, ln ≈ 1.28.
        assert!(est.contrast > 0.8, "{est:?}");
        // One box: another sun can cast part of the same edges, never as well.
        assert!(est.rival < 0.9, "{est:?}");
    }

    #[test]
    fn the_gain_is_the_ratio_across_shadow_edges_and_lifting_restores_the_light() {
        // A textured image; the left half shadowed by a factor of 4 (R), 3 (G), 2 (B) in
        // linear light.
        let (w, h) = (64usize, 48usize);
        let mut lit = Image::<f32>::new(w, h, 3);
        let mut shadowed = Image::<f32>::new(w, h, 3);
        let mut mask = Image::<f32>::new(w, h, 1);
        let true_gain = [4.0f32, 3.0, 2.0];
        for y in 0..h {
            for x in 0..w {
                let texture = 0.4 + 0.05 * (((x * 7 + y * 13) % 5) as f32 / 4.0);
                for k in 0..3 {
                    let v = texture + 0.05 * k as f32;
                    lit.data_mut()[3 * (y * w + x) + k] = v;
                    shadowed.data_mut()[3 * (y * w + x) + k] = if x < w / 2 {
                        to_display(to_linear(v) / true_gain[k])
                    } else {
                        v
                    };
                }
                if x < w / 2 {
                    mask.data_mut()[y * w + x] = 1.0;
                }
            }
        }
        let mut edges = ShadowEdges::default();
        edges.add(&shadowed, &mask);
        let gain = edges.gain().expect("enough pairs");
        for k in 0..3 {
            assert!(
                (gain[k] / true_gain[k] - 1.0).abs() < 0.1,
                "channel {k}: {} vs {}",
                gain[k],
                true_gain[k]
            );
        }
        let restored = lift_shadows(&shadowed, &mask, gain, 0.0);
        let err = restored
            .data()
            .iter()
            .zip(lit.data())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(err < 0.03, "largest error {err}");
        // Without shadow edges there is no gain.
        let mut none = ShadowEdges::default();
        none.add(&lit, &Image::new(w, h, 1));
        assert!(none.gain().is_none());
    }
}
