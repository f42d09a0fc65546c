//! Deterministic hashing and a small seeded generator.
//!
//! Everything in the synthetic world derives from one `u64` seed through these functions, so a
//! scene is bit-identical across runs, thread counts and platforms (no `rand` version coupling).

use matloc_core::hash::{mix64, splitmix64_next};

/// 32-bit hash of a lattice point; cheap enough for per-sample noise lookups.
#[inline]
pub(crate) fn hash3(i: i32, j: i32, k: i32, seed: u32) -> u32 {
    let mut h = (i as u32).wrapping_mul(0x8DA6_B343)
        ^ (j as u32).wrapping_mul(0xD816_3841)
        ^ (k as u32).wrapping_mul(0xCB1A_B31F)
        ^ seed.wrapping_mul(0x9E37_79B9);
    h ^= h >> 15;
    h = h.wrapping_mul(0x2C1B_3C6D);
    h ^= h >> 12;
    h = h.wrapping_mul(0x297A_2D39);
    h ^= h >> 15;
    h
}

/// Uniform value in `[0, 1)` from a hash.
#[inline]
pub(crate) fn unit(h: u32) -> f32 {
    (h >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
}

/// A seeded SplitMix64 stream.
#[derive(Clone, Debug)]
pub(crate) struct Rng(u64);

impl Rng {
    pub(crate) fn new(seed: u64) -> Self {
        Rng(mix64(seed ^ 0x5EED_0F5E_ED0F_5EED))
    }

    /// An independent stream for a named purpose, so adding draws in one part of the generator
    /// does not shift every later part.
    pub(crate) fn fork(&self, tag: u64) -> Rng {
        Rng(mix64(
            self.0 ^ mix64(tag.wrapping_add(0x1234_5678_9ABC_DEF1)),
        ))
    }

    pub(crate) fn next_u64(&mut self) -> u64 {
        splitmix64_next(&mut self.0)
    }

    /// Uniform in `[0, 1)`.
    pub(crate) fn f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[lo, hi)`.
    pub(crate) fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.f64()
    }

    /// Uniform index in `0..n` (`n > 0`).
    pub(crate) fn index(&mut self, n: usize) -> usize {
        ((self.f64() * n as f64) as usize).min(n.saturating_sub(1))
    }

    /// Standard normal (Box–Muller).
    pub(crate) fn normal(&mut self) -> f64 {
        let u1 = self.f64().max(1e-300);
        let u2 = self.f64();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    pub(crate) fn u32(&mut self) -> u32 {
        (self.next_u64() >> 32) as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_reproducible_and_forks_differ() {
        let a: Vec<u64> = (0..4)
            .scan(Rng::new(7), |r, _| Some(r.next_u64()))
            .collect();
        let b: Vec<u64> = (0..4)
            .scan(Rng::new(7), |r, _| Some(r.next_u64()))
            .collect();
        assert_eq!(a, b);
        let r = Rng::new(7);
        assert_ne!(r.fork(1).next_u64(), r.fork(2).next_u64());
        let mut r = Rng::new(1);
        for _ in 0..1000 {
            let x = r.range(-2.0, 3.0);
            assert!((-2.0..3.0).contains(&x));
            assert!(r.index(5) < 5);
        }
    }
}
