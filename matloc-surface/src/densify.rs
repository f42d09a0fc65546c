//! Sparse points → a coarse z-depth map of one view: each point is projected (lens included)
//! into a grid of cells whose longer side is `grid_max_side`; a cell keeps its nearest point (a
//! z-buffer, so a point hidden behind a nearer one in the same cell is ignored); empty cells
//! then take the depth of the nearest filled cell within the fill radius (a multi-source
//! breadth-first fill, which keeps depth edges rather than blurring them).
//!
//! Before the fill, gross outliers go: a cell more than 4× off the view's median depth, and a
//! cell that no other filled cell nearby confirms (depth within 20 %) — a lone point is more
//! likely a wrong match than a surface.
//!
//! The map's aspect matches the camera's, so consumers that scale pixel coordinates by
//! `map size / camera size` read it like a full-resolution depth map.

use std::collections::VecDeque;

use matloc_core::Camera;
use matloc_core::image::Image;
use matloc_core::pose::Pose;
use nalgebra::Point3;

/// A coarse depth map and how many points landed in it.
#[derive(Clone, Debug)]
pub struct DensifiedDepth {
    /// z-depth in metres, `0` where there is no surface.
    pub depth: Image<f32>,
    /// Points that projected into the view in front of the camera.
    pub points_in_view: usize,
}

/// Grid size for a camera: longer side `max_side` cells (or the image size when smaller).
pub fn grid_size(camera: &Camera, max_side: usize) -> (usize, usize) {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let long = w.max(h).max(1);
    if long <= max_side {
        return (w.max(1), h.max(1));
    }
    let s = max_side as f64 / long as f64;
    (
        ((w as f64 * s).round() as usize).max(1),
        ((h as f64 * s).round() as usize).max(1),
    )
}

/// Bytes per cell while a map is densified: z-buffer (f32), fill distance (u32), a queue
/// entry (usize) and the output depth (f32).
pub const CELL_BYTES: u64 = 4 + 4 + 8 + 4;

/// The memory densifying a `gw × gh` grid takes.
pub fn densify_request(gw: usize, gh: usize) -> matloc_core::limits::MemoryRequest {
    matloc_core::limits::MemoryRequest {
        what: "densifying a depth map from points",
        count: (gw as u64).saturating_mul(gh as u64),
        unit: "cells",
        bytes_each: CELL_BYTES,
        remedy: "lower `surface.grid_max_side`",
    }
}

/// Projects `points` into the view and fills the grid; `fill_radius` is a fraction of the
/// grid's longer side.
pub fn densify<'a>(
    camera: &Camera,
    cam_from_world: &Pose,
    points: impl IntoIterator<Item = &'a Point3<f64>>,
    grid_max_side: usize,
    fill_radius: f64,
) -> DensifiedDepth {
    let (gw, gh) = grid_size(camera, grid_max_side);
    let (sx, sy) = (
        gw as f64 / camera.width as f64,
        gh as f64 / camera.height as f64,
    );
    let mut z = vec![f32::INFINITY; gw * gh];
    let mut in_view = 0;
    for p in points {
        let pc = cam_from_world * p;
        let Some(px) = camera.project(&pc.coords) else {
            continue;
        };
        if !camera.contains(px) {
            continue;
        }
        in_view += 1;
        let (cx, cy) = (
            ((px.x * sx) as usize).min(gw - 1),
            ((px.y * sy) as usize).min(gh - 1),
        );
        let cell = &mut z[cy * gw + cx];
        *cell = cell.min(pc.z as f32);
    }
    reject_far_from_median(&mut z, MEDIAN_RATIO);
    reject_isolated(&mut z, gw, gh, outlier_radius(gw, gh), OUTLIER_TOLERANCE);
    // Breadth-first fill from every filled cell at once (8-neighbourhood, Chebyshev radius).
    let radius = (fill_radius * gw.max(gh) as f64).round() as u32;
    let mut dist = vec![u32::MAX; gw * gh];
    let mut queue = VecDeque::new();
    for (i, v) in z.iter().enumerate() {
        if v.is_finite() {
            dist[i] = 0;
            queue.push_back(i);
        }
    }
    while let Some(i) = queue.pop_front() {
        let d = dist[i];
        if d >= radius {
            continue;
        }
        let (x, y) = ((i % gw) as isize, (i / gw) as isize);
        for (dx, dy) in [
            (-1, -1),
            (0, -1),
            (1, -1),
            (-1, 0),
            (1, 0),
            (-1, 1),
            (0, 1),
            (1, 1),
        ] {
            let (nx, ny) = (x + dx, y + dy);
            if nx < 0 || ny < 0 || nx >= gw as isize || ny >= gh as isize {
                continue;
            }
            let j = ny as usize * gw + nx as usize;
            if dist[j] == u32::MAX {
                dist[j] = d + 1;
                z[j] = z[i];
                queue.push_back(j);
            }
        }
    }
    let data = z
        .into_iter()
        .map(|v| if v.is_finite() { v } else { 0.0 })
        .collect();
    DensifiedDepth {
        depth: Image::from_vec(gw, gh, 1, data).expect("grid shape matches its data"),
        points_in_view: in_view,
    }
}

/// A cell deeper than this many times the view's median depth, or shallower than its
/// inverse, is dropped (an aerial view's surface spans far less; an oblique one up to ~3×).
const MEDIAN_RATIO: f32 = 4.0;

/// Empties filled cells whose depth is more than `ratio` times off the median of the cells.
fn reject_far_from_median(z: &mut [f32], ratio: f32) {
    let mut filled: Vec<f32> = z.iter().copied().filter(|v| v.is_finite()).collect();
    if filled.is_empty() {
        return;
    }
    let mid = filled.len() / 2;
    let (_, &mut median, _) = filled.select_nth_unstable_by(mid, f32::total_cmp);
    for v in z.iter_mut() {
        if v.is_finite() && (*v > median * ratio || *v < median / ratio) {
            *v = f32::INFINITY;
        }
    }
}

/// Relative depth difference within which two nearby cells confirm each other.
const OUTLIER_TOLERANCE: f32 = 0.2;

/// Neighbourhood (Chebyshev radius, cells) in which a cell looks for confirmation: a tenth of
/// the grid's longer side, at least 2.
fn outlier_radius(gw: usize, gh: usize) -> usize {
    (gw.max(gh) / 10).max(2)
}

/// Empties every filled cell that no other filled cell within `radius` confirms (depth within
/// `tol` relative). A wrong match triangulates to a lone point far off the surface; its box
/// would otherwise stretch a block's scene bounds by tens of metres. A real surface point has
/// neighbours on the same surface.
fn reject_isolated(z: &mut [f32], gw: usize, gh: usize, radius: usize, tol: f32) {
    let keep: Vec<bool> = (0..z.len())
        .map(|i| {
            let v = z[i];
            if !v.is_finite() {
                return false;
            }
            let (x, y) = (i % gw, i / gw);
            let (x0, x1) = (x.saturating_sub(radius), (x + radius).min(gw - 1));
            let (y0, y1) = (y.saturating_sub(radius), (y + radius).min(gh - 1));
            (y0..=y1).any(|yy| {
                (x0..=x1).any(|xx| {
                    let j = yy * gw + xx;
                    j != i && z[j].is_finite() && (z[j] - v).abs() <= tol * v.max(z[j])
                })
            })
        })
        .collect();
    for (v, k) in z.iter_mut().zip(keep) {
        if !k {
            *v = f32::INFINITY;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::pose::look_at;
    use nalgebra::{Point2, Vector3};
    use proptest::prelude::*;

    fn cam() -> Camera {
        Camera::pinhole(160, 120, 150.0, 150.0, 80.0, 60.0).unwrap()
    }

    /// A nadir camera 30 m above the plane z = 0 sees depth 30 everywhere.
    #[test]
    fn plane_seen_from_above_fills_to_its_depth() {
        let pose = look_at(
            &Point3::new(0.0, 0.0, 30.0),
            &Point3::origin(),
            &Vector3::y(),
        )
        .unwrap();
        let pts: Vec<Point3<f64>> = (0..400)
            .map(|k| Point3::new((k % 20) as f64 - 9.5, (k / 20) as f64 * 0.7 - 7.0, 0.0))
            .collect();
        let d = densify(&cam(), &pose, &pts, 48, 1.0);
        assert_eq!((d.depth.width(), d.depth.height()), (48, 36));
        assert!(d.points_in_view > 300);
        for v in d.depth.data() {
            assert!((v - 30.0).abs() < 1e-3, "{v}");
        }
    }

    /// A nearer point hides a farther one in the same cell; cells beyond the radius stay empty.
    #[test]
    fn z_buffer_and_radius() {
        let pose = Pose::identity();
        let c = cam();
        let at = |px: Point2<f64>, z: f64| {
            let b = c.unproject(px).unwrap();
            Point3::from(b / b.z * z)
        };
        let pts = [
            at(Point2::new(80.0, 60.0), 10.0),
            at(Point2::new(80.5, 60.5), 20.0),
            at(Point2::new(90.0, 60.0), 10.5),
            // Alone and far off the others: rejected.
            at(Point2::new(10.0, 10.0), 40.0),
        ];
        let d = densify(&c, &pose, &pts, 48, 0.0);
        let filled: Vec<f32> = d
            .depth
            .data()
            .iter()
            .copied()
            .filter(|v| *v > 0.0)
            .collect();
        assert_eq!(filled, vec![10.0, 10.5]);
        assert_eq!(d.points_in_view, 4);
        // Behind the camera or outside the image: not in view.
        let d = densify(
            &c,
            &pose,
            &[Point3::new(0.0, 0.0, -5.0), Point3::new(100.0, 0.0, 1.0)],
            48,
            1.0,
        );
        assert_eq!(d.points_in_view, 0);
        assert!(d.depth.data().iter().all(|v| *v == 0.0));
    }

    #[test]
    fn a_grid_beyond_the_memory_budget_is_refused() {
        use matloc_core::limits::{BudgetSource, MemoryBudget, check_against};
        let budget = Some(MemoryBudget {
            bytes: 64 << 20,
            source: BudgetSource::Explicit,
        });
        let big = Camera::pinhole(40_000, 30_000, 3e4, 3e4, 2e4, 1.5e4).unwrap();
        let (gw, gh) = grid_size(&big, 4096);
        assert_eq!((gw, gh), (4096, 3072));
        let e = check_against(&densify_request(gw, gh), budget)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("12582912 cells") && e.contains("surface.grid_max_side"),
            "{e}"
        );
        let (gw, gh) = grid_size(&big, 48);
        assert!(check_against(&densify_request(gw, gh), budget).is_ok());
    }

    proptest! {
        /// Every filled value is one of the projected depths, and the grid keeps the aspect.
        #[test]
        fn fill_only_copies_point_depths(
            w in 8u32..400, h in 8u32..400, max_side in 4usize..64,
            zs in proptest::collection::vec((0.0f64..1.0, 0.0f64..1.0, 1.0f64..50.0), 1..20),
        ) {
            let c = Camera::pinhole(w, h, w as f64, w as f64, w as f64 / 2.0, h as f64 / 2.0).unwrap();
            let pts: Vec<Point3<f64>> = zs.iter().map(|&(u, v, z)| {
                let b = c.unproject(Point2::new(u * w as f64, v * h as f64)).unwrap();
                Point3::from(b / b.z * z)
            }).collect();
            let d = densify(&c, &Pose::identity(), &pts, max_side, 0.3);
            let (gw, gh) = grid_size(&c, max_side);
            prop_assert!(gw.max(gh) <= max_side.max(w.max(h) as usize));
            prop_assert_eq!((d.depth.width(), d.depth.height()), (gw, gh));
            for v in d.depth.data() {
                prop_assert!(*v == 0.0 || zs.iter().any(|t| (t.2 as f32 - v).abs() < 1e-3));
            }
        }
    }
}
