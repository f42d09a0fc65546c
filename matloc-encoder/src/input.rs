//! What the query encoder's network sees of an image: the standardised RGB channels, or the two
//! channels of its colour that a cast shadow does not change ([`shadow_invariant`]), and
//! optionally each channel's local contrast ([`local_contrast`]). Training and queries go
//! through the same [`planes`], so whatever it divides out, it divides out of both.

use crate::{EncoderConfig, EncoderError};
use matloc_core::Image;
pub use matloc_core::shadow::shadow_invariant;
use matloc_core::shadow::standardise;

/// The network input of one RGB image, channel-major `input_channels(cfg) × H × W`.
pub(crate) fn planes(img: &Image<f32>, cfg: &EncoderConfig) -> Result<Vec<f32>, EncoderError> {
    let (w, h, c) = img.shape();
    if c != 3 || w < 8 || h < 8 {
        return Err(EncoderError::BadInput(format!(
            "need an RGB image of at least 8 x 8, got {w} x {h} x {c}"
        )));
    }
    let mut data = Vec::with_capacity(input_channels(cfg) * h * w);
    if cfg.shadow_invariant {
        // Always standardised: exposure and white balance are offsets here.
        let mut inv = shadow_invariant(img);
        for plane in inv.chunks_exact_mut(w * h) {
            // The spread of the standardised RGB channels.
            standardise(plane, 0.5);
        }
        data.extend(inv);
    } else {
        for ch in 0..3 {
            let (offset, scale) = if cfg.standardize_input {
                channel_standardisation(img, ch)
            } else {
                (0.5, 2.0)
            };
            data.extend(
                img.data()
                    .iter()
                    .skip(ch)
                    .step_by(3)
                    .map(|v| scale * (v - offset)),
            );
        }
    }
    if cfg.local_contrast {
        data.extend(local_contrast(img));
    }
    Ok(data)
}

/// Channels of the network input: RGB (or the two shadow-invariant channels), plus the local
/// contrast when configured.
pub(crate) fn input_channels(cfg: &EncoderConfig) -> usize {
    let colour = if cfg.shadow_invariant { 2 } else { 3 };
    colour + if cfg.local_contrast { 3 } else { 0 }
}

/// Half-width of the local-mean window of [`local_contrast`], pixels.
const LOCAL_RADIUS: usize = 6;

/// Local contrast of an RGB image, channel-major `3 × H × W`: `ln(L / (mean₁₃ₓ₁₃(L) + ε)) / 2`
/// clamped to ±1.5, with `L` the channel's linear light (display value^2.2) and the mean over a
/// 13 × 13 window (clamped at the border).
pub fn local_contrast(img: &Image<f32>) -> Vec<f32> {
    let (w, h, _) = img.shape();
    let mut out = Vec::with_capacity(3 * w * h);
    let r = LOCAL_RADIUS;
    for ch in 0..3 {
        let lin: Vec<f32> = (0..w * h)
            .map(|i| img.data()[i * 3 + ch].max(0.0).powf(2.2))
            .collect();
        // Separable box mean with clamped indices.
        let mut rows = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let (a, b) = (x.saturating_sub(r), (x + r).min(w - 1));
                let sum: f32 = lin[y * w + a..=y * w + b].iter().sum();
                rows[y * w + x] = sum / (b - a + 1) as f32;
            }
        }
        for y in 0..h {
            let (a, b) = (y.saturating_sub(r), (y + r).min(h - 1));
            for x in 0..w {
                let sum: f32 = (a..=b).map(|yy| rows[yy * w + x]).sum();
                let mean = sum / (b - a + 1) as f32;
                let v = (lin[y * w + x] + 1e-3) / (mean + 1e-3);
                out.push((0.5 * v.ln()).clamp(-1.5, 1.5));
            }
        }
    }
    out
}

/// `(mean, 1 / (2 σ + ε · mean))` of channel `ch`: the input `(v − mean) / (2 σ)` has the
/// spread of the unstandardised `2v − 1` on a typical image (σ ≈ 0.25), and a gain on the
/// channel changes nothing (ε scales with it; it only keeps a flat channel finite).
fn channel_standardisation(img: &Image<f32>, ch: usize) -> (f32, f32) {
    let n = (img.data().len() / 3).max(1) as f64;
    let (mut sum, mut sq) = (0.0f64, 0.0f64);
    for v in img.data().iter().skip(ch).step_by(3) {
        sum += *v as f64;
        sq += (*v as f64) * (*v as f64);
    }
    let mean = sum / n;
    let sd = (sq / n - mean * mean).max(0.0).sqrt();
    (mean as f32, (1.0 / (2.0 * sd + 0.05 * mean + 1e-6)) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Display value of linear light `v` (the 2.2 curve the invariant inverts).
    fn display(v: f32) -> f32 {
        v.max(0.0).powf(1.0 / 2.2)
    }

    fn textured(w: usize, h: usize) -> Image<f32> {
        let data: Vec<f32> = (0..w * h * 3)
            .map(|i| 0.15 + 0.6 * (((i / 3) * 7919 + (i % 3) * 31) % 97) as f32 / 97.0)
            .collect();
        Image::from_vec(w, h, 3, data).unwrap()
    }

    #[test]
    fn exposure_and_white_balance_do_not_change_the_invariant_input() {
        let img = textured(24, 16);
        // +0.4 EV and a warm white balance, applied in linear light.
        let gain = [1.1f32 * 1.32, 1.32, 0.85 * 1.32];
        let data: Vec<f32> = img
            .data()
            .chunks_exact(3)
            .flat_map(|p| [0, 1, 2].map(|k| display(gain[k] * p[k].powf(2.2))))
            .collect();
        let other = Image::from_vec(24, 16, 3, data).unwrap();
        let cfg = EncoderConfig {
            shadow_invariant: true,
            ..EncoderConfig::default()
        };
        let (a, b) = (planes(&img, &cfg).unwrap(), planes(&other, &cfg).unwrap());
        assert_eq!(a.len(), 2 * 24 * 16);
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(worst < 1e-3, "the input changed by {worst}");
        assert!(a.iter().any(|v| v.abs() > 0.3), "texture lost");
    }

    #[test]
    fn the_input_has_the_configured_channels() {
        let img = textured(16, 12);
        for (shadow_invariant, local_contrast, channels) in [
            (false, false, 3),
            (true, false, 2),
            (false, true, 6),
            (true, true, 5),
        ] {
            let cfg = EncoderConfig {
                shadow_invariant,
                local_contrast,
                ..EncoderConfig::default()
            };
            assert_eq!(input_channels(&cfg), channels);
            assert_eq!(planes(&img, &cfg).unwrap().len(), channels * 16 * 12);
        }
        let grey = Image::from_vec(16, 12, 1, vec![0.5; 16 * 12]).unwrap();
        assert!(planes(&grey, &EncoderConfig::default()).is_err());
    }

    #[test]
    fn local_contrast_divides_out_smooth_shading() {
        let (w, h) = (40, 30);
        let texture: Vec<f32> = (0..w * h * 3)
            .map(|i| 0.3 + 0.4 * (((i / 3) * 7919 % 97) as f32 / 97.0))
            .collect();
        let img = Image::from_vec(w, h, 3, texture.clone()).unwrap();
        // The same texture under a shadow: linear light × 0.25 (display × 0.25^(1/2.2)).
        let dim = 0.25f32.powf(1.0 / 2.2);
        let shaded = Image::from_vec(w, h, 3, texture.iter().map(|v| v * dim).collect()).unwrap();
        let (a, b) = (local_contrast(&img), local_contrast(&shaded));
        assert_eq!(a.len(), 3 * w * h);
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(
            worst < 0.02,
            "shading changed the local contrast by {worst}"
        );
        assert!(a.iter().any(|v| v.abs() > 0.1), "texture lost");
    }
}
