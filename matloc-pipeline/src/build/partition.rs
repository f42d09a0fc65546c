//! The partition stage: each training pose's ray samples → voxel occupancy → pose-aware
//! blocks (one sub-NeRF per block, every pose served by exactly one), recorded in the manifest.

use std::time::Instant;

use matloc_data::{Dataset, Split};
use matloc_partition::{Partition, Partitioner, samples_from_dataset};

use crate::build::common::BuildEvent;
use crate::config::MapConfig;
use crate::error::PipelineError;
use crate::map::layout::PARTITION_FILE;
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
        let mut samples = samples_from_dataset(dataset, &train, &config.samples, &|| {})?;
        // Pose ids are positions among the training frames (block_dataset relies on it).
        for (k, s) in samples.iter_mut().enumerate() {
            s.id = k;
        }
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
