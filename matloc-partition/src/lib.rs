//! Scene partitions for large-scale NeRF maps (paper Section 3.2, Tables 5–6).
//!
//! Every training pose becomes a cloud of sample points along its camera rays up to the surface
//! ([`samples`]); the points fall into a global voxel grid, giving each pose a set of occupied
//! voxels ([`voxel`]). The **pose-aware** partition ([`PoseAwarePartitioner`]) clusters poses by
//! `1 − Jaccard` of those sets into size-balanced blocks ([`cluster`]); all samples of a pose go
//! to its block, so `Num_NeRF(P) = 1`. The **Mega-NeRF grid** baseline ([`GridPartitioner`])
//! sends each sample point to every ground-grid centroid within the overlap factor of its
//! nearest one, so one pose may need several sub-NeRFs. [`num_nerf`] counts them for any
//! partition and pose, training or unseen.

pub mod aabb;
pub mod cluster;
pub mod error;
pub mod partition;
pub mod samples;
pub mod voxel;

pub use aabb::Aabb;
pub use error::PartitionError;
pub use partition::{
    Block, GridConfig, GridPartitioner, Method, MethodConfig, PARTITION_VERSION, Partition,
    Partitioner, PoseAwareConfig, PoseAwarePartitioner, assign_pose, coverage, mean_num_nerf,
    num_nerf, read_partition, write_partition,
};
pub use samples::{
    DepthMapSurface, PoseSamples, SampleConfig, SkyPolicy, SurfaceRay, SurfaceSource, sample_pose,
    samples_from_dataset,
};
pub use voxel::{Occupancy, VoxelGrid, jaccard_distance, weighted_jaccard_distance};
