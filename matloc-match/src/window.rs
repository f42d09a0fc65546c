//! Nearest-neighbour tables restricted to an image-space window (beyond the paper).
//!
//! The map is rendered at the coarse pose, so a rendered cell and its true query cell are close
//! in the image: a 3 m / 5° start moves a point by ~12 px at f = 139 px and 35 m. Restricting
//! each query cell's candidates to the rendered cells within `radius_px` (and symmetrically each
//! rendered cell's candidates) removes most distractors when the query features are weak (an
//! encoder rather than the oracle), at a cost of `n · (window cells) · D` instead of
//! `n · m · D` (each pair computed once for both directions).
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
    /// Prepared row → cell index, increasing (ties keep the lowest index in either order);
    /// `None` for the identity.
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

/// The run of columns of map grid row `row` whose cell centres lie within `radius_px` of `p`
/// (a disc meets a row of cells in one run), by the same f64 test as the all-pairs definition.
///
/// `state` carries the run's ends between calls: for centres `p` of one pixel row visited in
/// increasing `x`, both ends only move right, so each call costs a few tests instead of a
/// search. Reset it to `(0, 0)` when `p`'s row changes.
fn row_run(
    b: &Side<'_>,
    p: [f64; 2],
    radius_px: f64,
    row: usize,
    state: &mut (usize, usize),
) -> Option<(usize, usize)> {
    let r2 = radius_px * radius_px;
    let inside = |col: usize| {
        let q = b.grid.cell_centre(col, row);
        (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) <= r2
    };
    let last = b.cols.checked_sub(1)?;
    let (lo, hi) = state;
    // Cells left of `p` and outside the disc stay outside for every later `p`.
    while *lo <= last && !inside(*lo) && b.grid.cell_centre(*lo, row)[0] < p[0] {
        *lo += 1;
    }
    if *lo > last || !inside(*lo) {
        return None;
    }
    // The previous right end lies between the new ends, so it is inside again and the run
    // only grows from there.
    *hi = (*hi).max(*lo);
    while *hi < last && inside(*hi + 1) {
        *hi += 1;
    }
    Some((*lo, *hi))
}

/// Candidates scored together: eight consecutive map cells of one grid row, one AVX register.
const LANES: usize = 8;

/// Query cells scored together against the same map values.
const QB: usize = 4;

/// Similarities of the `QB` query rows `a` with `G · LANES` consecutive map cells from
/// `cell0` (dim-major map `mt`, `stride` values per dim): each is the sequential multiply-add
/// chain over the dims of [`crate::kernel`]; the `QB · G` chains are independent, which hides
/// the FMA latency, and each map value loaded feeds `QB` of them.
#[inline(always)]
fn score<const G: usize>(
    a: &[&[f32]; QB],
    mt: &[f32],
    stride: usize,
    cell0: usize,
) -> [[[f32; LANES]; 2]; QB] {
    let d = a[0].len();
    let a: [&[f32]; QB] = std::array::from_fn(|q| &a[q][..d]);
    let mut s = [[[0f32; LANES]; G]; QB];
    for k in 0..d {
        let o = k * stride + cell0;
        let col = &mt[o..o + G * LANES];
        for q in 0..QB {
            let x = a[q][k];
            for g in 0..G {
                for l in 0..LANES {
                    s[q][g][l] = x.mul_add(col[g * LANES + l], s[q][g][l]);
                }
            }
        }
    }
    let mut out = [[[0f32; LANES]; 2]; QB];
    for q in 0..QB {
        out[q][..G].copy_from_slice(&s[q]);
    }
    out
}

/// Folds one lane group (masked lanes hold `-∞`) into a query's row entry, lanes in
/// increasing cell order, skipped when no lane can change it. Cells arrive in increasing order,
/// so a tie never replaces the entry's argmax ([`NnTable::push`]'s lowest-index rule) and a
/// `-∞` lane changes nothing (similarities of finite features are finite).
#[inline(always)]
fn fold_row(v: &[f32; LANES], cell0: usize, best: &mut f32, second: &mut f32, arg: &mut u32) {
    let top = v
        .iter()
        .fold(f32::NEG_INFINITY, |a, &x| if x > a { x } else { a });
    if top <= *second {
        return;
    }
    for (l, &x) in v.iter().enumerate() {
        if x > *best {
            *second = *best;
            *best = x;
            *arg = (cell0 + l) as u32;
        } else if x > *second {
            *second = x;
        }
    }
}

/// Folds query `i`'s similarities with eight consecutive cells (masked lanes `-∞`) into their
/// column entries, branch-free. Queries arrive in increasing order within a chunk, so, as in
/// [`fold_row`], only a strictly larger value takes the argmax.
#[inline(always)]
fn fold_cols(v: &[f32; LANES], cell0: usize, i: u32, cols: &mut NnTable) {
    let best: &mut [f32; LANES] = (&mut cols.best[cell0..cell0 + LANES])
        .try_into()
        .expect("LANES values");
    let second: &mut [f32; LANES] = (&mut cols.second[cell0..cell0 + LANES])
        .try_into()
        .expect("LANES values");
    let arg: &mut [u32; LANES] = (&mut cols.arg[cell0..cell0 + LANES])
        .try_into()
        .expect("LANES values");
    for l in 0..LANES {
        let (x, b, s) = (v[l], best[l], second[l]);
        let wins = x > b;
        second[l] = if wins {
            b
        } else if x > s {
            x
        } else {
            s
        };
        best[l] = if wins { x } else { b };
        arg[l] = if wins { i } else { arg[l] };
    }
}

/// Windowed nearest-neighbour tables: rows over the query side, columns over the map side.
///
/// A pair is a candidate when the two cell centres are within `radius_px`, a symmetric
/// relation, so each similarity is computed once and folded into both tables. The map side is
/// transposed to dim-major over its whole grid (holes included, masked), so eight consecutive
/// cells of a window row are scored with one vector multiply-add per dim; each similarity is
/// still the same sequential chain of fused multiply-adds over the dims as [`crate::kernel`]'s,
/// so the tables equal the all-pairs ones bit for bit. Four neighbouring query cells are scored
/// against the same map values (their windows nearly coincide). Query rows are split into
/// chunks, each with its own partial column table, merged at the end.
///
/// At 80 × 60 against 80 × 60 cells and 47 dims (this VM, 2026-12-02): radius 64 px
/// 15–19 ms against 31–38 ms for the previous per-pair kernel (gathered rows, one chain per
/// pair), 32 px 7–8 against 8–10 ms; at 16 px the transposition makes it slower (3.4 against
/// 2.7 ms).
pub(crate) fn nn_tables_windowed(
    query: &Side<'_>,
    map: &Side<'_>,
    d: usize,
    radius_px: f64,
) -> NnTables {
    let (n, m) = (query.n(), map.n());
    let cells = map.cols * map.rows;
    // Dim-major map over grid cells, padded so a lane group may run past a row's end.
    let stride = cells + 4 * LANES;
    let mut mt = vec![0f32; d * stride];
    let mut valid = vec![false; stride];
    for (cell, ok) in valid.iter_mut().enumerate().take(cells) {
        if let Some(j) = map.row(cell) {
            *ok = true;
            for k in 0..d {
                mt[k * stride + cell] = map.data[j * d + k];
            }
        }
    }
    const CHUNK: usize = 256;
    let parts: Vec<(NnTable, NnTable)> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let (i0, i1) = (c * CHUNK, ((c + 1) * CHUNK).min(n));
            let mut rows = NnTable::empty(i1 - i0);
            // Column table over grid cells (padded like the map).
            let mut cols = NnTable::empty(stride);
            // Run ends per map row for the current pixel row of queries (see `row_run`).
            let mut run_state = vec![(0usize, 0usize); map.rows];
            let mut state_y = f64::NAN;
            let mut i = i0;
            while i < i1 {
                // A block of up to QB neighbouring query cells on one pixel row: their windows
                // cover the same map rows and nearly the same runs, so each map value loaded
                // feeds QB multiply-adds.
                let y = query.centre(i)[1];
                if y != state_y {
                    run_state.fill((0, 0));
                    state_y = y;
                }
                let mut nq = 1;
                while nq < QB && i + nq < i1 && query.centre(i + nq)[1] == y {
                    nq += 1;
                }
                let ps: [[f64; 2]; QB] = std::array::from_fn(|q| query.centre(i + q.min(nq - 1)));
                let a: [&[f32]; QB] = std::array::from_fn(|q| {
                    let iq = i + q.min(nq - 1);
                    &query.data[iq * d..(iq + 1) * d]
                });
                let mut best = [f32::NEG_INFINITY; QB];
                let mut second = [f32::NEG_INFINITY; QB];
                let mut arg = [NO_INDEX; QB];
                let r0 = ((y - radius_px - map.grid.offset[1]) / map.grid.stride - 0.5)
                    .ceil()
                    .max(0.0);
                let r1 = ((y + radius_px - map.grid.offset[1]) / map.grid.stride - 0.5)
                    .floor()
                    .min(map.rows as f64 - 1.0);
                // One grid row outside the guess on each side, in case rounding moved it.
                let (ra, rb) = if r1 < r0 {
                    (0, 0)
                } else {
                    (
                        (r0 as usize).saturating_sub(1),
                        (r1 as usize + 2).min(map.rows),
                    )
                };
                for r in ra..rb {
                    let mut runs = [None; QB];
                    for (q, run) in runs.iter_mut().enumerate().take(nq) {
                        *run = row_run(map, ps[q], radius_px, r, &mut run_state[r]);
                    }
                    let Some(lo) = runs.iter().flatten().map(|x| x.0).min() else {
                        continue;
                    };
                    let hi = runs.iter().flatten().map(|x| x.1).max().unwrap_or(lo);
                    let base = r * map.cols;
                    let mut c0 = lo;
                    while c0 <= hi {
                        let rem = hi + 1 - c0;
                        let groups = if rem > LANES { 2 } else { 1 };
                        let cell0 = base + c0;
                        let acc = if groups == 2 {
                            score::<2>(&a, &mt, stride, cell0)
                        } else {
                            score::<1>(&a, &mt, stride, cell0)
                        };
                        for (q, run) in runs.iter().enumerate() {
                            let Some((qlo, qhi)) = *run else {
                                continue;
                            };
                            for (g, v) in acc[q].iter().enumerate().take(groups) {
                                let cg = cell0 + g * LANES;
                                let cc = c0 + g * LANES;
                                let v: [f32; LANES] = std::array::from_fn(|l| {
                                    if (qlo..=qhi).contains(&(cc + l)) && valid[cg + l] {
                                        v[l]
                                    } else {
                                        f32::NEG_INFINITY
                                    }
                                });
                                fold_row(&v, cg, &mut best[q], &mut second[q], &mut arg[q]);
                                fold_cols(&v, cg, (i + q) as u32, &mut cols);
                            }
                        }
                        c0 += groups * LANES;
                    }
                }
                for q in 0..nq {
                    let e = i + q - i0;
                    rows.best[e] = best[q];
                    rows.second[e] = second[q];
                    // Cells → prepared map rows.
                    rows.arg[e] = if arg[q] == NO_INDEX {
                        NO_INDEX
                    } else {
                        map.row(arg[q] as usize).map_or(NO_INDEX, |j| j as u32)
                    };
                }
                i += nq;
            }
            (rows, cols)
        })
        .collect();
    // Chunks come back in order, so the row tables concatenate; the column tables merge over
    // grid cells, then move to prepared map rows once.
    let mut rows = NnTable::empty(0);
    let mut by_cell = NnTable::empty(stride);
    for (r, c) in parts {
        rows.best.extend(r.best);
        rows.second.extend(r.second);
        rows.arg.extend(r.arg);
        by_cell.merge(&c);
    }
    let mut cols = NnTable::empty(m);
    for j in 0..m {
        let cell = map.cell(j);
        cols.best[j] = by_cell.best[cell];
        cols.second[j] = by_cell.second[cell];
        cols.arg[j] = by_cell.arg[cell];
    }
    NnTables { rows, cols }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernel::dot_fma;
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
