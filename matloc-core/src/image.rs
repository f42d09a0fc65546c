//! Dense image and feature-map buffers.
//!
//! Layout: `H × W × C`, row-major, channels interleaved: the value of channel `c` at pixel
//! `(x = col, y = row)` is `data[(y * W + x) * C + c]`. RGB images are `Image<f32>` with three
//! channels in `[0, 1]` (linear 8-bit values divided by 255, no gamma change); depth maps are
//! single-channel `Image<f32>` in metres; NeRF and encoder features are [`FeatureMap`]s.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Errors raised when building a buffer from raw parts.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum ImageError {
    /// The data length does not equal `width * height * channels`.
    #[error("buffer of {width}x{height}x{channels} needs {expected} values, got {actual}")]
    SizeMismatch {
        /// Width in pixels.
        width: usize,
        /// Height in pixels.
        height: usize,
        /// Channels per pixel.
        channels: usize,
        /// `width * height * channels`.
        expected: usize,
        /// Length of the data given.
        actual: usize,
    },
    /// Two buffers that must agree in shape do not.
    #[error("shape mismatch: {a:?} vs {b:?} (width, height, channels)")]
    ShapeMismatch {
        /// Shape of the first buffer.
        a: (usize, usize, usize),
        /// Shape of the second buffer.
        b: (usize, usize, usize),
    },
}

/// An `H × W × C` row-major buffer (see the module docs for the layout).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Image<T> {
    width: usize,
    height: usize,
    channels: usize,
    data: Vec<T>,
}

/// A dense feature map: an [`Image<f32>`] whose channels are feature dimensions.
pub type FeatureMap = Image<f32>;

impl<T: Copy + Default> Image<T> {
    /// A buffer filled with `T::default()`.
    pub fn new(width: usize, height: usize, channels: usize) -> Self {
        Image {
            width,
            height,
            channels,
            data: vec![T::default(); width * height * channels],
        }
    }
}

impl<T> Image<T> {
    /// Wraps existing data, checking its length.
    pub fn from_vec(
        width: usize,
        height: usize,
        channels: usize,
        data: Vec<T>,
    ) -> Result<Self, ImageError> {
        let expected = width * height * channels;
        if data.len() != expected {
            return Err(ImageError::SizeMismatch {
                width,
                height,
                channels,
                expected,
                actual: data.len(),
            });
        }
        Ok(Image {
            width,
            height,
            channels,
            data,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Channels per pixel.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// `(width, height, channels)`.
    pub fn shape(&self) -> (usize, usize, usize) {
        (self.width, self.height, self.channels)
    }

    /// All values in layout order.
    pub fn data(&self) -> &[T] {
        &self.data
    }

    /// All values in layout order, mutable.
    pub fn data_mut(&mut self) -> &mut [T] {
        &mut self.data
    }

    /// Consumes the buffer and returns its data.
    pub fn into_vec(self) -> Vec<T> {
        self.data
    }

    /// The channels of pixel `(x, y)`. Panics when out of bounds, like slice indexing.
    pub fn pixel(&self, x: usize, y: usize) -> &[T] {
        let i = (y * self.width + x) * self.channels;
        &self.data[i..i + self.channels]
    }

    /// The channels of pixel `(x, y)`, mutable.
    pub fn pixel_mut(&mut self, x: usize, y: usize) -> &mut [T] {
        let i = (y * self.width + x) * self.channels;
        &mut self.data[i..i + self.channels]
    }

    /// One row (`W × C` values).
    pub fn row(&self, y: usize) -> &[T] {
        let n = self.width * self.channels;
        &self.data[y * n..(y + 1) * n]
    }

    /// Checks that another buffer has the same shape.
    pub fn check_same_shape<U>(&self, other: &Image<U>) -> Result<(), ImageError> {
        if self.shape() != other.shape() {
            return Err(ImageError::ShapeMismatch {
                a: self.shape(),
                b: other.shape(),
            });
        }
        Ok(())
    }
}

impl<T: Copy + Default> Image<T> {
    /// A new buffer holding the listed channels, in the order given.
    ///
    /// Panics if a channel index is out of range (a programming error, not user input).
    pub fn select_channels(&self, channels: &[usize]) -> Image<T> {
        let mut out = Image::new(self.width, self.height, channels.len());
        for (src, dst) in self
            .data
            .chunks_exact(self.channels.max(1))
            .zip(out.data.chunks_exact_mut(channels.len().max(1)))
        {
            for (d, &c) in dst.iter_mut().zip(channels) {
                *d = src[c];
            }
        }
        out
    }
}

impl Image<f32> {
    /// Bilinear sample at a continuous pixel coordinate (pixel centres at `+0.5`), clamped at
    /// the border; writes `channels` values into `out`.
    pub fn sample_bilinear(&self, x: f64, y: f64, out: &mut [f32]) {
        let fx = (x - 0.5).clamp(0.0, (self.width - 1) as f64);
        let fy = (y - 0.5).clamp(0.0, (self.height - 1) as f64);
        let x0 = fx.floor() as usize;
        let y0 = fy.floor() as usize;
        let x1 = (x0 + 1).min(self.width - 1);
        let y1 = (y0 + 1).min(self.height - 1);
        let ax = (fx - x0 as f64) as f32;
        let ay = (fy - y0 as f64) as f32;
        let (p00, p10, p01, p11) = (
            self.pixel(x0, y0),
            self.pixel(x1, y0),
            self.pixel(x0, y1),
            self.pixel(x1, y1),
        );
        for c in 0..self.channels {
            let top = p00[c] + ax * (p10[c] - p00[c]);
            let bottom = p01[c] + ax * (p11[c] - p01[c]);
            out[c] = top + ay * (bottom - top);
        }
    }

    /// Separable Gaussian blur with standard deviation `sigma` pixels (kernel radius ⌈3σ⌉,
    /// edges clamped); `sigma <= 0` returns a copy. Models optical blur of a lens.
    pub fn gaussian_blur(&self, sigma: f32) -> Image<f32> {
        if sigma.is_nan() || sigma <= 0.0 || self.data.is_empty() {
            return self.clone();
        }
        let radius = (3.0 * sigma).ceil() as i64;
        let mut kernel: Vec<f32> = (-radius..=radius)
            .map(|d| (-((d * d) as f32) / (2.0 * sigma * sigma)).exp())
            .collect();
        let sum: f32 = kernel.iter().sum();
        kernel.iter_mut().for_each(|k| *k /= sum);
        let (w, h, c) = self.shape();
        let pass = |src: &[f32], horizontal: bool| -> Vec<f32> {
            let mut out = vec![0.0f32; src.len()];
            for y in 0..h {
                for x in 0..w {
                    for ch in 0..c {
                        let mut acc = 0.0;
                        for (i, k) in kernel.iter().enumerate() {
                            let d = i as i64 - radius;
                            let (sx, sy) = if horizontal {
                                ((x as i64 + d).clamp(0, w as i64 - 1) as usize, y)
                            } else {
                                (x, (y as i64 + d).clamp(0, h as i64 - 1) as usize)
                            };
                            acc += k * src[(sy * w + sx) * c + ch];
                        }
                        out[(y * w + x) * c + ch] = acc;
                    }
                }
            }
            out
        };
        let once = pass(&self.data, true);
        Image {
            width: w,
            height: h,
            channels: c,
            data: pass(&once, false),
        }
    }
}

/// Area-averaging resize of a multi-channel image to `width × height` (each output pixel is the
/// coverage-weighted mean of the source pixels under its footprint; upsampling repeats pixels).
pub fn resize_area(img: &Image<f32>, width: usize, height: usize) -> Image<f32> {
    let (sw, sh, c) = (img.width(), img.height(), img.channels());
    let mut out = Image::<f32>::new(width, height, c);
    if sw == 0 || sh == 0 || width == 0 || height == 0 {
        return out;
    }
    // Per output coordinate: the source indices and weights covering its footprint.
    let taps = |src: usize, dst: usize| -> Vec<Vec<(usize, f32)>> {
        let scale = src as f64 / dst as f64;
        (0..dst)
            .map(|o| {
                let (a, b) = (o as f64 * scale, (o + 1) as f64 * scale);
                let mut t = Vec::new();
                let mut i = a.floor() as usize;
                while (i as f64) < b && i < src {
                    let w = (b.min(i as f64 + 1.0) - a.max(i as f64)).max(0.0);
                    if w > 0.0 {
                        t.push((i, w as f32));
                    }
                    i += 1;
                }
                let total: f32 = t.iter().map(|x| x.1).sum();
                t.iter_mut()
                    .for_each(|x| x.1 /= total.max(f32::MIN_POSITIVE));
                t
            })
            .collect()
    };
    let (tx, ty) = (taps(sw, width), taps(sh, height));
    // Horizontal pass into an sh × width buffer, then vertical.
    let src = img.data();
    let mut tmp = vec![0.0f32; sh * width * c];
    for y in 0..sh {
        for (x, t) in tx.iter().enumerate() {
            for &(i, w) in t {
                for k in 0..c {
                    tmp[(y * width + x) * c + k] += w * src[(y * sw + i) * c + k];
                }
            }
        }
    }
    let dst = out.data_mut();
    for (y, t) in ty.iter().enumerate() {
        for &(j, w) in t {
            for x in 0..width {
                for k in 0..c {
                    dst[(y * width + x) * c + k] += w * tmp[(j * width + x) * c + k];
                }
            }
        }
    }
    out
}

/// Averages `factor × factor` blocks (box filter). Trailing rows/columns that do not fill a
/// block are dropped, so the output is `(W / factor) × (H / factor)` and output pixel `i`
/// covers input pixels `[i·factor, (i+1)·factor)`: the pixel scale is exactly `1 / factor`.
pub fn downscale_box(img: &Image<f32>, factor: u32) -> Image<f32> {
    let f = factor.max(1) as usize;
    if f == 1 {
        return img.clone();
    }
    let (w, h, c) = img.shape();
    let (ow, oh) = ((w / f).max(1).min(w), (h / f).max(1).min(h));
    let mut out = Image::new(ow, oh, c);
    let mut acc = vec![0.0f32; c];
    for oy in 0..oh {
        for ox in 0..ow {
            acc.iter_mut().for_each(|a| *a = 0.0);
            let mut n = 0usize;
            for y in oy * f..((oy + 1) * f).min(h) {
                for x in ox * f..((ox + 1) * f).min(w) {
                    for (a, v) in acc.iter_mut().zip(img.pixel(x, y)) {
                        *a += v;
                    }
                    n += 1;
                }
            }
            let inv = 1.0 / n.max(1) as f32;
            for (o, a) in out.pixel_mut(ox, oy).iter_mut().zip(&acc) {
                *o = a * inv;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_is_row_major_interleaved() {
        let img = Image::from_vec(3, 2, 2, (0..12).collect::<Vec<i32>>()).unwrap();
        assert_eq!(img.pixel(0, 0), &[0, 1]);
        assert_eq!(img.pixel(2, 0), &[4, 5]);
        assert_eq!(img.pixel(0, 1), &[6, 7]);
        assert_eq!(img.row(1), &[6, 7, 8, 9, 10, 11]);
        assert_eq!(img.select_channels(&[1]).data(), &[1, 3, 5, 7, 9, 11]);
    }

    #[test]
    fn wrong_length_is_an_error() {
        assert!(matches!(
            Image::from_vec(3, 2, 2, vec![0u8; 11]),
            Err(ImageError::SizeMismatch {
                expected: 12,
                actual: 11,
                ..
            })
        ));
    }

    #[test]
    fn gaussian_blur_keeps_the_mean_and_smooths_an_edge() {
        let (w, h) = (16, 4);
        let data: Vec<f32> = (0..w * h * 3)
            .map(|i| if (i / 3) % w < w / 2 { 0.0 } else { 1.0 })
            .collect();
        let img = Image::from_vec(w, h, 3, data).unwrap();
        let b = img.gaussian_blur(0.5);
        let mean = |im: &Image<f32>| im.data().iter().sum::<f32>() / im.data().len() as f32;
        assert!((mean(&b) - mean(&img)).abs() < 1e-6);
        let left = b.data()[(w / 2 - 1) * 3];
        let right = b.data()[(w / 2) * 3];
        assert!(left > 0.0 && left < 0.2, "{left}");
        assert!(right < 1.0 && right > 0.8, "{right}");
        assert_eq!(img.gaussian_blur(0.0), img);
    }

    #[test]
    fn bilinear_hits_pixel_centres_and_midpoints() {
        let img = Image::from_vec(2, 1, 1, vec![0.0f32, 1.0]).unwrap();
        let mut v = [0.0f32];
        img.sample_bilinear(0.5, 0.5, &mut v);
        assert_eq!(v[0], 0.0);
        img.sample_bilinear(1.0, 0.5, &mut v);
        assert!((v[0] - 0.5).abs() < 1e-6);
        img.sample_bilinear(10.0, 0.5, &mut v);
        assert_eq!(v[0], 1.0);
    }
    #[test]
    fn area_resize_preserves_means_and_integer_boxes() {
        let mut img = Image::<f32>::new(160, 120, 3);
        for y in 0..120 {
            for x in 0..160 {
                let p = img.pixel_mut(x, y);
                p.copy_from_slice(&[x as f32 / 160.0, y as f32 / 120.0, 0.5]);
            }
        }
        let small = resize_area(&img, 64, 48);
        for k in 0..3 {
            let m = |im: &Image<f32>| {
                im.data().iter().skip(k).step_by(3).sum::<f32>() / (im.width() * im.height()) as f32
            };
            assert!((m(&img) - m(&small)).abs() < 1e-4);
        }
        let half = resize_area(&img, 80, 60);
        let d = img.data();
        let expect = (d[0] + d[3] + d[160 * 3] + d[161 * 3]) / 4.0;
        assert!((half.data()[0] - expect).abs() < 1e-6);
    }

    #[test]
    fn box_downscale_averages_blocks() {
        let img = Image::from_vec(4, 2, 1, vec![0.0, 2.0, 4.0, 6.0, 2.0, 4.0, 6.0, 8.0]).unwrap();
        let out = downscale_box(&img, 2);
        assert_eq!(out.shape(), (2, 1, 1));
        assert_eq!(out.data(), &[2.0, 6.0]);
    }
}
