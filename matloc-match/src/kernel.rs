//! Nearest-neighbour tables of a dot-product similarity matrix `S = A·Bᵀ` (`A`: `n × d`,
//! `B`: `m × d`, both row-major `f32`), computed three ways:
//!
//! - [`nn_tables_tiled`]: the production kernel. It walks `S` in register-sized tiles and keeps
//!   running row and column maxima, so `S` is never written to memory: the cost is the
//!   `2·n·m·d` FLOP of the products plus a few compare/blend instructions per entry, instead of
//!   a store-bound pass over an `n·m` matrix followed by two more read passes.
//! - [`nn_tables_reference`]: the materialised matrix with plain loops and the same per-entry
//!   arithmetic (a fused multiply-add chain over `k = 0..d`), so its tables equal the tiled ones
//!   bit for bit. Tests use it as the oracle.
//! - `nn_tables_faer` (`faer` feature): faer's GEMM into a materialised matrix, then row and column scans: the
//!   straightforward baseline benchmarks compare against. Its summation order differs, so near
//!   ties may resolve differently from the other two.
//!
//! Tie-breaking everywhere: the lowest index wins among equal maxima. `second` is the second
//! largest value of the row/column as a multiset (equal to `best` when the maximum is tied) and
//! `f32::NEG_INFINITY` when the row/column has a single entry.

use rayon::prelude::*;

/// Sentinel index for "no neighbour" (only seen when the other side is empty).
pub const NO_INDEX: u32 = u32::MAX;

/// Best and second-best similarity per row (or column), with the argmax.
#[derive(Clone, Debug, PartialEq)]
pub struct NnTable {
    /// Largest similarity.
    pub best: Vec<f32>,
    /// Second largest similarity (multiset order), `-inf` if there is none.
    pub second: Vec<f32>,
    /// Index of the largest similarity on the other side (lowest index among ties).
    pub arg: Vec<u32>,
}

impl NnTable {
    pub(crate) fn empty(len: usize) -> Self {
        NnTable {
            best: vec![f32::NEG_INFINITY; len],
            second: vec![f32::NEG_INFINITY; len],
            arg: vec![NO_INDEX; len],
        }
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.best.len()
    }

    /// Whether the table has no entries.
    pub fn is_empty(&self) -> bool {
        self.best.is_empty()
    }

    /// Folds `(value, index)` into entry `e`, keeping the lowest index among ties.
    #[inline]
    pub(crate) fn push(&mut self, e: usize, value: f32, index: u32) {
        let best = self.best[e];
        if value > best || (value == best && index < self.arg[e]) {
            self.second[e] = best;
            self.best[e] = value;
            self.arg[e] = index;
        } else if value > self.second[e] {
            self.second[e] = value;
        }
    }

    /// Merges another partial table over disjoint index sets of the other side.
    pub(crate) fn merge(&mut self, other: &NnTable) {
        for e in 0..self.len() {
            let (b0, b1) = (self.best[e], other.best[e]);
            let second = self.second[e].max(other.second[e]).max(b0.min(b1));
            if b1 > b0 || (b1 == b0 && other.arg[e] < self.arg[e]) {
                self.best[e] = b1;
                self.arg[e] = other.arg[e];
            }
            self.second[e] = second;
        }
    }
}

/// Row tables (one entry per row of `A`) and column tables (one per row of `B`).
#[derive(Clone, Debug, PartialEq)]
pub struct NnTables {
    /// For each query row: its nearest map row.
    pub rows: NnTable,
    /// For each map row: its nearest query row.
    pub cols: NnTable,
}

/// Dot product with the exact operation order every kernel here uses.
#[inline(always)]
pub(crate) fn dot_fma(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = 0.0f32;
    for (x, y) in a.iter().zip(b) {
        acc = x.mul_add(*y, acc);
    }
    acc
}

fn check_shapes(a: &[f32], n: usize, b: &[f32], m: usize, d: usize) {
    // Internal invariant: callers in this crate validate shapes and return typed errors first.
    assert_eq!(a.len(), n * d, "A must be n x d");
    assert_eq!(b.len(), m * d, "B must be m x d");
}

/// Materialises `S` with plain loops and scans it. Bit-identical to [`nn_tables_tiled`].
pub fn nn_tables_reference(a: &[f32], n: usize, b: &[f32], m: usize, d: usize) -> NnTables {
    check_shapes(a, n, b, m, d);
    let mut s = vec![0.0f32; n * m];
    for i in 0..n {
        for j in 0..m {
            s[i * m + j] = dot_fma(&a[i * d..(i + 1) * d], &b[j * d..(j + 1) * d]);
        }
    }
    scan_matrix(&s, n, m)
}

/// faer GEMM into a materialised `n × m` matrix, then row and column scans (baseline).
#[cfg(feature = "faer")]
pub fn nn_tables_faer(a: &[f32], n: usize, b: &[f32], m: usize, d: usize) -> NnTables {
    check_shapes(a, n, b, m, d);
    if n == 0 || m == 0 || d == 0 {
        return nn_tables_reference(a, n, b, m, d);
    }
    let mut s = vec![0.0f32; n * m];
    let lhs = faer::MatRef::from_row_major_slice(a, n, d);
    // Bᵀ as a d × m view of the row-major m × d buffer.
    let rhs = faer::MatRef::from_column_major_slice(b, d, m);
    let dst = faer::MatMut::from_row_major_slice_mut(&mut s, n, m);
    faer::linalg::matmul::matmul(
        dst,
        faer::Accum::Replace,
        lhs,
        rhs,
        1.0f32,
        faer::Par::rayon(0),
    );
    scan_matrix(&s, n, m)
}

fn scan_matrix(s: &[f32], n: usize, m: usize) -> NnTables {
    let mut rows = NnTable::empty(n);
    let mut cols = NnTable::empty(m);
    rows.best
        .par_iter_mut()
        .zip(rows.second.par_iter_mut())
        .zip(rows.arg.par_iter_mut())
        .enumerate()
        .for_each(|(i, ((best, second), arg))| {
            for (j, &v) in s[i * m..(i + 1) * m].iter().enumerate() {
                if v > *best {
                    *second = *best;
                    *best = v;
                    *arg = j as u32;
                } else if v > *second {
                    *second = v;
                }
            }
        });
    // Row-order pass over the matrix so the column scan reads memory sequentially.
    for i in 0..n {
        for (j, &v) in s[i * m..(i + 1) * m].iter().enumerate() {
            cols.push(j, v, i as u32);
        }
    }
    NnTables { rows, cols }
}

/// Tiled nearest-neighbour tables; `S` is never materialised. Equal to
/// [`nn_tables_reference`] bit for bit (same FMA order, same tie-breaking). With
/// `track_second = false` the `second` tables are left at `-inf`, which saves work when no
/// ratio test is needed. Parallel over blocks of rows on the global rayon pool.
pub fn nn_tables_tiled(
    a: &[f32],
    n: usize,
    b: &[f32],
    m: usize,
    d: usize,
    track_second: bool,
) -> NnTables {
    check_shapes(a, n, b, m, d);
    if n == 0 || m == 0 {
        return NnTables {
            rows: NnTable::empty(n),
            cols: NnTable::empty(m),
        };
    }
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            return avx2::tables(a, n, b, m, d, track_second);
        }
    }
    portable_tables(a, n, b, m, d, track_second)
}

/// Row-at-a-time fallback for CPUs without AVX2/FMA; same results, no SIMD blocking.
fn portable_tables(
    a: &[f32],
    n: usize,
    b: &[f32],
    m: usize,
    d: usize,
    track_second: bool,
) -> NnTables {
    const CHUNK: usize = 64;
    let mut rows = NnTable::empty(n);
    let parts: Vec<(usize, NnTable, NnTable)> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let lo = c * CHUNK;
            let hi = (lo + CHUNK).min(n);
            let mut r = NnTable::empty(hi - lo);
            let mut col = NnTable::empty(m);
            for i in lo..hi {
                for j in 0..m {
                    let v = dot_fma(&a[i * d..(i + 1) * d], &b[j * d..(j + 1) * d]);
                    r.push(i - lo, v, j as u32);
                    col.push(j, v, i as u32);
                }
            }
            (lo, r, col)
        })
        .collect();
    let mut cols = NnTable::empty(m);
    for (lo, r, col) in parts {
        rows.best[lo..lo + r.len()].copy_from_slice(&r.best);
        rows.second[lo..lo + r.len()].copy_from_slice(&r.second);
        rows.arg[lo..lo + r.len()].copy_from_slice(&r.arg);
        cols.merge(&col);
    }
    if !track_second {
        rows.second.fill(f32::NEG_INFINITY);
        cols.second.fill(f32::NEG_INFINITY);
    }
    NnTables { rows, cols }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    //! AVX2 + FMA microkernel: 4 query rows × 16 map columns per tile (8 accumulators), the
    //! d-loop fully unrolled for d ≤ 16 through a const generic, row maxima kept per lane in
    //! registers across a column block, column maxima reduced over the 4 rows of a tile in
    //! registers and then merged into a per-thread column state.

    use super::{NO_INDEX, NnTable, NnTables};
    use rayon::prelude::*;
    use std::arch::x86_64::*;

    const R: usize = 4;
    const NC: usize = 16;
    const ROW_CHUNK: usize = 64;

    /// Per-thread column state, padded to whole panels.
    struct ColState {
        best: Vec<f32>,
        second: Vec<f32>,
        arg: Vec<u32>,
    }

    impl ColState {
        fn new(len: usize) -> Self {
            ColState {
                best: vec![f32::NEG_INFINITY; len],
                second: vec![f32::NEG_INFINITY; len],
                arg: vec![NO_INDEX; len],
            }
        }
    }

    struct Packed<'a> {
        /// Row tiles: `[tile][k][r]`.
        a: &'a [f32],
        /// Column panels: `[panel][k][lane]` with 16 lanes.
        b: &'a [f32],
        n: usize,
        m: usize,
        d: usize,
        panels: usize,
        panels_per_block: usize,
    }

    pub(super) fn tables(
        a: &[f32],
        n: usize,
        b: &[f32],
        m: usize,
        d: usize,
        second: bool,
    ) -> NnTables {
        let tiles = n.div_ceil(R);
        let panels = m.div_ceil(NC);
        let mut pa = vec![0.0f32; tiles * R * d];
        for i in 0..n {
            let (t, r) = (i / R, i % R);
            for k in 0..d {
                pa[t * R * d + k * R + r] = a[i * d + k];
            }
        }
        let mut pb = vec![0.0f32; panels * NC * d];
        for j in 0..m {
            let (p, l) = (j / NC, j % NC);
            for k in 0..d {
                pb[p * NC * d + k * NC + l] = b[j * d + k];
            }
        }
        // Keep one column block of B (and its column state) inside L1/L2: ~32 KiB of B.
        let panels_per_block = (32 * 1024 / (NC * 4 * d.max(1))).clamp(1, panels);
        let packed = Packed {
            a: &pa,
            b: &pb,
            n,
            m,
            d,
            panels,
            panels_per_block,
        };
        macro_rules! dispatch {
            ($($k:literal)*) => {
                match (d, second) {
                    $(($k, true) => run::<$k, true>(&packed), ($k, false) => run::<$k, false>(&packed),)*
                    (_, true) => run::<0, true>(&packed),
                    (_, false) => run::<0, false>(&packed),
                }
            };
        }
        dispatch!(1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16)
    }

    fn run<const D: usize, const SECOND: bool>(p: &Packed) -> NnTables {
        let n = p.n;
        let mut rows = NnTable::empty(n);
        let chunks = n.div_ceil(ROW_CHUNK);
        let mut row_parts: Vec<NnTable> = (0..chunks)
            .map(|c| NnTable::empty(ROW_CHUNK.min(n - c * ROW_CHUNK)))
            .collect();
        let padded_m = p.panels * NC;
        let cols = row_parts
            .par_iter_mut()
            .enumerate()
            .fold(
                || ColState::new(padded_m),
                |mut st, (c, out)| {
                    // SAFETY: `tables` is only reached after runtime detection of AVX2 and FMA.
                    unsafe { chunk::<D, SECOND>(p, c, out, &mut st) };
                    st
                },
            )
            .map(|st| {
                let mut t = NnTable {
                    best: st.best,
                    second: st.second,
                    arg: st.arg,
                };
                t.best.truncate(p.m);
                t.second.truncate(p.m);
                t.arg.truncate(p.m);
                t
            })
            .reduce_with(|mut x, y| {
                x.merge(&y);
                x
            })
            .unwrap_or_else(|| NnTable::empty(p.m));
        for (c, part) in row_parts.iter().enumerate() {
            let lo = c * ROW_CHUNK;
            rows.best[lo..lo + part.len()].copy_from_slice(&part.best);
            rows.second[lo..lo + part.len()].copy_from_slice(&part.second);
            rows.arg[lo..lo + part.len()].copy_from_slice(&part.arg);
        }
        NnTables { rows, cols }
    }

    /// Processes rows `[c·64, c·64 + 64)` against all columns.
    #[target_feature(enable = "avx2,fma")]
    unsafe fn chunk<const D: usize, const SECOND: bool>(
        p: &Packed,
        c: usize,
        out: &mut NnTable,
        st: &mut ColState,
    ) {
        // SAFETY: the caller guarantees AVX2 + FMA; every pointer offset stays inside the packed
        // buffers (tiles and panels are padded to whole multiples of R and NC) and the column
        // state, which is padded to whole panels.
        unsafe {
            let d = if D == 0 { p.d } else { D };
            let row_lo = c * ROW_CHUNK;
            let row_hi = (row_lo + ROW_CHUNK).min(p.n);
            let tile_lo = row_lo / R;
            let tile_hi = row_hi.div_ceil(R);
            let ntiles = tile_hi - tile_lo;
            let neg_inf = _mm256_set1_ps(f32::NEG_INFINITY);
            // Per-lane running row state for every tile row of this chunk, kept across column blocks.
            let zero_idx = _mm256_castsi256_ps(_mm256_set1_epi32(NO_INDEX as i32));
            let mut rbest = vec![neg_inf; ntiles * R];
            let mut rsecond = vec![neg_inf; ntiles * R];
            let mut rarg = vec![zero_idx; ntiles * R];
            let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
            let eight = _mm256_set1_epi32(8);
            // Masks for padded columns of the last panel and padded rows of the last tile.
            let last_panel = p.panels - 1;
            let mut col_bias = [0.0f32; NC];
            for (l, v) in col_bias.iter_mut().enumerate() {
                if last_panel * NC + l >= p.m {
                    *v = f32::NEG_INFINITY;
                }
            }
            let col_bias = [
                _mm256_loadu_ps(col_bias.as_ptr()),
                _mm256_loadu_ps(col_bias.as_ptr().add(8)),
            ];

            let mut pb_lo = 0;
            while pb_lo < p.panels {
                let pb_hi = (pb_lo + p.panels_per_block).min(p.panels);
                for t in tile_lo..tile_hi {
                    let ts = (t - tile_lo) * R;
                    let a_tile = p.a.as_ptr().add(t * R * d);
                    let mut row_bias = [_mm256_setzero_ps(); R];
                    let partial_rows = (t + 1) * R > p.n;
                    if partial_rows {
                        for (r, bias) in row_bias.iter_mut().enumerate() {
                            if t * R + r >= p.n {
                                *bias = neg_inf;
                            }
                        }
                    }
                    let mut best = [neg_inf; R];
                    let mut second = [neg_inf; R];
                    let mut arg = [zero_idx; R];
                    best.copy_from_slice(&rbest[ts..ts + R]);
                    second.copy_from_slice(&rsecond[ts..ts + R]);
                    arg.copy_from_slice(&rarg[ts..ts + R]);
                    let row_idx = [
                        _mm256_castsi256_ps(_mm256_set1_epi32((t * R) as i32)),
                        _mm256_castsi256_ps(_mm256_set1_epi32((t * R + 1) as i32)),
                        _mm256_castsi256_ps(_mm256_set1_epi32((t * R + 2) as i32)),
                        _mm256_castsi256_ps(_mm256_set1_epi32((t * R + 3) as i32)),
                    ];
                    for pi in pb_lo..pb_hi {
                        let bp = p.b.as_ptr().add(pi * NC * d);
                        let mut acc = [[_mm256_setzero_ps(); 2]; R];
                        for k in 0..d {
                            let b0 = _mm256_loadu_ps(bp.add(k * NC));
                            let b1 = _mm256_loadu_ps(bp.add(k * NC + 8));
                            for r in 0..R {
                                let av = _mm256_broadcast_ss(&*a_tile.add(k * R + r));
                                acc[r][0] = _mm256_fmadd_ps(av, b0, acc[r][0]);
                                acc[r][1] = _mm256_fmadd_ps(av, b1, acc[r][1]);
                            }
                        }
                        if pi == last_panel {
                            for accr in acc.iter_mut() {
                                accr[0] = _mm256_add_ps(accr[0], col_bias[0]);
                                accr[1] = _mm256_add_ps(accr[1], col_bias[1]);
                            }
                        }
                        if partial_rows {
                            for r in 0..R {
                                acc[r][0] = _mm256_add_ps(acc[r][0], row_bias[r]);
                                acc[r][1] = _mm256_add_ps(acc[r][1], row_bias[r]);
                            }
                        }
                        // Row maxima: lane l sees columns in increasing order, so strict `>`
                        // keeps the lowest index among ties.
                        let j0 = _mm256_add_epi32(_mm256_set1_epi32((pi * NC) as i32), lanes);
                        let jv = [
                            _mm256_castsi256_ps(j0),
                            _mm256_castsi256_ps(_mm256_add_epi32(j0, eight)),
                        ];
                        for r in 0..R {
                            for h in 0..2 {
                                let s = acc[r][h];
                                let gt = _mm256_cmp_ps::<_CMP_GT_OQ>(s, best[r]);
                                if SECOND {
                                    second[r] = _mm256_max_ps(second[r], _mm256_min_ps(s, best[r]));
                                }
                                best[r] = _mm256_max_ps(best[r], s);
                                arg[r] = _mm256_blendv_ps(arg[r], jv[h], gt);
                            }
                        }
                        // Column maxima: reduce the 4 rows of the tile in registers, then merge
                        // into the thread's column state (which holds only lower row indices).
                        for h in 0..2 {
                            let mut cb = acc[0][h];
                            let mut cs = neg_inf;
                            let mut ca = row_idx[0];
                            for r in 1..R {
                                let s = acc[r][h];
                                let gt = _mm256_cmp_ps::<_CMP_GT_OQ>(s, cb);
                                if SECOND {
                                    cs = _mm256_max_ps(cs, _mm256_min_ps(s, cb));
                                }
                                cb = _mm256_max_ps(cb, s);
                                ca = _mm256_blendv_ps(ca, row_idx[r], gt);
                            }
                            let off = pi * NC + h * 8;
                            let pbest = st.best.as_mut_ptr().add(off);
                            let parg = st.arg.as_mut_ptr().add(off) as *mut f32;
                            let b0 = _mm256_loadu_ps(pbest);
                            let a0 = _mm256_loadu_ps(parg);
                            let gt = _mm256_cmp_ps::<_CMP_GT_OQ>(cb, b0);
                            if SECOND {
                                let psecond = st.second.as_mut_ptr().add(off);
                                let s0 = _mm256_loadu_ps(psecond);
                                let ns =
                                    _mm256_max_ps(_mm256_max_ps(s0, cs), _mm256_min_ps(b0, cb));
                                _mm256_storeu_ps(psecond, ns);
                            }
                            _mm256_storeu_ps(pbest, _mm256_max_ps(b0, cb));
                            _mm256_storeu_ps(parg, _mm256_blendv_ps(a0, ca, gt));
                        }
                    }
                    rbest[ts..ts + R].copy_from_slice(&best);
                    rsecond[ts..ts + R].copy_from_slice(&second);
                    rarg[ts..ts + R].copy_from_slice(&arg);
                }
                pb_lo = pb_hi;
            }

            // Horizontal reduction of the per-lane row state.
            for i in row_lo..row_hi {
                let ts = i - tile_lo * R;
                let mut bl = [0.0f32; 8];
                let mut sl = [0.0f32; 8];
                let mut al = [0u32; 8];
                _mm256_storeu_ps(bl.as_mut_ptr(), rbest[ts]);
                _mm256_storeu_ps(sl.as_mut_ptr(), rsecond[ts]);
                _mm256_storeu_ps(al.as_mut_ptr() as *mut f32, rarg[ts]);
                let mut win = 0;
                for l in 1..8 {
                    if bl[l] > bl[win] || (bl[l] == bl[win] && al[l] < al[win]) {
                        win = l;
                    }
                }
                let e = i - row_lo;
                out.best[e] = bl[win];
                out.arg[e] = al[win];
                if SECOND {
                    let mut s2 = sl[win];
                    for l in 0..8 {
                        if l != win {
                            s2 = s2.max(bl[l]);
                        }
                    }
                    out.second[e] = s2;
                }
            }
        }
    }
}
