//! FAST-9 detection with Harris ranking, orientation and rotated BRIEF description.

use std::sync::OnceLock;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::gray::GrayImage;

/// A 256-bit binary descriptor.
pub type Descriptor = [u64; 4];

/// A detected keypoint, in level-0 pixel coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Keypoint {
    /// Continuous `x` (pixel centres at `+0.5`).
    pub x: f32,
    /// Continuous `y`.
    pub y: f32,
    /// Pyramid level it was found on.
    pub level: u8,
    /// Orientation (radians, image axes: x right, y down).
    pub angle: f32,
    /// Harris response (for ranking).
    pub response: f32,
}

/// Detector settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct KeypointConfig {
    /// Keypoints to keep over all levels.
    pub max_keypoints: usize,
    /// Pyramid levels.
    pub levels: usize,
    /// Scale between levels.
    pub scale_factor: f32,
    /// FAST intensity threshold (images in `[0, 1]`; ORB's 20/255 ≈ 0.08).
    pub fast_threshold: f32,
    /// Cell size (pixels of the level) of the spreading grid; each cell keeps at most a share
    /// of the level's budget proportional to its area, twice over.
    pub cell_px: usize,
    /// Place each keypoint at the peak of a parabola fitted to the Harris response of its 3×3
    /// neighbourhood (per axis) instead of the pixel centre: positions to a fraction of a
    /// pixel, which is what a pose from keypoints is limited by.
    pub subpixel: bool,
    /// Detect on the image upsampled 2× (bilinear) and report positions in the image's
    /// pixels: more and finer keypoints, at about four times the detection cost (as SIFT
    /// doubles its first octave). On 320×240 views it halved the structure localizer's error
    /// (which turns it on); off by default.
    pub upsample: bool,
}

impl Default for KeypointConfig {
    fn default() -> Self {
        Self {
            max_keypoints: 1500,
            levels: 5,
            scale_factor: 1.2,
            fast_threshold: 0.05,
            cell_px: 32,
            subpixel: true,
            upsample: false,
        }
    }
}

/// Patch radius of the orientation moment and the BRIEF pattern.
const PATCH_RADIUS: i32 = 15;
/// Keypoints closer to the border than this are dropped (patch + Harris window).
pub(crate) const BORDER: usize = PATCH_RADIUS as usize + 2;

/// The 16-pixel Bresenham circle of radius 3, clockwise from the top.
const CIRCLE: [(i32, i32); 16] = [
    (0, -3),
    (1, -3),
    (2, -2),
    (3, -1),
    (3, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 3),
    (-1, 3),
    (-2, 2),
    (-3, 1),
    (-3, 0),
    (-3, -1),
    (-2, -2),
    (-1, -3),
];

/// The BRIEF test pattern: 256 point pairs from an isotropic Gaussian (σ = 31/5, as in
/// Calonder et al.) restricted to the disk of radius 15, from a fixed seed.
fn pattern() -> &'static [[(f32, f32); 2]; 256] {
    static PATTERN: OnceLock<[[(f32, f32); 2]; 256]> = OnceLock::new();
    PATTERN.get_or_init(|| {
        let mut rng = ChaCha8Rng::seed_from_u64(0x000b_5eed);
        let normal = Normal::new(0.0f32, 31.0 / 5.0).expect("valid sigma");
        let mut draw = || loop {
            let (x, y) = (normal.sample(&mut rng), normal.sample(&mut rng));
            if x * x + y * y <= (PATCH_RADIUS as f32 - 0.5).powi(2) {
                return (x, y);
            }
        };
        let mut p = [[(0.0, 0.0); 2]; 256];
        for pair in &mut p {
            *pair = [draw(), draw()];
        }
        p
    })
}

/// True if 9 contiguous bits (circularly) of the 16-bit mask are set.
#[inline]
fn has_arc9(mask: u32) -> bool {
    let m = mask | (mask << 16);
    let mut run = m;
    for k in 1..9 {
        run &= m >> k;
    }
    run != 0
}

/// FAST-9 test at `(x, y)` (caller keeps 3 pixels from the border).
#[inline]
fn is_fast_corner(img: &GrayImage, x: usize, y: usize, t: f32) -> bool {
    let c = img.at(x, y);
    let (hi, lo) = (c + t, c - t);
    // Reject quickly with the four compass points: a 9-arc covers at least two of them.
    let probe = |i: usize| {
        let (dx, dy) = CIRCLE[i];
        img.at((x as i32 + dx) as usize, (y as i32 + dy) as usize)
    };
    let compass = [probe(0), probe(4), probe(8), probe(12)];
    let brighter = compass.iter().filter(|&&v| v > hi).count();
    let darker = compass.iter().filter(|&&v| v < lo).count();
    if brighter < 2 && darker < 2 {
        return false;
    }
    let (mut bright_mask, mut dark_mask) = (0u32, 0u32);
    for (i, (dx, dy)) in CIRCLE.iter().enumerate() {
        let v = img.at((x as i32 + dx) as usize, (y as i32 + dy) as usize);
        if v > hi {
            bright_mask |= 1 << i;
        } else if v < lo {
            dark_mask |= 1 << i;
        }
    }
    has_arc9(bright_mask) || has_arc9(dark_mask)
}

/// Harris response (k = 0.04) over a 7×7 window of central-difference gradients.
pub(crate) fn harris(img: &GrayImage, x: usize, y: usize) -> f32 {
    let (mut a, mut b, mut c) = (0.0f32, 0.0f32, 0.0f32);
    for yy in y - 3..=y + 3 {
        for xx in x - 3..=x + 3 {
            let ix = 0.5 * (img.at(xx + 1, yy) - img.at(xx - 1, yy));
            let iy = 0.5 * (img.at(xx, yy + 1) - img.at(xx, yy - 1));
            a += ix * ix;
            b += iy * iy;
            c += ix * iy;
        }
    }
    a * b - c * c - 0.04 * (a + b) * (a + b)
}

/// Offset of the peak of the parabola through `(-1, a)`, `(0, b)`, `(1, c)`, within
/// `[-0.5, 0.5]`; 0 where the three values do not make a maximum at the centre.
fn parabola_peak(a: f32, b: f32, c: f32) -> f32 {
    let curvature = a - 2.0 * b + c;
    if curvature >= 0.0 || !curvature.is_finite() {
        return 0.0;
    }
    (0.5 * (a - c) / curvature).clamp(-0.5, 0.5)
}

/// Sub-pixel offset of a corner at `(x, y)` from its Harris response around it.
fn subpixel_offset(img: &GrayImage, x: usize, y: usize, r: f32) -> (f32, f32) {
    let dx = parabola_peak(harris(img, x - 1, y), r, harris(img, x + 1, y));
    let dy = parabola_peak(harris(img, x, y - 1), r, harris(img, x, y + 1));
    (dx, dy)
}

/// Orientation by the intensity centroid over the disk of radius 15.
fn orientation(img: &GrayImage, x: usize, y: usize) -> f32 {
    let (mut m01, mut m10) = (0.0f32, 0.0f32);
    for dy in -PATCH_RADIUS..=PATCH_RADIUS {
        let span = ((PATCH_RADIUS * PATCH_RADIUS - dy * dy) as f32).sqrt() as i32;
        let yy = (y as i32 + dy) as usize;
        for dx in -span..=span {
            let v = img.at((x as i32 + dx) as usize, yy);
            m10 += dx as f32 * v;
            m01 += dy as f32 * v;
        }
    }
    m01.atan2(m10)
}

/// Rotated BRIEF on the smoothed image.
fn describe(smooth: &GrayImage, x: usize, y: usize, angle: f32) -> Descriptor {
    let (s, c) = angle.sin_cos();
    let sample = |(px, py): (f32, f32)| {
        let rx = (c * px - s * py).round() as i32;
        let ry = (s * px + c * py).round() as i32;
        smooth.at((x as i32 + rx) as usize, (y as i32 + ry) as usize)
    };
    let mut d = [0u64; 4];
    for (i, [p, q]) in pattern().iter().enumerate() {
        if sample(*p) < sample(*q) {
            d[i / 64] |= 1 << (i % 64);
        }
    }
    d
}

/// Keypoints of one level before the spreading cap: `(x, y, response)` in level pixels.
fn level_candidates(img: &GrayImage, t: f32) -> Vec<(usize, usize, f32)> {
    let (w, h) = (img.width(), img.height());
    if w <= 2 * BORDER || h <= 2 * BORDER {
        return Vec::new();
    }
    let rows: Vec<Vec<(usize, f32)>> = (BORDER..h - BORDER)
        .into_par_iter()
        .map(|y| {
            (BORDER..w - BORDER)
                .filter(|&x| is_fast_corner(img, x, y, t))
                .map(|x| (x, harris(img, x, y)))
                .collect()
        })
        .collect();
    // 3×3 non-maximum suppression among corners (ties keep the first in raster order).
    let mut score = vec![f32::NEG_INFINITY; w * h];
    for (k, row) in rows.iter().enumerate() {
        for &(x, r) in row {
            score[(BORDER + k) * w + x] = r;
        }
    }
    let mut out = Vec::new();
    for (k, row) in rows.iter().enumerate() {
        let y = BORDER + k;
        for &(x, r) in row {
            let mut is_max = true;
            'n: for yy in y - 1..=y + 1 {
                for xx in x - 1..=x + 1 {
                    if (xx, yy) == (x, y) {
                        continue;
                    }
                    let s = score[yy * w + xx];
                    if s > r || (s == r && (yy, xx) < (y, x)) {
                        is_max = false;
                        break 'n;
                    }
                }
            }
            if is_max && r > 0.0 {
                out.push((x, y, r));
            }
        }
    }
    out
}

/// Detects keypoints on a pyramid and computes their descriptors. Images smaller than the
/// patch give no keypoints (not an error).
pub fn detect_and_describe(
    image: &GrayImage,
    config: &KeypointConfig,
) -> (Vec<Keypoint>, Vec<Descriptor>) {
    detect_with(image, config, binary_describer)
}

/// The rotated-BRIEF describer of one pyramid level.
pub(crate) fn binary_describer(
    level: &GrayImage,
) -> impl Fn(usize, usize, f32) -> Descriptor + Sync + use<> {
    let smooth = level.gaussian_blur(2.0);
    move |x, y, angle| describe(&smooth, x, y, angle)
}

/// Detects keypoints on a pyramid and describes each with `describer(level image)`, called
/// once per level, whose result describes a keypoint at `(x, y)` of that level with its
/// orientation.
/// The detector's pyramid of `image`: the image (upsampled 2× with `config.upsample`), then
/// each level `config.scale_factor` smaller, down to the patch border.
pub(crate) fn pyramid(image: &GrayImage, config: &KeypointConfig) -> Vec<GrayImage> {
    let levels = config.levels.max(1);
    let sf = config.scale_factor.max(1.01);
    let base = if config.upsample {
        image.resized(2 * image.width(), 2 * image.height())
    } else {
        image.clone()
    };
    let mut pyramid = Vec::with_capacity(levels);
    for l in 0..levels {
        if l > 0 {
            let scale = sf.powi(l as i32);
            let w = (base.width() as f32 / scale).round() as usize;
            let h = (base.height() as f32 / scale).round() as usize;
            if w <= 2 * BORDER || h <= 2 * BORDER {
                break;
            }
            pyramid.push(base.resized(w, h));
        } else {
            pyramid.push(base.clone());
        }
    }
    pyramid
}

/// Image pixels per pixel of `level` (x, y).
pub(crate) fn level_scale(image: &GrayImage, level: &GrayImage) -> (f32, f32) {
    (
        image.width() as f32 / level.width().max(1) as f32,
        image.height() as f32 / level.height().max(1) as f32,
    )
}

pub(crate) fn detect_with<D, F, G>(
    image: &GrayImage,
    config: &KeypointConfig,
    describer: G,
) -> (Vec<Keypoint>, Vec<D>)
where
    D: Send,
    F: Fn(usize, usize, f32) -> D + Sync,
    G: Fn(&GrayImage) -> F,
{
    let levels = config.levels.max(1);
    let sf = config.scale_factor.max(1.01);
    // Budget per level proportional to its area (geometric series).
    let area_ratio = 1.0 / (sf * sf);
    let total: f32 = (0..levels).map(|l| area_ratio.powi(l as i32)).sum();
    let mut keypoints = Vec::new();
    let mut descriptors = Vec::new();
    for (l, level_img) in pyramid(image, config).iter().enumerate() {
        let (scale_x, scale_y) = level_scale(image, level_img);
        let budget =
            ((config.max_keypoints as f32) * area_ratio.powi(l as i32) / total).ceil() as usize;
        let mut cands = level_candidates(level_img, config.fast_threshold);
        cands.sort_by(|a, b| b.2.total_cmp(&a.2));
        // Spread: at most 2× the area share of the budget per cell, strongest first.
        let cell = config.cell_px.max(8);
        let (cw, ch) = (
            level_img.width().div_ceil(cell),
            level_img.height().div_ceil(cell),
        );
        let per_cell = ((2 * budget) as f32 / (cw * ch) as f32).ceil().max(1.0) as usize;
        let mut counts = vec![0usize; cw * ch];
        let mut chosen = Vec::with_capacity(budget);
        for (x, y, r) in cands {
            if chosen.len() >= budget {
                break;
            }
            let c = (y / cell) * cw + x / cell;
            if counts[c] < per_cell {
                counts[c] += 1;
                chosen.push((x, y, r));
            }
        }
        let describe_at = describer(level_img);
        let described: Vec<(Keypoint, D)> = chosen
            .par_iter()
            .map(|&(x, y, r)| {
                let angle = orientation(level_img, x, y);
                let d = describe_at(x, y, angle);
                let (dx, dy) = if config.subpixel {
                    subpixel_offset(level_img, x, y, r)
                } else {
                    (0.0, 0.0)
                };
                (
                    Keypoint {
                        x: (x as f32 + 0.5 + dx) * scale_x,
                        y: (y as f32 + 0.5 + dy) * scale_y,
                        level: l as u8,
                        angle,
                        response: r,
                    },
                    d,
                )
            })
            .collect();
        for (k, d) in described {
            keypoints.push(k);
            descriptors.push(d);
        }
    }
    (keypoints, descriptors)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arc_detection() {
        assert!(has_arc9(0b1_1111_1111));
        assert!(!has_arc9(0b1111_1111));
        // Wraps around bit 15 → bit 0.
        assert!(has_arc9(0b1111_0000_0000_0000 | 0b1_1111));
        assert!(!has_arc9(0b0101_0101_0101_0101));
    }

    #[test]
    fn pattern_stays_in_the_disk() {
        for [p, q] in pattern() {
            for (x, y) in [p, q] {
                assert!(x * x + y * y <= (PATCH_RADIUS as f32).powi(2));
            }
        }
    }

    #[test]
    fn corners_of_a_square_are_found() {
        let (w, h) = (96, 96);
        let mut data = vec![0.1f32; w * h];
        for y in 30..66 {
            for x in 30..66 {
                data[y * w + x] = 0.9;
            }
        }
        let img = GrayImage::from_vec(w, h, data).unwrap();
        let cfg = KeypointConfig {
            levels: 1,
            ..KeypointConfig::default()
        };
        let (kps, descs) = detect_and_describe(&img, &cfg);
        assert_eq!(kps.len(), descs.len());
        for corner in [(30.0, 30.0), (66.0, 30.0), (30.0, 66.0), (66.0, 66.0)] {
            let near = kps
                .iter()
                .any(|k| (k.x - corner.0).abs() <= 2.5 && (k.y - corner.1).abs() <= 2.5);
            assert!(near, "no keypoint near {corner:?}: {kps:?}");
        }
        // Nothing along the straight edges' middles or the flat areas.
        assert!(kps.len() <= 8, "{}", kps.len());
    }

    #[test]
    fn parabola_peak_finds_the_vertex() {
        // Samples of -(x - 0.3)² at -1, 0, 1.
        let f = |x: f32| -(x - 0.3) * (x - 0.3);
        assert!((parabola_peak(f(-1.0), f(0.0), f(1.0)) - 0.3).abs() < 1e-5);
        // No maximum at the centre: no offset.
        assert_eq!(parabola_peak(1.0, 0.0, 1.0), 0.0);
        assert_eq!(parabola_peak(0.0, 0.0, 0.0), 0.0);
        assert_eq!(parabola_peak(f32::NAN, 0.0, 0.0), 0.0);
    }

    /// A bright square with its corner at `(x0, y0)` (fractional), each pixel the covered
    /// area's share (8×8 samples).
    fn square_at(w: usize, h: usize, x0: f32, y0: f32) -> GrayImage {
        let mut data = vec![0.1f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut covered = 0;
                for sy in 0..8 {
                    for sx in 0..8 {
                        let px = x as f32 + (sx as f32 + 0.5) / 8.0;
                        let py = y as f32 + (sy as f32 + 0.5) / 8.0;
                        let inside = px >= x0 && px < x0 + 36.0 && py >= y0 && py < y0 + 36.0;
                        covered += usize::from(inside);
                    }
                }
                data[y * w + x] += 0.8 * covered as f32 / 64.0;
            }
        }
        GrayImage::from_vec(w, h, data).unwrap()
    }

    #[test]
    fn subpixel_positions_follow_a_fractional_shift() {
        // The same square moved by a fraction of a pixel: the keypoints must move with it.
        let cfg = |subpixel| KeypointConfig {
            levels: 1,
            subpixel,
            upsample: false,
            ..KeypointConfig::default()
        };
        let corner = |img: &GrayImage, subpixel: bool| {
            let (kps, _) = detect_and_describe(img, &cfg(subpixel));
            // The keypoint nearest the square's top-left corner.
            kps.into_iter()
                .min_by(|a, b| {
                    let d = |k: &Keypoint| (k.x - 30.0).powi(2) + (k.y - 30.0).powi(2);
                    d(a).total_cmp(&d(b))
                })
                .map(|k| (k.x, k.y))
                .unwrap()
        };
        let base = square_at(96, 96, 30.0, 30.0);
        let mut error = [0.0f32; 2];
        for (i, subpixel) in [false, true].into_iter().enumerate() {
            let c0 = corner(&base, subpixel);
            for shift in [0.2f32, 0.4, 0.6, 0.8] {
                let c = corner(&square_at(96, 96, 30.0 + shift, 30.0 + shift), subpixel);
                error[i] += ((c.0 - c0.0) - shift).abs() + ((c.1 - c0.1) - shift).abs();
            }
        }
        // Integer positions are off by up to half a pixel per axis; the fit follows the shift
        // (measured: 2.05 px summed over the 8 offsets against 4.0; the parabola through a
        // Harris peak is biased towards the pixel centre, so not to zero).
        assert!(
            error[1] < 0.6 * error[0],
            "shift error with sub-pixel {:.3} px, without {:.3} px",
            error[1],
            error[0]
        );
    }

    #[test]
    fn upsampled_detection_reports_positions_in_the_image() {
        let img = square_at(96, 96, 30.0, 30.0);
        let cfg = KeypointConfig {
            levels: 1,
            upsample: true,
            ..KeypointConfig::default()
        };
        let (kps, _) = detect_and_describe(&img, &cfg);
        // The four corners (a corner detector places them slightly inside the bright square,
        // the same way at each corner), centred on the square's centre (48, 48) in the
        // image's pixels: a scale or half-pixel error of the 2× grid would move the centre.
        assert_eq!(kps.len(), 4, "{kps:?}");
        for k in &kps {
            let inside = (k.x - 48.0).abs().min((k.y - 48.0).abs());
            assert!((16.5..=18.0).contains(&inside), "{k:?}");
        }
        let cx = kps.iter().map(|k| k.x).sum::<f32>() / 4.0;
        let cy = kps.iter().map(|k| k.y).sum::<f32>() / 4.0;
        assert!(
            (cx - 48.0).abs() < 0.05 && (cy - 48.0).abs() < 0.05,
            "{cx} {cy}"
        );
    }

    #[test]
    fn tiny_and_empty_images_give_nothing() {
        for (w, h) in [(0, 0), (1, 1), (20, 200), (34, 34)] {
            let img = GrayImage::from_vec(w, h, vec![0.5; w * h]).unwrap();
            let (k, d) = detect_and_describe(&img, &KeypointConfig::default());
            assert!(k.is_empty() && d.is_empty());
        }
    }
}
