//! `matloc partition`: split a dataset's scene into sub-NeRF blocks (pose-aware or Mega-NeRF
//! grid), write the partition JSON and a top-down plot, and report Num_NeRF(P).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use matloc_data::Split;
use matloc_partition::{
    GridConfig, GridPartitioner, Method, Partition, Partitioner, PoseAwareConfig,
    PoseAwarePartitioner, PoseSamples, SampleConfig, assign_pose, coverage, mean_num_nerf,
    write_partition,
};

use matloc_pipeline::build::partition::samples_on_surfaces;
use matloc_surface::{FrameSurfaces, SurfaceConfig};

use crate::plot;
use crate::progress;

/// Partition strategy on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum MethodArg {
    /// Cluster poses by voxel-occupancy overlap (one sub-NeRF per pose).
    PoseAware,
    /// Mega-NeRF ground grid with overlapping borders.
    Grid,
}

/// Arguments of `matloc partition`.
#[derive(Args, Debug)]
pub struct PartitionArgs {
    /// Dataset directory (needs depth maps, e.g. from `matloc synth`).
    #[arg(long)]
    data: PathBuf,
    /// Partition strategy.
    #[arg(long, value_enum, default_value = "pose-aware")]
    method: MethodArg,
    /// Training poses per block; also sets the grid size when --grid is not given.
    #[arg(long, default_value_t = 150)]
    target_size: usize,
    /// Grid centroids as KXxKY, e.g. 2x2 (grid method; default: as many blocks as pose-aware).
    #[arg(long)]
    grid: Option<String>,
    /// Overlap factor of the grid method.
    #[arg(long, default_value_t = 1.15)]
    overlap: f64,
    /// Voxel edge in metres.
    #[arg(long, default_value_t = 3.0)]
    voxel_size: f64,
    /// Use every Nth pixel as a ray.
    #[arg(long, default_value_t = 8)]
    stride: u32,
    /// Sample points per ray before the surface.
    #[arg(long, default_value_t = 8)]
    points_per_ray: usize,
    /// Use count-weighted Jaccard distances.
    #[arg(long)]
    weighted: bool,
    /// Clustering seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output JSON (default: DATA/partition-METHOD.json).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Output plot (default: the JSON path with .png).
    #[arg(long)]
    plot: Option<PathBuf>,
}

fn parse_grid(s: &str) -> Result<(usize, usize)> {
    let lower = s.to_ascii_lowercase();
    let (a, b) = lower
        .split_once('x')
        .with_context(|| format!("--grid expects KXxKY such as 2x2, got `{s}`"))?;
    let kx: usize = a
        .trim()
        .parse()
        .with_context(|| format!("bad --grid `{s}`"))?;
    let ky: usize = b
        .trim()
        .parse()
        .with_context(|| format!("bad --grid `{s}`"))?;
    if kx == 0 || ky == 0 || kx * ky > 10_000 {
        bail!("--grid needs 1..=10000 centroids, got {kx}x{ky}");
    }
    Ok((kx, ky))
}

/// A near-square grid of about `k` cells for a scene of extent `ex × ey`.
fn grid_for(k: usize, ex: f64, ey: f64) -> (usize, usize) {
    let k = k.max(1);
    let ky = ((k as f64 * ey / ex.max(1e-9)).sqrt().round() as usize).clamp(1, k);
    (k.div_ceil(ky), ky)
}

/// Runs the command.
pub fn run(args: &PartitionArgs, quiet: bool) -> Result<()> {
    let start = Instant::now();
    let dataset = matloc_data::read_dataset(&args.data)
        .with_context(|| format!("reading dataset {}", args.data.display()))?;
    let train_idx = dataset.split_indices(Split::Train);
    let test_idx = dataset.split_indices(Split::Test);
    if train_idx.is_empty() {
        bail!("{} has no training frames", args.data.display());
    }
    let sample_cfg = SampleConfig {
        pixel_stride: args.stride,
        points_per_ray: args.points_per_ray,
        ..SampleConfig::default()
    };
    let t0 = Instant::now();
    let bar = progress::bar((train_idx.len() + test_idx.len()) as u64, "sampling", quiet);
    // The surface of training views as a map build finds it; test views see the same points.
    let surfaces = FrameSurfaces::prepare(
        &dataset,
        &train_idx,
        &SurfaceConfig::default(),
        &|_, _, _| {},
    )?;
    tracing::info!(source = %surfaces.plan().kind, "partition surface");
    let train = samples_on_surfaces(&dataset, &train_idx, &surfaces, &sample_cfg, &|| bar.inc(1))?;
    let test = samples_on_surfaces(&dataset, &test_idx, &surfaces, &sample_cfg, &|| bar.inc(1))?;
    bar.finish_and_clear();
    let sample_secs = t0.elapsed().as_secs_f64();
    let n_points: usize = train.iter().map(|p| p.points.len()).sum();

    let pose_aware = PoseAwarePartitioner {
        config: PoseAwareConfig {
            target_size: args.target_size,
            voxel_size: args.voxel_size,
            weighted: args.weighted,
            seed: args.seed,
            ..PoseAwareConfig::default()
        },
    };
    let partitioner: Box<dyn Partitioner> = match args.method {
        MethodArg::PoseAware => Box::new(pose_aware),
        MethodArg::Grid => {
            let (kx, ky) = match &args.grid {
                Some(g) => parse_grid(g)?,
                None => {
                    let k = pose_aware.num_blocks(train.len());
                    let b = matloc_partition::Aabb::of_points(
                        train.iter().flat_map(|p| p.points.iter()),
                    )
                    .context("no sample points")?;
                    grid_for(k, b.max[0] - b.min[0], b.max[1] - b.min[1])
                }
            };
            Box::new(GridPartitioner {
                config: GridConfig {
                    kx,
                    ky,
                    overlap: args.overlap,
                    voxel_size: args.voxel_size,
                    ..GridConfig::default()
                },
            })
        }
    };
    let spinner = progress::bar(1, "partition", quiet);
    let t1 = Instant::now();
    let partition = partitioner.partition(&train)?;
    let part_secs = t1.elapsed().as_secs_f64();
    spinner.finish_and_clear();

    let t2 = Instant::now();
    let nn_train = mean_num_nerf(&partition, &train);
    let nn_test = mean_num_nerf(&partition, &test);
    let cov_test = if test.is_empty() {
        f64::NAN
    } else {
        test.iter().map(|p| coverage(&partition, p)).sum::<f64>() / test.len() as f64
    };
    let eval_secs = t2.elapsed().as_secs_f64();

    let out = args.out.clone().unwrap_or_else(|| {
        let name = match args.method {
            MethodArg::PoseAware => "partition-pose-aware.json",
            MethodArg::Grid => "partition-grid.json",
        };
        dataset.root.join(name)
    });
    let plot_path = args
        .plot
        .clone()
        .unwrap_or_else(|| out.with_extension("png"));
    write_partition(&out, &partition)?;
    let title = format!(
        "{} partition: {} blocks, {} train poses, mean Num_NeRF train {:.2} test {:.2}",
        partitioner.name(),
        partition.blocks.len(),
        train.len(),
        nn_train,
        nn_test
    );
    draw(&partition, &train, &test, &title, &plot_path)?;

    outln!(
        "{} partition of {} ({} train poses, {} test poses, {} sample points, voxel {} m)",
        partitioner.name(),
        dataset.root.display(),
        train.len(),
        test.len(),
        n_points,
        partition.voxel_size
    )?;
    outln!(
        "{:>5} {:>6} {:>28} {:>22} {:>14} {:>14}",
        "block",
        "poses",
        "centroid x, y, z (m)",
        "box size x, y, z (m)",
        "sampling m3",
        "occupied m3"
    )?;
    for b in &partition.blocks {
        let s = [0, 1, 2].map(|a| b.bounds.max[a] - b.bounds.min[a]);
        outln!(
            "{:>5} {:>6} {:>28} {:>22} {:>14.0} {:>14.0}",
            b.id,
            b.pose_ids.len(),
            format!(
                "{:.1}, {:.1}, {:.1}",
                b.centroid[0], b.centroid[1], b.centroid[2]
            ),
            format!("{:.0}, {:.0}, {:.0}", s[0], s[1], s[2]),
            b.sampling_volume_m3,
            b.occupied_volume_m3
        )?;
    }
    let vols: Vec<f64> = partition
        .blocks
        .iter()
        .map(|b| b.sampling_volume_m3)
        .collect();
    outln!(
        "mean sampling volume per block: {:.0} m3; scene box: {:.0} m3",
        vols.iter().sum::<f64>() / vols.len().max(1) as f64,
        partition.scene_bounds.volume()
    )?;
    outln!(
        "mean Num_NeRF(P): train {nn_train:.3}, test {nn_test:.3}; test samples inside their block box: {:.1} %",
        100.0 * cov_test
    )?;
    outln!(
        "time: sampling {sample_secs:.2} s, partition {part_secs:.2} s, Num_NeRF {eval_secs:.2} s, total {:.2} s",
        start.elapsed().as_secs_f64()
    )?;
    outln!("wrote {} and {}", out.display(), plot_path.display())?;
    Ok(())
}

/// The top-down plot: sample points and block boxes coloured per block, camera positions with
/// their viewing direction, and a legend with the block table.
fn draw(
    partition: &Partition,
    train: &[PoseSamples],
    test: &[PoseSamples],
    title: &str,
    path: &Path,
) -> Result<()> {
    // Sample points: at most ~300k.
    let total: usize = train.iter().map(|p| p.points.len()).sum();
    let step = total.div_ceil(300_000).max(1);
    let mut points = Vec::with_capacity(total / step + 1);
    for p in train {
        let block = match partition.method {
            Method::PoseAware => assign_pose(partition, p),
            Method::Grid => None,
        };
        for q in p.points.iter().step_by(step) {
            if let Some(b) = block.or_else(|| nearest_block(partition, q.x, q.y)) {
                points.push(([q.x, q.y], b));
            }
        }
    }
    let blocks: Vec<plot::PartitionBlock> = partition
        .blocks
        .iter()
        .map(|b| plot::PartitionBlock {
            id: b.id,
            min: [b.bounds.min[0], b.bounds.min[1]],
            max: [b.bounds.max[0], b.bounds.max[1]],
            poses: b.pose_ids.len(),
            volume_m3: b.sampling_volume_m3,
        })
        .collect();
    let camera = |p: &PoseSamples, test: bool| {
        let o = p.center();
        let d = p.viewing_direction();
        plot::CameraMark {
            position: [o.x, o.y],
            direction: [d.x, d.y],
            block: assign_pose(partition, p),
            test,
        }
    };
    let cameras: Vec<plot::CameraMark> = train
        .iter()
        .map(|p| camera(p, false))
        .chain(test.iter().map(|p| camera(p, true)))
        .collect();
    let sb = &partition.scene_bounds;
    plot::partition_map(
        path,
        &plot::PartitionMap {
            title,
            scene_min: [sb.min[0], sb.min[1]],
            scene_max: [sb.max[0], sb.max[1]],
            points: &points,
            blocks: &blocks,
            cameras: &cameras,
        },
    )
}

fn nearest_block(partition: &Partition, x: f64, y: f64) -> Option<usize> {
    partition
        .blocks
        .iter()
        .map(|b| {
            (
                b.id,
                (x - b.centroid[0]).powi(2) + (y - b.centroid[1]).powi(2),
            )
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}
