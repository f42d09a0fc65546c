//! A small raster plotting helper: a canvas with a world → pixel transform, points, lines,
//! rectangles, colours and text in a built-in 5×7 bitmap font (no font files needed). Meant for
//! top-down maps, error curves and similar diagnostic pictures.

// A shared helper: not every drawing primitive has a caller in every command yet.
#![allow(dead_code)]

use std::path::Path;

use anyhow::{Context, Result};
use image::{ImageEncoder, RgbImage};

/// An RGB colour.
pub type Color = [u8; 3];

/// White.
pub const WHITE: Color = [255, 255, 255];
/// Black.
pub const BLACK: Color = [0, 0, 0];
/// Mid grey.
pub const GREY: Color = [128, 128, 128];

/// A categorical colour for index `i` (12 distinct hues, then repeating).
pub fn palette(i: usize) -> Color {
    const P: [Color; 12] = [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
        [0, 0, 128],
        [128, 128, 0],
    ];
    P[i % P.len()]
}

/// A raster canvas; world coordinates map into a plot area with y pointing up.
pub struct Canvas {
    img: RgbImage,
    area: [f64; 4],
    world_min: [f64; 2],
    scale: [f64; 2],
}

impl Canvas {
    /// A `width × height` canvas filled with `background`; the plot area is the whole canvas and
    /// the world window is the unit square until [`Canvas::set_view`] is called.
    pub fn new(width: u32, height: u32, background: Color) -> Canvas {
        let img = RgbImage::from_pixel(width.max(1), height.max(1), image::Rgb(background));
        let mut c = Canvas {
            img,
            area: [0.0, 0.0, width as f64, height as f64],
            world_min: [0.0, 0.0],
            scale: [width as f64, height as f64],
        };
        c.set_view(
            [0.0, 0.0, width as f64, height as f64],
            [0.0, 0.0],
            [1.0, 1.0],
            false,
        );
        c
    }

    /// Canvas width in pixels.
    pub fn width(&self) -> u32 {
        self.img.width()
    }

    /// Canvas height in pixels.
    pub fn height(&self) -> u32 {
        self.img.height()
    }

    /// Maps the world window `[min, max]` into the pixel rectangle `area = [left, top, width,
    /// height]`. With `equal_aspect`, one metre is the same number of pixels on both axes and the
    /// window is centred in the area.
    pub fn set_view(&mut self, area: [f64; 4], min: [f64; 2], max: [f64; 2], equal_aspect: bool) {
        let ex = (max[0] - min[0]).abs().max(1e-12);
        let ey = (max[1] - min[1]).abs().max(1e-12);
        let mut sx = area[2] / ex;
        let mut sy = area[3] / ey;
        let mut world_min = min;
        if equal_aspect {
            let s = sx.min(sy);
            // Centre the window: widen the shorter side.
            world_min[0] -= 0.5 * (area[2] / s - ex);
            world_min[1] -= 0.5 * (area[3] / s - ey);
            sx = s;
            sy = s;
        }
        self.area = area;
        self.world_min = world_min;
        self.scale = [sx, sy];
    }

    /// The plot area `[left, top, width, height]` in pixels.
    pub fn area(&self) -> [f64; 4] {
        self.area
    }

    /// Pixel position of world point `(x, y)`.
    pub fn to_px(&self, x: f64, y: f64) -> (f64, f64) {
        (
            self.area[0] + (x - self.world_min[0]) * self.scale[0],
            self.area[1] + self.area[3] - (y - self.world_min[1]) * self.scale[1],
        )
    }

    /// World length of one pixel along x.
    pub fn metres_per_px(&self) -> f64 {
        1.0 / self.scale[0]
    }

    /// Blends `color` into pixel `(x, y)` with opacity `alpha` (ignored outside the canvas).
    pub fn blend_px(&mut self, x: i64, y: i64, color: Color, alpha: f64) {
        if x < 0 || y < 0 || x >= self.img.width() as i64 || y >= self.img.height() as i64 {
            return;
        }
        let a = alpha.clamp(0.0, 1.0);
        let p = self.img.get_pixel_mut(x as u32, y as u32);
        for c in 0..3 {
            p.0[c] = (f64::from(p.0[c]) * (1.0 - a) + f64::from(color[c]) * a).round() as u8;
        }
    }

    /// Fills the pixel rectangle `[x, x + w) × [y, y + h)`.
    pub fn fill_rect_px(&mut self, x: f64, y: f64, w: f64, h: f64, color: Color, alpha: f64) {
        let (x0, y0) = (x.round() as i64, y.round() as i64);
        let (x1, y1) = ((x + w).round() as i64, (y + h).round() as i64);
        for yy in y0.max(0)..y1.min(self.img.height() as i64) {
            for xx in x0.max(0)..x1.min(self.img.width() as i64) {
                self.blend_px(xx, yy, color, alpha);
            }
        }
    }

    /// A straight pixel line of the given thickness.
    pub fn line_px(&mut self, a: (f64, f64), b: (f64, f64), color: Color, thickness: f64) {
        let len = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
        if !len.is_finite() || len > 1e5 {
            return;
        }
        let steps = len.ceil().max(1.0) as usize * 2;
        let r = (thickness / 2.0).max(0.5);
        for i in 0..=steps {
            let t = i as f64 / steps as f64;
            let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
            self.fill_rect_px(x - r + 0.5, y - r + 0.5, 2.0 * r, 2.0 * r, color, 1.0);
        }
    }

    /// An axis-aligned pixel rectangle outline.
    pub fn rect_px(&mut self, x: f64, y: f64, w: f64, h: f64, color: Color, thickness: f64) {
        self.line_px((x, y), (x + w, y), color, thickness);
        self.line_px((x + w, y), (x + w, y + h), color, thickness);
        self.line_px((x + w, y + h), (x, y + h), color, thickness);
        self.line_px((x, y + h), (x, y), color, thickness);
    }

    /// A filled disc of radius `r` pixels.
    pub fn disc_px(&mut self, cx: f64, cy: f64, r: f64, color: Color, alpha: f64) {
        let ri = r.ceil() as i64 + 1;
        let (x0, y0) = (cx.floor() as i64, cy.floor() as i64);
        for dy in -ri..=ri {
            for dx in -ri..=ri {
                let (x, y) = (x0 + dx, y0 + dy);
                let d2 = (x as f64 + 0.5 - cx).powi(2) + (y as f64 + 0.5 - cy).powi(2);
                if d2 <= r * r {
                    self.blend_px(x, y, color, alpha);
                }
            }
        }
    }

    /// A world point drawn as a disc of `radius_px` pixels.
    pub fn point(&mut self, x: f64, y: f64, radius_px: f64, color: Color, alpha: f64) {
        let (px, py) = self.to_px(x, y);
        if radius_px <= 0.5 {
            self.blend_px(px.floor() as i64, py.floor() as i64, color, alpha);
        } else {
            self.disc_px(px, py, radius_px, color, alpha);
        }
    }

    /// A world line segment.
    pub fn line(&mut self, a: [f64; 2], b: [f64; 2], color: Color, thickness: f64) {
        let pa = self.to_px(a[0], a[1]);
        let pb = self.to_px(b[0], b[1]);
        self.line_px(pa, pb, color, thickness);
    }

    /// A world axis-aligned rectangle outline.
    pub fn rect(&mut self, min: [f64; 2], max: [f64; 2], color: Color, thickness: f64) {
        let (x0, y1) = self.to_px(min[0], min[1]);
        let (x1, y0) = self.to_px(max[0], max[1]);
        self.rect_px(x0, y0, x1 - x0, y1 - y0, color, thickness);
    }

    /// A filled world rectangle with opacity `alpha`.
    pub fn fill_rect(&mut self, min: [f64; 2], max: [f64; 2], color: Color, alpha: f64) {
        let (x0, y1) = self.to_px(min[0], min[1]);
        let (x1, y0) = self.to_px(max[0], max[1]);
        self.fill_rect_px(x0, y0, x1 - x0, y1 - y0, color, alpha);
    }

    /// Draws `text` with its top-left corner at pixel `(x, y)`, each font pixel `scale` pixels
    /// wide; returns the width drawn in pixels. Lower-case letters are drawn as capitals and
    /// characters outside the font as `?`.
    pub fn text_px(&mut self, x: f64, y: f64, text: &str, color: Color, scale: u32) -> f64 {
        let s = f64::from(scale.max(1));
        let mut cx = x;
        for ch in text.chars() {
            let rows = glyph(ch);
            for (r, bits) in rows.iter().enumerate() {
                for c in 0..5 {
                    if bits & (0x10 >> c) != 0 {
                        self.fill_rect_px(cx + c as f64 * s, y + r as f64 * s, s, s, color, 1.0);
                    }
                }
            }
            cx += 6.0 * s;
        }
        cx - x
    }

    /// Width in pixels that [`Canvas::text_px`] would draw.
    pub fn text_width(text: &str, scale: u32) -> f64 {
        text.chars().count() as f64 * 6.0 * f64::from(scale.max(1))
    }

    /// A frame around the plot area with the world window's extent written at its corners,
    /// in the unit `unit`.
    pub fn frame(&mut self, color: Color, unit: &str) {
        let [l, t, w, h] = self.area;
        self.rect_px(l, t, w, h, color, 1.0);
        let [wx0, wy0] = self.world_min;
        let wx1 = wx0 + w / self.scale[0];
        let wy1 = wy0 + h / self.scale[1];
        let bottom = format!("x {wx0:.0} .. {wx1:.0} {unit}");
        self.text_px(l, t + h + 4.0, &bottom, color, 1);
        let side = format!("y {wy0:.0} .. {wy1:.0} {unit}");
        let sw = Canvas::text_width(&side, 1);
        self.text_px(l + w - sw, t + h + 4.0, &side, color, 1);
    }

    /// The pixels.
    pub fn image(&self) -> &RgbImage {
        &self.img
    }

    /// Writes the canvas as a PNG, atomically.
    pub fn save_png(&self, path: &Path) -> Result<()> {
        let mut bytes = Vec::new();
        image::codecs::png::PngEncoder::new(&mut bytes)
            .write_image(
                self.img.as_raw(),
                self.img.width(),
                self.img.height(),
                image::ExtendedColorType::Rgb8,
            )
            .context("encoding PNG")?;
        matloc_data::fsutil::write_atomic(path, &bytes)
            .with_context(|| format!("writing {}", path.display()))
    }
}

/// Rows (top to bottom) of a 5×7 glyph; bit 4 is the leftmost column.
fn glyph(ch: char) -> [u8; 7] {
    let c = ch.to_ascii_uppercase();
    match c {
        ' ' => [0; 7],
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '.' => [0, 0, 0, 0, 0, 0x0C, 0x0C],
        ',' => [0, 0, 0, 0, 0x0C, 0x04, 0x08],
        ':' => [0, 0x0C, 0x0C, 0, 0x0C, 0x0C, 0],
        ';' => [0, 0x0C, 0x0C, 0, 0x0C, 0x04, 0x08],
        '-' => [0, 0, 0, 0x0E, 0, 0, 0],
        '+' => [0, 0x04, 0x04, 0x1F, 0x04, 0x04, 0],
        '=' => [0, 0, 0x1F, 0, 0x1F, 0, 0],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        '[' => [0x0E, 0x08, 0x08, 0x08, 0x08, 0x08, 0x0E],
        ']' => [0x0E, 0x02, 0x02, 0x02, 0x02, 0x02, 0x0E],
        '/' => [0, 0x01, 0x02, 0x04, 0x08, 0x10, 0],
        '%' => [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03],
        '_' => [0, 0, 0, 0, 0, 0, 0x1F],
        '<' => [0x02, 0x04, 0x08, 0x10, 0x08, 0x04, 0x02],
        '>' => [0x08, 0x04, 0x02, 0x01, 0x02, 0x04, 0x08],
        '!' => [0x04, 0x04, 0x04, 0x04, 0x04, 0, 0x04],
        '#' => [0x0A, 0x0A, 0x1F, 0x0A, 0x1F, 0x0A, 0x0A],
        '*' => [0, 0x04, 0x15, 0x0E, 0x15, 0x04, 0],
        '\'' => [0x04, 0x04, 0x08, 0, 0, 0, 0],
        '|' => [0x04; 7],
        '~' => [0, 0, 0x08, 0x15, 0x02, 0, 0],
        _ => [0x0E, 0x11, 0x01, 0x02, 0x04, 0, 0x04],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn world_to_pixel_and_drawing() {
        let mut c = Canvas::new(200, 100, WHITE);
        c.set_view([0.0, 0.0, 200.0, 100.0], [0.0, 0.0], [10.0, 10.0], true);
        // Equal aspect: 10 px per metre, window centred horizontally.
        let (x, y) = c.to_px(0.0, 0.0);
        assert!((x - 50.0).abs() < 1e-9 && (y - 100.0).abs() < 1e-9);
        let (x, y) = c.to_px(10.0, 10.0);
        assert!((x - 150.0).abs() < 1e-9 && y.abs() < 1e-9);
        c.point(5.0, 5.0, 3.0, BLACK, 1.0);
        assert_eq!(c.image().get_pixel(100, 50).0, BLACK);
        let w = c.text_px(2.0, 2.0, "Ab1", palette(0), 2);
        assert_eq!(w, 36.0);
        assert_ne!(c.image().get_pixel(4, 3).0, WHITE);
        c.line([0.0, 0.0], [10.0, 0.0], palette(1), 1.0);
        // Lines and points outside the canvas are clipped, not a panic.
        c.line([-1e9, 0.0], [1e9, 0.0], BLACK, 3.0);
        c.point(-100.0, 500.0, 4.0, BLACK, 1.0);
    }
}
