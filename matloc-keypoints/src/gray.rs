//! Single-channel float images: conversion, resizing and smoothing.

use matloc_core::Image;

/// A single-channel `f32` image, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct GrayImage {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

impl GrayImage {
    /// A `width × height` image from row-major values; `None` if the length does not match.
    pub fn from_vec(width: usize, height: usize, data: Vec<f32>) -> Option<Self> {
        (data.len() == width * height).then_some(Self {
            width,
            height,
            data,
        })
    }

    /// Luma (Rec. 601 weights) of an RGB image, or the single channel of a grey one; other
    /// channel counts use the mean of the channels.
    pub fn from_image(image: &Image<f32>) -> Self {
        let (w, h, c) = image.shape();
        let src = image.data();
        let data = (0..w * h)
            .map(|i| {
                let p = &src[i * c..(i + 1) * c];
                match c {
                    3 => 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2],
                    0 => 0.0,
                    _ => p.iter().sum::<f32>() / c as f32,
                }
            })
            .collect();
        Self {
            width: w,
            height: h,
            data,
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Row-major values.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// Value at `(x, y)` (no bounds check beyond the slice's).
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Bilinear resize to `width × height` (pixel-centre aligned). Downscaling by more than 2×
    /// should go through a pre-blur; the pyramid's 1.2 steps do not need one.
    pub fn resized(&self, width: usize, height: usize) -> Self {
        let mut data = vec![0.0f32; width * height];
        if self.width == 0 || self.height == 0 {
            return Self {
                width,
                height,
                data,
            };
        }
        let sx = self.width as f32 / width.max(1) as f32;
        let sy = self.height as f32 / height.max(1) as f32;
        for y in 0..height {
            let fy = ((y as f32 + 0.5) * sy - 0.5).clamp(0.0, (self.height - 1) as f32);
            let y0 = fy.floor() as usize;
            let y1 = (y0 + 1).min(self.height - 1);
            let ty = fy - y0 as f32;
            for x in 0..width {
                let fx = ((x as f32 + 0.5) * sx - 0.5).clamp(0.0, (self.width - 1) as f32);
                let x0 = fx.floor() as usize;
                let x1 = (x0 + 1).min(self.width - 1);
                let tx = fx - x0 as f32;
                let top = self.at(x0, y0) * (1.0 - tx) + self.at(x1, y0) * tx;
                let bottom = self.at(x0, y1) * (1.0 - tx) + self.at(x1, y1) * tx;
                data[y * width + x] = top * (1.0 - ty) + bottom * ty;
            }
        }
        Self {
            width,
            height,
            data,
        }
    }

    /// Unsharp mask in place: `v + amount · (v − blur_σ(v))`, clamped to `[0, 1]`;
    /// `amount ≤ 0` (or not finite) returns the image untouched, without a copy.
    pub fn unsharp(mut self, amount: f32, sigma: f32) -> Self {
        if !(amount > 0.0 && amount.is_finite()) {
            return self;
        }
        let blurred = self.gaussian_blur(sigma);
        for (v, b) in self.data.iter_mut().zip(&blurred.data) {
            *v = (*v + amount * (*v - b)).clamp(0.0, 1.0);
        }
        self
    }

    /// Separable Gaussian blur with standard deviation `sigma` (radius ⌈3σ⌉, clamped edges).
    pub fn gaussian_blur(&self, sigma: f32) -> Self {
        if sigma <= 0.0 || self.data.is_empty() {
            return self.clone();
        }
        let r = (3.0 * sigma).ceil() as isize;
        let mut k: Vec<f32> = (-r..=r)
            .map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp())
            .collect();
        let s: f32 = k.iter().sum();
        k.iter_mut().for_each(|v| *v /= s);
        let (w, h) = (self.width as isize, self.height as isize);
        let mut tmp = vec![0.0f32; self.data.len()];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for (i, kv) in k.iter().enumerate() {
                    let xx = (x + i as isize - r).clamp(0, w - 1);
                    acc += kv * self.data[(y * w + xx) as usize];
                }
                tmp[(y * w + x) as usize] = acc;
            }
        }
        let mut out = vec![0.0f32; self.data.len()];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for (i, kv) in k.iter().enumerate() {
                    let yy = (y + i as isize - r).clamp(0, h - 1);
                    acc += kv * tmp[(yy * w + x) as usize];
                }
                out[(y * w + x) as usize] = acc;
            }
        }
        Self {
            width: self.width,
            height: self.height,
            data: out,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// The mask keeps flat regions, stays in [0, 1], and steepens an edge.
        #[test]
        fn unsharp_keeps_flats_and_range_and_steepens_edges(
            level in 0.0f32..1.0,
            amount in 0.1f32..3.0,
            edge in 3usize..13,
        ) {
            let (w, h) = (16, 8);
            let flat = GrayImage::from_vec(w, h, vec![level; w * h]).unwrap();
            for v in flat.clone().unsharp(amount, 1.0).data() {
                prop_assert!((v - level).abs() < 1e-5);
            }
            let step: Vec<f32> = (0..w * h).map(|i| if i % w < edge { 0.2 } else { 0.8 }).collect();
            let img = GrayImage::from_vec(w, h, step).unwrap();
            let sharp = img.clone().unsharp(amount, 1.0);
            prop_assert!(sharp.data().iter().all(|v| (0.0..=1.0).contains(v)));
            let jump = |g: &GrayImage| g.at(edge, 4) - g.at(edge - 1, 4);
            prop_assert!(jump(&sharp) > jump(&img.gaussian_blur(1.0)));
            prop_assert!(jump(&sharp) >= jump(&img) - 1e-6);
            // No mask at all for a non-positive amount.
            prop_assert_eq!(img.clone().unsharp(0.0, 1.0), img);
        }
    }
}
