//! Image preparation for the place CNN: training augmentation (random crops,
//! small rotations, photometric jitter), all on [`Image<f32>`] RGB buffers in `[0, 1]`.

use matloc_core::Image;
use matloc_core::image::resize_area;
use rand::Rng;
use serde::{Deserialize, Serialize};

/// Augmentation ranges.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AugmentConfig {
    /// Smallest crop side relative to the full image (1 = no cropping).
    pub min_crop: f64,
    /// Largest random shift of the crop centre, fraction of the image size.
    pub max_shift: f64,
    /// Largest in-plane rotation, degrees.
    pub max_rotation_deg: f64,
    /// Largest brightness offset (added).
    pub brightness: f32,
    /// Largest relative contrast change.
    pub contrast: f32,
    /// Largest relative per-channel gain change (colour cast).
    pub channel_gain: f32,
    /// Standard deviation of the additive pixel noise.
    pub noise_std: f32,
}

impl Default for AugmentConfig {
    fn default() -> Self {
        AugmentConfig {
            min_crop: 0.8,
            max_shift: 0.06,
            max_rotation_deg: 5.0,
            brightness: 0.1,
            contrast: 0.2,
            channel_gain: 0.08,
            noise_std: 0.01,
        }
    }
}

impl AugmentConfig {
    /// No augmentation at all.
    pub fn none() -> Self {
        AugmentConfig {
            min_crop: 1.0,
            max_shift: 0.0,
            max_rotation_deg: 0.0,
            brightness: 0.0,
            contrast: 0.0,
            channel_gain: 0.0,
            noise_std: 0.0,
        }
    }
}

/// One random augmentation of `src` (ideally prepared at twice the output size) into a
/// `width × height` image: a rotated, shifted crop sampled at twice the output resolution and
/// box-averaged down (so the warp does not alias), then photometric jitter and noise.
pub fn augment(
    src: &Image<f32>,
    width: usize,
    height: usize,
    cfg: &AugmentConfig,
    rng: &mut impl Rng,
) -> Image<f32> {
    let (sw, sh) = (src.width() as f64, src.height() as f64);
    let c = src.channels();
    let crop = if cfg.min_crop < 1.0 {
        rng.random_range(cfg.min_crop.max(0.1)..=1.0)
    } else {
        1.0
    };
    let mut sym = |r: f64| {
        if r > 0.0 {
            rng.random_range(-r..=r)
        } else {
            0.0
        }
    };
    let shift_x = sym(cfg.max_shift) * sw;
    let shift_y = sym(cfg.max_shift) * sh;
    let theta = sym(cfg.max_rotation_deg).to_radians();
    let (sin, cos) = theta.sin_cos();
    let (w2, h2) = (2 * width, 2 * height);
    let mut big = Image::<f32>::new(w2, h2, c);
    {
        let data = big.data_mut();
        for v in 0..h2 {
            for u in 0..w2 {
                // Output pixel centre relative to the image centre, in source pixels.
                let ox = ((u as f64 + 0.5) / w2 as f64 - 0.5) * sw * crop;
                let oy = ((v as f64 + 0.5) / h2 as f64 - 0.5) * sh * crop;
                let x = 0.5 * sw + shift_x + cos * ox - sin * oy;
                let y = 0.5 * sh + shift_y + sin * ox + cos * oy;
                let at = (v * w2 + u) * c;
                src.sample_bilinear(x, y, &mut data[at..at + c]);
            }
        }
    }
    let mut out = resize_area(&big, width, height);
    let mut symf = |r: f32| {
        if r > 0.0 {
            rng.random_range(-r..=r)
        } else {
            0.0
        }
    };
    let brightness = symf(cfg.brightness);
    let contrast = 1.0 + symf(cfg.contrast);
    let gains: Vec<f32> = (0..c).map(|_| 1.0 + symf(cfg.channel_gain)).collect();
    let n = (width * height) as f32;
    let mean: Vec<f32> = (0..c)
        .map(|k| out.data().iter().skip(k).step_by(c).sum::<f32>() / n.max(1.0))
        .collect();
    let noise = cfg.noise_std;
    for (i, v) in out.data_mut().iter_mut().enumerate() {
        let k = i % c;
        let mut x = (*v - mean[k]) * contrast + mean[k];
        x = x * gains[k] + brightness;
        if noise > 0.0 {
            // Sum of uniforms: cheap, near-Gaussian noise with std `noise`.
            let u: f32 = (0..3).map(|_| rng.random_range(-1.0f32..1.0)).sum();
            x += u * noise;
        }
        *v = x.clamp(0.0, 1.0);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn ramp(w: usize, h: usize) -> Image<f32> {
        let mut img = Image::<f32>::new(w, h, 3);
        for y in 0..h {
            for x in 0..w {
                let p = (y * w + x) * 3;
                img.data_mut()[p] = x as f32 / w as f32;
                img.data_mut()[p + 1] = y as f32 / h as f32;
                img.data_mut()[p + 2] = 0.5;
            }
        }
        img
    }

    #[test]
    fn identity_augmentation_is_a_resize() {
        let img = ramp(128, 96);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let a = augment(&img, 64, 48, &AugmentConfig::none(), &mut rng);
        let b = resize_area(&img, 64, 48);
        let max = a
            .data()
            .iter()
            .zip(b.data())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(max < 1e-5, "{max}");
    }

    #[test]
    fn augmentation_stays_in_range_and_is_seeded() {
        let img = ramp(128, 96);
        let cfg = AugmentConfig::default();
        let a = augment(&img, 64, 48, &cfg, &mut ChaCha8Rng::seed_from_u64(4));
        let b = augment(&img, 64, 48, &cfg, &mut ChaCha8Rng::seed_from_u64(4));
        let c = augment(&img, 64, 48, &cfg, &mut ChaCha8Rng::seed_from_u64(5));
        assert_eq!(a, b);
        assert_ne!(a, c);
        assert!(a.data().iter().all(|v| (0.0..=1.0).contains(v)));
    }
}
