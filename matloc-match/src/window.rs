//! Nearest-neighbour tables restricted to an image-space window (beyond the paper).
//!
//! The map is rendered at the coarse pose, so a rendered cell and its true query cell are close
//! in the image: a 3 m / 5° start moves a point by ~12 px at f = 139 px and 35 m. Restricting
//! each query cell's candidates to the rendered cells within `radius_px` (and symmetrically each
//! rendered cell's candidates) removes most distractors when the query features are weak (an
//! encoder rather than the oracle), at a cost of `n · (window cells) · D` instead of `n · m · D`.
//! The tables have the same meaning as the full ones ([`crate::kernel`]): best, second best,
//! argmax (lowest index among ties), so [`crate::mutual_from_tables`] applies unchanged.

use crate::kernel::{NO_INDEX, NnTable, NnTables};
use crate::types::QueryGrid;
use rayon::prelude::*;

/// A grid of prepared rows laid out in image space.
pub(crate) struct Side<'a> {
    /// Prepared rows (`d` values each).
    pub data: &'a [f32],
    /// Grid columns and rows.
    pub cols: usize,
    pub rows: usize,
    /// Cell → pixel mapping.
    pub grid: QueryGrid,
    /// Cell index → prepared row (`u32::MAX`: none); `None` for the identity.
    pub row_of: Option<&'a [u32]>,
    /// Prepared row → cell index; `None` for the identity.
    pub cell_of: Option<&'a [usize]>,
}

impl Side<'_> {
    fn n(&self) -> usize {
        match self.cell_of {
            Some(c) => c.len(),
            None => self.cols * self.rows,
        }
    }

    fn cell(&self, row: usize) -> usize {
        self.cell_of.map_or(row, |c| c[row])
    }

    fn row(&self, cell: usize) -> Option<usize> {
        match self.row_of {
            None => Some(cell),
            Some(m) => match m[cell] {
                u32::MAX => None,
                r => Some(r as usize),
            },
        }
    }

    fn centre(&self, row: usize) -> [f64; 2] {
        let c = self.cell(row);
        self.grid.cell_centre(c % self.cols, c / self.cols)
    }
}

/// For every row of `a`, the best and second-best similarity among the rows of `b` whose cell
/// centre lies within `radius_px` of its own.
fn one_side(a: &Side<'_>, b: &Side<'_>, d: usize, radius_px: f64) -> NnTable {
    let n = a.n();
    let r2 = radius_px * radius_px;
    let per: Vec<(f32, f32, u32)> = (0..n)
        .into_par_iter()
        .map(|i| {
            let p = a.centre(i);
            let qa = &a.data[i * d..(i + 1) * d];
            // Cells of b whose centres can be within the radius.
            let lo = |x: f64, off: f64, s: f64| ((x - radius_px - off) / s - 0.5).ceil().max(0.0);
            let hi = |x: f64, off: f64, s: f64| ((x + radius_px - off) / s - 0.5).floor();
            let (c0, c1) = (
                lo(p[0], b.grid.offset[0], b.grid.stride) as usize,
                hi(p[0], b.grid.offset[0], b.grid.stride),
            );
            let (r0, r1) = (
                lo(p[1], b.grid.offset[1], b.grid.stride) as usize,
                hi(p[1], b.grid.offset[1], b.grid.stride),
            );
            let (mut best, mut second, mut arg) = (f32::NEG_INFINITY, f32::NEG_INFINITY, NO_INDEX);
            if c1 < 0.0 || r1 < 0.0 {
                return (best, second, arg);
            }
            let c1 = (c1 as usize).min(b.cols.saturating_sub(1));
            let r1 = (r1 as usize).min(b.rows.saturating_sub(1));
            for row in r0..=r1 {
                for col in c0..=c1 {
                    let cell = row * b.cols + col;
                    let Some(j) = b.row(cell) else { continue };
                    let q = b.grid.cell_centre(col, row);
                    if (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) > r2 {
                        continue;
                    }
                    let v: f32 = qa
                        .iter()
                        .zip(&b.data[j * d..(j + 1) * d])
                        .fold(0.0f32, |s, (x, y)| x.mul_add(*y, s));
                    let j = j as u32;
                    if v > best || (v == best && j < arg) {
                        second = best;
                        best = v;
                        arg = j;
                    } else if v > second {
                        second = v;
                    }
                }
            }
            (best, second, arg)
        })
        .collect();
    let mut t = NnTable {
        best: Vec::with_capacity(n),
        second: Vec::with_capacity(n),
        arg: Vec::with_capacity(n),
    };
    for (b, s, a) in per {
        t.best.push(b);
        t.second.push(s);
        t.arg.push(a);
    }
    t
}

/// Windowed nearest-neighbour tables: rows over the query side, columns over the map side.
pub(crate) fn nn_tables_windowed(
    query: &Side<'_>,
    map: &Side<'_>,
    d: usize,
    radius_px: f64,
) -> NnTables {
    NnTables {
        rows: one_side(query, map, d, radius_px),
        cols: one_side(map, query, d, radius_px),
    }
}
