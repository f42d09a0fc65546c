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

thread_local! {
    /// Tests set it to run the portable path on a machine with AVX2.
    static FORCE_PORTABLE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    //! The window's inner loop in AVX2 + FMA: the portable loop folds every similarity into
    //! the row and column maxima one lane at a time, which costs more than the similarity
    //! itself at small D (80 × 60 cells, 64 px, D = 5: 9.0 ms, of which ~1 ms multiply-adds).
    //! Here, as in the global kernel ([`crate::kernel`]), each query keeps per-lane maxima in
    //! registers across the whole window, and the column maxima of a lane group are reduced
    //! over the block's queries in registers before one merge into the table.

    use super::{LANES, NO_INDEX, NnTable, QB};
    use std::arch::x86_64::*;

    /// Per-lane running row maxima of the block's queries (index bits stored as floats).
    pub(super) struct Lanes {
        best: [__m256; QB],
        second: [__m256; QB],
        arg: [__m256; QB],
    }

    impl Lanes {
        pub(super) fn new() -> Self {
            // SAFETY: plain register constructors; the module is only used after AVX2
            // detection, and these are baseline AVX on x86-64-v3 builds anyway.
            unsafe {
                let ninf = _mm256_set1_ps(f32::NEG_INFINITY);
                let none = _mm256_castsi256_ps(_mm256_set1_epi32(NO_INDEX as i32));
                Lanes {
                    best: [ninf; QB],
                    second: [ninf; QB],
                    arg: [none; QB],
                }
            }
        }

        /// Top two of query `q`'s lanes (multiset order) and the best's cell, lowest among
        /// ties.
        pub(super) fn reduce(&self, q: usize) -> (f32, f32, u32) {
            let (mut b, mut s, mut a) = ([0f32; LANES], [0f32; LANES], [0u32; LANES]);
            // SAFETY: stores of 8 lanes into arrays of 8.
            unsafe {
                _mm256_storeu_ps(b.as_mut_ptr(), self.best[q]);
                _mm256_storeu_ps(s.as_mut_ptr(), self.second[q]);
                _mm256_storeu_ps(a.as_mut_ptr() as *mut f32, self.arg[q]);
            }
            let mut win = 0;
            for l in 1..LANES {
                if b[l] > b[win] || (b[l] == b[win] && a[l] < a[win]) {
                    win = l;
                }
            }
            let mut second = s[win];
            for l in 0..LANES {
                if l != win {
                    second = second.max(b[l]);
                }
            }
            (b[win], second, a[win])
        }
    }

    /// One map row's candidates of a query block.
    pub(super) struct Span<'a> {
        /// Query rows (`QB`, the last repeated past `nq`).
        pub a: &'a [&'a [f32]; QB],
        pub nq: usize,
        pub first_query: u32,
        /// Per query, the run of map columns within the window.
        pub runs: &'a [Option<(usize, usize)>; QB],
        /// Union of the runs.
        pub lo: usize,
        pub hi: usize,
        /// Cell index of column 0 of this map row.
        pub base: usize,
        /// Dim-major map, `stride` values per dim, padded.
        pub mt: &'a [f32],
        pub stride: usize,
        /// 0 / -inf per cell, padded like `mt`.
        pub hole: &'a [f32],
    }

    /// Folds the similarities of a span into the row lanes and the column table.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn span(sp: &Span<'_>, lanes: &mut Lanes, cols: &mut NnTable) {
        let d = sp.a[0].len();
        // SAFETY: `lo..=hi` are columns of one map row, so every 8-lane load from
        // `base + c0` stays inside `mt`, `hole` and `cols`, which are padded by four lane
        // groups past the last cell; query rows hold `d` values.
        unsafe {
            let ninf = _mm256_set1_ps(f32::NEG_INFINITY);
            let lane_ids = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
            let qidx: [__m256; QB] = std::array::from_fn(|q| {
                _mm256_castsi256_ps(_mm256_set1_epi32((sp.first_query + q as u32) as i32))
            });
            // Run bounds as i32 lanes (`qlo - 1`, `qhi + 1`); an absent run admits nothing.
            let bounds: [(__m256i, __m256i); QB] = std::array::from_fn(|q| match sp.runs[q] {
                Some((l, h)) if q < sp.nq => (
                    _mm256_set1_epi32(l as i32 - 1),
                    _mm256_set1_epi32(h as i32 + 1),
                ),
                _ => (_mm256_set1_epi32(i32::MAX), _mm256_set1_epi32(i32::MIN)),
            });
            let mut c0 = sp.lo;
            while c0 <= sp.hi {
                let cell0 = sp.base + c0;
                let mp = sp.mt.as_ptr().add(cell0);
                // Two lane groups when the span has more than one left: eight independent
                // multiply-add chains hide the FMA latency (four do not, at large D).
                let groups = if sp.hi + 1 - c0 > LANES { 2 } else { 1 };
                let mut acc = [[_mm256_setzero_ps(); 2]; QB];
                if groups == 2 {
                    for k in 0..d {
                        let m0 = _mm256_loadu_ps(mp.add(k * sp.stride));
                        let m1 = _mm256_loadu_ps(mp.add(k * sp.stride + LANES));
                        for q in 0..QB {
                            let x = _mm256_set1_ps(*sp.a[q].get_unchecked(k));
                            acc[q][0] = _mm256_fmadd_ps(x, m0, acc[q][0]);
                            acc[q][1] = _mm256_fmadd_ps(x, m1, acc[q][1]);
                        }
                    }
                } else {
                    for k in 0..d {
                        let m0 = _mm256_loadu_ps(mp.add(k * sp.stride));
                        for q in 0..QB {
                            let x = _mm256_set1_ps(*sp.a[q].get_unchecked(k));
                            acc[q][0] = _mm256_fmadd_ps(x, m0, acc[q][0]);
                        }
                    }
                }
                for g in 0..groups {
                    let cg = cell0 + g * LANES;
                    let hole = _mm256_loadu_ps(sp.hole.as_ptr().add(cg));
                    let col =
                        _mm256_add_epi32(_mm256_set1_epi32((c0 + g * LANES) as i32), lane_ids);
                    let cell = _mm256_castsi256_ps(_mm256_add_epi32(
                        _mm256_set1_epi32(cg as i32),
                        lane_ids,
                    ));
                    let mut cb = ninf;
                    let mut cs = ninf;
                    let mut ca = _mm256_castsi256_ps(_mm256_set1_epi32(NO_INDEX as i32));
                    for q in 0..sp.nq {
                        let (lo, hi) = bounds[q];
                        let inside = _mm256_castsi256_ps(_mm256_and_si256(
                            _mm256_cmpgt_epi32(col, lo),
                            _mm256_cmpgt_epi32(hi, col),
                        ));
                        let v = _mm256_blendv_ps(ninf, _mm256_add_ps(acc[q][g], hole), inside);
                        // Rows: a lane sees cells in increasing order, so strict `>` keeps
                        // the lowest cell among ties.
                        let gt = _mm256_cmp_ps::<_CMP_GT_OQ>(v, lanes.best[q]);
                        lanes.second[q] =
                            _mm256_max_ps(lanes.second[q], _mm256_min_ps(v, lanes.best[q]));
                        lanes.best[q] = _mm256_max_ps(lanes.best[q], v);
                        lanes.arg[q] = _mm256_blendv_ps(lanes.arg[q], cell, gt);
                        // Columns: queries in increasing order, same rule.
                        let gt = _mm256_cmp_ps::<_CMP_GT_OQ>(v, cb);
                        cs = _mm256_max_ps(cs, _mm256_min_ps(v, cb));
                        cb = _mm256_max_ps(cb, v);
                        ca = _mm256_blendv_ps(ca, qidx[q], gt);
                    }
                    // Merge: the table holds only earlier queries, which win ties.
                    let pb = cols.best.as_mut_ptr().add(cg);
                    let ps = cols.second.as_mut_ptr().add(cg);
                    let pa = cols.arg.as_mut_ptr().add(cg) as *mut f32;
                    let b0 = _mm256_loadu_ps(pb);
                    let s0 = _mm256_loadu_ps(ps);
                    let a0 = _mm256_loadu_ps(pa);
                    let gt = _mm256_cmp_ps::<_CMP_GT_OQ>(cb, b0);
                    _mm256_storeu_ps(
                        ps,
                        _mm256_max_ps(_mm256_max_ps(s0, cs), _mm256_min_ps(b0, cb)),
                    );
                    _mm256_storeu_ps(pb, _mm256_max_ps(b0, cb));
                    _mm256_storeu_ps(pa, _mm256_blendv_ps(a0, ca, gt));
                }
                c0 += groups * LANES;
            }
        }
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
/// At 80 × 60 against 80 × 60 cells and 47 dims (2 cores, 2026-12-02): radius 64 px
/// 15–19 ms against 31–38 ms for the previous per-pair kernel (gathered rows, one chain per
/// pair), 32 px 7–8 against 8–10 ms; at 16 px the transposition makes it slower (3.4 against
/// 2.7 ms). With the AVX2 folds (the `avx2` module; portable loop and vector kernel
/// alternating, 64 px): 47 dims 18.1–18.7 → 10.9–12.4 ms, 5 dims 10.3–11.7 → 3.9–4.3 ms.
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
    // 0 on a rendered cell, -inf on a hole or the padding (the vector kernel adds it).
    let mut hole = vec![f32::NEG_INFINITY; stride];
    for (cell, h) in hole.iter_mut().enumerate().take(cells) {
        if let Some(j) = map.row(cell) {
            *h = 0.0;
            for k in 0..d {
                mt[k * stride + cell] = map.data[j * d + k];
            }
        }
    }
    #[cfg(target_arch = "x86_64")]
    let use_avx2 =
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma");
    #[cfg(not(target_arch = "x86_64"))]
    let use_avx2 = false;
    let use_avx2 = use_avx2 && !FORCE_PORTABLE.with(|f| f.get());
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
                #[cfg(target_arch = "x86_64")]
                let mut lanes = avx2::Lanes::new();
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
                    #[cfg(target_arch = "x86_64")]
                    if use_avx2 {
                        let span = avx2::Span {
                            a: &a,
                            nq,
                            first_query: i as u32,
                            runs: &runs,
                            lo,
                            hi,
                            base,
                            mt: &mt,
                            stride,
                            hole: &hole,
                        };
                        // SAFETY: AVX2 and FMA were detected at run time.
                        unsafe { avx2::span(&span, &mut lanes, &mut cols) };
                        continue;
                    }
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
                                    if (qlo..=qhi).contains(&(cc + l)) && hole[cg + l] == 0.0 {
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
                #[cfg(target_arch = "x86_64")]
                if use_avx2 {
                    for q in 0..nq {
                        (best[q], second[q], arg[q]) = lanes.reduce(q);
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
        /// The one-sweep kernel, vector and portable, equals the all-pairs definition bit for
        /// bit, with holes in the map grid, another stride and offset on the map side, and
        /// ties (values rounded to a coarse lattice).
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
            let expected = reference(&query, &map, d, radius);
            // The vector kernel (where the CPU has it) and the portable loop.
            prop_assert_eq!(&nn_tables_windowed(&query, &map, d, radius), &expected);
            FORCE_PORTABLE.with(|f| f.set(true));
            let portable = nn_tables_windowed(&query, &map, d, radius);
            FORCE_PORTABLE.with(|f| f.set(false));
            prop_assert_eq!(&portable, &expected);
        }
    }
}
