//! Partition types, the [`Partitioner`] trait, both partitioners, `Num_NeRF(P)` and file I/O.

use std::path::Path;

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::aabb::Aabb;
use crate::cluster::{DistanceMatrix, KMedoidsConfig, balanced_k_medoids};
use crate::error::PartitionError;
use crate::samples::{PoseSamples, pose_is_finite};
use crate::voxel::{Occupancy, VoxelGrid, jaccard_distance, weighted_jaccard_distance};

/// Format version written into every partition file.
pub const PARTITION_VERSION: u32 = 1;

/// Which partition strategy made a [`Partition`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Poses clustered by voxel-occupancy overlap; one block per pose.
    PoseAware,
    /// Mega-NeRF's ground grid of centroids with overlap.
    Grid,
}

/// Settings of [`PoseAwarePartitioner`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseAwareConfig {
    /// Poses per block (the paper uses 150); the block count is `ceil(N / target_size)`.
    pub target_size: usize,
    /// Overrides the block count when set.
    pub num_blocks: Option<usize>,
    /// Voxel edge, metres.
    pub voxel_size: f64,
    /// Allowed deviation of a block's size from the mean block size, relative.
    pub balance_tolerance: f64,
    /// Use count-weighted Jaccard instead of set Jaccard.
    pub weighted: bool,
    /// Weight of the tie-break term: distance between the poses' mean sample points divided by
    /// the scene diagonal. Jaccard is 1 for every pair that shares no voxel, which leaves the
    /// assignment of far poses arbitrary; this term keeps blocks spatially compact.
    pub centroid_weight: f64,
    /// Clustering seed.
    pub seed: u64,
    /// Clustering restarts.
    pub restarts: usize,
    /// Clustering rounds per restart.
    pub max_iter: usize,
    /// Percentage of a block's sample points farthest from their camera left out of its box.
    pub bounds_percentile: f64,
    /// Margin added on every side of a block's box, metres.
    pub bounds_margin_m: f64,
}

impl Default for PoseAwareConfig {
    fn default() -> Self {
        PoseAwareConfig {
            target_size: 150,
            num_blocks: None,
            voxel_size: 3.0,
            balance_tolerance: 0.25,
            weighted: false,
            centroid_weight: 0.05,
            seed: 0,
            restarts: 4,
            max_iter: 30,
            bounds_percentile: 1.0,
            bounds_margin_m: 2.0,
        }
    }
}

/// Settings of [`GridPartitioner`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GridConfig {
    /// Centroids along x.
    pub kx: usize,
    /// Centroids along y.
    pub ky: usize,
    /// A point belongs to every centroid within `overlap ×` its nearest centroid's distance.
    pub overlap: f64,
    /// Voxel edge used for the occupied-volume report, metres.
    pub voxel_size: f64,
    /// Percentage of a block's sample points farthest from their camera left out of its box.
    pub bounds_percentile: f64,
    /// Margin added on every side of a block's box, metres.
    pub bounds_margin_m: f64,
}

impl Default for GridConfig {
    fn default() -> Self {
        GridConfig {
            kx: 2,
            ky: 2,
            overlap: 1.15,
            voxel_size: 3.0,
            bounds_percentile: 1.0,
            bounds_margin_m: 2.0,
        }
    }
}

/// The settings a partition was made with.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "kebab-case")]
pub enum MethodConfig {
    /// See [`PoseAwareConfig`].
    PoseAware(PoseAwareConfig),
    /// See [`GridConfig`].
    Grid(GridConfig),
}

/// One sub-NeRF's share of the scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Block {
    /// Block index (position in [`Partition::blocks`]).
    pub id: usize,
    /// Poses (their [`PoseSamples::id`]) the block serves. Pose-aware: each pose in exactly one
    /// block; grid: every pose with a sample in the block.
    pub pose_ids: Vec<usize>,
    /// Pose-aware: mean of the members' sample points; grid: the grid centroid.
    pub centroid: [f64; 3],
    /// The sub-NeRF's scene box: the block's sample points without the farthest
    /// `bounds_percentile` % from their camera, plus a margin.
    pub bounds: Aabb,
    /// Volume of `bounds`, m³ (the paper's "sampling space" of a sub-block, Table 6).
    pub sampling_volume_m3: f64,
    /// Volume of the voxels the block's samples occupy, m³.
    pub occupied_volume_m3: f64,
    /// Occupied voxel ids (pose-aware only): lets unseen poses be assigned without samples of
    /// the training poses.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub voxels: Vec<u64>,
}

/// A partition of the scene into sub-NeRF blocks.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Partition {
    /// File format version ([`PARTITION_VERSION`]).
    pub version: u32,
    /// Strategy.
    pub method: Method,
    /// Settings of the strategy.
    pub config: MethodConfig,
    /// Voxel edge, metres.
    pub voxel_size: f64,
    /// Box of all training sample points.
    pub scene_bounds: Aabb,
    /// The voxel grid block voxel ids refer to.
    pub voxel_grid: VoxelGrid,
    /// Number of training poses partitioned.
    pub num_poses: usize,
    /// The blocks.
    pub blocks: Vec<Block>,
}

impl Partition {
    /// Block sizes (poses per block).
    pub fn block_sizes(&self) -> Vec<usize> {
        self.blocks.iter().map(|b| b.pose_ids.len()).collect()
    }

    /// Block that lists pose `id` as a member (the first one for grid partitions).
    pub fn block_of_member(&self, id: usize) -> Option<usize> {
        self.blocks
            .iter()
            .position(|b| b.pose_ids.binary_search(&id).is_ok())
    }
}

/// Splits a scene into sub-NeRF blocks from the training poses and their sample points.
pub trait Partitioner {
    /// Short name of the strategy.
    fn name(&self) -> &'static str;
    /// Partitions `poses` (ids must be unique).
    fn partition(&self, poses: &[PoseSamples]) -> Result<Partition, PartitionError>;
}

fn check_input(poses: &[PoseSamples], blocks: usize) -> Result<(), PartitionError> {
    if poses.len() < blocks.max(1) {
        return Err(PartitionError::TooFewPoses {
            poses: poses.len(),
            blocks: blocks.max(1),
        });
    }
    for (index, p) in poses.iter().enumerate() {
        if !pose_is_finite(&p.cam_from_world) {
            return Err(PartitionError::NonFinitePose { index });
        }
        if p.points.is_empty() {
            return Err(PartitionError::EmptySamples { index });
        }
        if !p
            .points
            .iter()
            .all(|q| q.coords.iter().all(|v| v.is_finite()))
        {
            return Err(PartitionError::NonFiniteSample { index });
        }
    }
    let mut ids: Vec<usize> = poses.iter().map(|p| p.id).collect();
    ids.sort_unstable();
    if ids.windows(2).any(|w| w[0] == w[1]) {
        return Err(PartitionError::Inconsistent(
            "pose ids are not unique".into(),
        ));
    }
    Ok(())
}

fn check_bounds_settings(percentile: f64, margin: f64) -> Result<(), PartitionError> {
    if !(percentile.is_finite() && (0.0..50.0).contains(&percentile)) {
        return Err(PartitionError::InvalidConfig {
            field: "bounds_percentile",
            reason: format!("must be in [0, 50), got {percentile}"),
        });
    }
    if !(margin.is_finite() && margin >= 0.0) {
        return Err(PartitionError::InvalidConfig {
            field: "bounds_margin_m",
            reason: format!("must be finite and >= 0, got {margin}"),
        });
    }
    Ok(())
}

/// Robust box of a block's sample points: the farthest `percentile` % of the points from their
/// own camera centre (far terrain seen at grazing angles) are left out, the box holds the rest,
/// plus `margin`. Trimming per coordinate instead cut the low ground out of an aerial block (on
/// `small` a block's floor sat 5.5 m above its lowest terrain: most sample points are in the air
/// above the ground, so the 1 % z-quantile is not the ground) and the sub-NeRF could not model
/// those views (median depth error 50–60 %).
fn robust_bounds(points: &[(&Point3<f64>, Point3<f64>)], percentile: f64, margin: f64) -> Aabb {
    let stride = points.len().div_ceil(200_000).max(1);
    let mut dist: Vec<f64> = points
        .iter()
        .step_by(stride)
        .map(|(p, c)| (*p - c).norm())
        .collect();
    let mut b = Aabb {
        min: [0.0; 3],
        max: [0.0; 3],
    };
    if dist.is_empty() {
        return b;
    }
    let n = dist.len();
    let hi_i = (((100.0 - percentile) / 100.0) * (n - 1) as f64).ceil() as usize;
    let limit = *dist
        .select_nth_unstable_by(hi_i.min(n - 1), f64::total_cmp)
        .1;
    b.min = [f64::INFINITY; 3];
    b.max = [f64::NEG_INFINITY; 3];
    for (p, c) in points {
        if (*p - c).norm() <= limit {
            for a in 0..3 {
                b.min[a] = b.min[a].min(p[a]);
                b.max[a] = b.max[a].max(p[a]);
            }
        }
    }
    for a in 0..3 {
        b.min[a] -= margin;
        b.max[a] += margin;
    }
    b
}

fn scene_box(poses: &[PoseSamples]) -> Aabb {
    Aabb::of_points(poses.iter().flat_map(|p| p.points.iter())).unwrap_or(Aabb {
        min: [0.0; 3],
        max: [0.0; 3],
    })
}

fn mean_of(points: &[&Point3<f64>]) -> [f64; 3] {
    let n = points.len().max(1) as f64;
    let s = points
        .iter()
        .fold(nalgebra::Vector3::zeros(), |acc, p| acc + p.coords);
    [s.x / n, s.y / n, s.z / n]
}

/// The pose-aware partition (paper Section 3.2).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PoseAwarePartitioner {
    /// Settings.
    pub config: PoseAwareConfig,
}

impl PoseAwarePartitioner {
    /// Number of blocks for `n` poses.
    pub fn num_blocks(&self, n: usize) -> usize {
        self.config
            .num_blocks
            .unwrap_or_else(|| n.div_ceil(self.config.target_size.max(1)))
            .max(1)
    }
}

impl Partitioner for PoseAwarePartitioner {
    fn name(&self) -> &'static str {
        "pose-aware"
    }

    fn partition(&self, poses: &[PoseSamples]) -> Result<Partition, PartitionError> {
        let cfg = &self.config;
        if cfg.target_size == 0 {
            return Err(PartitionError::InvalidConfig {
                field: "target_size",
                reason: "must be at least 1".into(),
            });
        }
        if !(cfg.centroid_weight.is_finite() && cfg.centroid_weight >= 0.0) {
            return Err(PartitionError::InvalidConfig {
                field: "centroid_weight",
                reason: format!("must be finite and >= 0, got {}", cfg.centroid_weight),
            });
        }
        check_bounds_settings(cfg.bounds_percentile, cfg.bounds_margin_m)?;
        let k = self.num_blocks(poses.len());
        check_input(poses, k)?;
        let scene = scene_box(poses);
        let grid = VoxelGrid::covering(&scene, cfg.voxel_size)?;
        let occ: Vec<Occupancy> = {
            use rayon::prelude::*;
            poses
                .par_iter()
                .map(|p| grid.occupancy(&p.points))
                .collect()
        };
        let means: Vec<Point3<f64>> = poses
            .iter()
            .map(|p| p.mean_point().unwrap_or_else(Point3::origin))
            .collect();
        let diag = (0..3)
            .map(|a| (scene.max[a] - scene.min[a]).powi(2))
            .sum::<f64>()
            .sqrt()
            .max(1e-9);
        let dist = DistanceMatrix::from_fn(poses.len(), |i, j| {
            let jd = if cfg.weighted {
                weighted_jaccard_distance(&occ[i], &occ[j])
            } else {
                jaccard_distance(&occ[i].ids, &occ[j].ids)
            };
            jd + cfg.centroid_weight * (means[i] - means[j]).norm() / diag
        });
        let clustering = balanced_k_medoids(
            &dist,
            &KMedoidsConfig {
                k,
                tolerance: cfg.balance_tolerance,
                seed: cfg.seed,
                restarts: cfg.restarts,
                max_iter: cfg.max_iter,
            },
        )?;
        let vox_vol = cfg.voxel_size.powi(3);
        let blocks = (0..k)
            .map(|b| {
                let members: Vec<usize> = (0..poses.len())
                    .filter(|&i| clustering.labels[i] == b)
                    .collect();
                let pts: Vec<&Point3<f64>> = members
                    .iter()
                    .flat_map(|&i| poses[i].points.iter())
                    .collect();
                let with_centres: Vec<(&Point3<f64>, Point3<f64>)> = members
                    .iter()
                    .flat_map(|&i| {
                        let c = poses[i].center();
                        poses[i].points.iter().map(move |q| (q, c))
                    })
                    .collect();
                let bounds =
                    robust_bounds(&with_centres, cfg.bounds_percentile, cfg.bounds_margin_m);
                let union = Occupancy::union(members.iter().map(|&i| &occ[i]));
                let mut pose_ids: Vec<usize> = members.iter().map(|&i| poses[i].id).collect();
                pose_ids.sort_unstable();
                Block {
                    id: b,
                    pose_ids,
                    centroid: mean_of(&pts),
                    sampling_volume_m3: bounds.volume(),
                    bounds,
                    occupied_volume_m3: union.len() as f64 * vox_vol,
                    voxels: union.ids,
                }
            })
            .collect();
        Ok(Partition {
            version: PARTITION_VERSION,
            method: Method::PoseAware,
            config: MethodConfig::PoseAware(*cfg),
            voxel_size: cfg.voxel_size,
            scene_bounds: scene,
            voxel_grid: grid,
            num_poses: poses.len(),
            blocks,
        })
    }
}

/// Mega-NeRF's grid partition: `kx × ky` centroids at the cell centres of a ground grid over
/// the scene box; distances are measured in the ground plane (x, y), so blocks are vertical
/// columns with overlapping borders.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GridPartitioner {
    /// Settings.
    pub config: GridConfig,
}

/// Blocks that point `p` belongs to under the overlap rule, appended to `out` (cleared first).
fn grid_members(blocks: &[Block], overlap: f64, p: &Point3<f64>, out: &mut Vec<usize>) {
    out.clear();
    let d2 = |b: &Block| (p.x - b.centroid[0]).powi(2) + (p.y - b.centroid[1]).powi(2);
    let nearest = blocks.iter().map(d2).fold(f64::INFINITY, f64::min);
    // Compare squared distances: d ≤ f·d_min ⇔ d² ≤ f²·d_min².
    let limit = overlap * overlap * nearest;
    out.extend(
        blocks
            .iter()
            .enumerate()
            .filter(|(_, b)| d2(b) <= limit)
            .map(|(i, _)| i),
    );
}

fn nearest_grid_block(blocks: &[Block], p: &Point3<f64>) -> Option<usize> {
    blocks
        .iter()
        .enumerate()
        .map(|(i, b)| {
            (
                i,
                (p.x - b.centroid[0]).powi(2) + (p.y - b.centroid[1]).powi(2),
            )
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

impl Partitioner for GridPartitioner {
    fn name(&self) -> &'static str {
        "grid"
    }

    fn partition(&self, poses: &[PoseSamples]) -> Result<Partition, PartitionError> {
        let cfg = &self.config;
        if cfg.kx == 0 || cfg.ky == 0 {
            return Err(PartitionError::InvalidConfig {
                field: "grid",
                reason: format!(
                    "needs at least one centroid per axis, got {}x{}",
                    cfg.kx, cfg.ky
                ),
            });
        }
        if !(cfg.overlap.is_finite() && cfg.overlap >= 1.0) {
            return Err(PartitionError::InvalidConfig {
                field: "overlap",
                reason: format!("must be finite and >= 1, got {}", cfg.overlap),
            });
        }
        check_bounds_settings(cfg.bounds_percentile, cfg.bounds_margin_m)?;
        // A grid block needs no minimum number of poses; only the input itself is checked.
        check_input(poses, 1)?;
        let scene = scene_box(poses);
        let grid = VoxelGrid::covering(&scene, cfg.voxel_size)?;
        let zc = 0.5 * (scene.min[2] + scene.max[2]);
        let mut blocks: Vec<Block> = Vec::with_capacity(cfg.kx * cfg.ky);
        for iy in 0..cfg.ky {
            for ix in 0..cfg.kx {
                let cx = scene.min[0]
                    + (ix as f64 + 0.5) * (scene.max[0] - scene.min[0]) / cfg.kx as f64;
                let cy = scene.min[1]
                    + (iy as f64 + 0.5) * (scene.max[1] - scene.min[1]) / cfg.ky as f64;
                blocks.push(Block {
                    id: blocks.len(),
                    pose_ids: Vec::new(),
                    centroid: [cx, cy, zc],
                    bounds: scene,
                    sampling_volume_m3: 0.0,
                    occupied_volume_m3: 0.0,
                    voxels: Vec::new(),
                });
            }
        }
        let nb = blocks.len();
        let mut block_points: Vec<Vec<(&Point3<f64>, Point3<f64>)>> = vec![Vec::new(); nb];
        let mut members = Vec::new();
        for p in poses {
            let mut hit = vec![false; nb];
            let c = p.center();
            for q in &p.points {
                grid_members(&blocks, cfg.overlap, q, &mut members);
                for &b in &members {
                    hit[b] = true;
                    block_points[b].push((q, c));
                }
            }
            for (b, h) in hit.into_iter().enumerate() {
                if h {
                    blocks[b].pose_ids.push(p.id);
                }
            }
        }
        let vox_vol = cfg.voxel_size.powi(3);
        for (b, pts) in blocks.iter_mut().zip(&block_points) {
            b.pose_ids.sort_unstable();
            if !pts.is_empty() {
                b.bounds = robust_bounds(pts, cfg.bounds_percentile, cfg.bounds_margin_m);
                b.sampling_volume_m3 = b.bounds.volume();
                b.occupied_volume_m3 =
                    grid.occupancy(pts.iter().map(|(q, _)| *q)).len() as f64 * vox_vol;
            }
        }
        Ok(Partition {
            version: PARTITION_VERSION,
            method: Method::Grid,
            config: MethodConfig::Grid(*cfg),
            voxel_size: cfg.voxel_size,
            scene_bounds: scene,
            voxel_grid: grid,
            num_poses: poses.len(),
            blocks,
        })
    }
}

/// The block that serves a pose as a whole.
///
/// Pose-aware: a member pose's own block; any other pose goes to the block whose occupied voxels
/// hold the largest share of its sample points (containment rather than Jaccard, which would
/// favour small blocks over the block that actually covers the pose), ties and zero overlap
/// broken by the nearest block centroid. Grid: the block nearest to most of its samples.
/// `None` for a pose without samples.
pub fn assign_pose(partition: &Partition, samples: &PoseSamples) -> Option<usize> {
    if samples.points.is_empty() || partition.blocks.is_empty() {
        return None;
    }
    match partition.method {
        Method::PoseAware => {
            if let Some(b) = partition.block_of_member(samples.id) {
                return Some(b);
            }
            let ids: Vec<u64> = samples
                .points
                .iter()
                .filter_map(|p| partition.voxel_grid.voxel_of(p))
                .collect();
            let mean = samples.mean_point()?;
            let score = |b: &Block| {
                let inside = ids
                    .iter()
                    .filter(|id| b.voxels.binary_search(id).is_ok())
                    .count();
                let dc = (mean.coords - nalgebra::Vector3::from(b.centroid)).norm();
                (inside, dc)
            };
            partition
                .blocks
                .iter()
                .enumerate()
                .map(|(i, b)| (i, score(b)))
                .max_by(|a, b| {
                    (a.1.0)
                        .cmp(&b.1.0)
                        .then(b.1.1.total_cmp(&a.1.1))
                        .then(b.0.cmp(&a.0))
                })
                .map(|(i, _)| i)
        }
        Method::Grid => {
            let mut votes = vec![0usize; partition.blocks.len()];
            for p in &samples.points {
                if let Some(b) = nearest_grid_block(&partition.blocks, p) {
                    votes[b] += 1;
                }
            }
            (0..votes.len()).max_by(|&a, &b| votes[a].cmp(&votes[b]).then(b.cmp(&a)))
        }
    }
}

/// `Num_NeRF(P)`: the number of sub-NeRFs that must be evaluated to render the pose's samples.
///
/// Pose-aware: 1 for any pose with samples (its samples all go to [`assign_pose`]'s block);
/// grid: the number of distinct blocks its samples belong to under the overlap rule. 0 for a
/// pose without samples.
pub fn num_nerf(partition: &Partition, samples: &PoseSamples) -> usize {
    match partition.method {
        Method::PoseAware => usize::from(assign_pose(partition, samples).is_some()),
        Method::Grid => {
            let overlap = match partition.config {
                MethodConfig::Grid(g) => g.overlap,
                MethodConfig::PoseAware(_) => 1.0,
            };
            let mut hit = vec![false; partition.blocks.len()];
            let mut members = Vec::new();
            for p in &samples.points {
                grid_members(&partition.blocks, overlap, p, &mut members);
                for &b in &members {
                    hit[b] = true;
                }
            }
            hit.into_iter().filter(|&h| h).count()
        }
    }
}

/// Mean `Num_NeRF(P)` over `poses` (0 for an empty set).
pub fn mean_num_nerf(partition: &Partition, poses: &[PoseSamples]) -> f64 {
    if poses.is_empty() {
        return 0.0;
    }
    poses
        .iter()
        .map(|p| num_nerf(partition, p) as f64)
        .sum::<f64>()
        / poses.len() as f64
}

/// Fraction of a pose's sample points inside the box of the block that serves them
/// (pose-aware: [`assign_pose`]'s block; grid: each point's nearest block). Tells whether a
/// sub-NeRF's scene box actually holds what an unseen pose needs.
pub fn coverage(partition: &Partition, samples: &PoseSamples) -> f64 {
    if samples.points.is_empty() {
        return 0.0;
    }
    let inside = match partition.method {
        Method::PoseAware => match assign_pose(partition, samples) {
            Some(b) => {
                let bx = &partition.blocks[b].bounds;
                samples.points.iter().filter(|p| bx.contains(p)).count()
            }
            None => 0,
        },
        Method::Grid => samples
            .points
            .iter()
            .filter(|p| {
                nearest_grid_block(&partition.blocks, p)
                    .is_some_and(|b| partition.blocks[b].bounds.contains(p))
            })
            .count(),
    };
    inside as f64 / samples.points.len() as f64
}

/// Writes a partition as pretty JSON, atomically.
pub fn write_partition(path: &Path, partition: &Partition) -> Result<(), PartitionError> {
    let bytes = serde_json::to_vec_pretty(partition).map_err(|source| PartitionError::Json {
        path: path.to_path_buf(),
        source,
    })?;
    matloc_core::fsutil::write_atomic(path, &bytes).map_err(|source| PartitionError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Reads a partition written by [`write_partition`], checking its version and block ids.
pub fn read_partition(path: &Path) -> Result<Partition, PartitionError> {
    let bytes = std::fs::read(path).map_err(|source| PartitionError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let p: Partition = serde_json::from_slice(&bytes).map_err(|source| PartitionError::Json {
        path: path.to_path_buf(),
        source,
    })?;
    if p.version != PARTITION_VERSION {
        return Err(PartitionError::UnsupportedVersion {
            found: p.version,
            expected: PARTITION_VERSION,
        });
    }
    if p.blocks.iter().enumerate().any(|(i, b)| b.id != i) {
        return Err(PartitionError::Inconsistent(
            "block ids must equal their positions".into(),
        ));
    }
    if p.blocks.iter().any(|b| {
        !b.pose_ids.windows(2).all(|w| w[0] < w[1]) || !b.voxels.windows(2).all(|w| w[0] < w[1])
    }) {
        return Err(PartitionError::Inconsistent(
            "pose ids and voxel ids must be strictly increasing".into(),
        ));
    }
    Ok(p)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_keeps_sparse_low_ground_and_drops_far_points() {
        // Rays from a camera 40 m up: 200 to flat ground (z = 0), 10 to a pit 3 m deep
        // under the camera (0.5 % of the points), 3 to far terrain 500 m away; 8 air samples
        // per ray plus the surface point, as the partition's sampler makes them. Per-axis
        // 1 % quantiles put the floor above the pit.
        let cam = Point3::new(0.0, 0.0, 40.0);
        let mut surfaces: Vec<Point3<f64>> = (0..200)
            .map(|i| Point3::new(-40.0 + 0.4 * i as f64, (i % 7) as f64, 0.0))
            .collect();
        surfaces.extend((0..10).map(|i| Point3::new(i as f64 * 0.5, 0.0, -3.0)));
        surfaces.extend((0..3).map(|i| Point3::new(500.0, i as f64, 0.0)));
        let mut pts = Vec::new();
        for s in &surfaces {
            for k in 1..=8 {
                pts.push(cam + (s - cam) * (k as f64 / 9.0));
            }
            pts.push(*s);
        }
        let with: Vec<(&Point3<f64>, Point3<f64>)> = pts.iter().map(|p| (p, cam)).collect();
        let b = robust_bounds(&with, 1.0, 2.0);
        assert!(b.min[2] <= -5.0 + 1e-9, "the pit is inside: {b:?}");
        assert!(b.max[0] < 400.0, "the far terrain is outside: {b:?}");
    }
}
