//! Photometric augmentation of the encoder's training images.
//!
//! Queries come from other days: other exposure, white balance and tone curve, blur and noise,
//! and — what changes an aerial image most — a sun that moved, so that shadows fall elsewhere.
//! The map's NeRF features are tied to positions, not to light, so the encoder is trained to
//! give the same features under all of these: each training image gets a random exposure,
//! contrast, per-channel gain and gamma, optional blur and noise, and shadows: those its own
//! scene casts under a random sun (screen-space shadow rays against the view's rendered depth),
//! or, where the view's geometry is unknown, parallelograms extruded along one random direction;
//! both are darkened in linear light and tinted towards the sky's blue, and some parallelograms
//! are lifted instead (a shadow of the map's flight lit by the sun).

use matloc_core::Image;
use matloc_core::shadow::{to_display, to_linear};
use nalgebra::{Point2, Vector3};

use crate::{ENCODER_STRIDE, EncoderSample, SampleView};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Photometric augmentation applied to training images.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JitterConfig {
    /// Brightness gain drawn from `1 ± brightness`.
    pub brightness: f32,
    /// Contrast about the image mean, `1 ± contrast`.
    pub contrast: f32,
    /// Per-channel gain `1 ± colour` (white balance).
    pub colour: f32,
    /// Tone-curve change: values raised to `exp(±gamma)`.
    pub gamma: f32,
    /// Gaussian pixel noise standard deviation.
    pub noise: f32,
    /// Largest Gaussian blur, pixels (half the images get a blur of `U(0, blur)`).
    pub blur: f32,
    /// Chance that an image with known geometry gets the shadows its scene casts under a random
    /// sun.
    pub scene_shadow_chance: f32,
    /// Sun elevation range of those shadows, degrees above the horizon.
    pub sun_elevation_deg: [f32; 2],
    /// Chance that an image gets parallelogram shadows.
    pub shadow_chance: f32,
    /// Most shadow regions in one image.
    pub shadow_count: u32,
    /// Linear-light factor range of a shadow `[darkest, lightest]` (a sunlit surface in a cast
    /// shadow keeps roughly its sky light, 0.15–0.4 of its light).
    pub shadow_factor: [f32; 2],
    /// Chance that a shadow region is lifted (divided by the factor) instead of darkened.
    pub shadow_lift: f32,
}

impl Default for JitterConfig {
    /// Brightness and contrast only: the heavier recipe ([`JitterConfig::another_day`]) made
    /// same-flight queries worse and did not make queries of another day good enough
    /// (docs/DECISIONS.md).
    fn default() -> Self {
        JitterConfig {
            brightness: 0.2,
            contrast: 0.2,
            ..JitterConfig::none()
        }
    }
}

impl JitterConfig {
    /// Exposure, white balance, tone curve, blur, noise and moved-sun shadows, for maps whose
    /// MatLoc queries come from another day.
    pub fn another_day() -> Self {
        JitterConfig {
            brightness: 0.3,
            contrast: 0.2,
            colour: 0.1,
            gamma: 0.15,
            noise: 0.015,
            blur: 0.8,
            scene_shadow_chance: 0.6,
            sun_elevation_deg: [15.0, 65.0],
            shadow_chance: 0.4,
            shadow_count: 8,
            shadow_factor: [0.15, 0.5],
            shadow_lift: 0.3,
        }
    }

    /// No augmentation.
    pub fn none() -> Self {
        JitterConfig {
            brightness: 0.0,
            contrast: 0.0,
            colour: 0.0,
            gamma: 0.0,
            noise: 0.0,
            blur: 0.0,
            scene_shadow_chance: 0.0,
            sun_elevation_deg: [15.0, 65.0],
            shadow_chance: 0.0,
            shadow_count: 0,
            shadow_factor: [1.0, 1.0],
            shadow_lift: 0.0,
        }
    }

    /// Checks the ranges (all finite, non-negative; shadow factors in `(0, 1]`, ordered).
    pub fn validate(&self) -> Result<(), String> {
        let fields = [
            ("brightness", self.brightness),
            ("contrast", self.contrast),
            ("colour", self.colour),
            ("gamma", self.gamma),
            ("noise", self.noise),
            ("blur", self.blur),
            ("shadow_chance", self.shadow_chance),
            ("scene_shadow_chance", self.scene_shadow_chance),
            ("shadow_lift", self.shadow_lift),
        ];
        for (name, v) in fields {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!(
                    "jitter.{name} must be a non-negative number, got {v}"
                ));
            }
        }
        for (name, v) in [
            ("brightness", self.brightness),
            ("contrast", self.contrast),
            ("colour", self.colour),
        ] {
            if v >= 1.0 {
                return Err(format!("jitter.{name} must be below 1, got {v}"));
            }
        }
        if self.blur > 10.0 {
            return Err(format!(
                "jitter.blur must be at most 10 px, got {}",
                self.blur
            ));
        }
        let [e0, e1] = self.sun_elevation_deg;
        if !(e0 > 0.0 && e0 <= e1 && e1 <= 90.0) {
            return Err(format!(
                "jitter.sun_elevation_deg must satisfy 0 < low <= high <= 90, got {:?}",
                self.sun_elevation_deg
            ));
        }
        let [lo, hi] = self.shadow_factor;
        if !(lo > 0.0 && lo <= hi && hi <= 1.0) {
            return Err(format!(
                "jitter.shadow_factor must satisfy 0 < darkest <= lightest <= 1, got {:?}",
                self.shadow_factor
            ));
        }
        Ok(())
    }
}

/// One random augmentation of a training sample's image (RGB, values in `[0, 1]`).
pub(crate) fn jitter(
    sample: &EncoderSample,
    cfg: &JitterConfig,
    rng: &mut ChaCha8Rng,
) -> Image<f32> {
    let img = &sample.image;
    let u = |a: f32, rng: &mut ChaCha8Rng| {
        if a > 0.0 {
            rng.random_range(-a..a)
        } else {
            0.0
        }
    };
    let mut out = img.clone();
    if let Some(view) = &sample.view
        && cfg.scene_shadow_chance > 0.0
        && rng.random::<f32>() < cfg.scene_shadow_chance
    {
        scene_shadows(&mut out, view, &sample.target, cfg, rng);
    }
    if cfg.shadow_chance > 0.0 && cfg.shadow_count > 0 && rng.random::<f32>() < cfg.shadow_chance {
        cast_shadows(&mut out, cfg, rng);
    }
    if cfg.blur > 0.0 && rng.random::<bool>() {
        out = out.gaussian_blur(rng.random_range(0.0..cfg.blur));
    }
    let gain = 1.0 + u(cfg.brightness, rng);
    let contrast = 1.0 + u(cfg.contrast, rng);
    let gamma = u(cfg.gamma, rng).exp();
    let ch = [
        1.0 + u(cfg.colour, rng),
        1.0 + u(cfg.colour, rng),
        1.0 + u(cfg.colour, rng),
    ];
    let mean = out.data().iter().sum::<f32>() / out.data().len().max(1) as f32;
    for (k, o) in out.data_mut().iter_mut().enumerate() {
        let n = if cfg.noise > 0.0 {
            // Box–Muller on the fly keeps the crate free of a distributions dependency.
            let u1: f32 = 1.0 - rng.random::<f32>();
            let u2: f32 = rng.random::<f32>();
            cfg.noise * (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
        } else {
            0.0
        };
        let v = (((*o - mean) * contrast + mean) * gain * ch[k % 3]).clamp(0.0, 1.0);
        *o = (v.powf(gamma) + n).clamp(0.0, 1.0);
    }
    out
}

/// A random sun direction in camera coordinates: azimuth uniform about `up`, elevation in
/// `cfg.sun_elevation_deg`.
fn random_sun(up: Vector3<f64>, cfg: &JitterConfig, rng: &mut ChaCha8Rng) -> Vector3<f64> {
    let helper = if up.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = up.cross(&helper).normalize();
    let e2 = up.cross(&e1);
    let az = rng.random_range(0.0..std::f64::consts::TAU);
    let [lo, hi] = cfg.sun_elevation_deg;
    let el = f64::from(if hi > lo {
        rng.random_range(lo..hi)
    } else {
        lo
    })
    .to_radians();
    (e1 * az.cos() + e2 * az.sin()) * el.cos() + up * el.sin()
}

/// Z-depth of the target grid at pixel `(x, y)` (cell centres at the middle of each stride
/// block): bilinear on smooth surfaces, the nearest cell across a depth edge; `None` where any
/// neighbour has no surface.
fn depth_at(target: &crate::RenderedView, x: f64, y: f64) -> Option<f64> {
    let s = f64::from(ENCODER_STRIDE);
    let gx = (x / s - 0.5).clamp(0.0, (target.cols - 1) as f64);
    let gy = (y / s - 0.5).clamp(0.0, (target.rows - 1) as f64);
    let (x0, y0) = (gx.floor() as usize, gy.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(target.cols - 1), (y0 + 1).min(target.rows - 1));
    let (ax, ay) = (gx - x0 as f64, gy - y0 as f64);
    let d = |cx: usize, cy: usize| {
        let v = target.depth_z[cy * target.cols + cx];
        (v.is_finite() && v > 0.0).then_some(f64::from(v))
    };
    let (a, b, c, e) = (d(x0, y0)?, d(x1, y0)?, d(x0, y1)?, d(x1, y1)?);
    let (lo, hi) = (a.min(b).min(c).min(e), a.max(b).max(c).max(e));
    if hi > 1.05 * lo {
        // A depth edge: the nearest cell, never a surface floating between the two.
        return Some(match (ax < 0.5, ay < 0.5) {
            (true, true) => a,
            (false, true) => b,
            (true, false) => c,
            (false, false) => e,
        });
    }
    let top = a + ax * (b - a);
    let bottom = c + ax * (e - c);
    Some(top + ay * (bottom - top))
}

/// Darkens what the view's own geometry shadows from a random sun: from each pixel's surface
/// point (the target's depth), a ray towards the sun is marched in growing steps; once a step
/// projects behind the visible surface (deeper than the depth there, within a thickness of
/// 0.3 × the pixel's depth) the pixel is in shadow. Shadows are darkened in linear light by a
/// random factor of `cfg.shadow_factor`, tinted blue, with a soft 0.7 px edge.
fn scene_shadows(
    img: &mut Image<f32>,
    view: &SampleView,
    target: &crate::RenderedView,
    cfg: &JitterConfig,
    rng: &mut ChaCha8Rng,
) {
    let (w, h, c) = img.shape();
    let cam = &view.camera;
    if c != 3
        || cam.width as usize != w
        || cam.height as usize != h
        || target.cols == 0
        || target.rows == 0
        || target.depth_z.len() != target.cols * target.rows
    {
        return;
    }
    let up = Vector3::from(view.up_cam);
    if up.norm().is_nan() || up.norm() <= 0.5 {
        return;
    }
    let sun = random_sun(up.normalize(), cfg, rng);
    let mut mask = Image::<f32>::new(w, h, 1);
    for y in 0..h {
        for x in 0..w {
            let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
            let (Some(z), Some(b)) = (depth_at(target, px, py), cam.unproject(Point2::new(px, py)))
            else {
                continue;
            };
            if b.z <= 1e-6 {
                continue;
            }
            let surface = b * (z / b.z);
            let mut t = 0.004 * z;
            for _ in 0..26 {
                let p = surface + sun * t;
                t *= 1.35;
                if p.z <= 1e-3 {
                    break;
                }
                let Some(q) = cam.project(&p) else { break };
                if !(q.x >= 0.0 && q.y >= 0.0 && q.x < w as f64 && q.y < h as f64) {
                    break;
                }
                let Some(d) = depth_at(target, q.x, q.y) else {
                    continue;
                };
                if p.z > d * 1.01 + 0.05 && p.z < d + 0.3 * z {
                    mask.data_mut()[y * w + x] = 1.0;
                    break;
                }
            }
        }
    }
    let mask = mask.gaussian_blur(0.7);
    let [lo, hi] = cfg.shadow_factor;
    let factor = if hi > lo {
        rng.random_range(lo..hi)
    } else {
        lo
    };
    let tint = [0.85f32, 1.0, 1.25];
    for (i, &alpha) in mask.data().iter().enumerate() {
        if alpha <= 0.0 {
            continue;
        }
        let p = &mut img.data_mut()[i * 3..i * 3 + 3];
        for k in 0..3 {
            let g = 1.0 + alpha * ((factor * tint[k]).min(1.0) - 1.0);
            p[k] = to_display(to_linear(p[k]) * g);
        }
    }
}

/// Darkens (or lifts) parallelograms extruded along one random direction: the footprint of
/// shadows cast by a sun at another azimuth and elevation.
fn cast_shadows(img: &mut Image<f32>, cfg: &JitterConfig, rng: &mut ChaCha8Rng) {
    let (w, h, c) = img.shape();
    if c != 3 || w == 0 || h == 0 {
        return;
    }
    let size = w.max(h) as f32;
    let theta = rng.random_range(0.0..std::f32::consts::TAU);
    let (dx, dy) = (theta.cos(), theta.sin());
    // Sky-lit shadow colour relative to sun + sky light: bluer than the lit surface.
    let tint = [0.85f32, 1.0, 1.25];
    let count = rng.random_range(1..=cfg.shadow_count);
    let [lo, hi] = cfg.shadow_factor;
    for _ in 0..count {
        let ax = rng.random_range(0.0..w as f32);
        let ay = rng.random_range(0.0..h as f32);
        let length = rng.random_range(0.05..0.4) * size;
        let half_base = 0.5 * rng.random_range(0.03..0.2) * size;
        let factor = if hi > lo {
            rng.random_range(lo..hi)
        } else {
            lo
        };
        let lift = rng.random::<f32>() < cfg.shadow_lift;
        let gains: [f32; 3] = std::array::from_fn(|k| {
            let g = (factor * tint[k]).min(1.0);
            if lift { 1.0 / g } else { g }
        });
        // Bounding box of the parallelogram (plus the 1 px soft edge).
        let corners = [
            (ax - dy * half_base, ay + dx * half_base),
            (ax + dy * half_base, ay - dx * half_base),
            (
                ax - dy * half_base + dx * length,
                ay + dx * half_base + dy * length,
            ),
            (
                ax + dy * half_base + dx * length,
                ay - dx * half_base + dy * length,
            ),
        ];
        let x0 = corners
            .iter()
            .map(|p| p.0)
            .fold(f32::INFINITY, f32::min)
            .floor()
            - 1.0;
        let x1 = corners
            .iter()
            .map(|p| p.0)
            .fold(f32::NEG_INFINITY, f32::max)
            .ceil()
            + 1.0;
        let y0 = corners
            .iter()
            .map(|p| p.1)
            .fold(f32::INFINITY, f32::min)
            .floor()
            - 1.0;
        let y1 = corners
            .iter()
            .map(|p| p.1)
            .fold(f32::NEG_INFINITY, f32::max)
            .ceil()
            + 1.0;
        let (x0, x1) = (x0.max(0.0) as usize, (x1.max(0.0) as usize).min(w));
        let (y0, y1) = (y0.max(0.0) as usize, (y1.max(0.0) as usize).min(h));
        for y in y0..y1 {
            for x in x0..x1 {
                let (px, py) = (x as f32 + 0.5 - ax, y as f32 + 0.5 - ay);
                let along = px * dx + py * dy;
                let across = -px * dy + py * dx;
                let inside = along
                    .min(length - along)
                    .min(half_base + across)
                    .min(half_base - across);
                let alpha = (inside + 0.5).clamp(0.0, 1.0);
                if alpha <= 0.0 {
                    continue;
                }
                let p = img.pixel_mut(x, y);
                for k in 0..3 {
                    let lin = to_linear(p[k]);
                    let g = 1.0 + alpha * (gains[k] - 1.0);
                    p[k] = to_display(lin * g);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn grey(w: usize, h: usize, v: f32) -> EncoderSample {
        EncoderSample {
            image: Image::from_vec(w, h, 3, vec![v; w * h * 3]).unwrap(),
            target: crate::RenderedView {
                cols: w / 4,
                rows: h / 4,
                dims: 0,
                features: Vec::new(),
                depth_z: vec![0.0; (w / 4) * (h / 4)],
                accumulation: vec![0.0; (w / 4) * (h / 4)],
            },
            view: None,
        }
    }

    #[test]
    fn none_is_the_identity_and_defaults_validate() {
        let img = grey(16, 12, 0.4);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        assert_eq!(jitter(&img, &JitterConfig::none(), &mut rng), img.image);
        JitterConfig::default().validate().unwrap();
        JitterConfig::another_day().validate().unwrap();
        JitterConfig::none().validate().unwrap();
        let bad = JitterConfig {
            shadow_factor: [0.5, 0.2],
            ..JitterConfig::default()
        };
        assert!(bad.validate().unwrap_err().contains("shadow_factor"));
        let bad = JitterConfig {
            blur: f32::NAN,
            ..JitterConfig::default()
        };
        assert!(bad.validate().unwrap_err().contains("blur"));
    }

    #[test]
    fn shadows_darken_regions_bluer_and_stay_in_range() {
        let cfg = JitterConfig {
            shadow_chance: 1.0,
            shadow_lift: 0.0,
            ..JitterConfig::none()
        };
        let cfg = JitterConfig {
            shadow_count: 8,
            shadow_factor: [0.2, 0.3],
            ..cfg
        };
        let img = grey(64, 48, 0.6);
        let mut darker = 0;
        for seed in 0..8 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let out = jitter(&img, &cfg, &mut rng);
            for p in out.data().chunks(3) {
                assert!(p.iter().all(|v| (0.0..=1.0).contains(v)));
                if p[1] < 0.5 {
                    darker += 1;
                    // Shadow light is the sky's: blue keeps more than red.
                    assert!(p[2] > p[0], "{p:?}");
                }
            }
        }
        assert!(darker > 100, "shadows too rare: {darker} px");
    }

    #[test]
    fn a_box_casts_a_shadow_on_the_ground_beside_it() {
        // Nadir view of flat ground 30 m away with a 10 m tall box in the middle.
        let (w, h) = (64usize, 48usize);
        let mut s = grey(w, h, 0.6);
        let (cols, rows) = (w / 4, h / 4);
        for r in 0..rows {
            for c in 0..cols {
                let in_box = (6..10).contains(&c) && (4..8).contains(&r);
                s.target.depth_z[r * cols + c] = if in_box { 20.0 } else { 30.0 };
                s.target.accumulation[r * cols + c] = 1.0;
            }
        }
        s.view = Some(SampleView {
            camera: matloc_core::Camera::from_hfov(w as u32, h as u32, 60.0).unwrap(),
            up_cam: [0.0, 0.0, -1.0],
        });
        let cfg = JitterConfig {
            scene_shadow_chance: 1.0,
            sun_elevation_deg: [40.0, 40.0],
            shadow_factor: [0.2, 0.2],
            ..JitterConfig::none()
        };
        let mut shadowed_ground = 0;
        for seed in 0..4 {
            let out = jitter(&s, &cfg, &mut ChaCha8Rng::seed_from_u64(seed));
            for y in 0..h {
                for x in 0..w {
                    let p = out.pixel(x, y);
                    let on_box = (26..38).contains(&x) && (18..30).contains(&y);
                    if on_box {
                        assert!(p[1] > 0.55, "the box top is lit, got {p:?} at {x},{y}");
                    } else if p[1] < 0.45 {
                        shadowed_ground += 1;
                        assert!(p[2] > p[0]);
                    }
                }
            }
        }
        // A 10 m box at 40° casts ~12 m of shadow, ~25 px at this scale, 16 px wide.
        assert!(
            shadowed_ground > 4 * 150,
            "{shadowed_ground} shadowed ground pixels"
        );
    }

    #[test]
    fn jitter_is_seeded() {
        let img = grey(32, 24, 0.5);
        let cfg = JitterConfig::another_day();
        let a = jitter(&img, &cfg, &mut ChaCha8Rng::seed_from_u64(3));
        let b = jitter(&img, &cfg, &mut ChaCha8Rng::seed_from_u64(3));
        assert_eq!(a, b);
    }
}
