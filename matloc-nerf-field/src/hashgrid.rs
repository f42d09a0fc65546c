use rand::Rng;
use rayon::prelude::*;

use crate::feature::F_POS_DIM;

/// Number of resolution levels.
pub const N_LEVELS: usize = 16;
/// Features stored per table entry.
pub const N_FEATURES_PER_LEVEL: usize = 2;

/// tiny-cuda-nn's spatial-hash primes (x, y, z).
const PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];

/// Points per work item of the level-major → point-major transpose.
const FWD_CHUNK: usize = 256;
/// Points per (level, block) work item of the forward sweep.
const LEVEL_BLOCK: usize = 16_384;
/// Points whose corner addresses are computed (and prefetched) before any is gathered.
const PREFETCH_BLOCK: usize = 32;

/// Hints the cache to fetch `base[offset]`; a pure performance hint with no effect on results.
#[inline(always)]
fn prefetch(base: *const f32, offset: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        // wrapping_add: the address is only a hint and is never dereferenced here.
        let p = base.wrapping_add(offset) as *const i8;
        // SAFETY: prefetch never faults, whatever the address.
        unsafe { std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(p) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (base, offset);
    }
}

/// Encodes `pts` at one level into `out[2p + f]`, in blocks: corner addresses first (with
/// prefetches), then the gathers, so many cache misses are in flight at once.
#[inline]
fn encode_level_block(lv: &LevelInfo, tab: &[f32], pts: &[[f32; 3]], out: &mut [f32]) {
    let mut idx = [[0u32; 8]; PREFETCH_BLOCK];
    let mut wts = [[0f32; 8]; PREFETCH_BLOCK];
    for (pb, ob) in pts
        .chunks(PREFETCH_BLOCK)
        .zip(out.chunks_mut(2 * PREFETCH_BLOCK))
    {
        for (i, p) in pb.iter().enumerate() {
            (idx[i], wts[i]) = HashGrid::corners(lv, *p);
            // Corners c and c^1 differ only in x and usually share a cache line.
            prefetch(tab.as_ptr(), idx[i][0] as usize * 2);
            prefetch(tab.as_ptr(), idx[i][2] as usize * 2);
            prefetch(tab.as_ptr(), idx[i][4] as usize * 2);
            prefetch(tab.as_ptr(), idx[i][6] as usize * 2);
        }
        for (i, o) in ob.chunks_exact_mut(2).enumerate() {
            let mut f0 = 0.0f32;
            let mut f1 = 0.0f32;
            for c in 0..8 {
                let e = idx[i][c] as usize * 2;
                f0 = wts[i][c].mul_add(tab[e], f0);
                f1 = wts[i][c].mul_add(tab[e + 1], f1);
            }
            o[0] = f0;
            o[1] = f1;
        }
    }
}

/// Geometry of one grid level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LevelInfo {
    /// Cells per axis N_l; the level has N_l + 1 vertices per axis.
    pub resolution: u32,
    /// First table entry of this level.
    pub offset: usize,
    /// Entries owned by this level: (N_l+1)³ if dense, else T.
    pub size: usize,
    /// Whether vertices are indexed densely (no hash collisions).
    pub dense: bool,
}

/// The tiny-cuda-nn spatial hash of integer vertex coordinates, before the modulo.
#[inline]
pub fn hash_coords(c: [u32; 3]) -> u32 {
    c[0].wrapping_mul(PRIMES[0]) ^ c[1].wrapping_mul(PRIMES[1]) ^ c[2].wrapping_mul(PRIMES[2])
}

/// Multi-resolution hash encoding: 16 levels × 2 features, trilinear interpolation.
///
/// Table entries are stored feature-interleaved (`table[2e + f]`) so one vertex is one 8-byte
/// load; levels are contiguous so a level's gradient slice can be owned by one thread.
#[derive(Clone, Debug)]
pub struct HashGrid {
    levels: Vec<LevelInfo>,
    /// Parameters, `2 × total entries`.
    pub table: Vec<f32>,
}

impl HashGrid {
    /// Level layout for table size `2^log2_t` and resolutions N_min..N_max
    /// (N_l = floor(N_min · b^l), b = exp((ln N_max − ln N_min)/(L−1))).
    pub fn layout(log2_t: u32, n_min: u32, n_max: u32) -> Vec<LevelInfo> {
        let t = 1usize << log2_t;
        let b = ((n_max as f64).ln() - (n_min as f64).ln()) / (N_LEVELS as f64 - 1.0);
        let b = b.exp();
        let mut offset = 0;
        (0..N_LEVELS)
            .map(|l| {
                // The small epsilon keeps exact powers (e.g. N_max itself) from flooring down.
                let res = ((n_min as f64) * b.powi(l as i32) + 1e-9).floor().max(1.0) as u32;
                let verts = (res as usize + 1).pow(3);
                let dense = verts <= t;
                let size = if dense { verts } else { t };
                let info = LevelInfo {
                    resolution: res,
                    offset,
                    size,
                    dense,
                };
                offset += size;
                info
            })
            .collect()
    }

    /// A grid with entries uniform in ±1e-4 (instant-ngp's initialisation).
    pub fn new<R: Rng>(log2_t: u32, n_min: u32, n_max: u32, rng: &mut R) -> Self {
        let levels = Self::layout(log2_t, n_min, n_max);
        let n = Self::entries_of(&levels) * N_FEATURES_PER_LEVEL;
        let table = (0..n).map(|_| rng.random_range(-1e-4f32..1e-4)).collect();
        Self { levels, table }
    }

    /// A grid with the given layout and parameters (used when loading).
    pub(crate) fn from_parts(levels: Vec<LevelInfo>, table: Vec<f32>) -> Self {
        Self { levels, table }
    }

    fn entries_of(levels: &[LevelInfo]) -> usize {
        levels.last().map_or(0, |l| l.offset + l.size)
    }

    /// Total number of table entries (each holds 2 features).
    pub fn num_entries(&self) -> usize {
        Self::entries_of(&self.levels)
    }

    /// Level layout.
    pub fn levels(&self) -> &[LevelInfo] {
        &self.levels
    }

    /// Entry indices (relative to the level) and trilinear weights of the 8 vertices around
    /// `p ∈ [0,1]³`. Corner c uses +1 on axis a iff bit a of c is set.
    #[inline(always)]
    pub fn corners(level: &LevelInfo, p: [f32; 3]) -> ([u32; 8], [f32; 8]) {
        let (i0, fr) = Self::cell(level, p);
        Self::corners_of_cell(level, i0, fr)
    }

    #[inline(always)]
    fn cell(level: &LevelInfo, p: [f32; 3]) -> ([u32; 3], [f32; 3]) {
        let res = level.resolution;
        let s = res as f32;
        let mut i0 = [0u32; 3];
        let mut fr = [0f32; 3];
        for a in 0..3 {
            // NaN fails the comparison and maps to 0 instead of propagating into indices.
            let x = if p[a] >= 0.0 { p[a].min(1.0) } else { 0.0 } * s;
            let fl = x.floor().min(s - 1.0).max(0.0);
            i0[a] = fl as u32;
            fr[a] = x - fl;
        }
        (i0, fr)
    }

    #[inline(always)]
    fn corners_of_cell(level: &LevelInfo, i0: [u32; 3], fr: [f32; 3]) -> ([u32; 8], [f32; 8]) {
        let mut idx = [0u32; 8];
        let mut w = [0f32; 8];
        let r = level.resolution + 1;
        let mask = (level.size as u32).wrapping_sub(1);
        for c in 0..8 {
            let bx = (c & 1) as u32;
            let by = ((c >> 1) & 1) as u32;
            let bz = ((c >> 2) & 1) as u32;
            let v = [i0[0] + bx, i0[1] + by, i0[2] + bz];
            idx[c] = if level.dense {
                v[0] + r * (v[1] + r * v[2])
            } else {
                hash_coords(v) & mask
            };
            let wx = if bx == 1 { fr[0] } else { 1.0 - fr[0] };
            let wy = if by == 1 { fr[1] } else { 1.0 - fr[1] };
            let wz = if bz == 1 { fr[2] } else { 1.0 - fr[2] };
            w[c] = wx * wy * wz;
        }
        (idx, w)
    }

    /// Encodes points in `[0,1]³` into `out` (`points.len() × 32`, point-major).
    ///
    /// Each level is swept over *all* points before the next (levels in parallel): a level's
    /// table (≤ 4 MB at T = 2^19) then stays in L3 during its sweep, whereas visiting all 16
    /// levels per small chunk of points cycles 64 MB through the cache and misses to DRAM.
    pub fn encode(&self, points: &[[f32; 3]], out: &mut [f32]) {
        self.encode_with_scratch(points, out, &mut Vec::new());
    }

    /// [`Self::encode`] with the level-major intermediate kept in `scratch` (resized as
    /// needed), so repeated calls do not allocate and page-fault fresh memory.
    pub fn encode_with_scratch(
        &self,
        points: &[[f32; 3]],
        out: &mut [f32],
        scratch: &mut Vec<f32>,
    ) {
        debug_assert_eq!(out.len(), points.len() * F_POS_DIM);
        let n = points.len();
        // Every element is overwritten below, so stale contents need no clearing.
        scratch.resize(n * F_POS_DIM, 0.0);
        self.encode_level_major(points, &mut scratch[..]);
        let lvl = &scratch[..];
        out.par_chunks_mut(FWD_CHUNK * F_POS_DIM)
            .enumerate()
            .for_each(|(ci, o)| {
                let p0 = ci * FWD_CHUNK;
                for (i, row) in o.chunks_exact_mut(F_POS_DIM).enumerate() {
                    let p = p0 + i;
                    for l in 0..N_LEVELS {
                        row[2 * l] = lvl[l * 2 * n + 2 * p];
                        row[2 * l + 1] = lvl[l * 2 * n + 2 * p + 1];
                    }
                }
            });
    }

    /// Level-major encoding: `out[l * 2n + 2p + f]`.
    pub fn encode_level_major(&self, points: &[[f32; 3]], out: &mut [f32]) {
        let n = points.len();
        debug_assert_eq!(out.len(), n * F_POS_DIM);
        if n == 0 {
            return;
        }
        // Work items are (level, point block) with levels outermost, so the two threads sweep
        // neighbouring levels at the same time.
        let block = LEVEL_BLOCK.min(n).max(1);
        let blocks_per_level = n.div_ceil(block);
        let mut items: Vec<(usize, usize, &mut [f32])> =
            Vec::with_capacity(N_LEVELS * blocks_per_level);
        for (l, lo) in out.chunks_mut(2 * n).enumerate() {
            for (b, o) in lo.chunks_mut(2 * block).enumerate() {
                items.push((l, b * block, o));
            }
        }
        items.into_par_iter().for_each(|(l, p0, o)| {
            let lv = &self.levels[l];
            let tab = &self.table[lv.offset * 2..(lv.offset + lv.size) * 2];
            let pts = &points[p0..p0 + o.len() / 2];
            encode_level_block(lv, tab, pts, o);
        });
    }

    /// Accumulates `∂L/∂table` into `grad` (same layout as `table`) given `∂L/∂out`
    /// (`points.len() × 32`). Parallel over levels: each level's gradient slice belongs to one
    /// task, so there are no atomics and no per-thread copies of the table.
    pub fn backward(&self, points: &[[f32; 3]], d_out: &[f32], grad: &mut [f32]) {
        self.backward_with_scratch(points, d_out, grad, &mut Vec::new());
    }

    /// [`Self::backward`] with its level-major copy of `d_out` kept in `scratch`.
    pub fn backward_with_scratch(
        &self,
        points: &[[f32; 3]],
        d_out: &[f32],
        grad: &mut [f32],
        scratch: &mut Vec<f32>,
    ) {
        debug_assert_eq!(d_out.len(), points.len() * F_POS_DIM);
        debug_assert_eq!(grad.len(), self.table.len());
        let n = points.len();
        // Level-major copy of the incoming gradient: each level task then streams 8 bytes
        // per point instead of touching a 128-byte row. Fully overwritten, so not cleared.
        scratch.resize(n * F_POS_DIM, 0.0);
        let d_lvl = &mut scratch[..];
        // Transposed by point chunks: each row of `d_out` is read once (a per-level pass read
        // all of `d_out` 16 times, using 8 bytes of every 64-byte line).
        let mut per_chunk: Vec<Vec<&mut [f32]>> = (0..n.div_ceil(FWD_CHUNK))
            .map(|_| Vec::with_capacity(N_LEVELS))
            .collect();
        for lvl in d_lvl.chunks_mut(2 * n.max(1)) {
            for (c, piece) in lvl.chunks_mut(2 * FWD_CHUNK).enumerate() {
                per_chunk[c].push(piece);
            }
        }
        per_chunk
            .into_par_iter()
            .enumerate()
            .for_each(|(c, mut outs)| {
                let rows = &d_out[c * FWD_CHUNK * F_POS_DIM..];
                let m = outs.first().map_or(0, |o| o.len() / 2);
                for (i, row) in rows.chunks_exact(F_POS_DIM).take(m).enumerate() {
                    for (l, o) in outs.iter_mut().enumerate() {
                        o[2 * i] = row[2 * l];
                        o[2 * i + 1] = row[2 * l + 1];
                    }
                }
            });
        let d_lvl = &scratch[..];
        let mut slices: Vec<(&LevelInfo, &mut [f32], &[f32])> = Vec::with_capacity(N_LEVELS);
        let mut rest = grad;
        for (l, lv) in self.levels.iter().enumerate() {
            let (head, tail) = rest.split_at_mut(lv.size * 2);
            slices.push((lv, head, &d_lvl[l * 2 * n..(l + 1) * 2 * n]));
            rest = tail;
        }
        // Fine levels miss the cache most; schedule them first for better balance.
        slices.reverse();
        slices.into_par_iter().for_each(|(lv, g, d)| {
            let mut idx = [[0u32; 8]; PREFETCH_BLOCK];
            let mut wts = [[0f32; 8]; PREFETCH_BLOCK];
            for (pb, db) in points
                .chunks(PREFETCH_BLOCK)
                .zip(d.chunks(2 * PREFETCH_BLOCK))
            {
                // Phase 1: all corner addresses of the block, prefetched, so the scattered
                // read-modify-writes of phase 2 overlap their cache misses.
                for (i, p) in pb.iter().enumerate() {
                    (idx[i], wts[i]) = Self::corners(lv, *p);
                    prefetch(g.as_ptr(), idx[i][0] as usize * 2);
                    prefetch(g.as_ptr(), idx[i][2] as usize * 2);
                    prefetch(g.as_ptr(), idx[i][4] as usize * 2);
                    prefetch(g.as_ptr(), idx[i][6] as usize * 2);
                }
                for (i, dp) in db.chunks_exact(2).enumerate() {
                    if dp[0] == 0.0 && dp[1] == 0.0 {
                        continue;
                    }
                    for c in 0..8 {
                        let e = idx[i][c] as usize * 2;
                        g[e] = wts[i][c].mul_add(dp[0], g[e]);
                        g[e + 1] = wts[i][c].mul_add(dp[1], g[e + 1]);
                    }
                }
            }
        });
    }

    /// `∂out/∂p` contracted with `∂L/∂out`: returns `∂L/∂p` for each point (`p ∈ [0,1]³`).
    ///
    /// Used for pose refinement (iNeRF-style); the gradient is zero where `p` was clamped.
    pub fn input_gradient(&self, points: &[[f32; 3]], d_out: &[f32]) -> Vec<[f32; 3]> {
        points
            .par_iter()
            .zip(d_out.par_chunks(F_POS_DIM))
            .map(|(p, d)| {
                let mut gp = [0f32; 3];
                for (l, lv) in self.levels.iter().enumerate() {
                    let tab = &self.table[lv.offset * 2..(lv.offset + lv.size) * 2];
                    let (i0, fr) = Self::cell(lv, *p);
                    let (idx, _) = Self::corners_of_cell(lv, i0, fr);
                    let s = lv.resolution as f32;
                    for c in 0..8 {
                        let e = idx[c] as usize * 2;
                        let v = d[2 * l] * tab[e] + d[2 * l + 1] * tab[e + 1];
                        let b = [c & 1, (c >> 1) & 1, (c >> 2) & 1];
                        let wa = |a: usize| if b[a] == 1 { fr[a] } else { 1.0 - fr[a] };
                        let sg = |a: usize| if b[a] == 1 { 1.0 } else { -1.0 };
                        gp[0] += v * sg(0) * wa(1) * wa(2) * s;
                        gp[1] += v * wa(0) * sg(1) * wa(2) * s;
                        gp[2] += v * wa(0) * wa(1) * sg(2) * s;
                    }
                }
                for a in 0..3 {
                    if !(0.0..=1.0).contains(&p[a]) {
                        gp[a] = 0.0;
                    }
                }
                gp
            })
            .collect()
    }
}
