//! Pose groups: the classes of the place classifier (two-stage K-means).
//!
//! Stage 1 clusters camera centres with k-means (k-means++ seeding, Lloyd iterations); stage 2
//! splits every spatial cluster by orientation, running spherical k-means on the unit viewing
//! directions with the angle between them as the distance. A group's coarse pose is its
//! **medoid**: the member with the smallest summed distance `‖Δc‖ / r + ∠ / α` to the other
//! members, so the coarse pose is always a real training pose (one with an image, a depth map and
//! a sub-NeRF).
//!
//! **Group count rule.** Both stages pick their cluster count from the data: the smallest `k`
//! for which every member lies within the stage's radius of its cluster centre —
//! `r = radius_factor ×` the median viewing distance of the training poses (camera to the mean of
//! its surface samples, or `spatial_radius_m` when set) for positions, `α = max_angle_deg` for
//! directions. A coarse pose within `r` of the truth and within `α` of its direction sees most
//! of the same ground, which is what the fine stage needs. `k` is capped so that clusters keep on
//! average at least `min_group_size` poses (a class with one or two images cannot be learnt).
//! All randomness comes from one seed, so the groups are reproducible.

use matloc_core::Pose;
use matloc_core::pose::{camera_center, viewing_direction};
use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::error::PlaceError;

/// Settings of [`PoseGroups::build`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GroupConfig {
    /// Spatial radius as a multiple of the median viewing distance.
    pub radius_factor: f64,
    /// Fixed spatial radius in metres (overrides `radius_factor` when set).
    pub spatial_radius_m: Option<f64>,
    /// Largest angle between a member's viewing direction and its group's mean direction, degrees.
    pub max_angle_deg: f64,
    /// Smallest mean number of poses per cluster in either stage.
    pub min_group_size: usize,
    /// Seed of the k-means++ initialisations.
    pub seed: u64,
    /// Restarts per k (the lowest-cost run wins).
    pub restarts: usize,
    /// Lloyd iterations per run.
    pub max_iter: usize,
}

impl Default for GroupConfig {
    fn default() -> Self {
        GroupConfig {
            radius_factor: 0.3,
            spatial_radius_m: None,
            max_angle_deg: 30.0,
            min_group_size: 2,
            seed: 0,
            restarts: 4,
            max_iter: 50,
        }
    }
}

impl GroupConfig {
    fn validate(&self) -> Result<(), PlaceError> {
        let bad =
            |field: &'static str, reason: String| Err(PlaceError::InvalidConfig { field, reason });
        if !(self.radius_factor.is_finite() && self.radius_factor > 0.0) {
            return bad(
                "radius_factor",
                format!("must be > 0, got {}", self.radius_factor),
            );
        }
        if let Some(r) = self.spatial_radius_m
            && !(r.is_finite() && r > 0.0)
        {
            return bad("spatial_radius_m", format!("must be > 0, got {r}"));
        }
        if !(self.max_angle_deg.is_finite()
            && self.max_angle_deg > 0.0
            && self.max_angle_deg <= 180.0)
        {
            return bad(
                "max_angle_deg",
                format!("must be in (0, 180], got {}", self.max_angle_deg),
            );
        }
        if self.min_group_size == 0 {
            return bad("min_group_size", "must be at least 1".into());
        }
        Ok(())
    }
}

/// One pose group.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseGroup {
    /// Group index (position in [`PoseGroups::groups`]).
    pub id: usize,
    /// Spatial cluster the group belongs to.
    pub spatial: usize,
    /// Mean camera centre of the spatial cluster, world frame.
    pub spatial_center: [f64; 3],
    /// Unit mean viewing direction of the group.
    pub direction: [f64; 3],
    /// Positions (in the input slice) of the member poses, increasing.
    pub members: Vec<usize>,
    /// Position of the medoid pose in the input slice.
    pub medoid: usize,
    /// The medoid's `cam_from_world`: the group's coarse pose.
    pub coarse_pose: Pose,
    /// Sub-NeRF block that serves the group (set from a partition), if known.
    #[serde(default)]
    pub block: Option<usize>,
}

/// The pose groups of a set of training poses.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseGroups {
    /// Settings used.
    pub config: GroupConfig,
    /// Spatial radius used, metres.
    pub spatial_radius_m: f64,
    /// Number of spatial clusters (stage 1).
    pub num_spatial: usize,
    /// The groups, ordered by spatial cluster then orientation cluster.
    pub groups: Vec<PoseGroup>,
    /// Group of each input pose.
    pub labels: Vec<usize>,
}

/// Checks that every pose is finite; the error names the first bad one.
pub(crate) fn check_poses(poses: &[Pose]) -> Result<(), PlaceError> {
    for (index, p) in poses.iter().enumerate() {
        let finite = p.translation.vector.iter().all(|v| v.is_finite())
            && p.rotation.coords.iter().all(|v| v.is_finite());
        if !finite {
            return Err(PlaceError::NonFinitePose { index });
        }
    }
    Ok(())
}

fn angle(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.dot(b).clamp(-1.0, 1.0).acos()
}

/// Result of one k-means run: labels, centres, cost (sum of squared distances).
struct KMeans<T> {
    labels: Vec<usize>,
    centers: Vec<T>,
    cost: f64,
}

/// Generic k-means with k-means++ seeding over items of type `T`.
///
/// `dist` is the distance that drives seeding and assignment; `mean` recomputes a centre from a
/// cluster's members. Empty clusters are reseeded with the item farthest from its centre.
fn kmeans<T: Clone>(
    items: &[T],
    k: usize,
    rng: &mut ChaCha8Rng,
    max_iter: usize,
    dist: &dyn Fn(&T, &T) -> f64,
    mean: &dyn Fn(&[&T]) -> T,
) -> KMeans<T> {
    let n = items.len();
    let mut centers = vec![items[rng.random_range(0..n)].clone()];
    let mut d2: Vec<f64> = items.iter().map(|x| dist(x, &centers[0]).powi(2)).collect();
    while centers.len() < k {
        let total: f64 = d2.iter().sum();
        let pick = if total > 0.0 {
            let mut r = rng.random::<f64>() * total;
            let mut chosen = n - 1;
            for (i, &w) in d2.iter().enumerate() {
                r -= w;
                if r <= 0.0 && w > 0.0 {
                    chosen = i;
                    break;
                }
            }
            chosen
        } else {
            rng.random_range(0..n)
        };
        centers.push(items[pick].clone());
        for (i, x) in items.iter().enumerate() {
            d2[i] = d2[i].min(dist(x, &centers[centers.len() - 1]).powi(2));
        }
    }
    let mut labels = vec![0usize; n];
    for _ in 0..max_iter.max(1) {
        let mut changed = false;
        for (i, x) in items.iter().enumerate() {
            let best = (0..k)
                .min_by(|&a, &b| {
                    dist(x, &centers[a])
                        .total_cmp(&dist(x, &centers[b]))
                        .then(a.cmp(&b))
                })
                .unwrap_or(0);
            if best != labels[i] {
                labels[i] = best;
                changed = true;
            }
        }
        for c in 0..k {
            let members: Vec<&T> = (0..n)
                .filter(|&i| labels[i] == c)
                .map(|i| &items[i])
                .collect();
            if members.is_empty() {
                // Reseed an empty cluster with the worst-served item.
                let far = (0..n)
                    .max_by(|&a, &b| {
                        dist(&items[a], &centers[labels[a]])
                            .total_cmp(&dist(&items[b], &centers[labels[b]]))
                            .then(b.cmp(&a))
                    })
                    .unwrap_or(0);
                centers[c] = items[far].clone();
                labels[far] = c;
                changed = true;
            } else {
                centers[c] = mean(&members);
            }
        }
        if !changed {
            break;
        }
    }
    let cost = items
        .iter()
        .zip(&labels)
        .map(|(x, &l)| dist(x, &centers[l]).powi(2))
        .sum();
    KMeans {
        labels,
        centers,
        cost,
    }
}

/// Smallest `k ≤ k_max` whose best-of-restarts clustering keeps every item within `radius` of
/// its centre (`k_max` when none does). The RNG stream of a run depends only on `(k, restart)`,
/// so the result does not depend on which `k` were tried before.
fn kmeans_smallest_k<T: Clone>(
    items: &[T],
    k_max: usize,
    radius: f64,
    cfg: &GroupConfig,
    stream: u64,
    dist: &dyn Fn(&T, &T) -> f64,
    mean: &dyn Fn(&[&T]) -> T,
) -> KMeans<T> {
    let mut last = None;
    for k in 1..=k_max.max(1) {
        let mut best: Option<KMeans<T>> = None;
        for restart in 0..cfg.restarts.max(1) {
            let mut rng =
                ChaCha8Rng::seed_from_u64(cfg.seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15));
            rng.set_stream((k as u64) << 16 | restart as u64);
            let run = kmeans(items, k, &mut rng, cfg.max_iter, dist, mean);
            if best.as_ref().is_none_or(|b| run.cost < b.cost - 1e-12) {
                best = Some(run);
            }
        }
        let run = best.expect("at least one restart");
        let fits = items
            .iter()
            .zip(&run.labels)
            .all(|(x, &l)| dist(x, &run.centers[l]) <= radius);
        if fits {
            return run;
        }
        last = Some(run);
    }
    last.expect("k_max >= 1")
}

/// Median distance from each camera to the mean of its surface points (`view_points[i]`).
pub fn median_viewing_distance(poses: &[Pose], view_points: &[Point3<f64>]) -> Option<f64> {
    let mut d: Vec<f64> = poses
        .iter()
        .zip(view_points)
        .map(|(p, q)| (camera_center(p) - q).norm())
        .filter(|d| d.is_finite())
        .collect();
    if d.is_empty() {
        return None;
    }
    let mid = d.len() / 2;
    Some(*d.select_nth_unstable_by(mid, f64::total_cmp).1)
}

impl PoseGroups {
    /// Groups `poses` (`cam_from_world`). `view_points[i]` is a point pose `i` looks at (e.g. the
    /// mean of its surface samples); it sets the spatial radius and may be empty when
    /// `spatial_radius_m` is given.
    pub fn build(
        poses: &[Pose],
        view_points: &[Point3<f64>],
        config: &GroupConfig,
    ) -> Result<PoseGroups, PlaceError> {
        config.validate()?;
        check_poses(poses)?;
        let n = poses.len();
        if n < config.min_group_size.max(2) {
            return Err(PlaceError::TooFewPoses {
                poses: n,
                groups: 1,
                min_group_size: config.min_group_size,
            });
        }
        let radius = match config.spatial_radius_m {
            Some(r) => r,
            None => {
                if view_points.len() != n {
                    return Err(PlaceError::InvalidConfig {
                        field: "spatial_radius_m",
                        reason: format!(
                            "needs a view point per pose ({} for {n} poses) or a fixed radius",
                            view_points.len()
                        ),
                    });
                }
                let d = median_viewing_distance(poses, view_points).ok_or(
                    PlaceError::InvalidConfig {
                        field: "radius_factor",
                        reason: "no finite viewing distance".into(),
                    },
                )?;
                (config.radius_factor * d).max(1e-6)
            }
        };
        let centers: Vec<Vector3<f64>> = poses.iter().map(|p| camera_center(p).coords).collect();
        let dirs: Vec<Vector3<f64>> = poses.iter().map(viewing_direction).collect();
        let euclid = |a: &Vector3<f64>, b: &Vector3<f64>| (a - b).norm();
        let mean_pt =
            |m: &[&Vector3<f64>]| m.iter().fold(Vector3::zeros(), |s, v| s + *v) / m.len() as f64;
        let spatial = kmeans_smallest_k(
            &centers,
            n / config.min_group_size,
            radius,
            config,
            1,
            &euclid,
            &mean_pt,
        );
        let max_angle = config.max_angle_deg.to_radians();
        let mean_dir = |m: &[&Vector3<f64>]| {
            let s = m.iter().fold(Vector3::zeros(), |s, v| s + *v);
            s.try_normalize(1e-12).unwrap_or(*m[0])
        };
        let mut groups = Vec::new();
        let mut labels = vec![usize::MAX; n];
        for (s, center) in spatial.centers.iter().enumerate() {
            let idx: Vec<usize> = (0..n).filter(|&i| spatial.labels[i] == s).collect();
            if idx.is_empty() {
                continue;
            }
            let sub_dirs: Vec<Vector3<f64>> = idx.iter().map(|&i| dirs[i]).collect();
            let k_max = (idx.len() / config.min_group_size).max(1);
            let orient = kmeans_smallest_k(
                &sub_dirs,
                k_max,
                max_angle,
                config,
                2 + s as u64,
                &angle,
                &mean_dir,
            );
            for (o, dir) in orient.centers.iter().enumerate() {
                let members: Vec<usize> = idx
                    .iter()
                    .zip(&orient.labels)
                    .filter(|(_, l)| **l == o)
                    .map(|(&i, _)| i)
                    .collect();
                if members.is_empty() {
                    continue;
                }
                let cost = |a: usize| -> f64 {
                    members
                        .iter()
                        .map(|&b| {
                            (centers[a] - centers[b]).norm() / radius
                                + angle(&dirs[a], &dirs[b]) / max_angle
                        })
                        .sum()
                };
                let medoid = members
                    .iter()
                    .copied()
                    .min_by(|&a, &b| cost(a).total_cmp(&cost(b)).then(a.cmp(&b)))
                    .expect("non-empty");
                let id = groups.len();
                for &m in &members {
                    labels[m] = id;
                }
                groups.push(PoseGroup {
                    id,
                    spatial: s,
                    spatial_center: [center.x, center.y, center.z],
                    direction: [dir.x, dir.y, dir.z],
                    members,
                    medoid,
                    coarse_pose: poses[medoid],
                    block: None,
                });
            }
        }
        Ok(PoseGroups {
            config: *config,
            spatial_radius_m: radius,
            num_spatial: spatial.centers.len(),
            groups,
            labels,
        })
    }

    /// Number of groups.
    pub fn len(&self) -> usize {
        self.groups.len()
    }

    /// True when there are no groups.
    pub fn is_empty(&self) -> bool {
        self.groups.is_empty()
    }

    /// The group an arbitrary pose belongs to under the same two-stage rule: nearest spatial
    /// centre, then the group of that spatial cluster with the closest mean direction. `None`
    /// for a non-finite pose.
    pub fn assign(&self, cam_from_world: &Pose) -> Option<usize> {
        check_poses(std::slice::from_ref(cam_from_world)).ok()?;
        let c = camera_center(cam_from_world).coords;
        let d = viewing_direction(cam_from_world);
        let spatial = self
            .groups
            .iter()
            .min_by(|a, b| {
                (Vector3::from(a.spatial_center) - c)
                    .norm()
                    .total_cmp(&(Vector3::from(b.spatial_center) - c).norm())
                    .then(a.id.cmp(&b.id))
            })?
            .spatial;
        self.groups
            .iter()
            .filter(|g| g.spatial == spatial)
            .min_by(|a, b| {
                angle(&Vector3::from(a.direction), &d)
                    .total_cmp(&angle(&Vector3::from(b.direction), &d))
                    .then(a.id.cmp(&b.id))
            })
            .map(|g| g.id)
    }

    /// Sets each group's serving block: the block most of its members belong to.
    /// `block_of(i)` gives the block of input pose `i`.
    pub fn attach_blocks(&mut self, block_of: impl Fn(usize) -> Option<usize>) {
        for g in &mut self.groups {
            let mut votes: Vec<(usize, usize)> = Vec::new();
            for &m in &g.members {
                if let Some(b) = block_of(m) {
                    match votes.iter_mut().find(|v| v.0 == b) {
                        Some(v) => v.1 += 1,
                        None => votes.push((b, 1)),
                    }
                }
            }
            // The medoid's own block wins ties, so the coarse pose is rendered by its own sub-NeRF.
            let medoid_block = block_of(g.medoid);
            g.block = votes
                .iter()
                .max_by(|a, b| {
                    a.1.cmp(&b.1)
                        .then((Some(a.0) == medoid_block).cmp(&(Some(b.0) == medoid_block)))
                        .then(b.0.cmp(&a.0))
                })
                .map(|v| v.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::pose::look_at;

    /// Four sites 100 m apart, each seen from two opposite headings, 6 poses per heading.
    /// Poses, their view points and their true (site, heading).
    type Layout = (Vec<Pose>, Vec<Point3<f64>>, Vec<(usize, usize)>);

    fn layout(jitter_seed: u64) -> Layout {
        let mut rng = ChaCha8Rng::seed_from_u64(jitter_seed);
        let (mut poses, mut targets, mut truth) = (Vec::new(), Vec::new(), Vec::new());
        for site in 0..4 {
            let base = Vector3::new((site % 2) as f64 * 100.0, (site / 2) as f64 * 100.0, 0.0);
            for heading in 0..2 {
                let h = if heading == 0 { 1.0 } else { -1.0 };
                for _ in 0..6 {
                    let j = Vector3::new(
                        rng.random_range(-3.0..3.0),
                        rng.random_range(-3.0..3.0),
                        0.0,
                    );
                    let eye = Point3::from(base + j + Vector3::new(0.0, 0.0, 30.0));
                    let target = Point3::from(base + j + Vector3::new(0.0, h * 25.0, 0.0));
                    poses.push(look_at(&eye, &target, &Vector3::z()).unwrap());
                    targets.push(target);
                    truth.push((site, heading));
                }
            }
        }
        (poses, targets, truth)
    }

    #[test]
    fn two_stage_groups_recover_sites_and_headings() {
        let (poses, targets, truth) = layout(3);
        let g = PoseGroups::build(&poses, &targets, &GroupConfig::default()).unwrap();
        assert_eq!(g.num_spatial, 4);
        assert_eq!(g.len(), 8);
        for i in 0..poses.len() {
            for j in 0..poses.len() {
                assert_eq!(g.labels[i] == g.labels[j], truth[i] == truth[j], "{i} {j}");
            }
        }
        // Every pose exactly once, medoids are members, assign() agrees with the labels.
        let mut all: Vec<usize> = g.groups.iter().flat_map(|x| x.members.clone()).collect();
        all.sort_unstable();
        assert_eq!(all, (0..poses.len()).collect::<Vec<_>>());
        for grp in &g.groups {
            assert!(grp.members.contains(&grp.medoid));
            assert_eq!(grp.coarse_pose, poses[grp.medoid]);
        }
        for (i, p) in poses.iter().enumerate() {
            assert_eq!(g.assign(p), Some(g.labels[i]));
        }
    }

    #[test]
    fn groups_are_deterministic_by_seed() {
        let (poses, targets, _) = layout(9);
        let cfg = GroupConfig {
            spatial_radius_m: Some(40.0),
            seed: 5,
            ..GroupConfig::default()
        };
        let a = PoseGroups::build(&poses, &targets, &cfg).unwrap();
        let b = PoseGroups::build(&poses, &targets, &cfg).unwrap();
        assert_eq!(a, b);
        assert_eq!(
            serde_json::to_string(&a).unwrap(),
            serde_json::to_string(&b).unwrap()
        );
    }

    #[test]
    fn group_count_follows_the_radius() {
        let (poses, targets, _) = layout(1);
        // A radius covering the whole layout leaves one spatial cluster (two headings).
        let wide = GroupConfig {
            spatial_radius_m: Some(500.0),
            ..GroupConfig::default()
        };
        let g = PoseGroups::build(&poses, &targets, &wide).unwrap();
        assert_eq!((g.num_spatial, g.len()), (1, 2));
        // A tolerant angle merges the headings too.
        let g = PoseGroups::build(
            &poses,
            &targets,
            &GroupConfig {
                max_angle_deg: 180.0,
                ..wide
            },
        )
        .unwrap();
        assert_eq!(g.len(), 1);
        // min_group_size caps the count.
        let tight = GroupConfig {
            spatial_radius_m: Some(0.01),
            min_group_size: 12,
            ..GroupConfig::default()
        };
        let g = PoseGroups::build(&poses, &targets, &tight).unwrap();
        assert!(g.num_spatial <= 4);
    }

    #[test]
    fn bad_input() {
        let (mut poses, targets, _) = layout(0);
        assert!(matches!(
            PoseGroups::build(&poses[..1], &targets[..1], &GroupConfig::default()),
            Err(PlaceError::TooFewPoses { poses: 1, .. })
        ));
        poses[5].translation.vector.y = f64::INFINITY;
        assert!(matches!(
            PoseGroups::build(&poses, &targets, &GroupConfig::default()),
            Err(PlaceError::NonFinitePose { index: 5 })
        ));
        assert!(matches!(
            PoseGroups::build(&poses, &[], &GroupConfig::default()),
            Err(PlaceError::NonFinitePose { .. } | PlaceError::InvalidConfig { .. })
        ));
    }

    #[test]
    fn blocks_attach_by_majority() {
        let (poses, targets, _) = layout(2);
        let mut g = PoseGroups::build(&poses, &targets, &GroupConfig::default()).unwrap();
        g.attach_blocks(|i| Some(i / 12));
        for grp in &g.groups {
            assert_eq!(grp.block, Some(grp.members[0] / 12));
        }
    }
}
