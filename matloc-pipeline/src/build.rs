//! Map building: partition → one sub-NeRF per block → (ground-truth pairs → query encoder →
//! per-region feature selection → pose groups and place predictor).
//!
//! Every stage writes its files through the [`MapDir`] (atomic, checksummed) and records itself
//! as completed in the manifest; [`build_map`] skips completed stages, so a killed build resumes
//! where it stopped, and a sub-NeRF that was interrupted mid-training resumes from its own
//! checkpoint. Stages run in order, except that independent sub-NeRF blocks train
//! [`NerfStageConfig::parallel_blocks`] at a time, each in its own thread pool with its share of
//! the cores; their files and stages are recorded in block order by the one manifest writer.
//! Measured on 2 cores (`matloc nerf train`, `small`): side by side with one thread each,
//! 68.6 / 127.4 s for 2 × 150 / 2 × 300 steps; one after the other with two threads, 83.9 /
//! 142.5 s. Per training step both use the cores fully (~29 s per 150 steps per block); side by
//! side overlaps each run's serial start and end.

use std::path::Path;
use std::time::Instant;

use matloc_data::{Dataset, Split};
use matloc_partition::{
    Partition, Partitioner, PoseAwareConfig, PoseAwarePartitioner, SampleConfig,
    samples_from_dataset,
};
use matloc_render::{FitOptions, config_for_dataset, train_on_dataset};
use serde::{Deserialize, Serialize};

use crate::error::PipelineError;
use crate::manifest::{BlockEntry, MapDir};

/// Sub-NeRF training settings of a map build.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct NerfStageConfig {
    /// Training steps per block.
    pub steps: u64,
    /// Steps between checkpoints (resume granularity).
    pub checkpoint_every: u64,
    /// Integer image downscale for training.
    pub downscale: u32,
    /// Changes to the model config derived from the dataset, as a JSON object merged into it
    /// (e.g. `{"field": {"log2_table_size": 15}, "train": {"batch_rays": 1024}}`).
    pub model_overrides: serde_json::Value,
    /// Blocks trained at the same time, each on its share of the cores (1 = one after the
    /// other, each on all cores). Per training step both use the cores fully; side by side
    /// overlaps each run's serial start and end (2 cores, 2 × 300 steps: 127 vs 143 s).
    pub parallel_blocks: usize,
}

impl Default for NerfStageConfig {
    fn default() -> Self {
        Self {
            steps: 3000,
            checkpoint_every: 500,
            downscale: 1,
            model_overrides: serde_json::Value::Null,
            parallel_blocks: 2,
        }
    }
}

/// Deep-merges `patch` into `base` (objects merge key by key; anything else replaces).
fn merge_json(base: &mut serde_json::Value, patch: &serde_json::Value) {
    match (base, patch) {
        (serde_json::Value::Object(b), serde_json::Value::Object(p)) => {
            for (k, v) in p {
                merge_json(b.entry(k.clone()).or_insert(serde_json::Value::Null), v);
            }
        }
        (_, serde_json::Value::Null) => {}
        (b, p) => *b = p.clone(),
    }
}

/// The sub-NeRF config of a block dataset: derived from the data, then the overrides.
pub fn block_model_config(
    dataset: &Dataset,
    nerf: &NerfStageConfig,
) -> Result<matloc_render::ModelConfig, PipelineError> {
    let base = config_for_dataset(dataset, nerf.steps);
    if nerf.model_overrides.is_null() {
        return Ok(base);
    }
    let mut v = serde_json::to_value(&base).map_err(|e| PipelineError::Config(e.to_string()))?;
    merge_json(&mut v, &nerf.model_overrides);
    serde_json::from_value(v)
        .map_err(|e| PipelineError::Config(format!("nerf.model_overrides: {e}")))
}

/// Everything that defines a map build. Stored in the manifest; resuming a build requires the
/// same config.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MapConfig {
    /// Ray samples of each training pose for the partition.
    pub samples: SampleConfig,
    /// Pose-aware partition (target ~150 poses per block, as the paper).
    pub partition: PoseAwareConfig,
    /// Sub-NeRF training.
    pub nerf: NerfStageConfig,
    /// Ground-truth pairs per block.
    pub pairs: crate::stages::PairStageConfig,
    /// Query encoder per block.
    pub encoder: crate::stages::EncoderStageConfig,
    /// Feature selection per block.
    pub select: crate::stages::SelectStageConfig,
    /// Pose groups and the place classifier.
    pub place: crate::stages::PlaceStageConfig,
    /// Held-out views and the confidence calibration.
    pub calibration: crate::stages::CalibrationConfig,
    /// Localizer settings stored with the map (the confidence model is replaced by the
    /// calibrated one when the map is loaded).
    pub localize: crate::localizer::LocalizeOptions,
}

/// A progress event of [`build_map`].
#[derive(Clone, Debug, PartialEq)]
pub enum BuildEvent {
    /// A stage starts; `total` units of work (0 = unknown).
    StageStarted {
        /// Stage name.
        name: String,
        /// Units of work.
        total: u64,
    },
    /// Progress inside the current stage.
    StageProgress {
        /// Units done.
        done: u64,
        /// Short status (loss, PSNR, ...).
        message: String,
    },
    /// Progress inside one of several stages running at the same time (sub-NeRF blocks
    /// trained side by side).
    StageProgressOf {
        /// Stage name.
        name: String,
        /// Units done.
        done: u64,
        /// Short status.
        message: String,
    },
    /// A stage finished (or was skipped because a previous build completed it).
    StageFinished {
        /// Stage name.
        name: String,
        /// Seconds (0 when skipped).
        seconds: f64,
        /// Whether it was skipped.
        skipped: bool,
    },
}

/// Name of the partition file inside the map.
pub const PARTITION_FILE: &str = "partition.json";

/// Directory of block `b` inside the map.
pub fn block_dir(b: usize) -> String {
    format!("blocks/{b}")
}

/// The dataset restricted to one block: its training frames, plus the test frames whose camera
/// centre lies inside the block's bounds (for evaluation), with the block's bounds as the scene
/// box.
pub fn block_dataset(dataset: &Dataset, partition: &Partition, block: usize) -> Dataset {
    let b = &partition.blocks[block];
    let train: Vec<usize> = dataset
        .frames
        .iter()
        .enumerate()
        .filter(|(_, f)| f.split == Split::Train)
        .map(|(i, _)| i)
        .collect();
    let mut frames = Vec::new();
    for &id in &b.pose_ids {
        if let Some(&i) = train.get(id) {
            frames.push(dataset.frames[i].clone());
        }
    }
    for f in dataset.split(Split::Test) {
        let c = f.center();
        let inside = (0..3).all(|k| c[k] >= b.bounds.min[k] && c[k] <= b.bounds.max[k]);
        if inside {
            frames.push(f.clone());
        }
    }
    let mut metadata = dataset.metadata.clone();
    metadata.bounds_min = Some(b.bounds.min);
    metadata.bounds_max = Some(b.bounds.max);
    Dataset {
        root: dataset.root.clone(),
        frames,
        metadata,
    }
}

/// Builds (or resumes building) a map of `dataset` in `out`.
pub fn build_map(
    dataset: &Dataset,
    out: &Path,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<MapDir, PipelineError> {
    let config_json =
        serde_json::to_value(config).map_err(|e| PipelineError::Config(e.to_string()))?;
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

    // Stage: partition.
    let partition: Partition = if map.stage_done("partition") {
        progress(&BuildEvent::StageFinished {
            name: "partition".into(),
            seconds: 0.0,
            skipped: true,
        });
        map.read_json(PARTITION_FILE)?
    } else {
        let t = Instant::now();
        let train: Vec<usize> = dataset
            .frames
            .iter()
            .enumerate()
            .filter(|(_, f)| f.split == Split::Train)
            .map(|(i, _)| i)
            .collect();
        progress(&BuildEvent::StageStarted {
            name: "partition".into(),
            total: train.len() as u64,
        });
        let mut samples = samples_from_dataset(dataset, &train, &config.samples, &|| {})
            .map_err(|e| PipelineError::Partition(e.to_string()))?;
        // Pose ids are positions among the training frames (block_dataset relies on it).
        for (k, s) in samples.iter_mut().enumerate() {
            s.id = k;
        }
        let partition = PoseAwarePartitioner {
            config: config.partition,
        }
        .partition(&samples)
        .map_err(|e| PipelineError::Partition(e.to_string()))?;
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

    // Stage: one sub-NeRF per block, `parallel_blocks` at a time.
    let mut pending = Vec::new();
    for b in 0..partition.blocks.len() {
        let name = format!("nerf/{b}");
        if map.stage_done(&name) {
            progress(&BuildEvent::StageFinished {
                name,
                seconds: 0.0,
                skipped: true,
            });
        } else {
            pending.push(b);
        }
    }
    let threads = rayon::current_num_threads();
    // No more blocks at once than threads: each gets at least one of its own.
    for group in pending.chunks(config.nerf.parallel_blocks.clamp(1, threads.max(1))) {
        train_blocks(
            dataset, &partition, &mut map, config, group, threads, progress,
        )?;
    }
    crate::stages::run_after_nerf(dataset, &partition, &mut map, config, progress)?;
    Ok(map)
}

/// A message from a block trained on its own thread.
enum BlockMsg {
    Progress(FitProgressLine),
    Done(Result<(), PipelineError>),
}

/// What the build reports of one training step.
struct FitProgressLine {
    done: u64,
    message: String,
}

/// Trains the NeRFs of `group` at the same time, `threads / group.len()` threads each, then
/// records their files and stages in block order (the manifest has one writer).
fn train_blocks(
    dataset: &Dataset,
    partition: &Partition,
    map: &mut MapDir,
    config: &MapConfig,
    group: &[usize],
    threads: usize,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    let t = Instant::now();
    let mut jobs = Vec::with_capacity(group.len());
    for &b in group {
        let sub = block_dataset(dataset, partition, b);
        let model_config = block_model_config(&sub, &config.nerf)?;
        let dir = map.path_of(&block_dir(b))?;
        std::fs::create_dir_all(&dir).map_err(|e| PipelineError::Io {
            path: dir.clone(),
            source: e,
        })?;
        progress(&BuildEvent::StageStarted {
            name: format!("nerf/{b}"),
            total: config.nerf.steps,
        });
        jobs.push((b, sub, model_config, dir));
    }
    let opts = FitOptions {
        steps: config.nerf.steps,
        checkpoint_every: config.nerf.checkpoint_every,
        downscale: config.nerf.downscale,
    };
    let per_block = (threads / group.len()).max(1);
    let concurrent = group.len() > 1;
    let (tx, rx) = std::sync::mpsc::channel::<(usize, BlockMsg)>();
    let mut results: Vec<Option<(Result<(), PipelineError>, f64)>> =
        (0..group.len()).map(|_| None).collect();
    std::thread::scope(|scope| {
        for (slot, (b, sub, model_config, dir)) in jobs.iter().enumerate() {
            let tx = tx.clone();
            let opts = &opts;
            scope.spawn(move || {
                let run = || {
                    train_on_dataset(sub, model_config, dir, opts, |p| {
                        let _ = tx.send((
                            slot,
                            BlockMsg::Progress(FitProgressLine {
                                done: p.stats.step + 1,
                                message: format!(
                                    "loss {:.4} psnr {:.1} dB, {:.0} rays/s",
                                    p.stats.loss, p.stats.psnr, p.rays_per_s
                                ),
                            }),
                        ));
                    })
                    .map(|_| ())
                    .map_err(PipelineError::from)
                };
                let out = match rayon::ThreadPoolBuilder::new()
                    .num_threads(per_block)
                    .thread_name({
                        let b = *b;
                        move |i| format!("nerf-{b}-{i}")
                    })
                    .build()
                {
                    Ok(pool) => pool.install(run),
                    Err(_) => Err(PipelineError::Internal(
                        "could not start a thread pool for a block",
                    )),
                };
                let _ = tx.send((slot, BlockMsg::Done(out)));
            });
        }
        drop(tx);
        for (slot, msg) in rx {
            let name = format!("nerf/{}", group[slot]);
            match msg {
                BlockMsg::Progress(p) if concurrent => progress(&BuildEvent::StageProgressOf {
                    name,
                    done: p.done,
                    message: p.message,
                }),
                BlockMsg::Progress(p) => progress(&BuildEvent::StageProgress {
                    done: p.done,
                    message: p.message,
                }),
                BlockMsg::Done(r) => results[slot] = Some((r, t.elapsed().as_secs_f64())),
            }
        }
    });
    for (slot, (b, _, _, dir)) in jobs.iter().enumerate() {
        let (result, secs) = results[slot].take().ok_or(PipelineError::Internal(
            "a block's training thread did not report",
        ))?;
        result?;
        finish_block(map, *b, dir)?;
        let name = format!("nerf/{b}");
        map.complete_stage(&name, secs)?;
        progress(&BuildEvent::StageFinished {
            name,
            seconds: secs,
            skipped: false,
        });
    }
    Ok(())
}

/// Drops a trained block's optimizer state and lists its files in the manifest.
fn finish_block(map: &mut MapDir, b: usize, dir: &Path) -> Result<(), PipelineError> {
    // Adam's moments (2× the weights) only serve resuming this stage, which is now done.
    let optimizer = dir.join(matloc_render::OPTIMIZER_FILE);
    if optimizer.exists() {
        std::fs::remove_file(&optimizer).map_err(|e| PipelineError::Io {
            path: optimizer.clone(),
            source: e,
        })?;
    }
    // The trainer wrote its files atomically; list them (checksums) in the manifest.
    crate::stages::register_dir(map, &block_dir(b))
}
