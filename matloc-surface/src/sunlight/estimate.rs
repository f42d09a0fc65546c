//! The sun's direction found from the posed images and their surfaces, for data that does not
//! say where the sun was: the direction whose cast shadows, traced over the surfaces with
//! [`shadow_mask`], fall where the images darken. Each candidate is scored by how much darker
//! the images are just inside its masks' edges than just outside ([`ShadowEdges::contrast`]),
//! shrunk towards 0 by [`PRIOR_PAIRS`] so a direction that casts a handful of lucky edges does
//! not win. A sphere of directions is searched coarse to fine.

use matloc_core::Image;
use matloc_core::shadow::{to_display, to_linear};
use nalgebra::Vector3;
use rayon::prelude::*;

use super::{DepthView, ShadowEdges, grid_size, shadow_mask};

/// One view the search traces shadows in: its surface, the neighbouring surfaces that vote
/// with it ([`shadow_mask`]) and its image (RGB in `[0, 1]`, any size).
#[derive(Clone, Debug)]
pub struct SunView<'a> {
    /// The view and its surface.
    pub view: DepthView<'a>,
    /// Neighbouring views whose surfaces also vote.
    pub others: Vec<DepthView<'a>>,
    /// The view's image.
    pub image: &'a Image<f32>,
}

/// The search's views: each of `picked` (indices into `views`) with its `neighbours` voting
/// and its image (`images[k]` for `picked[k]`).
pub fn sun_views<'a>(
    views: &[DepthView<'a>],
    neighbours: &[Vec<usize>],
    picked: &[usize],
    images: &'a [Image<f32>],
) -> Vec<SunView<'a>> {
    picked
        .iter()
        .zip(images)
        .map(|(&v, image)| SunView {
            view: views[v],
            others: neighbours[v].iter().map(|&o| views[o]).collect(),
            image,
        })
        .collect()
}

/// What the search found.
#[derive(Clone, Debug, PartialEq)]
pub struct SunEstimate {
    /// Unit direction towards the sun, in the views' world frame.
    pub direction: Vector3<f64>,
    /// Mean `ln(lit / shadowed)` brightness across its shadows' edges (0: its shadows fall
    /// where nothing darkens).
    pub contrast: f64,
    /// Pixel pairs across its shadows' edges, on the finest grid.
    pub pairs: u64,
    /// The best score of any direction at least [`RIVAL_DEG`] away, against this one's
    /// (1: an equally good other sun; small: the images single this one out).
    pub rival: f64,
}

/// Directions tried first, spread evenly over the sphere (about 8° apart).
const COARSE: usize = 600;
/// Coarse directions refined.
const SEEDS: usize = 3;
/// How far apart two directions must be to count as different suns, degrees.
pub const RIVAL_DEG: f64 = 20.0;
/// Pairs of no contrast added to every candidate's edges: a direction casting a handful of
/// edges that happen to darken scores near 0, not at their mean.
const PRIOR_PAIRS: f64 = 100.0;

/// The sun direction that best explains the shadows of `views`, searched on mask grids whose
/// longer side is `max_side` (the coarse pass at half of it); `None` when no direction casts
/// a shadow edge in any view.
pub fn estimate_sun(views: &[SunView], max_side: usize) -> Option<SunEstimate> {
    let coarse_side = (max_side / 2).max(8);
    let coarse = Grids::new(views, coarse_side);
    let scored: Vec<(Vector3<f64>, f64)> = fibonacci_sphere(COARSE)
        .into_par_iter()
        .map(|d| (d, coarse.score(views, &d).0))
        .collect();
    // The best few directions at least RIVAL_DEG apart, best first.
    let mut order: Vec<usize> = (0..scored.len()).collect();
    order.sort_by(|&a, &b| scored[b].1.total_cmp(&scored[a].1));
    let cos_rival = RIVAL_DEG.to_radians().cos();
    let mut seeds: Vec<Vector3<f64>> = Vec::new();
    for &i in &order {
        if seeds.len() == SEEDS || !scored[i].1.is_finite() {
            break;
        }
        if seeds.iter().all(|s| s.dot(&scored[i].0) < cos_rival) {
            seeds.push(scored[i].0);
        }
    }
    if seeds.is_empty() {
        return None;
    }
    // Each seed refined on the coarse grid (±8° in 2° steps), the best then on the fine grid
    // (±2° in 1° steps).
    let refined: Vec<(Vector3<f64>, f64)> = seeds
        .iter()
        .map(|s| {
            let (d, score, _) = best_of(&around(s, 8.0, 2.0), |d| coarse.score(views, d));
            (d, score)
        })
        .collect();
    let (seed, _) = refined.iter().copied().max_by(|a, b| a.1.total_cmp(&b.1))?;
    let fine = Grids::new(views, max_side);
    let (direction, _, edges) = best_of(&around(&seed, 2.0, 1.0), |d| fine.score(views, d));
    let (contrast, pairs) = edges.contrast()?;
    // The best rival on the coarse pass, against the winner on the same grid.
    let own = coarse.score(views, &direction).0;
    let rival = scored
        .iter()
        .filter(|(d, _)| d.dot(&direction) < cos_rival)
        .map(|&(_, s)| s)
        .fold(f64::NEG_INFINITY, f64::max);
    let rival = if own > 0.0 {
        (rival / own).max(0.0)
    } else {
        1.0
    };
    Some(SunEstimate {
        direction,
        contrast,
        pairs,
        rival,
    })
}

/// The edges the shadows of a sun in direction `sun` make in `views` (masks on grids of
/// `max_side`): [`ShadowEdges::contrast`] says how well that sun explains the images' shadows.
pub fn sun_edges(views: &[SunView], sun: &Vector3<f64>, max_side: usize) -> ShadowEdges {
    Grids::new(views, max_side).score(views, sun).1
}

/// The views' images resampled to their mask grids of one size.
struct Grids {
    max_side: usize,
    images: Vec<Image<f32>>,
}

impl Grids {
    fn new(views: &[SunView], max_side: usize) -> Self {
        let images = views
            .iter()
            .map(|v| {
                let (w, h) = grid_size(v.view.camera, max_side);
                shrink(v.image, w, h)
            })
            .collect();
        Grids { max_side, images }
    }

    /// The mean edge contrast of the shadows cast in every view by a sun in direction `d`,
    /// shrunk by [`PRIOR_PAIRS`] (−∞ without edges), and the edges.
    fn score(&self, views: &[SunView], d: &Vector3<f64>) -> (f64, ShadowEdges) {
        let mut edges = ShadowEdges::default();
        for (v, img) in views.iter().zip(&self.images) {
            let mask = shadow_mask(&v.view, &v.others, d, self.max_side);
            edges.add(img, &mask);
        }
        let score = match edges.contrast() {
            Some((mean, n)) => mean * n as f64 / (n as f64 + PRIOR_PAIRS),
            None => f64::NEG_INFINITY,
        };
        (score, edges)
    }
}

/// The candidate of `dirs` with the highest `score`, scored in parallel, with its score and
/// edges.
fn best_of(
    dirs: &[Vector3<f64>],
    score: impl Fn(&Vector3<f64>) -> (f64, ShadowEdges) + Sync,
) -> (Vector3<f64>, f64, ShadowEdges) {
    dirs.par_iter()
        .map(|d| {
            let (s, edges) = score(d);
            (*d, s, edges)
        })
        .reduce(
            || (dirs[0], f64::NEG_INFINITY, ShadowEdges::default()),
            |a, b| if b.1 > a.1 { b } else { a },
        )
}

/// `n` unit vectors spread evenly over the sphere (a Fibonacci lattice).
fn fibonacci_sphere(n: usize) -> Vec<Vector3<f64>> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let a = golden * i as f64;
            Vector3::new(r * a.cos(), r * a.sin(), z)
        })
        .collect()
}

/// Unit directions on a square grid of `step_deg` spacing reaching `radius_deg` from `centre`
/// in its tangent plane (the centre included).
fn around(centre: &Vector3<f64>, radius_deg: f64, step_deg: f64) -> Vec<Vector3<f64>> {
    let c = centre.normalize();
    let helper = if c.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = c.cross(&helper).normalize();
    let e2 = c.cross(&e1);
    let k = (radius_deg / step_deg).round() as i32;
    let step = step_deg.to_radians();
    let mut out = Vec::with_capacity(((2 * k + 1) * (2 * k + 1)) as usize);
    for i in -k..=k {
        for j in -k..=k {
            out.push((c + e1 * (f64::from(i) * step) + e2 * (f64::from(j) * step)).normalize());
        }
    }
    out
}

/// `img` (RGB) averaged down to `w × h` in linear light (box filter over each cell's source
/// pixels; a cell smaller than a pixel takes the nearest one).
fn shrink(img: &Image<f32>, w: usize, h: usize) -> Image<f32> {
    let (sw, sh, c) = img.shape();
    let mut out = Image::<f32>::new(w, h, 3);
    if c != 3 || sw == 0 || sh == 0 {
        return out;
    }
    let src = img.data();
    for y in 0..h {
        let y0 = y * sh / h;
        let y1 = ((y + 1) * sh / h).max(y0 + 1).min(sh);
        for x in 0..w {
            let x0 = x * sw / w;
            let x1 = ((x + 1) * sw / w).max(x0 + 1).min(sw);
            let mut acc = [0.0f32; 3];
            for yy in y0..y1 {
                for xx in x0..x1 {
                    for k in 0..3 {
                        acc[k] += to_linear(src[3 * (yy * sw + xx) + k]);
                    }
                }
            }
            let n = ((y1 - y0) * (x1 - x0)) as f32;
            for k in 0..3 {
                out.data_mut()[3 * (y * w + x) + k] = to_display(acc[k] / n);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lattice_covers_the_sphere_evenly() {
        let dirs = fibonacci_sphere(600);
        // Every direction of a second lattice has a lattice direction within 6°.
        for d in fibonacci_sphere(97) {
            let best = dirs.iter().map(|e| e.dot(&d)).fold(-1.0, f64::max);
            assert!(best > 6f64.to_radians().cos(), "{d:?}: {best}");
        }
        let near = around(&Vector3::new(0.3, -0.5, 0.8), 8.0, 2.0);
        assert_eq!(near.len(), 81);
        let c = Vector3::new(0.3, -0.5, 0.8).normalize();
        let widest = near
            .iter()
            .map(|d| d.dot(&c).acos().to_degrees())
            .fold(0.0, f64::max);
        assert!((widest - 8.0 * 2f64.sqrt()).abs() < 0.2, "{widest}");
    }

    #[test]
    fn shrinking_averages_linear_light() {
        let img = Image::from_vec(2, 1, 3, vec![1.0, 1.0, 1.0, 0.0, 0.0, 0.0]).unwrap();
        let one = shrink(&img, 1, 1);
        assert!((to_linear(one.data()[0]) - 0.5).abs() < 1e-5);
    }
}
