//! Map building, stage by stage: partition → one sub-NeRF per block → per block (ground-truth
//! pairs → query encoder → feature selection) → pose groups and place classifier → confidence
//! calibration. One file per stage.
//!
//! Every stage writes its files through the [`MapDir`] (atomic, checksummed) and records itself
//! as completed in the manifest; [`build_map`] skips completed stages, so a killed build resumes
//! where it stopped, and a sub-NeRF interrupted mid-training resumes from its own checkpoint.
//!
//! The build is three steps that also run as separate jobs: [`plan_map`] (dataset checks,
//! surface, partition, the keypoint structure of the training images, the job list;
//! [`jobs`] also writes the Slurm scripts), [`build_block`] per block (sub-NeRF, pairs, encoder, selection; as a job,
//! [`run_block_job`] records into the block's own record, so blocks build side by side on
//! several machines) and [`finish_map`] (merges the block records, place predictor,
//! calibration). [`build_map`] runs the three in one process.

pub mod calibration;
pub mod common;
pub mod encoder;
pub mod jobs;
pub mod nerf;
pub mod pairs;
pub mod partition;
pub mod place;
pub mod select;
pub mod structure;
pub mod sunlight;

use std::path::Path;

use matloc_data::{Dataset, Split};
use matloc_partition::{Partition, Partitioner, PoseAwarePartitioner};

use crate::error::PipelineError;
use crate::map::layout::PARTITION_FILE;
use crate::map::manifest::{MapDir, MapError};

pub use crate::config::MapConfig;
pub use common::{BuildEvent, CurveLog, block_dataset};
pub use jobs::JobCommands;
pub use nerf::block_model_config;

/// Builds (or resumes building) a map of `dataset` in `out` with the paper's pose-aware
/// partition.
pub fn build_map(
    dataset: &Dataset,
    out: &Path,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<MapDir, PipelineError> {
    let partitioner = PoseAwarePartitioner {
        config: config.partition,
    };
    build_map_with(dataset, out, config, &partitioner, progress)
}

/// [`build_map`] with another [`Partitioner`] (e.g. the Mega-NeRF grid baseline).
pub fn build_map_with(
    dataset: &Dataset,
    out: &Path,
    config: &MapConfig,
    partitioner: &dyn Partitioner,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<MapDir, PipelineError> {
    let mut log = common::BuildLog::default();
    let progress = &mut |e: &BuildEvent| {
        log.event(e);
        progress(e);
    };
    let Planned {
        mut map,
        dataset,
        partition,
    } = plan_map_with(dataset, out, config, partitioner, progress)?;
    let all: Vec<usize> = (0..partition.blocks.len()).collect();
    // Blocks that `map block` jobs completed count as done here too.
    for &b in &all {
        map.merge_block(b)?;
    }
    map.save()?;
    // All sub-NeRFs first: `parallel_blocks` of them train side by side.
    nerf::run(&dataset, &partition, &all, &mut map, config, progress)?;
    // Each stage reports once: the NeRFs above, the rest of each block here.
    for &b in &all {
        block_after_nerf(&dataset, &partition, b, &mut map, config, progress)?;
    }
    finish_map(&dataset, &partition, &mut map, config, progress)?;
    tracing::info!(out = %out.display(), blocks = partition.blocks.len(), "map complete");
    Ok(map)
}

/// A map after its plan step, or opened for a block or finish job: the map, the dataset at
/// the working resolution, and the partition.
pub struct Planned {
    /// The map directory.
    pub map: MapDir,
    /// The dataset at the map's working resolution.
    pub dataset: Dataset,
    /// The partition the plan stored.
    pub partition: Partition,
}

/// The plan step of a build run as jobs, with the pose-aware partition ([`plan_map_with`]),
/// then the job list in `plan.json` ([`jobs::write_plan`]: each block's command and the finish
/// command, running `jobs.program` on `jobs.data`; read it back with [`jobs::read_plan`]).
pub fn plan_map(
    dataset: &Dataset,
    out: &Path,
    config: &MapConfig,
    jobs: &JobCommands,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<Planned, PipelineError> {
    let partitioner = PoseAwarePartitioner {
        config: config.partition,
    };
    let mut planned = plan_map_with(dataset, out, config, &partitioner, progress)?;
    let blocks = planned.partition.blocks.len();
    jobs::write_plan(&mut planned.map, blocks, jobs)?;
    Ok(planned)
}

/// The plan step: checks the dataset, creates (or resumes) the map in `out`, finds the surface
/// and partitions the training poses. Nothing of a block is built.
pub fn plan_map_with(
    dataset: &Dataset,
    out: &Path,
    config: &MapConfig,
    partitioner: &dyn Partitioner,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<Planned, PipelineError> {
    tracing::info!(out = %out.display(), frames = dataset.frames.len(), "planning map");
    config.validate().map_err(PipelineError::Config)?;
    // Physically impossible intrinsics or poses stop the build before anything is written.
    let implausible = matloc_data::summary::plausibility(dataset);
    if !implausible.is_empty() {
        let shown: Vec<String> = implausible.iter().take(5).map(|p| p.to_string()).collect();
        return Err(PipelineError::Config(format!(
            "{} frame problem(s) in the dataset: {}{}",
            implausible.len(),
            shown.join("; "),
            if implausible.len() > 5 { "; …" } else { "" }
        )));
    }
    // Every image and depth map decodes in full (what `matloc dataset info` checks), before
    // the map exists: the first failure is the error, the others are logged.
    tracing::info!(
        files = matloc_data::summary::decoded_file_count(dataset),
        "decoding the images and depth maps"
    );
    let mut failures = matloc_data::summary::decode_failures(dataset, &|| {}).into_iter();
    if let Some(first) = failures.next() {
        for f in failures {
            tracing::error!("{}", f.problem());
        }
        return Err(first.error.into());
    }
    // Every stage at the working resolution.
    let working = matloc_data::images::working_dataset(dataset, config.images.max_side)?;
    // A surface source that cannot exist fails here, not after the map directory is made.
    matloc_surface::plan(
        &working,
        &working.split_indices(Split::Train),
        config.surface.source,
    )?;
    let config_json = serde_json::to_value(config).map_err(|source| PipelineError::ConfigJson {
        field: "map config",
        source,
    })?;
    let mut map = MapDir::create_or_resume(out, config_json)?;
    if map.manifest().scene.is_null() {
        map.manifest_mut().scene = serde_json::json!({
            "dataset": working.root.display().to_string(),
            "bounds_min": working.metadata.bounds_min,
            "bounds_max": working.metadata.bounds_max,
            "train_frames": working.split(Split::Train).count(),
            "test_frames": working.split(Split::Test).count(),
            "camera": working.split(Split::Train).next().map(|f| f.camera),
            "conventions": "cam_from_world, OpenCV camera axes, metres",
        });
        map.save()?;
    }
    let partition = partition::run(&working, &mut map, config, partitioner, progress)?;
    structure::run(&working, &mut map, config, progress)?;
    sunlight::run(&working, &mut map, config, progress)?;
    Ok(Planned {
        map,
        dataset: working,
        partition,
    })
}

/// Block `b`'s stages: sub-NeRF, ground-truth pairs, query encoder, feature selection (each
/// skipped when done). `dataset` is at the working resolution ([`Planned::dataset`]).
pub fn build_block(
    dataset: &Dataset,
    partition: &Partition,
    b: usize,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    nerf::run(dataset, partition, &[b], map, config, progress)?;
    block_after_nerf(dataset, partition, b, map, config, progress)
}

/// Block `b`'s stages after its sub-NeRF: pairs, encoder, selection.
fn block_after_nerf(
    dataset: &Dataset,
    partition: &Partition,
    b: usize,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    let (fit, _) = common::views_of_block(dataset, partition, b, config.calibration.holdout_every);
    if fit.is_empty() {
        return Err(PipelineError::Config(format!(
            "block {b} has no training views left after the hold-out"
        )));
    }
    pairs::run(b, &fit, map, config, progress)?;
    encoder::run(dataset, partition, b, map, config, progress)?;
    select::run(dataset, partition, b, map, config, progress)?;
    Ok(())
}

/// The finish step: merges every block's record into the manifest (refusing, with the list,
/// while any block is not built), then the place predictor and the calibration.
pub fn finish_map(
    dataset: &Dataset,
    partition: &Partition,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    if map.block().is_some() {
        return Err(PipelineError::Internal(
            "the finish step needs the whole map, not one block",
        ));
    }
    let total = partition.blocks.len();
    let mut missing = Vec::new();
    for b in 0..total {
        if !map.merge_block(b)? {
            missing.push(b);
        }
    }
    if !missing.is_empty() {
        return Err(MapError::BlocksMissing {
            blocks: missing,
            total,
        }
        .into());
    }
    map.save()?;
    place::run(dataset, partition, map, config, progress)?;
    calibration::run(dataset, partition, map, config, progress)?;
    Ok(())
}

/// Opens a planned map for a job: the config the plan recorded, `dataset` (as read, with the
/// map's split applied) at the map's working resolution, and the stored partition.
fn open_planned(dataset: &Dataset, map: MapDir) -> Result<(Planned, MapConfig), PipelineError> {
    let config: MapConfig = serde_json::from_value(map.manifest().config.clone())
        .map_err(|source| PipelineError::ManifestConfig { source })?;
    if !map.stage_done("partition") {
        return Err(MapError::StageMissing {
            stage: "partition".into(),
        }
        .into());
    }
    let partition: Partition = map.read_json(PARTITION_FILE)?;
    let working = matloc_data::images::working_dataset(dataset, config.images.max_side)?;
    Ok((
        Planned {
            map,
            dataset: working,
            partition,
        },
        config,
    ))
}

/// The job of block `b` of the planned map in `root`: [`build_block`] with the map opened for
/// the block ([`MapDir::open_block`]), so it writes only under `blocks/B/` and records its
/// progress in the block's record; rerun after a kill, it resumes.
pub fn run_block_job(
    dataset: &Dataset,
    root: &Path,
    b: usize,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<MapDir, PipelineError> {
    let mut log = common::BuildLog::default();
    let progress = &mut |e: &BuildEvent| {
        log.event(e);
        progress(e);
    };
    let map = MapDir::open_block(root, b)?;
    let (mut p, config) = open_planned(dataset, map)?;
    tracing::info!(map = %root.display(), block = b, "building block");
    build_block(&p.dataset, &p.partition, b, &mut p.map, &config, progress)?;
    // Saved even when every stage was done earlier, so the record exists.
    p.map.save()?;
    Ok(p.map)
}

/// The finish job of the planned map in `root`: [`finish_map`] once every block job has
/// succeeded.
pub fn run_finish_job(
    dataset: &Dataset,
    root: &Path,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<MapDir, PipelineError> {
    let mut log = common::BuildLog::default();
    let progress = &mut |e: &BuildEvent| {
        log.event(e);
        progress(e);
    };
    let map = MapDir::open(root)?;
    let (mut p, config) = open_planned(dataset, map)?;
    finish_map(&p.dataset, &p.partition, &mut p.map, &config, progress)?;
    tracing::info!(map = %root.display(), blocks = p.partition.blocks.len(), "map complete");
    Ok(p.map)
}
