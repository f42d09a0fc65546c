//! Brute-force descriptor matching — Hamming distances for binary descriptors, Euclidean for
//! gradient histograms: mutual nearest neighbours + ratio test + a distance cap.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::detect::Descriptor;
use crate::gradient::{GradientDescriptor, gradient_distance_sq};

/// Which descriptor keypoints are described and matched with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DescriptorKind {
    /// Rotated BRIEF, 256 bits, Hamming distance: the fastest to match.
    Binary,
    /// Gradient histograms (SIFT's layout, RootSIFT's normalisation), Euclidean distance:
    /// more correct matches, and a larger share of them, under another light or viewpoint.
    #[default]
    Gradient,
}

/// A descriptor brute-force matching can compare.
pub trait KeypointDescriptor: Sync {
    /// A cheap distance, monotone in the true one (e.g. squared).
    fn raw_distance(&self, other: &Self) -> u32;
    /// The distance a raw distance stands for: what the ratio test and the cap compare.
    fn distance_of_raw(raw: u32) -> f32;
}

impl KeypointDescriptor for Descriptor {
    #[inline]
    fn raw_distance(&self, other: &Self) -> u32 {
        hamming(self, other)
    }

    #[inline]
    fn distance_of_raw(raw: u32) -> f32 {
        raw as f32
    }
}

impl KeypointDescriptor for GradientDescriptor {
    #[inline]
    fn raw_distance(&self, other: &Self) -> u32 {
        gradient_distance_sq(self, other)
    }

    #[inline]
    fn distance_of_raw(raw: u32) -> f32 {
        (raw as f32).sqrt()
    }
}

/// Matching settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MatchConfig {
    /// Lowe's ratio: keep a match if best < ratio · second best (1.0 disables).
    pub ratio: f32,
    /// Maximum distance of a match: Hamming bits of 256 for binary descriptors, quantised
    /// Euclidean units for gradient descriptors (unit vectors × 512, so at most 724).
    pub max_distance: u32,
    /// Require the match to be the nearest neighbour in both directions.
    pub mutual: bool,
}

impl Default for MatchConfig {
    fn default() -> Self {
        Self {
            ratio: 0.8,
            max_distance: 64,
            mutual: true,
        }
    }
}

impl MatchConfig {
    /// The defaults for gradient descriptors: the same ratio and mutual test, no cap.
    pub fn gradient() -> Self {
        Self {
            max_distance: 724,
            ..Self::default()
        }
    }
}

/// A match between descriptor `a` of the first set and `b` of the second.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct KeypointMatch {
    /// Index in the first set.
    pub a: usize,
    /// Index in the second set.
    pub b: usize,
    /// Distance (rounded down for gradient descriptors).
    pub distance: u32,
}

/// Hamming distance of two 256-bit descriptors.
#[inline]
pub fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    (a[0] ^ b[0]).count_ones()
        + (a[1] ^ b[1]).count_ones()
        + (a[2] ^ b[2]).count_ones()
        + (a[3] ^ b[3]).count_ones()
}

/// Best and second-best neighbour of each query descriptor in `train`.
fn nearest<D: KeypointDescriptor>(query: &[D], train: &[D]) -> Vec<(usize, u32, u32)> {
    query
        .par_iter()
        .map(|q| {
            let (mut best, mut d1, mut d2) = (usize::MAX, u32::MAX, u32::MAX);
            for (j, t) in train.iter().enumerate() {
                let d = q.raw_distance(t);
                if d < d1 {
                    d2 = d1;
                    d1 = d;
                    best = j;
                } else if d < d2 {
                    d2 = d;
                }
            }
            (best, d1, d2)
        })
        .collect()
}

/// Matches descriptor set `a` against `b`.
pub fn match_descriptors<D: KeypointDescriptor>(
    a: &[D],
    b: &[D],
    config: &MatchConfig,
) -> Vec<KeypointMatch> {
    if a.is_empty() || b.is_empty() {
        return Vec::new();
    }
    let ab = nearest(a, b);
    let ba = if config.mutual {
        nearest(b, a)
    } else {
        Vec::new()
    };
    ab.iter()
        .enumerate()
        .filter_map(|(i, &(j, d1, d2))| {
            if j == usize::MAX {
                return None;
            }
            let second = (d2 != u32::MAX).then(|| D::distance_of_raw(d2));
            let d1 = D::distance_of_raw(d1);
            if d1 > config.max_distance as f32 {
                return None;
            }
            if config.ratio < 1.0 && second.is_some_and(|d2| d1 >= config.ratio * d2) {
                return None;
            }
            if config.mutual && ba[j].0 != i {
                return None;
            }
            Some(KeypointMatch {
                a: i,
                b: j,
                distance: d1 as u32,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn desc(seed: u64) -> Descriptor {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut d = [0u64; 4];
        for w in &mut d {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            *w = s;
        }
        d
    }

    #[test]
    fn hamming_counts_bits() {
        assert_eq!(hamming(&[0; 4], &[0; 4]), 0);
        assert_eq!(hamming(&[0; 4], &[u64::MAX; 4]), 256);
        assert_eq!(hamming(&[1, 0, 0, 0], &[0, 0, 0, 3]), 3);
    }

    proptest! {
        #[test]
        fn identical_sets_match_identically(n in 1usize..60, seed in any::<u64>()) {
            let a: Vec<Descriptor> = (0..n as u64).map(|i| desc(seed ^ (i * 7919 + 1))).collect();
            let m = match_descriptors(&a, &a, &MatchConfig { ratio: 1.0, ..MatchConfig::default() });
            prop_assert_eq!(m.len(), n);
            for x in &m {
                prop_assert_eq!(x.a, x.b);
                prop_assert_eq!(x.distance, 0);
            }
        }

        #[test]
        fn matches_are_mutual_and_permutation_invariant(n in 2usize..40, seed in any::<u64>()) {
            let a: Vec<Descriptor> = (0..n as u64).map(|i| desc(seed ^ (i + 11))).collect();
            let b: Vec<Descriptor> = (0..n as u64).map(|i| desc(seed.rotate_left(7) ^ (i + 3))).collect();
            let cfg = MatchConfig { ratio: 1.0, max_distance: 256, mutual: true };
            let m = match_descriptors(&a, &b, &cfg);
            let back = match_descriptors(&b, &a, &cfg);
            let mut fwd: Vec<(usize, usize)> = m.iter().map(|x| (x.a, x.b)).collect();
            let mut bwd: Vec<(usize, usize)> = back.iter().map(|x| (x.b, x.a)).collect();
            fwd.sort();
            bwd.sort();
            // Ties can break differently per direction; without ties the sets agree.
            let ties = m.iter().any(|x| b.iter().enumerate().any(|(j, t)| j != x.b && hamming(&a[x.a], t) == x.distance));
            if !ties {
                prop_assert_eq!(fwd, bwd);
            }
        }
    }

    #[test]
    fn empty_sets_give_no_matches() {
        assert!(match_descriptors(&[], &[desc(1)], &MatchConfig::default()).is_empty());
        assert!(match_descriptors(&[desc(1)], &[], &MatchConfig::default()).is_empty());
    }
}
