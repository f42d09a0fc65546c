//! A height field of the surface the training cameras saw, on a square grid in the plane
//! perpendicular to the world's up axis, with the number of training cameras that saw each cell.

use nalgebra::{Point3, Vector3};

use crate::error::SurfaceError;

/// An orthonormal frame with `up` as its third axis: a world point `p` has ground coordinates
/// `(p·e1, p·e2)` and height `p·up`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GroundFrame {
    /// First horizontal axis.
    pub e1: Vector3<f64>,
    /// Second horizontal axis (`up × e1`).
    pub e2: Vector3<f64>,
    /// Unit up axis.
    pub up: Vector3<f64>,
}

impl GroundFrame {
    /// The frame of `up` (normalised here): `e1` is the world axis least aligned with `up`,
    /// made perpendicular to it, so for `up = +z` the frame is the world's own `(x, y, z)`.
    /// `None` for a zero or non-finite `up`.
    pub fn new(up: Vector3<f64>) -> Option<GroundFrame> {
        if !up.iter().all(|v| v.is_finite()) {
            return None;
        }
        let up = up.try_normalize(1e-12)?;
        let axis = (0..3)
            .min_by(|&a, &b| up[a].abs().total_cmp(&up[b].abs()))
            .unwrap_or(0);
        let a = Vector3::ith(axis, 1.0);
        let e1 = (a - up * a.dot(&up)).try_normalize(1e-12)?;
        let e2 = up.cross(&e1);
        Some(GroundFrame { e1, e2, up })
    }

    /// Ground coordinates `(u, v)` and height `h` of a world point.
    pub fn local(&self, p: &Point3<f64>) -> [f64; 3] {
        [
            p.coords.dot(&self.e1),
            p.coords.dot(&self.e2),
            p.coords.dot(&self.up),
        ]
    }

    /// The world point of ground coordinates `(u, v)` and height `h`.
    pub fn world(&self, u: f64, v: f64, h: f64) -> Point3<f64> {
        Point3::from(self.e1 * u + self.e2 * v + self.up * h)
    }
}

/// Cells with no observed point hold this height.
const UNKNOWN: f64 = f64::NEG_INFINITY;

/// Highest observed surface point per cell and the training cameras that saw the cell.
#[derive(Clone, Debug)]
pub struct SurfaceGrid {
    frame: GroundFrame,
    /// Ground coordinates of the corner of cell `(0, 0)`.
    origin: [f64; 2],
    cell_m: f64,
    dims: [usize; 2],
    /// Highest point per cell (row-major, `u` fastest), [`UNKNOWN`] where none.
    height: Vec<f64>,
    /// Distinct training cameras with a point in the cell.
    views: Vec<u32>,
    /// Lowest known cell height.
    min_height: f64,
}

/// Cells allowed in a grid (4096² cells of 12 bytes: 200 MB).
const MAX_CELLS: usize = 4096 * 4096;

impl SurfaceGrid {
    /// The grid of `cell_m` cells over the surface points each training camera saw (`seen[c]`
    /// is camera `c`'s points; non-finite points are skipped). Errors: `cell_m` not positive,
    /// no finite point, or a grid of more than 4096² cells.
    pub fn build(
        frame: GroundFrame,
        cell_m: f64,
        seen: &[Vec<Point3<f64>>],
    ) -> Result<SurfaceGrid, SurfaceError> {
        if !(cell_m.is_finite() && cell_m > 0.0) {
            return Err(SurfaceError::InvalidConfig {
                field: "virtual.cell_m",
                reason: format!("must be finite and positive, got {cell_m}"),
            });
        }
        let finite = |p: &&Point3<f64>| p.coords.iter().all(|v| v.is_finite());
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for p in seen.iter().flatten().filter(finite) {
            let l = frame.local(p);
            for a in 0..2 {
                lo[a] = lo[a].min(l[a]);
                hi[a] = hi[a].max(l[a]);
            }
        }
        if !(lo[0].is_finite() && hi[0].is_finite()) {
            return Err(SurfaceError::NoSurfaceSeen);
        }
        let dims = [0, 1].map(|a| ((hi[a] - lo[a]) / cell_m).floor() as usize + 1);
        if dims[0].saturating_mul(dims[1]) > MAX_CELLS {
            return Err(SurfaceError::InvalidConfig {
                field: "virtual.cell_m",
                reason: format!(
                    "gives a {}×{} grid over the surface, more than 4096² cells; use larger cells",
                    dims[0], dims[1]
                ),
            });
        }
        let mut grid = SurfaceGrid {
            frame,
            origin: lo,
            cell_m,
            dims,
            height: vec![UNKNOWN; dims[0] * dims[1]],
            views: vec![0; dims[0] * dims[1]],
            min_height: f64::INFINITY,
        };
        let mut cells = Vec::new();
        for points in seen {
            cells.clear();
            for p in points.iter().filter(finite) {
                let [u, v, h] = frame.local(p);
                if let Some(i) = grid.index(u, v) {
                    grid.height[i] = grid.height[i].max(h);
                    cells.push(i);
                }
            }
            cells.sort_unstable();
            cells.dedup();
            for &i in &cells {
                grid.views[i] += 1;
            }
        }
        grid.min_height = grid
            .height
            .iter()
            .copied()
            .filter(|h| *h > UNKNOWN)
            .fold(f64::INFINITY, f64::min);
        Ok(grid)
    }

    /// The grid's ground frame.
    pub fn frame(&self) -> &GroundFrame {
        &self.frame
    }

    /// Cell edge, metres.
    pub fn cell_m(&self) -> f64 {
        self.cell_m
    }

    /// Ground-coordinate bounds `([u0, v0], [u1, v1])` of the grid.
    pub fn extent(&self) -> ([f64; 2], [f64; 2]) {
        (
            self.origin,
            [0, 1].map(|a| self.origin[a] + self.dims[a] as f64 * self.cell_m),
        )
    }

    fn index(&self, u: f64, v: f64) -> Option<usize> {
        let x = (u - self.origin[0]) / self.cell_m;
        let y = (v - self.origin[1]) / self.cell_m;
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        let (x, y) = (x as usize, y as usize);
        (x < self.dims[0] && y < self.dims[1]).then_some(y * self.dims[0] + x)
    }

    /// Index of the cell of ground point `(u, v)` (row-major, `u` fastest), `None` outside
    /// the grid.
    pub fn cell(&self, u: f64, v: f64) -> Option<usize> {
        self.index(u, v)
    }

    /// The cells holding at least one of `points` (non-finite points and points outside the
    /// grid skipped), increasing and without repeats.
    pub fn cells_of(&self, points: &[Point3<f64>]) -> Vec<usize> {
        let mut cells: Vec<usize> = points
            .iter()
            .filter_map(|p| {
                let [u, v, _] = self.frame.local(p);
                self.index(u, v)
            })
            .collect();
        cells.sort_unstable();
        cells.dedup();
        cells
    }

    /// A length that any ray from `origin` crosses the grid's observed surface within: the
    /// horizontal distance to the grid's farthest corner plus the height above its lowest
    /// observed cell.
    pub fn reach(&self, origin: &Point3<f64>) -> f64 {
        let [u, v, h] = self.frame.local(origin);
        let (lo, hi) = self.extent();
        let du = (u - lo[0]).abs().max((u - hi[0]).abs());
        let dv = (v - lo[1]).abs().max((v - hi[1]).abs());
        let dh = if self.min_height.is_finite() {
            (h - self.min_height).abs()
        } else {
            0.0
        };
        du.hypot(dv) + dh + self.cell_m
    }

    /// Highest surface height observed in the cell of ground point `(u, v)`.
    pub fn height(&self, u: f64, v: f64) -> Option<f64> {
        self.index(u, v)
            .map(|i| self.height[i])
            .filter(|h| *h > UNKNOWN)
    }

    /// Training cameras that saw the cell of ground point `(u, v)` (0 outside the grid).
    pub fn views(&self, u: f64, v: f64) -> u32 {
        self.index(u, v).map_or(0, |i| self.views[i])
    }

    /// Highest observed surface height over the cells that a disc of `radius` metres around
    /// `(u, v)` touches (`None` when none of them was observed).
    pub fn max_height_within(&self, u: f64, v: f64, radius: f64) -> Option<f64> {
        let r = radius.max(0.0);
        let steps = (r / self.cell_m).ceil() as i64;
        let mut best: Option<f64> = None;
        for dy in -steps..=steps {
            for dx in -steps..=steps {
                let (cu, cv) = (u + dx as f64 * self.cell_m, v + dy as f64 * self.cell_m);
                // Cells whose nearest point to (u, v) is within the radius.
                let gap = |d: i64| ((d.abs() - 1).max(0) as f64) * self.cell_m;
                if gap(dx).hypot(gap(dy)) > r {
                    continue;
                }
                if let Some(h) = self.height(cu, cv) {
                    best = Some(best.map_or(h, |b: f64| b.max(h)));
                }
            }
        }
        best
    }

    /// First surface point along the ray from `origin` in direction `dir` (unit), within
    /// `max_t` metres: the first sample, every half cell, at or below its cell's observed
    /// height. Unobserved cells let the ray through. `None` when the ray hits nothing.
    pub fn cast(
        &self,
        origin: &Point3<f64>,
        dir: &Vector3<f64>,
        max_t: f64,
    ) -> Option<Point3<f64>> {
        let o = self.frame.local(origin);
        let d = [
            dir.dot(&self.frame.e1),
            dir.dot(&self.frame.e2),
            dir.dot(&self.frame.up),
        ];
        let step = 0.5 * self.cell_m;
        let mut t = 0.0;
        while t <= max_t {
            let (u, v, h) = (o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]);
            if let Some(g) = self.height(u, v)
                && h <= g
            {
                return Some(self.frame.world(u, v, h));
            }
            // Below every observed surface and going down or level: nothing left to hit.
            if h < self.min_height && d[2] <= 0.0 {
                return None;
            }
            t += step;
        }
        None
    }
}
