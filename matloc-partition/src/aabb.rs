//! Axis-aligned boxes in the world frame.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

/// An axis-aligned box, world frame, metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    /// Minimum corner.
    pub min: [f64; 3],
    /// Maximum corner.
    pub max: [f64; 3],
}

impl Aabb {
    /// The smallest box holding all `points` (`None` when there are none).
    pub fn of_points<'a>(points: impl IntoIterator<Item = &'a Point3<f64>>) -> Option<Aabb> {
        let mut it = points.into_iter();
        let first = it.next()?;
        let mut b = Aabb {
            min: [first.x, first.y, first.z],
            max: [first.x, first.y, first.z],
        };
        for p in it {
            for a in 0..3 {
                b.min[a] = b.min[a].min(p[a]);
                b.max[a] = b.max[a].max(p[a]);
            }
        }
        Some(b)
    }

    /// Volume in m³.
    pub fn volume(&self) -> f64 {
        (0..3)
            .map(|a| (self.max[a] - self.min[a]).max(0.0))
            .product()
    }

    /// True when `p` lies inside (boundary included).
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        (0..3).all(|a| p[a] >= self.min[a] && p[a] <= self.max[a])
    }

    /// Centre of the box.
    pub fn center(&self) -> [f64; 3] {
        [0, 1, 2].map(|a| 0.5 * (self.min[a] + self.max[a]))
    }
}
