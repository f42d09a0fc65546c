//! A shadow-invariant view of an RGB image: what of a surface's colour stays when a cast shadow
//! moves over it. Under daylight a shadowed surface keeps the bluish sky light and loses the
//! yellowish sunlight, so in log linear RGB leaving a shadow moves a colour along one direction,
//! nearly the same for every sun strength; the two coordinates orthogonal to it do not change
//! (the idea of Finlayson et al.'s illuminant-invariant images). Exposure and white balance
//! become per-channel offsets, which a per-image standardisation removes. What is lost is the
//! brightness along that direction, so texture that differs only in lightness fades.

use crate::Image;

/// Colour of direct sunlight the invariant assumes (yellowish; the synthetic world's).
pub const SUN_COLOUR: [f32; 3] = [1.0, 0.96, 0.88];
/// Colour of the sky light a shadow keeps (bluish; the synthetic world's).
pub const SKY_COLOUR: [f32; 3] = [0.55, 0.65, 0.85];

/// Direction, in log linear RGB, in which a surface's colour moves when it leaves a cast
/// shadow: `ln(sun + sky) − ln(sky)` for [`SUN_COLOUR`] 2.5 times the strength of
/// [`SKY_COLOUR`] (unit length; close to daylight's). It turns by under 2° for a sun from 1× to 6× the
/// sky, so one direction serves every sun elevation.
pub const SHADOW_DIRECTION: [f32; 3] = [0.6495, 0.5861, 0.4844];

/// Display-encoded value → linear light: the 2.2 power the synthetic world and most cameras
/// use (negative values count as 0).
pub fn to_linear(v: f32) -> f32 {
    v.max(0.0).powf(2.2)
}

/// Linear light → display value in `[0, 1]` (the inverse of [`to_linear`], clipped).
pub fn to_display(v: f32) -> f32 {
    v.clamp(0.0, 1.0).powf(1.0 / 2.2)
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Unit axes of the plane orthogonal to [`SHADOW_DIRECTION`]: red − blue made orthogonal, then
/// the direction × that axis.
fn invariant_axes() -> [[f32; 3]; 2] {
    let d = SHADOW_DIRECTION;
    let a = [1.0f32, 0.0, -1.0];
    let ad = dot(a, d);
    let mut e1 = [a[0] - ad * d[0], a[1] - ad * d[1], a[2] - ad * d[2]];
    let n1 = dot(e1, e1).sqrt();
    e1.iter_mut().for_each(|v| *v /= n1);
    let e2 = [
        d[1] * e1[2] - d[2] * e1[1],
        d[2] * e1[0] - d[0] * e1[2],
        d[0] * e1[1] - d[1] * e1[0],
    ];
    [e1, e2]
}

/// The two shadow-invariant channels of an RGB image (`[0, 1]` display values, HWC),
/// channel-major `2 × H × W`: each pixel's log linear colour (display value^2.2, floored at
/// 1/255 of full scale) projected onto the plane orthogonal to [`SHADOW_DIRECTION`].
/// Unstandardised: exposure and white balance are still offsets of each plane.
pub fn shadow_invariant(img: &Image<f32>) -> Vec<f32> {
    let [e1, e2] = invariant_axes();
    let (w, h, c) = img.shape();
    debug_assert_eq!(c, 3, "shadow_invariant needs RGB");
    let mut out = vec![0.0f32; 2 * w * h];
    for (i, px) in img.data().chunks_exact(3).enumerate() {
        let l = [0, 1, 2].map(|k| (px[k].max(1.0 / 255.0)).powf(2.2).ln());
        out[i] = dot(l, e1);
        out[w * h + i] = dot(l, e2);
    }
    out
}

/// Shifts and scales `plane` in place to mean 0 and standard deviation `spread` (a flat
/// plane stays finite: its deviation is floored at 1e-3 before scaling).
pub fn standardise(plane: &mut [f32], spread: f32) {
    let n = plane.len().max(1) as f64;
    let mean = plane.iter().map(|&x| x as f64).sum::<f64>() / n;
    let var = plane
        .iter()
        .map(|&x| (x as f64 - mean).powi(2))
        .sum::<f64>()
        / n;
    let scale = spread / (var.sqrt() as f32 + 1e-3);
    for v in plane.iter_mut() {
        *v = (*v - mean as f32) * scale;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Display value of linear light `v` (the 2.2 curve the invariant inverts).
    fn display(v: f32) -> f32 {
        v.max(0.0).powf(1.0 / 2.2)
    }

    /// A surface of albedo `a` lit by a sun of strength `s` (0: in shadow) and the sky.
    fn lit(a: [f32; 3], s: f32) -> [f32; 3] {
        [0, 1, 2].map(|k| display(0.3 * a[k] * (s * SUN_COLOUR[k] + SKY_COLOUR[k])))
    }

    fn invariant_of(px: [f32; 3]) -> [f32; 2] {
        let img = Image::from_vec(1, 1, 3, px.to_vec()).unwrap();
        let v = shadow_invariant(&img);
        [v[0], v[1]]
    }

    proptest! {
        /// A surface moving out of a cast shadow into sunlight 1× to 3.5× the sky (the
        /// synthetic world's sun from 15° to 60° elevation) changes its log linear colour by
        /// 1.5 to 3; its invariant moves by under 4 % of that.
        #[test]
        fn a_cast_shadow_does_not_change_the_invariant(
            a in prop::array::uniform3(0.1f32..0.9),
            s in 1.0f32..3.5,
        ) {
            let (p, q) = (lit(a, 0.0), lit(a, s));
            let (shade, sun) = (invariant_of(p), invariant_of(q));
            let moved = (sun[0] - shade[0]).hypot(sun[1] - shade[1]);
            let change = (0..3)
                .map(|k| (2.2 * (q[k] / p[k]).ln()).powi(2))
                .sum::<f32>()
                .sqrt();
            prop_assert!(moved < 0.04 * change, "invariant moved by {moved} of {change}");
        }

        /// Two surfaces whose albedos differ in hue differ in the invariant.
        #[test]
        fn the_invariant_keeps_hue(
            a in prop::array::uniform3(0.2f32..0.8),
            k in 0usize..3,
            s in 0.0f32..4.0,
        ) {
            let mut b = a;
            b[k] *= 1.6;
            let (x, y) = (invariant_of(lit(a, s)), invariant_of(lit(b, s)));
            prop_assert!((x[0] - y[0]).hypot(x[1] - y[1]) > 0.2);
        }
    }

    /// The constant is the normalised `ln(2.5 sun + sky) − ln(sky)`.
    #[test]
    fn the_shadow_direction_follows_from_the_light_colours() {
        let d = [0, 1, 2].map(|k| (2.5 * SUN_COLOUR[k] + SKY_COLOUR[k]).ln() - SKY_COLOUR[k].ln());
        let n = dot(d, d).sqrt();
        for k in 0..3 {
            assert!((d[k] / n - SHADOW_DIRECTION[k]).abs() < 1e-4, "{d:?}");
        }
    }

    #[test]
    fn standardise_sets_mean_and_spread() {
        let mut p: Vec<f32> = (0..100).map(|i| 3.0 + 0.1 * i as f32).collect();
        standardise(&mut p, 0.5);
        let mean = p.iter().sum::<f32>() / 100.0;
        let sd = (p.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / 100.0).sqrt();
        assert!(mean.abs() < 1e-5 && (sd - 0.5).abs() < 1e-3, "{mean} {sd}");
        let mut flat = vec![2.0f32; 10];
        standardise(&mut flat, 1.0);
        assert!(flat.iter().all(|v| *v == 0.0));
    }
}
