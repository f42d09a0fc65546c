//! A float gradient-histogram descriptor (SIFT's layout, RootSIFT's normalisation) on the
//! detector's keypoints: a square of 4 × 4 cells around the keypoint, turned to its
//! orientation, each cell an 8-bin histogram of gradient directions weighted by magnitude
//! and a Gaussian over the square, spread trilinearly over cells and bins. The 128 values
//! are L2-normalised, clipped at 0.2 and normalised again (SIFT), then L1-normalised and
//! square-rooted (RootSIFT: the Euclidean distance of the results is the Hellinger distance
//! of the histograms), and stored as bytes (× 512, at most 255).
//!
//! Gradients change sign and scale with the light but their directions do not, and a
//! histogram over a cell tolerates a pixel or two of shift: the descriptor keeps matching
//! under brightness, contrast and white-balance changes where a binary test between two
//! pixels can flip.

use std::f32::consts::{SQRT_2, TAU};

use rayon::prelude::*;

use crate::detect::{
    Descriptor, Keypoint, KeypointConfig, binary_describer, detect_with, harris, level_scale,
    pyramid,
};
use crate::gray::GrayImage;

/// A 128-value gradient-histogram descriptor, quantised to bytes.
pub type GradientDescriptor = [u8; 128];

/// Half the side of the described square, level pixels: its turned corners stay inside the
/// detector's border.
const HALF_WIDTH: f32 = 11.0;
/// Cells per side.
const CELLS: usize = 4;
/// Orientation bins per cell.
const BINS: usize = 8;
/// Blur of the level image before its gradients are taken.
const SMOOTH_SIGMA: f32 = 1.0;
/// SIFT's clip of a normalised histogram value.
const CLIP: f32 = 0.2;
/// Byte quantisation scale.
const QUANT: f32 = 512.0;

/// Detects keypoints as [`crate::detect_and_describe`] does and describes each with a
/// [`GradientDescriptor`]. Images smaller than the patch give no keypoints.
pub fn detect_and_describe_gradients(
    image: &GrayImage,
    config: &KeypointConfig,
) -> (Vec<Keypoint>, Vec<GradientDescriptor>) {
    detect_with(image, config, |level| {
        let field = GradientField::new(level);
        move |x, y, angle| field.describe(x as f32, y as f32, angle)
    })
}

/// Gradient-histogram descriptors of keypoints [`crate::detect_and_describe`] found in
/// `image` with `config` (the same image and configuration): each described on its own
/// pyramid level, exactly as [`detect_and_describe_gradients`] would have, without detecting
/// again. A keypoint whose level the pyramid lacks gets an all-zero descriptor.
pub fn describe_gradients_at(
    image: &GrayImage,
    config: &KeypointConfig,
    keypoints: &[Keypoint],
) -> Vec<GradientDescriptor> {
    let pyramid = pyramid(image, config);
    let used: Vec<bool> = (0..pyramid.len())
        .map(|l| keypoints.iter().any(|k| usize::from(k.level) == l))
        .collect();
    let fields: Vec<Option<GradientField>> = pyramid
        .par_iter()
        .zip(used.par_iter())
        .map(|(level, &used)| used.then(|| GradientField::new(level)))
        .collect();
    keypoints
        .par_iter()
        .map(|k| {
            let l = usize::from(k.level);
            match (pyramid.get(l), fields.get(l).and_then(Option::as_ref)) {
                (Some(level), Some(field)) => {
                    let (x, y) = detected_pixel(image, level, k);
                    field.describe(x as f32, y as f32, k.angle)
                }
                _ => [0; 128],
            }
        })
        .collect()
}

/// The pixel of `level` the detector found keypoint `k` at: its position less the sub-pixel
/// offset (at most half a pixel), rounded; where the offset was a full half pixel both
/// neighbours are candidates, and the one whose Harris response is the keypoint's wins.
fn detected_pixel(image: &GrayImage, level: &GrayImage, k: &Keypoint) -> (usize, usize) {
    let (sx, sy) = level_scale(image, level);
    let candidates = |v: f32, side: usize| -> Vec<usize> {
        let inside = |c: f32| (c.max(0.0) as usize).min(side.saturating_sub(1));
        if (v - v.floor() - 0.5).abs() < 1e-3 {
            vec![inside(v.floor()), inside(v.ceil())]
        } else {
            vec![inside(v.round())]
        }
    };
    let xs = candidates(k.x / sx - 0.5, level.width());
    let ys = candidates(k.y / sy - 0.5, level.height());
    if xs.len() == 1 && ys.len() == 1 {
        return (xs[0], ys[0]);
    }
    let mut best = (xs[0], ys[0]);
    let mut best_gap = f32::INFINITY;
    for &x in &xs {
        for &y in &ys {
            // The Harris window reaches four pixels out.
            let inside = x >= 4 && y >= 4 && x + 4 < level.width() && y + 4 < level.height();
            let gap = if inside {
                (harris(level, x, y) - k.response).abs()
            } else {
                f32::INFINITY
            };
            if gap < best_gap {
                (best, best_gap) = ((x, y), gap);
            }
        }
    }
    best
}

/// Detects keypoints as [`crate::detect_and_describe`] does and describes each both ways:
/// rotated BRIEF and gradient histogram, for one detection's cost.
pub fn detect_and_describe_both(
    image: &GrayImage,
    config: &KeypointConfig,
) -> (Vec<Keypoint>, Vec<Descriptor>, Vec<GradientDescriptor>) {
    let (keypoints, both): (Vec<Keypoint>, Vec<(Descriptor, GradientDescriptor)>) =
        detect_with(image, config, |level| {
            let field = GradientField::new(level);
            let binary = binary_describer(level);
            move |x, y, angle| {
                (
                    binary(x, y, angle),
                    field.describe(x as f32, y as f32, angle),
                )
            }
        });
    let (binary, gradient) = both.into_iter().unzip();
    (keypoints, binary, gradient)
}

/// An image's gradients (magnitude and direction per pixel, after a 1 px blur), computed once
/// and shared by every keypoint described on it.
pub struct GradientField {
    width: usize,
    height: usize,
    magnitude: Vec<f32>,
    /// Direction, radians in `(−π, π]`.
    direction: Vec<f32>,
}

impl GradientField {
    /// The gradients of `image` (central differences on the image blurred by 1 px; zero on
    /// the border).
    pub fn new(image: &GrayImage) -> Self {
        let smooth = image.gaussian_blur(SMOOTH_SIGMA);
        let (w, h) = (smooth.width(), smooth.height());
        let mut magnitude = vec![0.0f32; w * h];
        let mut direction = vec![0.0f32; w * h];
        for y in 1..h.saturating_sub(1) {
            for x in 1..w - 1 {
                let gx = smooth.at(x + 1, y) - smooth.at(x - 1, y);
                let gy = smooth.at(x, y + 1) - smooth.at(x, y - 1);
                magnitude[y * w + x] = (gx * gx + gy * gy).sqrt();
                direction[y * w + x] = gy.atan2(gx);
            }
        }
        Self {
            width: w,
            height: h,
            magnitude,
            direction,
        }
    }

    /// The descriptor of the square centred on `(x, y)` (pixel indices) turned by `angle`
    /// (radians, image axes). Samples outside the image are left out; a flat patch gives
    /// zeros.
    pub fn describe(&self, x: f32, y: f32, angle: f32) -> GradientDescriptor {
        let mut hist = [0.0f32; CELLS * CELLS * BINS];
        let (s, c) = angle.sin_cos();
        let cell = 2.0 * HALF_WIDTH / CELLS as f32;
        let two_sigma2 = 2.0 * HALF_WIDTH * HALF_WIDTH;
        let reach = (HALF_WIDTH * SQRT_2).ceil() as i32;
        let (w, h) = (self.width as i32, self.height as i32);
        let (cx, cy) = (x.round() as i32, y.round() as i32);
        for dy in -reach..=reach {
            let py = cy + dy;
            if py < 1 || py >= h - 1 {
                continue;
            }
            for dx in -reach..=reach {
                let px = cx + dx;
                if px < 1 || px >= w - 1 {
                    continue;
                }
                // Offset in the keypoint's frame (the image offset turned by −angle).
                let (fx, fy) = ((px as f32) - x, (py as f32) - y);
                let u = c * fx + s * fy;
                let v = -s * fx + c * fy;
                if u.abs() >= HALF_WIDTH || v.abs() >= HALF_WIDTH {
                    continue;
                }
                let at = py as usize * self.width + px as usize;
                let magnitude = self.magnitude[at];
                if magnitude <= 0.0 {
                    continue;
                }
                let weight = magnitude * (-(u * u + v * v) / two_sigma2).exp();
                let o = (self.direction[at] - angle).rem_euclid(TAU) / TAU * BINS as f32;
                let cu = (u + HALF_WIDTH) / cell - 0.5;
                let cv = (v + HALF_WIDTH) / cell - 0.5;
                let (u0, v0, o0) = (cu.floor(), cv.floor(), o.floor());
                let (tu, tv, to) = (cu - u0, cv - v0, o - o0);
                for (iu, wu) in [(u0 as i32, 1.0 - tu), (u0 as i32 + 1, tu)] {
                    if !(0..CELLS as i32).contains(&iu) {
                        continue;
                    }
                    for (iv, wv) in [(v0 as i32, 1.0 - tv), (v0 as i32 + 1, tv)] {
                        if !(0..CELLS as i32).contains(&iv) {
                            continue;
                        }
                        let base = (iv as usize * CELLS + iu as usize) * BINS;
                        let ob = o0 as usize % BINS;
                        let share = weight * wu * wv;
                        hist[base + ob] += share * (1.0 - to);
                        hist[base + (ob + 1) % BINS] += share * to;
                    }
                }
            }
        }
        normalise(&mut hist);
        let mut out = [0u8; 128];
        for (o, v) in out.iter_mut().zip(hist) {
            *o = (v * QUANT).round().clamp(0.0, 255.0) as u8;
        }
        out
    }
}

/// SIFT's normalise–clip–normalise, then RootSIFT's L1 normalisation and square root; an
/// all-zero histogram stays zero.
fn normalise(hist: &mut [f32]) {
    let l2 = |h: &[f32]| h.iter().map(|v| v * v).sum::<f32>().sqrt();
    let n = l2(hist);
    if n.is_nan() || n <= 0.0 {
        hist.fill(0.0);
        return;
    }
    for v in hist.iter_mut() {
        *v = (*v / n).min(CLIP);
    }
    let l1: f32 = hist.iter().sum();
    for v in hist.iter_mut() {
        *v = (*v / l1).sqrt();
    }
}

/// Euclidean distance of two gradient descriptors, squared, in quantised units.
#[inline]
pub fn gradient_distance_sq(a: &GradientDescriptor, b: &GradientDescriptor) -> u32 {
    let mut acc = 0i32;
    for (x, y) in a.iter().zip(b) {
        let d = i32::from(*x) - i32::from(*y);
        acc += d * d;
    }
    acc as u32
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A textured image: a few sinusoids and blobs, in `[0.1, 0.9]`.
    fn texture(w: usize, h: usize, seed: u32) -> GrayImage {
        let f = seed as f32 * 0.37;
        let data = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                let v = 0.5
                    + 0.18 * (0.21 * x + 0.13 * y + f).sin()
                    + 0.12 * (0.07 * x - 0.31 * y + 2.0 * f).cos()
                    + 0.1 * ((0.05 * x + f).sin() * (0.09 * y - f).cos() * 3.0).tanh();
                v.clamp(0.1, 0.9)
            })
            .collect();
        GrayImage::from_vec(w, h, data).unwrap()
    }

    fn norm(d: &GradientDescriptor) -> f32 {
        d.iter()
            .map(|&v| f32::from(v) * f32::from(v))
            .sum::<f32>()
            .sqrt()
    }

    /// Described after detection, on the keypoints a binary detection found, the gradient
    /// descriptors are those a gradient detection gives, with and without the 2× upsampling,
    /// keypoints a half pixel off their detected pixel included.
    #[test]
    fn describing_detected_keypoints_again_gives_the_detections_descriptors() {
        let img = texture(160, 120, 5);
        for upsample in [false, true] {
            let config = KeypointConfig {
                upsample,
                max_keypoints: 400,
                ..KeypointConfig::default()
            };
            let (keypoints, _) = crate::detect_and_describe(&img, &config);
            let (again, expected) = detect_and_describe_gradients(&img, &config);
            let pyramid = pyramid(&img, &config);
            let half = keypoints
                .iter()
                .filter(|k| {
                    let (sx, sy) = level_scale(&img, &pyramid[usize::from(k.level)]);
                    let v = [k.x / sx - 0.5, k.y / sy - 0.5];
                    v.iter().any(|v| (v - v.floor() - 0.5).abs() < 1e-3)
                })
                .count();
            // Keypoints whose sub-pixel offset is a full half pixel, where the detected pixel
            // is told by its Harris response: both cases are covered.
            assert!(half > 0 && half < keypoints.len(), "{half}");
            assert!(keypoints.len() > 50, "{}", keypoints.len());
            assert_eq!(keypoints, again);
            let described = describe_gradients_at(&img, &config, &keypoints);
            let differing = described
                .iter()
                .zip(&expected)
                .filter(|(a, b)| a != b)
                .count();
            assert_eq!(differing, 0, "of {}", expected.len());
        }
    }

    #[test]
    fn descriptors_are_unit_length_and_flat_patches_zero() {
        let img = texture(64, 64, 1);
        let d = GradientField::new(&img).describe(32.0, 32.0, 0.3);
        // RootSIFT values have unit L2 norm before the byte scale.
        let n = norm(&d) / QUANT;
        assert!((n - 1.0).abs() < 0.02, "{n}");
        let flat = GrayImage::from_vec(64, 64, vec![0.4; 64 * 64]).unwrap();
        assert_eq!(
            GradientField::new(&flat).describe(32.0, 32.0, 0.0),
            [0u8; 128]
        );
    }

    #[test]
    fn turning_the_image_and_the_angle_together_keeps_the_descriptor() {
        // The image turned by 90° (x' = h−1−y, y' = x) and the keypoint angle by +90°.
        let (w, h) = (64, 64);
        let img = texture(w, h, 3);
        let mut turned = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                turned[x * w + (h - 1 - y)] = img.at(x, y);
            }
        }
        let turned = GrayImage::from_vec(h, w, turned).unwrap();
        let a = GradientField::new(&img).describe(30.0, 33.0, 0.4);
        let b = GradientField::new(&turned).describe(
            (h - 1 - 33) as f32,
            30.0,
            0.4 + std::f32::consts::FRAC_PI_2,
        );
        let other = GradientField::new(&img).describe(36.0, 27.0, 0.4);
        let d = (gradient_distance_sq(&a, &b) as f32).sqrt();
        let far = (gradient_distance_sq(&a, &other) as f32).sqrt();
        assert!(d < 0.1 * QUANT, "turned {d}, another patch {far}");
        assert!(far > 3.0 * d, "turned {d}, another patch {far}");
    }

    proptest! {
        /// A change of light — white balance (a gain per colour channel), exposure,
        /// contrast (a gamma) and an offset, applied to a colour image before its gray is
        /// taken (unclipped: a saturated sensor loses the texture itself) — leaves the descriptor nearer its own place's than any other's nearby.
        #[test]
        fn light_changes_barely_move_the_descriptor(
            gains in proptest::array::uniform3(0.6f32..1.5),
            exposure in 0.6f32..1.6,
            offset in -0.15f32..0.15,
            gamma in 0.8f32..1.25,
            seed in 0u32..50,
            angle in -3.1f32..3.1,
        ) {
            let (w, h) = (64, 64);
            // Colour: the texture with a second pattern mixed into red and blue.
            let base = texture(w, h, seed);
            let other = texture(w, h, seed + 101);
            let mut rgb = Vec::with_capacity(w * h * 3);
            let mut relit = Vec::with_capacity(w * h * 3);
            for (a, b) in base.data().iter().zip(other.data()) {
                let px = [0.7 * a + 0.3 * b, *a, 0.5 * a + 0.5 * b];
                for (c, v) in px.iter().enumerate() {
                    rgb.push(*v);
                    relit.push(exposure * gains[c] * v.powf(gamma) + offset);
                }
            }
            let gray = |data: Vec<f32>| {
                GrayImage::from_image(&matloc_core::Image::from_vec(w, h, 3, data).unwrap())
            };
            let (img, relit) = (gray(rgb), gray(relit));
            let (field, relit_field) = (GradientField::new(&img), GradientField::new(&relit));
            let b = relit_field.describe(32.0, 31.0, angle);
            // The relit descriptor's nearest among the original's on a 5 × 5 grid 4 px apart
            // is the one at its own place.
            let mut nearest = (u32::MAX, (0, 0));
            for i in -2i32..=2 {
                for j in -2i32..=2 {
                    let a = field.describe(32.0 + 4.0 * i as f32, 31.0 + 4.0 * j as f32, angle);
                    let d = gradient_distance_sq(&a, &b);
                    if d < nearest.0 {
                        nearest = (d, (i, j));
                    }
                }
            }
            let d = (nearest.0 as f32).sqrt();
            prop_assert_eq!(nearest.1, (0, 0), "relit nearest at another place ({})", d);
            prop_assert!(d < 0.25 * QUANT, "relit {}", d);
        }

        /// Distances are symmetric, zero on the diagonal and obey the triangle inequality.
        #[test]
        fn distance_is_a_metric(a in proptest::collection::vec(any::<u8>(), 128),
                                b in proptest::collection::vec(any::<u8>(), 128),
                                c in proptest::collection::vec(any::<u8>(), 128)) {
            let (a, b, c): (GradientDescriptor, GradientDescriptor, GradientDescriptor) =
                (a.try_into().unwrap(), b.try_into().unwrap(), c.try_into().unwrap());
            let d = |x: &GradientDescriptor, y: &GradientDescriptor| (gradient_distance_sq(x, y) as f64).sqrt();
            prop_assert_eq!(gradient_distance_sq(&a, &a), 0);
            prop_assert_eq!(gradient_distance_sq(&a, &b), gradient_distance_sq(&b, &a));
            prop_assert!(d(&a, &c) <= d(&a, &b) + d(&b, &c) + 1e-9);
        }
    }

    #[test]
    fn keypoints_and_descriptors_come_in_pairs() {
        let img = texture(160, 120, 5);
        let config = KeypointConfig::default();
        let (k, d) = detect_and_describe_gradients(&img, &config);
        assert_eq!(k.len(), d.len());
        assert!(!k.is_empty());
        // Both at once: the same keypoints and the same descriptors as each alone.
        let (kb, db) = crate::detect_and_describe(&img, &config);
        let (k2, b2, g2) = detect_and_describe_both(&img, &config);
        assert_eq!((k2, b2, &g2), (kb, db, &d));
    }
}
