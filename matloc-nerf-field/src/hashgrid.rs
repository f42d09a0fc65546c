use rand::Rng;
use rayon::prelude::*;

use crate::feature::F_POS_DIM;

/// Number of resolution levels.
pub const N_LEVELS: usize = 16;
/// Features stored per table entry.
pub const N_FEATURES_PER_LEVEL: usize = 2;

/// tiny-cuda-nn's spatial-hash primes (x, y, z).
const PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];

/// Points per parallel work item in the forward pass: enough to amortise rayon overhead,
/// small enough that the chunk's output stays in L1/L2 while all 16 levels are visited.
const FWD_CHUNK: usize = 256;

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
            // max/min (not clamp) so that NaN maps to 0 instead of propagating into indices.
            let x = p[a].max(0.0).min(1.0) * s;
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
    pub fn encode(&self, points: &[[f32; 3]], out: &mut [f32]) {
        debug_assert_eq!(out.len(), points.len() * F_POS_DIM);
        out.par_chunks_mut(FWD_CHUNK * F_POS_DIM)
            .zip(points.par_chunks(FWD_CHUNK))
            .for_each(|(o, pts)| self.encode_chunk(pts, o));
    }

    /// Serial encoding of one chunk; levels outermost so one level's table region stays hot.
    pub(crate) fn encode_chunk(&self, pts: &[[f32; 3]], out: &mut [f32]) {
        for (l, lv) in self.levels.iter().enumerate() {
            let tab = &self.table[lv.offset * 2..(lv.offset + lv.size) * 2];
            for (p, orow) in pts.iter().zip(out.chunks_exact_mut(F_POS_DIM)) {
                let (idx, w) = Self::corners(lv, *p);
                let mut f0 = 0.0f32;
                let mut f1 = 0.0f32;
                for c in 0..8 {
                    let e = idx[c] as usize * 2;
                    f0 = w[c].mul_add(tab[e], f0);
                    f1 = w[c].mul_add(tab[e + 1], f1);
                }
                orow[2 * l] = f0;
                orow[2 * l + 1] = f1;
            }
        }
    }

    /// Accumulates `∂L/∂table` into `grad` (same layout as `table`) given `∂L/∂out`
    /// (`points.len() × 32`). Parallel over levels: each level's gradient slice belongs to one
    /// task, so there are no atomics and no per-thread copies of the table.
    pub fn backward(&self, points: &[[f32; 3]], d_out: &[f32], grad: &mut [f32]) {
        debug_assert_eq!(d_out.len(), points.len() * F_POS_DIM);
        debug_assert_eq!(grad.len(), self.table.len());
        let n = points.len();
        // Level-major copy of the incoming gradient: each level task then streams 8 bytes
        // per point instead of touching a 128-byte row.
        let mut d_lvl = vec![0f32; n * F_POS_DIM];
        d_lvl
            .par_chunks_mut(2 * n)
            .enumerate()
            .for_each(|(l, dst)| {
                for (p, d) in dst.chunks_exact_mut(2).enumerate() {
                    d[0] = d_out[p * F_POS_DIM + 2 * l];
                    d[1] = d_out[p * F_POS_DIM + 2 * l + 1];
                }
            });
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
            for (p, dp) in points.iter().zip(d.chunks_exact(2)) {
                if dp[0] == 0.0 && dp[1] == 0.0 {
                    continue;
                }
                let (idx, w) = Self::corners(lv, *p);
                for c in 0..8 {
                    let e = idx[c] as usize * 2;
                    g[e] = w[c].mul_add(dp[0], g[e]);
                    g[e + 1] = w[c].mul_add(dp[1], g[e + 1]);
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
