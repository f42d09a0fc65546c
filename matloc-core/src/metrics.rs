//! Error metrics: pose errors, recall at thresholds, PSNR and SSIM.

use crate::hash::splitmix64_next;
use crate::image::{Image, ImageError};
use crate::pose::{Pose, camera_center};

/// Distance between the camera centres of two `cam_from_world` poses, in scene units (metres).
pub fn translation_error_m(cam_from_world_est: &Pose, cam_from_world_gt: &Pose) -> f64 {
    (camera_center(cam_from_world_est) - camera_center(cam_from_world_gt)).norm()
}

/// Geodesic angle of `R_est R_gtᵀ`, in degrees.
pub fn rotation_error_deg(cam_from_world_est: &Pose, cam_from_world_gt: &Pose) -> f64 {
    cam_from_world_est
        .rotation
        .angle_to(&cam_from_world_gt.rotation)
        .to_degrees()
}

/// Fraction of queries whose errors are both within `(max_translation_m, max_rotation_deg)`.
///
/// `errors` holds `(translation_m, rotation_deg)` per query; a failed query should be passed
/// as `(f64::INFINITY, f64::INFINITY)` so it counts against recall. Empty input gives 0.
pub fn recall_at(errors: &[(f64, f64)], max_translation_m: f64, max_rotation_deg: f64) -> f64 {
    if errors.is_empty() {
        return 0.0;
    }
    let hits = errors
        .iter()
        .filter(|(t, r)| *t <= max_translation_m && *r <= max_rotation_deg)
        .count();
    hits as f64 / errors.len() as f64
}

/// Median of a slice (NaNs sort last); `None` for empty input.
pub fn median(values: &[f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

/// Pearson correlation of paired samples; `None` for fewer than two pairs, unequal lengths
/// or a constant side (the correlation is undefined there).
pub fn pearson(xs: &[f64], ys: &[f64]) -> Option<f64> {
    if xs.len() != ys.len() || xs.len() < 2 {
        return None;
    }
    let n = xs.len() as f64;
    let (mx, my) = (xs.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (x, y) in xs.iter().zip(ys) {
        sxy += (x - mx) * (y - my);
        sxx += (x - mx) * (x - mx);
        syy += (y - my) * (y - my);
    }
    let den = (sxx * syy).sqrt();
    (den > 0.0 && den.is_finite()).then(|| sxy / den)
}

/// `median(a) − median(b)` for paired samples and its bootstrap confidence interval.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PairedDifference {
    /// `median(a) − median(b)` on the samples as given.
    pub difference: f64,
    /// Lower end of the percentile interval.
    pub low: f64,
    /// Upper end of the percentile interval.
    pub high: f64,
}

/// Difference of the medians of two paired samples (`a[i]` and `b[i]` measured on the same
/// case) with a percentile bootstrap interval at `level` (e.g. 0.95) over `resamples`
/// resamples, deterministic from `seed`.
///
/// Cases are resampled in clusters of `cluster` consecutive entries with the pairing kept:
/// several starts of one query share its image, so they are not independent, and resampling
/// them one by one would make the interval too narrow. `None` when the lengths differ, the
/// input is empty, `cluster` is 0 or does not divide the length, `resamples` is 0 or `level`
/// is not in (0, 1).
pub fn paired_median_difference(
    a: &[f64],
    b: &[f64],
    cluster: usize,
    resamples: usize,
    level: f64,
    seed: u64,
) -> Option<PairedDifference> {
    let n = a.len();
    if n == 0
        || b.len() != n
        || cluster == 0
        || !n.is_multiple_of(cluster)
        || resamples == 0
        || !(level > 0.0 && level < 1.0)
    {
        return None;
    }
    let clusters = n / cluster;
    let difference = median(a)? - median(b)?;
    // SplitMix64 is enough for resampling indices and keeps this crate free of a RNG
    // dependency.
    let mut state = seed;
    let (mut ra, mut rb) = (Vec::with_capacity(n), Vec::with_capacity(n));
    let mut diffs = Vec::with_capacity(resamples);
    for _ in 0..resamples {
        ra.clear();
        rb.clear();
        for _ in 0..clusters {
            let c = (splitmix64_next(&mut state) % clusters as u64) as usize;
            ra.extend_from_slice(&a[c * cluster..(c + 1) * cluster]);
            rb.extend_from_slice(&b[c * cluster..(c + 1) * cluster]);
        }
        diffs.push(median(&ra)? - median(&rb)?);
    }
    diffs.sort_by(|x, y| x.total_cmp(y));
    let tail = 0.5 * (1.0 - level);
    let at = |q: f64| diffs[((q * resamples as f64).floor() as usize).min(resamples - 1)];
    Some(PairedDifference {
        difference,
        low: at(tail),
        high: at(1.0 - tail),
    })
}

/// Peak signal-to-noise ratio in dB for images with values in `[0, 1]`.
///
/// Identical images give `f64::INFINITY`.
pub fn psnr(a: &Image<f32>, b: &Image<f32>) -> Result<f64, ImageError> {
    a.check_same_shape(b)?;
    let n = a.data().len().max(1) as f64;
    let mse: f64 = a
        .data()
        .iter()
        .zip(b.data())
        .map(|(&x, &y)| {
            let d = x as f64 - y as f64;
            d * d
        })
        .sum::<f64>()
        / n;
    Ok(-10.0 * mse.log10())
}

/// Side of the SSIM Gaussian window (Wang et al. 2004).
const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM Gaussian window, pixels.
const SSIM_SIGMA: f64 = 1.5;

/// Structural similarity (Wang et al. 2004) for images with values in `[0, 1]`.
///
/// Standard settings: 11×11 Gaussian window with σ = 1.5 (normalised), K1 = 0.01, K2 = 0.03,
/// statistics over the window positions that fit entirely in the image ("valid"), mean over
/// positions and then over channels. This equals scikit-image's `structural_similarity` with
/// `gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1`. Images smaller
/// than the window give an error-free result computed with the window clipped to the image.
pub fn ssim(a: &Image<f32>, b: &Image<f32>) -> Result<f64, ImageError> {
    a.check_same_shape(b)?;
    let (w, h, ch) = a.shape();
    if w == 0 || h == 0 || ch == 0 {
        return Ok(1.0);
    }
    let radius = SSIM_WINDOW / 2;
    let kernel: Vec<f64> = {
        let k: Vec<f64> = (0..SSIM_WINDOW)
            .map(|i| {
                let d = i as f64 - radius as f64;
                (-d * d / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp()
            })
            .collect();
        let s: f64 = k.iter().sum();
        k.into_iter().map(|v| v / s).collect()
    };
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    // Window positions: valid region, or the single clipped position for tiny images.
    let (wx, wy) = (w.min(SSIM_WINDOW), h.min(SSIM_WINDOW));
    let (nx, ny) = (w - wx + 1, h - wy + 1);
    let kx: Vec<f64> = normalised_slice(&kernel, wx);
    let ky: Vec<f64> = normalised_slice(&kernel, wy);

    let mut total = 0.0;
    for c in 0..ch {
        // Separable filtering of the five moment images: rows first, then columns.
        let get = |img: &Image<f32>, x: usize, y: usize| img.data()[(y * w + x) * ch + c] as f64;
        let mut rows = vec![[0.0f64; 5]; nx * h];
        for y in 0..h {
            for ox in 0..nx {
                let mut m = [0.0f64; 5];
                for (i, &k) in kx.iter().enumerate() {
                    let (p, q) = (get(a, ox + i, y), get(b, ox + i, y));
                    m[0] += k * p;
                    m[1] += k * q;
                    m[2] += k * p * p;
                    m[3] += k * q * q;
                    m[4] += k * p * q;
                }
                rows[y * nx + ox] = m;
            }
        }
        let mut sum = 0.0;
        for oy in 0..ny {
            for ox in 0..nx {
                let mut m = [0.0f64; 5];
                for (j, &k) in ky.iter().enumerate() {
                    let r = rows[(oy + j) * nx + ox];
                    for t in 0..5 {
                        m[t] += k * r[t];
                    }
                }
                let (mu_a, mu_b) = (m[0], m[1]);
                let var_a = m[2] - mu_a * mu_a;
                let var_b = m[3] - mu_b * mu_b;
                let cov = m[4] - mu_a * mu_b;
                sum += ((2.0 * mu_a * mu_b + c1) * (2.0 * cov + c2))
                    / ((mu_a * mu_a + mu_b * mu_b + c1) * (var_a + var_b + c2));
            }
        }
        total += sum / (nx * ny) as f64;
    }
    Ok(total / ch as f64)
}

/// The central `n` taps of a kernel, renormalised to sum to one.
fn normalised_slice(kernel: &[f64], n: usize) -> Vec<f64> {
    let start = (kernel.len() - n) / 2;
    let s: f64 = kernel[start..start + n].iter().sum();
    kernel[start..start + n].iter().map(|v| v / s).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

    /// Deterministic test pattern (no RNG so the reference value below is reproducible).
    fn pattern(w: usize, h: usize, phase: f32) -> Image<f32> {
        let mut img = Image::new(w, h, 1);
        for y in 0..h {
            for x in 0..w {
                let v = 0.5
                    + 0.3 * ((x as f32 * 0.37 + phase).sin() * (y as f32 * 0.23).cos())
                    + 0.15 * (((x * 7 + y * 13) % 17) as f32 / 17.0 - 0.5);
                img.pixel_mut(x, y)[0] = v;
            }
        }
        img
    }

    #[test]
    fn pearson_of_affine_and_degenerate_inputs() {
        let x = [1.0, 2.0, 4.0, 7.0];
        let up: Vec<f64> = x.iter().map(|v| 3.0 * v - 1.0).collect();
        let down: Vec<f64> = x.iter().map(|v| -0.5 * v + 2.0).collect();
        assert!((pearson(&x, &up).unwrap() - 1.0).abs() < 1e-12);
        assert!((pearson(&x, &down).unwrap() + 1.0).abs() < 1e-12);
        let r = pearson(&[1.0, 2.0, 3.0], &[1.0, 3.0, 2.0]).unwrap();
        assert!((r - 0.5).abs() < 1e-12);
        assert_eq!(pearson(&x, &[5.0; 4]), None);
        assert_eq!(pearson(&[1.0], &[2.0]), None);
        assert_eq!(pearson(&x, &up[..3]), None);
    }

    #[test]
    fn ssim_matches_scikit_image_reference() {
        // Reference: skimage 0.26 structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
        // use_sample_covariance=False, data_range=1.0) on these exact arrays, computed by
        // bench/reference/ssim_reference.py.
        let a = pattern(48, 40, 0.0);
        let b = pattern(48, 40, 0.4);
        let s = ssim(&a, &b).unwrap();
        assert!((s - SSIM_REFERENCE).abs() < 1e-6, "ssim = {s}");
        assert!((ssim(&a, &a).unwrap() - 1.0).abs() < 1e-12);
    }

    /// Value printed by bench/reference/ssim_reference.py.
    const SSIM_REFERENCE: f64 = 0.926567529521;

    #[test]
    fn psnr_of_known_noise() {
        let a = Image::from_vec(2, 2, 1, vec![0.0f32, 0.0, 0.0, 0.0]).unwrap();
        let b = Image::from_vec(2, 2, 1, vec![0.1f32, 0.1, 0.1, 0.1]).unwrap();
        assert!((psnr(&a, &b).unwrap() - 20.0).abs() < 1e-5);
        assert!(psnr(&a, &a).unwrap().is_infinite());
        let c = Image::new(3, 2, 1);
        assert!(psnr(&a, &c).is_err());
    }

    #[test]
    fn pose_errors() {
        let a = Isometry3::identity();
        let b = Isometry3::from_parts(
            Translation3::new(3.0, 4.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 10f64.to_radians()),
        );
        assert!((rotation_error_deg(&a, &b) - 10.0).abs() < 1e-9);
        // The centre of b is -R^T t, whose norm is |t| = 5.
        assert!((translation_error_m(&a, &b) - 5.0).abs() < 1e-9);
    }

    #[test]
    fn recall_and_median() {
        let e = [
            (0.1, 1.0),
            (0.5, 1.0),
            (0.2, 3.0),
            (f64::INFINITY, f64::INFINITY),
        ];
        assert_eq!(recall_at(&e, 0.25, 2.0), 0.25);
        assert_eq!(recall_at(&e, 1.0, 5.0), 0.75);
        assert_eq!(recall_at(&[], 1.0, 5.0), 0.0);
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(median(&[]), None);
    }

    #[test]
    fn paired_difference_rejects_bad_input() {
        let a = [1.0, 2.0, 3.0, 4.0];
        assert!(paired_median_difference(&a, &a[..3], 1, 100, 0.95, 0).is_none());
        assert!(paired_median_difference(&[], &[], 1, 100, 0.95, 0).is_none());
        assert!(paired_median_difference(&a, &a, 0, 100, 0.95, 0).is_none());
        assert!(paired_median_difference(&a, &a, 3, 100, 0.95, 0).is_none());
        assert!(paired_median_difference(&a, &a, 2, 0, 0.95, 0).is_none());
        assert!(paired_median_difference(&a, &a, 2, 100, 1.0, 0).is_none());
    }

    #[test]
    fn paired_difference_separates_a_clear_shift_from_noise() {
        // 60 cases in 20 clusters of 3; b is a shifted by 0.5 plus small noise.
        let a: Vec<f64> = (0..60).map(|i| ((i * 37) % 60) as f64 / 60.0).collect();
        let b: Vec<f64> = a
            .iter()
            .enumerate()
            .map(|(i, x)| x + 0.5 + 0.01 * ((i % 7) as f64 - 3.0))
            .collect();
        let d = paired_median_difference(&a, &b, 3, 2000, 0.95, 1).unwrap();
        assert!(d.high < 0.0, "{d:?}");
        assert!(d.low <= d.difference && d.difference <= d.high, "{d:?}");
        // Against itself the difference is exactly 0 in every resample.
        let z = paired_median_difference(&a, &a, 3, 500, 0.95, 1).unwrap();
        assert_eq!((z.difference, z.low, z.high), (0.0, 0.0, 0.0));
    }

    proptest::proptest! {
        #[test]
        fn paired_difference_is_deterministic_and_shift_equivariant(
            a in proptest::collection::vec(0.0f64..10.0, 12),
            b in proptest::collection::vec(0.0f64..10.0, 12),
            shift in -5.0f64..5.0,
            seed in 0u64..1000,
        ) {
            let d = paired_median_difference(&a, &b, 2, 300, 0.9, seed).unwrap();
            proptest::prop_assert_eq!(d, paired_median_difference(&a, &b, 2, 300, 0.9, seed).unwrap());
            proptest::prop_assert!(d.low <= d.high);
            let shifted: Vec<f64> = a.iter().map(|x| x + shift).collect();
            let s = paired_median_difference(&shifted, &b, 2, 300, 0.9, seed).unwrap();
            for (x, y) in [(s.difference, d.difference), (s.low, d.low), (s.high, d.high)] {
                proptest::prop_assert!((x - y - shift).abs() < 1e-9);
            }
        }
    }
}
