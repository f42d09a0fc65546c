//! The mapped volume: where a camera localized against the map can be. Every method's pose
//! passes through [`MappedVolume::refusal`] ([`crate::methods::localize_with`]), so a
//! consensus that puts the camera hundreds of metres above or beside the survey is refused
//! with the reason, whichever method found it.
//!
//! The volume is the union of the blocks' scene boxes (each block's training sample points,
//! from its cameras to the surface they see, so it holds the training cameras) and the box of
//! the training camera centres the keypoint structure keeps, each grown on every side by the
//! map's scene box's shortest side. In an aerial map that side is the survey's height over the
//! ground (tiny: 30.5 m; the outside benchmark's path-traced surveys, whose rays run below the
//! ground: 112 and 120 m), so a camera may sit up to that far beside the mapped ground and up to
//! twice the survey's height: views lower and more oblique than the survey's are inside, a
//! camera that sees the mapped ground at all from farther away sees it too small to localize.

use matloc_core::pose::{Pose, camera_center};
use matloc_partition::{Aabb, Partition};
use matloc_structure::StructureMap;
use nalgebra::Point3;

/// Where a localized camera can be (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct MappedVolume {
    /// The boxes before growing.
    pub boxes: Vec<Aabb>,
    /// How far each box is grown on every side, metres.
    pub margin_m: f64,
}

impl MappedVolume {
    /// The volume of a map with this partition and (when it has one) keypoint structure;
    /// `None` when the map records no finite box or no positive margin (nothing is refused).
    pub fn of_map(partition: &Partition, structure: Option<&StructureMap>) -> Option<Self> {
        let s = &partition.scene_bounds;
        let margin_m = (0..3)
            .map(|a| s.max[a] - s.min[a])
            .fold(f64::INFINITY, f64::min);
        if !(margin_m.is_finite() && margin_m > 0.0) {
            return None;
        }
        let centres: Vec<Point3<f64>> = structure
            .map(|m| m.images().iter().map(|i| i.center()).collect())
            .unwrap_or_default();
        let boxes: Vec<Aabb> = partition
            .blocks
            .iter()
            .map(|b| b.bounds)
            .chain(Aabb::of_points(&centres))
            .filter(|b| b.min.iter().chain(&b.max).all(|v| v.is_finite()))
            .collect();
        (!boxes.is_empty()).then_some(MappedVolume { boxes, margin_m })
    }

    /// Distance from `p` to the nearest box (0 inside one), metres.
    pub fn distance(&self, p: &Point3<f64>) -> f64 {
        self.boxes
            .iter()
            .map(|b| {
                (0..3)
                    .map(|a| (b.min[a] - p[a]).max(p[a] - b.max[a]).max(0.0).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// Whether a camera centred at `p` is inside the volume (a non-finite centre is not).
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        p.iter().all(|v| v.is_finite()) && self.distance(p) <= self.margin_m
    }

    /// Why a camera with pose `cam_from_world` is refused, `None` when it is inside.
    pub fn refusal(&self, cam_from_world: &Pose) -> Option<String> {
        let c = camera_center(cam_from_world);
        let d = self.distance(&c);
        (!self.contains(&c)).then(|| {
            format!(
                "the camera centre ({:.1}, {:.1}, {:.1}) lies {d:.1} m from the mapped volume, \
                 beyond its {:.1} m margin (the scene box's shortest side)",
                c.x, c.y, c.z, self.margin_m
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::pose::Pose;
    use nalgebra::{Translation3, UnitQuaternion};

    fn volume() -> MappedVolume {
        // A survey at 30 m over a 100 m square: tiny's block.
        MappedVolume {
            boxes: vec![Aabb {
                min: [-50.0, -50.0, -2.0],
                max: [50.0, 50.0, 32.0],
            }],
            margin_m: 30.0,
        }
    }

    fn at(x: f64, y: f64, z: f64) -> Pose {
        Pose::from_parts(Translation3::new(x, y, z), UnitQuaternion::identity()).inverse()
    }

    #[test]
    fn lower_and_oblique_views_are_inside_and_far_cameras_are_refused() {
        let v = volume();
        // Inside, lower than the survey, beside the mapped ground, up to twice the height.
        for p in [(0.0, 0.0, 15.0), (-70.0, 10.0, 12.0), (20.0, 20.0, 60.0)] {
            assert!(v.refusal(&at(p.0, p.1, p.2)).is_none(), "{p:?}");
        }
        // 340 m up, 859 m beside, far below.
        for p in [(0.0, 0.0, 340.0), (909.0, 0.0, 30.0), (0.0, 0.0, -100.0)] {
            let r = v.refusal(&at(p.0, p.1, p.2)).expect("refused");
            assert!(
                r.contains("mapped volume") && r.contains("30.0 m margin"),
                "{r}"
            );
        }
        assert!(v.refusal(&at(f64::NAN, 0.0, 0.0)).is_some());
    }
}
