//! Procedural pattern primitives: gradient noise, fractal sums, prefiltered pulses and spots,
//! and linear-RGB helpers. Every pattern takes the world-space footprint `fw` of the pixel
//! (metres) and drops or box-filters detail finer than it (see [`crate::texture`]).

use super::rng::{hash3, unit};

/// Linear RGB.
pub(crate) type Rgb = [f32; 3];

#[inline]
fn fade(t: f32) -> f32 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

#[inline]
fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a + (b - a) * t
}

const D: f32 = std::f32::consts::FRAC_1_SQRT_2;

/// Unit gradient directions for 2D noise (8 compass directions).
const G2: [(f32, f32); 8] = [
    (1.0, 0.0),
    (-1.0, 0.0),
    (0.0, 1.0),
    (0.0, -1.0),
    (D, D),
    (-D, D),
    (D, -D),
    (-D, -D),
];

/// 2D gradient noise, roughly in `[-1, 1]`, zero mean.
#[inline]
pub(crate) fn noise2(x: f32, y: f32, seed: u32) -> f32 {
    let xf = x.floor();
    let yf = y.floor();
    let (ix, iy) = (xf as i32, yf as i32);
    let (fx, fy) = (x - xf, y - yf);
    let g = |i: i32, j: i32, dx: f32, dy: f32| {
        let (gx, gy) = G2[(hash3(i, j, 0, seed) & 7) as usize];
        gx * dx + gy * dy
    };
    let n00 = g(ix, iy, fx, fy);
    let n10 = g(ix + 1, iy, fx - 1.0, fy);
    let n01 = g(ix, iy + 1, fx, fy - 1.0);
    let n11 = g(ix + 1, iy + 1, fx - 1.0, fy - 1.0);
    let u = fade(fx);
    let v = fade(fy);
    1.4 * lerp(lerp(n00, n10, u), lerp(n01, n11, u), v)
}

/// The 12 cube-edge gradients of classic 3D gradient noise.
const G3: [(f32, f32, f32); 12] = [
    (1.0, 1.0, 0.0),
    (-1.0, 1.0, 0.0),
    (1.0, -1.0, 0.0),
    (-1.0, -1.0, 0.0),
    (1.0, 0.0, 1.0),
    (-1.0, 0.0, 1.0),
    (1.0, 0.0, -1.0),
    (-1.0, 0.0, -1.0),
    (0.0, 1.0, 1.0),
    (0.0, -1.0, 1.0),
    (0.0, 1.0, -1.0),
    (0.0, -1.0, -1.0),
];

/// 3D gradient noise, roughly in `[-1, 1]`, zero mean.
#[inline]
pub(crate) fn noise3(x: f32, y: f32, z: f32, seed: u32) -> f32 {
    let (xf, yf, zf) = (x.floor(), y.floor(), z.floor());
    let (ix, iy, iz) = (xf as i32, yf as i32, zf as i32);
    let (fx, fy, fz) = (x - xf, y - yf, z - zf);
    let g = |i: i32, j: i32, k: i32, dx: f32, dy: f32, dz: f32| {
        let (gx, gy, gz) = G3[(hash3(i, j, k, seed) % 12) as usize];
        gx * dx + gy * dy + gz * dz
    };
    let (u, v, w) = (fade(fx), fade(fy), fade(fz));
    let x00 = lerp(
        g(ix, iy, iz, fx, fy, fz),
        g(ix + 1, iy, iz, fx - 1.0, fy, fz),
        u,
    );
    let x10 = lerp(
        g(ix, iy + 1, iz, fx, fy - 1.0, fz),
        g(ix + 1, iy + 1, iz, fx - 1.0, fy - 1.0, fz),
        u,
    );
    let x01 = lerp(
        g(ix, iy, iz + 1, fx, fy, fz - 1.0),
        g(ix + 1, iy, iz + 1, fx - 1.0, fy, fz - 1.0),
        u,
    );
    let x11 = lerp(
        g(ix, iy + 1, iz + 1, fx, fy - 1.0, fz - 1.0),
        g(ix + 1, iy + 1, iz + 1, fx - 1.0, fy - 1.0, fz - 1.0),
        u,
    );
    lerp(lerp(x00, x10, v), lerp(x01, x11, v), w)
}

/// Weight of a noise octave of frequency `freq` (1/m) seen through a footprint `fw` (m):
/// 1 well below Nyquist, fading to 0 once a period spans fewer than ~2 footprints.
#[inline]
fn octave_weight(freq: f32, fw: f32) -> f32 {
    let r = freq * fw;
    (2.0 - 4.0 * r).clamp(0.0, 1.0)
}

/// Fractal sum of 2D gradient noise starting at `freq` (1/m), prefiltered for footprint `fw`.
///
/// Normalised by the full amplitude sum, so filtered-out detail lowers the contrast the way a
/// true average over the footprint would, instead of being renormalised back.
pub(crate) fn fbm2(x: f32, y: f32, freq: f32, octaves: u32, seed: u32, fw: f32) -> f32 {
    let mut sum = 0.0;
    let mut amp = 1.0;
    let mut norm = 0.0;
    let mut f = freq;
    let mut active = true;
    for o in 0..octaves {
        norm += amp;
        if active {
            let w = octave_weight(f, fw);
            if w <= 0.0 {
                active = false;
            } else {
                sum += amp * w * noise2(x * f, y * f, seed.wrapping_add(o * 7919));
            }
        }
        amp *= 0.5;
        f *= 2.0;
    }
    sum / norm
}

/// Fractal sum of 3D gradient noise; see [`fbm2`].
pub(crate) fn fbm3(p: [f32; 3], freq: f32, octaves: u32, seed: u32, fw: f32) -> f32 {
    let mut sum = 0.0;
    let mut amp = 1.0;
    let mut norm = 0.0;
    let mut f = freq;
    let mut active = true;
    for o in 0..octaves {
        norm += amp;
        if active {
            let w = octave_weight(f, fw);
            if w <= 0.0 {
                active = false;
            } else {
                sum += amp * w * noise3(p[0] * f, p[1] * f, p[2] * f, seed.wrapping_add(o * 7919));
            }
        }
        amp *= 0.5;
        f *= 2.0;
    }
    sum / norm
}

/// Fraction of the box `[x − fw/2, x + fw/2]` covered by `[lo, hi]`: a box-filtered step pulse.
#[inline]
pub(crate) fn pulse(x: f32, lo: f32, hi: f32, fw: f32) -> f32 {
    let h = 0.5 * fw.max(1e-4);
    ((x + h).clamp(lo, hi) - (x - h).clamp(lo, hi)) / (2.0 * h)
}

/// Box-filtered pulse `[lo, hi]` repeated with `period`, evaluated at `x` already reduced to
/// `[0, period)`; the neighbouring copies matter when the footprint straddles a cell border.
#[inline]
pub(crate) fn periodic_pulse(x: f32, lo: f32, hi: f32, period: f32, fw: f32) -> f32 {
    (pulse(x, lo, hi, fw)
        + pulse(x, lo - period, hi - period, fw)
        + pulse(x, lo + period, hi + period, fw))
    .min(1.0)
}

/// How much of a periodic pattern with period `period` survives footprint `fw`: 1 while a
/// period spans at least 4 footprints, 0 below 2 (then callers blend to the pattern's mean).
#[inline]
pub(crate) fn detail(period: f32, fw: f32) -> f32 {
    octave_weight(1.0 / period.max(1e-6), fw)
}

/// Scattered round spots on a jittered grid of `cell`-sized cells: each cell holds a spot with
/// probability `prob`, radius in `[rmin, rmax]` (`1.45 rmax <= cell / 2`, ragged edges included). Returns the box-filtered
/// coverage and a per-spot random value for its colour.
#[inline]
pub(crate) fn spots(
    x: f32,
    y: f32,
    cell: f32,
    prob: f32,
    rmin: f32,
    rmax: f32,
    seed: u32,
    fw: f32,
) -> (f32, f32) {
    let (ci, cj) = ((x / cell).floor(), (y / cell).floor());
    let h = hash3(ci as i32, cj as i32, 91, seed);
    if unit(h) >= prob {
        return (0.0, 0.0);
    }
    let h2 = hash3(ci as i32, cj as i32, 92, seed);
    let r = rmin + (rmax - rmin) * unit(h2);
    // Ragged outlines reach ~1.45 r; keep them inside the cell.
    let room = (0.5 * cell - 1.45 * r).max(0.0);
    let cx = (ci + 0.5) * cell + room * (2.0 * unit(h2.rotate_left(11)) - 1.0);
    let cy = (cj + 0.5) * cell + room * (2.0 * unit(h2.rotate_left(22)) - 1.0);
    let mut d = ((x - cx) * (x - cx) + (y - cy) * (y - cy)).sqrt();
    if d < 1.3 * r + fw {
        // Ragged outlines: real shrubs and stains are not discs.
        d += 0.3 * r * noise2(x * 2.5 / r, y * 2.5 / r, seed ^ 0x0D);
    }
    // Spots far below the footprint would flicker: fade them to their area-averaged tint.
    let cov = pulse(d, -r, r, fw) * detail(4.0 * r, fw);
    (cov, unit(hash3(ci as i32, cj as i32, 93, seed)))
}

#[inline]
pub(crate) fn mix(a: Rgb, b: Rgb, t: f32) -> Rgb {
    [
        lerp(a[0], b[0], t),
        lerp(a[1], b[1], t),
        lerp(a[2], b[2], t),
    ]
}

#[inline]
pub(crate) fn scale(a: Rgb, s: f32) -> Rgb {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// Linear RGB from 8-bit sRGB-ish values (gamma 2.2 is close enough for albedo palettes).
pub(crate) fn srgb(r: u8, g: u8, b: u8) -> Rgb {
    let f = |c: u8| (c as f32 / 255.0).powf(2.2);
    [f(r), f(g), f(b)]
}

/// Per-cell random value in `[0, 1)` for cell `(i, j)` of a pattern.
#[inline]
pub(crate) fn cell_rand(i: i32, j: i32, seed: u32) -> f32 {
    unit(hash3(i, j, 17, seed))
}

/// Multiplicative brightness jitter `1 + amount * noise`, for breaking up flat colours.
#[inline]
pub(crate) fn vary(c: Rgb, amount: f32, n: f32) -> Rgb {
    scale(c, (1.0 + amount * n).max(0.05))
}

// ---------------------------------------------------------------------------------------------
// Surface albedo of every scene part.

#[inline]
pub(crate) fn smooth(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_bounded_and_continuous() {
        let mut max = 0.0f32;
        for i in 0..2000 {
            let x = i as f32 * 0.173 - 50.0;
            let y = i as f32 * 0.311 + 3.0;
            let n = noise2(x, y, 3);
            let m = noise3(x, y, 0.5 * x, 9);
            max = max.max(n.abs()).max(m.abs());
            assert!((noise2(x + 1e-3, y, 3) - n).abs() < 0.02);
        }
        assert!(max < 1.6 && max > 0.3, "max {max}");
        // Integer lattice points are zero for gradient noise.
        assert_eq!(noise2(4.0, -7.0, 1), 0.0);
    }

    #[test]
    fn prefilter_drops_contrast_with_footprint() {
        let var = |fw: f32| {
            let mut s = 0.0;
            for i in 0..4000 {
                let v = fbm2(i as f32 * 0.37, i as f32 * 0.11, 4.0, 5, 2, fw);
                s += v * v;
            }
            s / 4000.0
        };
        assert!(var(0.0) > var(0.1));
        assert!(var(0.1) > var(1.0));
        assert_eq!(var(10.0), 0.0);
    }

    #[test]
    fn pulse_integrates_box() {
        assert!((pulse(0.5, 0.0, 1.0, 0.1) - 1.0).abs() < 1e-6);
        assert_eq!(pulse(2.0, 0.0, 1.0, 0.1), 0.0);
        assert!((pulse(1.0, 0.0, 1.0, 0.2) - 0.5).abs() < 1e-6);
        assert!((periodic_pulse(0.0, 0.05, 0.95, 1.0, 0.2) - 0.5).abs() < 1e-6);
    }
}
