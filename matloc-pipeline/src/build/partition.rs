//! The partition stage: each training pose's ray samples → voxel occupancy → pose-aware
//! blocks (one sub-NeRF per block, every pose served by exactly one), recorded in the manifest.

use std::time::Instant;

use matloc_data::{Dataset, Split};
use matloc_partition::{
    DepthMapSurface, Partition, Partitioner, PoseSamples, SampleConfig, sample_pose,
};
use matloc_surface::FrameSurfaces;
use rayon::prelude::*;
use serde::Serialize;

use crate::build::common::BuildEvent;
use crate::config::MapConfig;
use crate::error::PipelineError;
use crate::map::layout::{PARTITION_FILE, SURFACE_FILE, SURFACE_POINTS_FILE};
use crate::map::manifest::{BlockEntry, MapDir};

/// Partitions the training poses with `partitioner` (or reads the partition a previous run
/// stored). Pose ids are positions among the training frames.
pub fn run(
    dataset: &Dataset,
    map: &mut MapDir,
    config: &MapConfig,
    partitioner: &dyn Partitioner,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<Partition, PipelineError> {
    let partition = if map.stage_done("partition") {
        progress(&BuildEvent::StageFinished {
            name: "partition".into(),
            seconds: 0.0,
            skipped: true,
        });
        map.read_json(PARTITION_FILE)?
    } else {
        let t = Instant::now();
        let train = dataset.split_indices(Split::Train);
        progress(&BuildEvent::StageStarted {
            name: "partition".into(),
            total: train.len() as u64,
        });
        let samples = surface_samples(dataset, &train, map, config, progress)?;
        let partition = partitioner.partition(&samples)?;
        map.write_json(PARTITION_FILE, &partition)?;
        map.manifest_mut().blocks = partition
            .blocks
            .iter()
            .map(|b| BlockEntry {
                id: b.id,
                bounds_min: b.bounds.min,
                bounds_max: b.bounds.max,
                num_poses: b.pose_ids.len(),
                selected_dims: Vec::new(),
            })
            .collect();
        let secs = t.elapsed().as_secs_f64();
        map.complete_stage("partition", secs)?;
        progress(&BuildEvent::StageFinished {
            name: "partition".into(),
            seconds: secs,
            skipped: false,
        });
        partition
    };
    Ok(partition)
}

/// What the partition's surface was, kept in the map (`surface.json`).
#[derive(Serialize)]
struct SurfaceRecord<'a> {
    plan: &'a matloc_surface::SurfacePlan,
    /// Sparse points used (0 with depth files).
    points: usize,
    /// Training frames and the number of points each saw (empty with depth files).
    points_per_frame: Vec<usize>,
}

/// Ray samples of every training pose up to its surface (depth files, the dataset's points or
/// triangulated ones; see `matloc_surface`). Pose ids are positions among the training frames
/// (`block_dataset` relies on it). The chosen source goes to `surface.json`, the points (when
/// points were used) to `surface_points.ply` for inspection.
fn surface_samples(
    dataset: &Dataset,
    train: &[usize],
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<Vec<PoseSamples>, PipelineError> {
    let surfaces =
        FrameSurfaces::prepare(dataset, train, &config.surface, &|phase, done, total| {
            if done == total || done % (total / 10).max(1) == 0 {
                tracing::info!(phase, done, total, "triangulating the surface");
            }
        })?;
    let plan = surfaces.plan().clone();
    tracing::info!(source = %plan.kind, detail = %plan.detail, "partition surface");
    progress(&BuildEvent::StageProgress {
        done: 0,
        message: format!("surface: {} ({})", plan.kind, plan.detail),
    });
    let mut samples = samples_on_surfaces(dataset, train, &surfaces, &config.samples, &|| {})?;
    for (k, s) in samples.iter_mut().enumerate() {
        s.id = k;
    }
    let record = SurfaceRecord {
        plan: &plan,
        points: surfaces.points().map_or(0, |p| p.len()),
        points_per_frame: match surfaces.points().and_then(|p| p.by_frame.as_ref()) {
            Some(b) => train.iter().map(|&i| b[i].len()).collect(),
            None => Vec::new(),
        },
    };
    map.write_json(SURFACE_FILE, &record)?;
    if let Some(p) = surfaces.points() {
        map.write_file(
            SURFACE_POINTS_FILE,
            &matloc_data::ply::ply_bytes(&p.xyz, None),
        )?;
    }
    Ok(samples)
}

/// Ray samples of the frames `indices` (ids = frame indices) up to the surface `surfaces`
/// gives them, in parallel; `progress` is called once per frame.
pub fn samples_on_surfaces(
    dataset: &Dataset,
    indices: &[usize],
    surfaces: &FrameSurfaces,
    config: &SampleConfig,
    progress: &(dyn Fn() + Sync),
) -> Result<Vec<PoseSamples>, PipelineError> {
    indices
        .par_iter()
        .map(|&i| {
            let frame = &dataset.frames[i];
            let depth = surfaces.depth(dataset, i)?;
            let surface = DepthMapSurface::new(&depth, &frame.camera);
            let s = sample_pose(i, &frame.camera, &frame.cam_from_world, &surface, config)?;
            progress();
            Ok(s)
        })
        .collect()
}
