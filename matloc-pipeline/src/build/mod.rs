//! Map building, stage by stage: partition → one sub-NeRF per block → per block (ground-truth
//! pairs → query encoder → feature selection) → pose groups and place classifier → confidence
//! calibration. One file per stage.
//!
//! Every stage writes its files through the [`MapDir`] (atomic, checksummed) and records itself
//! as completed in the manifest; [`build_map`] skips completed stages, so a killed build resumes
//! where it stopped, and a sub-NeRF interrupted mid-training resumes from its own checkpoint.

pub mod calibration;
pub mod common;
pub mod encoder;
pub mod nerf;
pub mod pairs;
pub mod partition;
pub mod place;
pub mod select;

use std::path::Path;

use matloc_data::{Dataset, Split};
use matloc_partition::{Partitioner, PoseAwarePartitioner};

use crate::error::PipelineError;
use crate::map::manifest::MapDir;

pub use crate::config::MapConfig;
pub use common::{BuildEvent, CurveLog, block_dataset};
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
    tracing::info!(out = %out.display(), frames = dataset.frames.len(), "building map");
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
    // Every stage at the working resolution; checked (image headers) before the map exists.
    let working = matloc_data::images::working_dataset(dataset, config.images.max_side)?;
    let dataset = &working;
    // A surface source that cannot exist fails here, not after the map directory is made.
    matloc_surface::plan(
        dataset,
        &dataset.split_indices(Split::Train),
        config.surface.source,
    )?;
    let config_json = serde_json::to_value(config).map_err(|source| PipelineError::ConfigJson {
        field: "map config",
        source,
    })?;
    let mut map = MapDir::create_or_resume(out, config_json)?;
    if map.manifest().scene.is_null() {
        map.manifest_mut().scene = serde_json::json!({
            "dataset": dataset.root.display().to_string(),
            "bounds_min": dataset.metadata.bounds_min,
            "bounds_max": dataset.metadata.bounds_max,
            "train_frames": dataset.split(Split::Train).count(),
            "test_frames": dataset.split(Split::Test).count(),
            "camera": dataset.split(Split::Train).next().map(|f| f.camera),
            "conventions": "cam_from_world, OpenCV camera axes, metres",
        });
        map.save()?;
    }

    let partition = partition::run(dataset, &mut map, config, partitioner, progress)?;
    nerf::run(dataset, &partition, &mut map, config, progress)?;
    for b in 0..partition.blocks.len() {
        let (fit, _) =
            common::views_of_block(dataset, &partition, b, config.calibration.holdout_every);
        if fit.is_empty() {
            return Err(PipelineError::Config(format!(
                "block {b} has no training views left after the hold-out"
            )));
        }
        pairs::run(b, &fit, &mut map, config, progress)?;
        encoder::run(dataset, &partition, b, &mut map, config, progress)?;
        select::run(dataset, &partition, b, &mut map, config, progress)?;
    }
    place::run(dataset, &partition, &mut map, config, progress)?;
    calibration::run(dataset, &partition, &mut map, config, progress)?;
    tracing::info!(out = %out.display(), blocks = partition.blocks.len(), "map complete");
    Ok(map)
}
