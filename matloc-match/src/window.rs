//! Nearest-neighbour tables restricted to an image-space window (beyond the paper).
//!
//! The map is rendered at the coarse pose, so a rendered cell and its true query cell are close
//! in the image: a 3 m / 5° start moves a point by ~12 px at f = 139 px and 35 m. Restricting
//! each query cell's candidates to the rendered cells within `radius_px` (and symmetrically each
//! rendered cell's candidates) removes most distractors when the query features are weak (an
//! encoder rather than the oracle), at a cost of `n · (window cells) · D` instead of `n · m · D` (each pair computed once for
//! both directions).
//! The tables have the same meaning as the full ones ([`crate::kernel`]): best, second best,
//! argmax (lowest index among ties), so [`crate::mutual_from_tables`] applies unchanged.

use crate::kernel::{NnTable, NnTables, dot_fma};
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

/// Candidate rows of `b` whose cell centres lie within `radius_px` of `p`, in cell order.
fn candidates(b: &Side<'_>, p: [f64; 2], radius_px: f64, out: &mut Vec<u32>) {
    out.clear();
    let lo = |x: f64, off: f64, s: f64| ((x - radius_px - off) / s - 0.5).ceil().max(0.0);
    let hi = |x: f64, off: f64, s: f64| ((x + radius_px - off) / s - 0.5).floor();
    let c1 = hi(p[0], b.grid.offset[0], b.grid.stride);
    let r1 = hi(p[1], b.grid.offset[1], b.grid.stride);
    if c1 < 0.0 || r1 < 0.0 || b.cols == 0 || b.rows == 0 {
        return;
    }
    let c0 = lo(p[0], b.grid.offset[0], b.grid.stride) as usize;
    let r0 = lo(p[1], b.grid.offset[1], b.grid.stride) as usize;
    let c1 = (c1 as usize).min(b.cols - 1);
    let r1 = (r1 as usize).min(b.rows - 1);
    let r2 = radius_px * radius_px;
    for row in r0..=r1 {
        for col in c0..=c1 {
            let Some(j) = b.row(row * b.cols + col) else {
                continue;
            };
            let q = b.grid.cell_centre(col, row);
            if (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) <= r2 {
                out.push(j as u32);
            }
        }
    }
}

/// Similarities of `a` with `LANES` rows of `b` at once: each is the same sequential chain of
/// fused multiply-adds as [`crate::kernel`]'s (so results equal the full kernels' bit for
/// bit), but the chains are independent, so they overlap in the FMA pipeline instead of
/// waiting on one another's latency.
const LANES: usize = 8;

#[inline(always)]
fn dots(a: &[f32], b: &[f32], rows: &[u32; LANES], d: usize) -> [f32; LANES] {
    let mut acc = [0.0f32; LANES];
    let rows: [&[f32]; LANES] = std::array::from_fn(|l| {
        let j = rows[l] as usize;
        &b[j * d..(j + 1) * d]
    });
    for k in 0..d {
        let x = a[k];
        for l in 0..LANES {
            acc[l] = x.mul_add(rows[l][k], acc[l]);
        }
    }
    acc
}

/// Windowed nearest-neighbour tables: rows over the query side, columns over the map side.
///
/// A pair is a candidate when the two cell centres are within `radius_px`, a symmetric
/// relation, so each similarity is computed once and folded into both tables: query rows
/// are split into chunks, each with its own partial column table, merged at the end.
pub(crate) fn nn_tables_windowed(
    query: &Side<'_>,
    map: &Side<'_>,
    d: usize,
    radius_px: f64,
) -> NnTables {
    let (n, m) = (query.n(), map.n());
    const CHUNK: usize = 256;
    let parts: Vec<(NnTable, NnTable)> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let (i0, i1) = (c * CHUNK, ((c + 1) * CHUNK).min(n));
            let mut rows = NnTable::empty(i1 - i0);
            let mut cols = NnTable::empty(m);
            let mut cand = Vec::new();
            for i in i0..i1 {
                candidates(map, query.centre(i), radius_px, &mut cand);
                let a = &query.data[i * d..(i + 1) * d];
                let mut push = |j: u32, v: f32| {
                    rows.push(i - i0, v, j);
                    cols.push(j as usize, v, i as u32);
                };
                let mut groups = cand.chunks_exact(LANES);
                for g in &mut groups {
                    let g: &[u32; LANES] = g.try_into().expect("chunks_exact gives LANES");
                    let v = dots(a, map.data, g, d);
                    for l in 0..LANES {
                        push(g[l], v[l]);
                    }
                }
                for &j in groups.remainder() {
                    let b = &map.data[j as usize * d..(j as usize + 1) * d];
                    push(j, dot_fma(a, b));
                }
            }
            (rows, cols)
        })
        .collect();
    // Chunks come back in order, so the row tables concatenate.
    let mut rows = NnTable::empty(0);
    let mut cols = NnTable::empty(m);
    for (r, c) in parts {
        rows.best.extend(r.best);
        rows.second.extend(r.second);
        rows.arg.extend(r.arg);
        cols.merge(&c);
    }
    NnTables { rows, cols }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Every pair of rows, kept when the centres are within the radius.
    fn reference(query: &Side<'_>, map: &Side<'_>, d: usize, radius_px: f64) -> NnTables {
        let (n, m) = (query.n(), map.n());
        let mut rows = NnTable::empty(n);
        let mut cols = NnTable::empty(m);
        for i in 0..n {
            let p = query.centre(i);
            for j in 0..m {
                let q = map.centre(j);
                if (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) > radius_px * radius_px {
                    continue;
                }
                let v = dot_fma(
                    &query.data[i * d..(i + 1) * d],
                    &map.data[j * d..(j + 1) * d],
                );
                rows.push(i, v, j as u32);
                cols.push(j, v, i as u32);
            }
        }
        NnTables { rows, cols }
    }

    proptest! {
        /// The one-sweep kernel equals the all-pairs definition bit for bit, with holes in the
        /// map grid, another stride and offset on the map side, and ties (values rounded to
        /// a coarse lattice).
        #[test]
        fn windowed_tables_equal_all_pairs(
            qc in 1usize..40, qr in 1usize..12, d in 1usize..20,
            mstride in 2.0f64..8.0, ox in -6.0f64..6.0, oy in -6.0f64..6.0,
            radius in 0.5f64..40.0, seed in any::<u64>(),
        ) {
            let mut s = seed | 1;
            let mut next = || {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                ((s >> 40) % 9) as f32 * 0.25 - 1.0
            };
            let q: Vec<f32> = (0..qc * qr * d).map(|_| next()).collect();
            let (mc, mr) = (qc.div_ceil(2) + 1, qr.div_ceil(2) + 1);
            let cell_of: Vec<usize> = (0..mc * mr).filter(|c| c % 5 != 2).collect();
            let mut row_of = vec![u32::MAX; mc * mr];
            for (k, &c) in cell_of.iter().enumerate() {
                row_of[c] = k as u32;
            }
            let m: Vec<f32> = (0..cell_of.len() * d).map(|_| next()).collect();
            let query = Side {
                data: &q,
                cols: qc,
                rows: qr,
                grid: QueryGrid::with_stride(4.0),
                row_of: None,
                cell_of: None,
            };
            let map = Side {
                data: &m,
                cols: mc,
                rows: mr,
                grid: QueryGrid { stride: mstride, offset: [ox, oy] },
                row_of: Some(&row_of),
                cell_of: Some(&cell_of),
            };
            prop_assert_eq!(
                nn_tables_windowed(&query, &map, d, radius),
                reference(&query, &map, d, radius)
            );
        }
    }
}
