//! A global voxel grid and per-pose occupancy sets with (weighted) Jaccard distances.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::aabb::Aabb;
use crate::error::PartitionError;

/// A regular grid of cubic voxels over an axis-aligned box; voxel ids are
/// `ix + nx * (iy + ny * iz)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct VoxelGrid {
    /// Corner of voxel `(0, 0, 0)`, world frame.
    pub origin: [f64; 3],
    /// Edge length of a voxel, metres.
    pub voxel_size: f64,
    /// Voxels along x, y, z.
    pub dims: [u64; 3],
}

impl VoxelGrid {
    /// The grid of `voxel_size` voxels that covers `bounds`.
    pub fn covering(bounds: &Aabb, voxel_size: f64) -> Result<VoxelGrid, PartitionError> {
        if !(voxel_size.is_finite() && voxel_size > 0.0) {
            return Err(PartitionError::InvalidConfig {
                field: "voxel_size",
                reason: format!("must be finite and positive, got {voxel_size}"),
            });
        }
        let mut dims = [0u64; 3];
        for a in 0..3 {
            let extent = (bounds.max[a] - bounds.min[a]).max(0.0);
            let n = (extent / voxel_size).floor() + 1.0;
            if !(n.is_finite() && n < 2e6) {
                return Err(PartitionError::InvalidConfig {
                    field: "voxel_size",
                    reason: format!("{voxel_size} m gives too many voxels along axis {a}"),
                });
            }
            dims[a] = n as u64;
        }
        Ok(VoxelGrid {
            origin: bounds.min,
            voxel_size,
            dims,
        })
    }

    /// Id of the voxel holding `p`, or `None` outside the grid.
    pub fn voxel_of(&self, p: &Point3<f64>) -> Option<u64> {
        let mut idx = [0u64; 3];
        for a in 0..3 {
            let f = ((p[a] - self.origin[a]) / self.voxel_size).floor();
            if !(f >= 0.0 && f < self.dims[a] as f64) {
                return None;
            }
            idx[a] = f as u64;
        }
        Some(idx[0] + self.dims[0] * (idx[1] + self.dims[1] * idx[2]))
    }

    /// Centre of voxel `id`.
    pub fn voxel_center(&self, id: u64) -> Point3<f64> {
        let ix = id % self.dims[0];
        let iy = (id / self.dims[0]) % self.dims[1];
        let iz = id / (self.dims[0] * self.dims[1]);
        Point3::new(
            self.origin[0] + (ix as f64 + 0.5) * self.voxel_size,
            self.origin[1] + (iy as f64 + 0.5) * self.voxel_size,
            self.origin[2] + (iz as f64 + 0.5) * self.voxel_size,
        )
    }

    /// Occupancy of `points` (points outside the grid are ignored).
    pub fn occupancy<'a>(&self, points: impl IntoIterator<Item = &'a Point3<f64>>) -> Occupancy {
        let ids: Vec<u64> = points
            .into_iter()
            .filter_map(|p| self.voxel_of(p))
            .collect();
        Occupancy::from_ids(ids)
    }
}

/// A sorted set of voxel ids with a point count per voxel.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Occupancy {
    /// Strictly increasing voxel ids.
    pub ids: Vec<u64>,
    /// Points that fell into each voxel (same length as `ids`).
    pub counts: Vec<u32>,
}

impl Occupancy {
    /// Builds the set from unsorted ids with repeats.
    pub fn from_ids(mut ids: Vec<u64>) -> Occupancy {
        ids.sort_unstable();
        let mut out = Occupancy::default();
        for id in ids {
            if out.ids.last() == Some(&id) {
                if let Some(c) = out.counts.last_mut() {
                    *c = c.saturating_add(1);
                }
            } else {
                out.ids.push(id);
                out.counts.push(1);
            }
        }
        out
    }

    /// Number of occupied voxels.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// True when no voxel is occupied.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Union of several occupancies, counts added.
    pub fn union<'a>(sets: impl IntoIterator<Item = &'a Occupancy>) -> Occupancy {
        let mut pairs: Vec<(u64, u32)> = sets
            .into_iter()
            .flat_map(|s| s.ids.iter().copied().zip(s.counts.iter().copied()))
            .collect();
        pairs.sort_unstable_by_key(|p| p.0);
        let mut out = Occupancy::default();
        for (id, c) in pairs {
            if out.ids.last() == Some(&id) {
                if let Some(last) = out.counts.last_mut() {
                    *last = last.saturating_add(c);
                }
            } else {
                out.ids.push(id);
                out.counts.push(c);
            }
        }
        out
    }
}

/// Size of the intersection of two strictly increasing id lists.
pub fn intersection_size(a: &[u64], b: &[u64]) -> usize {
    let (mut i, mut j, mut n) = (0, 0, 0);
    while i < a.len() && j < b.len() {
        match a[i].cmp(&b[j]) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                n += 1;
                i += 1;
                j += 1;
            }
        }
    }
    n
}

/// `1 − |A ∩ B| / |A ∪ B|` of two strictly increasing id lists; two empty sets are at distance 0.
pub fn jaccard_distance(a: &[u64], b: &[u64]) -> f64 {
    let inter = intersection_size(a, b);
    let union = a.len() + b.len() - inter;
    if union == 0 {
        0.0
    } else {
        1.0 - inter as f64 / union as f64
    }
}

/// Weighted Jaccard distance `1 − Σ min(wa, wb) / Σ max(wa, wb)` with each occupancy's counts
/// normalised to sum 1, so a pose with more rays does not dominate.
pub fn weighted_jaccard_distance(a: &Occupancy, b: &Occupancy) -> f64 {
    let sa: f64 = a.counts.iter().map(|&c| f64::from(c)).sum();
    let sb: f64 = b.counts.iter().map(|&c| f64::from(c)).sum();
    if sa == 0.0 && sb == 0.0 {
        return 0.0;
    }
    let wa = |i: usize| f64::from(a.counts[i]) / sa.max(f64::MIN_POSITIVE);
    let wb = |j: usize| f64::from(b.counts[j]) / sb.max(f64::MIN_POSITIVE);
    let (mut i, mut j) = (0, 0);
    let (mut num, mut den) = (0.0, 0.0);
    while i < a.ids.len() || j < b.ids.len() {
        let take_a = j >= b.ids.len() || (i < a.ids.len() && a.ids[i] < b.ids[j]);
        let take_b = i >= a.ids.len() || (j < b.ids.len() && b.ids[j] < a.ids[i]);
        if take_a {
            den += wa(i);
            i += 1;
        } else if take_b {
            den += wb(j);
            j += 1;
        } else {
            num += wa(i).min(wb(j));
            den += wa(i).max(wb(j));
            i += 1;
            j += 1;
        }
    }
    if den <= 0.0 {
        0.0
    } else {
        (1.0 - num / den).max(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn set() -> impl Strategy<Value = Vec<u64>> {
        prop::collection::btree_set(0u64..200, 0..60).prop_map(|s| s.into_iter().collect())
    }

    fn occ() -> impl Strategy<Value = Occupancy> {
        prop::collection::vec(0u64..100, 0..200).prop_map(Occupancy::from_ids)
    }

    proptest! {
        #[test]
        fn jaccard_properties(a in set(), b in set(), c in set()) {
            let dab = jaccard_distance(&a, &b);
            prop_assert!((0.0..=1.0).contains(&dab));
            prop_assert_eq!(dab, jaccard_distance(&b, &a));
            prop_assert_eq!(jaccard_distance(&a, &a), 0.0);
            // The Jaccard distance is a metric: the triangle inequality holds exactly.
            let dac = jaccard_distance(&a, &c);
            let dbc = jaccard_distance(&b, &c);
            prop_assert!(dac <= dab + dbc + 1e-12);
            let disjoint: Vec<u64> = b.iter().map(|x| x + 1000).collect();
            if !a.is_empty() || !disjoint.is_empty() {
                prop_assert_eq!(jaccard_distance(&a, &disjoint), 1.0);
            }
        }

        #[test]
        fn weighted_jaccard_properties(a in occ(), b in occ(), c in occ()) {
            let dab = weighted_jaccard_distance(&a, &b);
            prop_assert!((0.0..=1.0 + 1e-12).contains(&dab));
            prop_assert!((dab - weighted_jaccard_distance(&b, &a)).abs() < 1e-12);
            prop_assert!(weighted_jaccard_distance(&a, &a) < 1e-12);
            let dac = weighted_jaccard_distance(&a, &c);
            let dbc = weighted_jaccard_distance(&b, &c);
            prop_assert!(dac <= dab + dbc + 1e-9);
            let mut shifted = b.clone();
            shifted.ids.iter_mut().for_each(|x| *x += 1000);
            if !a.is_empty() && !shifted.is_empty() {
                prop_assert!((weighted_jaccard_distance(&a, &shifted) - 1.0).abs() < 1e-12);
            }
        }

        #[test]
        fn occupancy_is_sorted_and_counts_points(ids in prop::collection::vec(0u64..50, 0..100)) {
            let o = Occupancy::from_ids(ids.clone());
            prop_assert!(o.ids.windows(2).all(|w| w[0] < w[1]));
            prop_assert_eq!(o.counts.iter().map(|&c| c as usize).sum::<usize>(), ids.len());
        }
    }

    #[test]
    fn voxel_ids_round_trip() {
        let b = Aabb {
            min: [-10.0, 0.0, 5.0],
            max: [10.0, 4.0, 9.0],
        };
        let g = VoxelGrid::covering(&b, 2.0).unwrap();
        assert_eq!(g.dims, [11, 3, 3]);
        let p = Point3::new(3.1, 1.2, 6.5);
        let id = g.voxel_of(&p).unwrap();
        let c = g.voxel_center(id);
        assert!((c - Point3::new(3.0, 1.0, 6.0)).norm() < 1e-12);
        assert!(g.voxel_of(&Point3::new(-11.0, 0.0, 5.0)).is_none());
        assert!(VoxelGrid::covering(&b, 0.0).is_err());
    }
}
