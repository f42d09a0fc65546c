//! Partition behaviour on hand-made layouts and the `tiny` synthetic world.

use matloc_core::pose::Pose;
use matloc_data::Split;
use matloc_partition::cluster::size_bounds;
use matloc_partition::{
    GridConfig, GridPartitioner, Method, PartitionError, Partitioner, PoseAwareConfig,
    PoseAwarePartitioner, PoseSamples, SampleConfig, SurfaceRay, SurfaceSource, assign_pose,
    mean_num_nerf, num_nerf, read_partition, sample_pose, write_partition,
};
use matloc_synth::{SynthConfig, World, generate};
use nalgebra::{Point2, Point3, Vector3};

struct WorldSurface<'a>(&'a World);

impl SurfaceSource for WorldSurface<'_> {
    fn surface_distance(&self, ray: &SurfaceRay) -> Option<f64> {
        self.0.raycast(&ray.origin, &ray.dir).map(|h| h.t)
    }
}

struct Tiny {
    train: Vec<PoseSamples>,
    test: Vec<PoseSamples>,
    /// Ground point seen by the image centre of each train pose.
    train_centers: Vec<Point3<f64>>,
}

fn tiny() -> Tiny {
    let cfg = SynthConfig::preset("tiny").unwrap();
    let (world, plan) = generate(&cfg).unwrap();
    let surface = WorldSurface(&world);
    let sc = SampleConfig::default();
    let (mut train, mut test, mut train_centers) = (Vec::new(), Vec::new(), Vec::new());
    for (i, f) in plan.frames.iter().enumerate() {
        let s = sample_pose(i, &f.camera, &f.cam_from_world, &surface, &sc).unwrap();
        match f.split {
            Split::Train => {
                let c = Point2::new(f.camera.width as f64 / 2.0, f.camera.height as f64 / 2.0);
                let b = f.camera.unproject(c).unwrap();
                let dir = f.cam_from_world.inverse().transform_vector(&b);
                let hit = world.raycast(&f.center(), &dir).unwrap();
                train_centers.push(hit.point);
                train.push(s);
            }
            _ => test.push(s),
        }
    }
    Tiny {
        train,
        test,
        train_centers,
    }
}

fn pose_aware(target: usize, seed: u64) -> PoseAwarePartitioner {
    PoseAwarePartitioner {
        config: PoseAwareConfig {
            target_size: target,
            seed,
            ..PoseAwareConfig::default()
        },
    }
}

#[test]
fn pose_aware_on_tiny_world() {
    let t = tiny();
    let n = t.train.len();
    assert!(n >= 30, "tiny preset has {n} train poses");
    let part = pose_aware(12, 3).partition(&t.train).unwrap();
    let k = n.div_ceil(12);
    assert_eq!(part.blocks.len(), k);
    assert_eq!(part.method, Method::PoseAware);

    // Every pose in exactly one block.
    let mut all: Vec<usize> = part
        .blocks
        .iter()
        .flat_map(|b| b.pose_ids.clone())
        .collect();
    all.sort_unstable();
    let mut expected: Vec<usize> = t.train.iter().map(|p| p.id).collect();
    expected.sort_unstable();
    assert_eq!(all, expected);

    // Sizes within the balance tolerance of the mean block size.
    let (lo, hi) = size_bounds(n, k, 0.25);
    for s in part.block_sizes() {
        assert!((lo..=hi).contains(&s), "block of {s} outside {lo}..={hi}");
    }

    // Num_NeRF(P) = 1 for every training and test pose.
    assert!(t.train.iter().all(|p| num_nerf(&part, p) == 1));
    assert_eq!(mean_num_nerf(&part, &t.train), 1.0);
    assert_eq!(mean_num_nerf(&part, &t.test), 1.0);

    // Every block's box holds nearly all of its members' samples, and has a positive volume.
    for b in &part.blocks {
        assert!(b.sampling_volume_m3 > 0.0);
        let members: Vec<&PoseSamples> = t
            .train
            .iter()
            .filter(|p| b.pose_ids.contains(&p.id))
            .collect();
        let total: usize = members.iter().map(|p| p.points.len()).sum();
        let inside: usize = members
            .iter()
            .map(|p| p.points.iter().filter(|q| b.bounds.contains(q)).count())
            .sum();
        assert!(inside as f64 >= 0.95 * total as f64, "{inside}/{total}");
    }

    // Poses that look at the same ground share a block far more often than chance.
    let label = |id: usize| part.block_of_member(id).unwrap();
    let (mut close, mut close_same, mut all_pairs, mut all_same) = (0, 0, 0, 0);
    for i in 0..n {
        for j in i + 1..n {
            let same = label(t.train[i].id) == label(t.train[j].id);
            all_pairs += 1;
            all_same += usize::from(same);
            if (t.train_centers[i] - t.train_centers[j]).xy().norm() < 8.0 {
                close += 1;
                close_same += usize::from(same);
            }
        }
    }
    let chance = all_same as f64 / all_pairs as f64;
    let rate = close_same as f64 / close.max(1) as f64;
    assert!(close >= 10, "only {close} co-visible pairs");
    assert!(
        rate > 2.0 * chance,
        "co-visible pairs share a block at {rate:.2}, chance {chance:.2}"
    );

    // A grid with as many blocks needs more than one sub-NeRF for some poses.
    let grid = GridPartitioner {
        config: GridConfig {
            kx: 2,
            ky: 2,
            ..GridConfig::default()
        },
    }
    .partition(&t.train)
    .unwrap();
    let g = mean_num_nerf(&grid, &t.test);
    assert!(g >= 1.0, "{g}");
    assert!(mean_num_nerf(&grid, &t.train) > 1.0);
}

#[test]
fn clustering_is_deterministic_by_seed() {
    let t = tiny();
    let a = pose_aware(10, 11).partition(&t.train).unwrap();
    let b = pose_aware(10, 11).partition(&t.train).unwrap();
    assert_eq!(a, b);
    let json = serde_json::to_string(&a).unwrap();
    assert_eq!(json, serde_json::to_string(&b).unwrap());
}

#[test]
fn unseen_pose_goes_to_the_block_that_holds_its_samples() {
    let t = tiny();
    let part = pose_aware(12, 0).partition(&t.train).unwrap();
    for p in t.train.iter().step_by(5) {
        let mut copy = p.clone();
        copy.id = 10_000 + p.id;
        let own = part.block_of_member(p.id).unwrap();
        let got = assign_pose(&part, &copy).unwrap();
        // The copy's voxels all lie in its twin's block, so that block wins unless another
        // block covers the same voxels too.
        let b = &part.blocks[got];
        let ids: Vec<u64> = copy
            .points
            .iter()
            .filter_map(|q| part.voxel_grid.voxel_of(q))
            .collect();
        let inside = ids
            .iter()
            .filter(|v| b.voxels.binary_search(v).is_ok())
            .count();
        assert_eq!(inside, ids.len(), "pose {} (own block {own})", p.id);
    }
}

fn pose_with(id: usize, points: Vec<Point3<f64>>) -> PoseSamples {
    PoseSamples {
        id,
        cam_from_world: Pose::identity(),
        points,
    }
}

#[test]
fn grid_partition_on_a_known_layout() {
    // Scene box [0, 100]² × [0, 10]: centroids at (25, 25), (75, 25), (25, 75), (75, 75).
    let corners = pose_with(
        0,
        vec![Point3::new(0.0, 0.0, 0.0), Point3::new(100.0, 100.0, 10.0)],
    );
    let only_first = pose_with(
        1,
        vec![Point3::new(10.0, 10.0, 5.0), Point3::new(45.0, 25.0, 5.0)],
    );
    let border = pose_with(2, vec![Point3::new(49.0, 25.0, 5.0)]);
    let center = pose_with(3, vec![Point3::new(50.0, 50.0, 5.0)]);
    let far_side = pose_with(4, vec![Point3::new(90.0, 90.0, 5.0)]);
    let poses = vec![corners, only_first, border, center, far_side];
    let part = GridPartitioner::default().partition(&poses).unwrap();
    assert_eq!(part.method, Method::Grid);
    let c: Vec<[f64; 2]> = part
        .blocks
        .iter()
        .map(|b| [b.centroid[0], b.centroid[1]])
        .collect();
    assert_eq!(
        c,
        vec![[25.0, 25.0], [75.0, 25.0], [25.0, 75.0], [75.0, 75.0]]
    );

    // (45, 25): 20 m to block 0, 30 m to block 1 > 1.15 × 20 → block 0 only.
    assert_eq!(num_nerf(&part, &poses[1]), 1);
    // (49, 25): 24 m vs 26 m ≤ 1.15 × 24 → blocks 0 and 1.
    assert_eq!(num_nerf(&part, &poses[2]), 2);
    // The centre is equidistant to all four.
    assert_eq!(num_nerf(&part, &poses[3]), 4);
    assert_eq!(num_nerf(&part, &poses[4]), 1);
    assert_eq!(part.blocks[0].pose_ids, vec![0, 1, 2, 3]);
    assert_eq!(part.blocks[1].pose_ids, vec![2, 3]);
    assert_eq!(part.blocks[2].pose_ids, vec![3]);
    assert_eq!(part.blocks[3].pose_ids, vec![0, 3, 4]);
    assert_eq!(assign_pose(&part, &poses[4]), Some(3));
    let mean = mean_num_nerf(&part, &poses[1..]);
    assert!((mean - 2.0).abs() < 1e-12, "{mean}");
}

#[test]
fn bad_input_gives_typed_errors() {
    let ok = |id| pose_with(id, vec![Point3::new(id as f64, 0.0, 0.0)]);
    let few = PoseAwarePartitioner {
        config: PoseAwareConfig {
            num_blocks: Some(5),
            ..PoseAwareConfig::default()
        },
    };
    assert!(matches!(
        few.partition(&[ok(0), ok(1), ok(2)]),
        Err(PartitionError::TooFewPoses {
            poses: 3,
            blocks: 5
        })
    ));
    assert!(matches!(
        pose_aware(10, 0).partition(&[]),
        Err(PartitionError::TooFewPoses { poses: 0, .. })
    ));

    let mut nan_pose = ok(1);
    nan_pose.cam_from_world.translation.vector = Vector3::new(f64::NAN, 0.0, 0.0);
    let partitioners: [&dyn Partitioner; 2] = [&pose_aware(2, 0), &GridPartitioner::default()];
    for p in partitioners {
        assert!(matches!(
            p.partition(&[ok(0), nan_pose.clone(), ok(2)]),
            Err(PartitionError::NonFinitePose { index: 1 })
        ));
        assert!(matches!(
            p.partition(&[ok(0), ok(1), pose_with(2, vec![])]),
            Err(PartitionError::EmptySamples { index: 2 })
        ));
        assert!(matches!(
            p.partition(&[
                pose_with(0, vec![Point3::new(f64::INFINITY, 0.0, 0.0)]),
                ok(1)
            ]),
            Err(PartitionError::NonFiniteSample { index: 0 })
        ));
    }
    let zero_grid = GridPartitioner {
        config: GridConfig {
            kx: 0,
            ..GridConfig::default()
        },
    };
    assert!(matches!(
        zero_grid.partition(&[ok(0)]),
        Err(PartitionError::InvalidConfig { field: "grid", .. })
    ));
}

#[test]
fn partition_file_round_trip() {
    let t = tiny();
    let part = pose_aware(20, 1).partition(&t.train).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("partition.json");
    write_partition(&path, &part).unwrap();
    assert_eq!(read_partition(&path).unwrap(), part);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    v["version"] = 99.into();
    std::fs::write(&path, serde_json::to_vec(&v).unwrap()).unwrap();
    assert!(matches!(
        read_partition(&path),
        Err(PartitionError::UnsupportedVersion { found: 99, .. })
    ));
    std::fs::write(&path, b"{").unwrap();
    assert!(matches!(
        read_partition(&path),
        Err(PartitionError::Json { .. })
    ));
}
