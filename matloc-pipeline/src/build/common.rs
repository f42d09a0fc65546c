//! What every build stage shares: progress events, the resumable stage runner, the manifest
//! listing of a stage's files, and which training views a block's stages use.

use std::time::Instant;

use matloc_core::{Camera, Image};
use matloc_data::{Dataset, Split};
use matloc_partition::Partition;

use crate::error::PipelineError;
use crate::gt::TrainingView;
use crate::map::manifest::MapDir;

/// A progress event of [`crate::build::build_map`].
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

/// Logs build events through `tracing` (target `matloc_pipeline::build`): every stage start
/// and end at info, progress inside a stage at info at most every tenth of its work or every
/// 30 s, and at debug otherwise — a batch job's log shows where a long build is.
#[derive(Default)]
pub struct BuildLog {
    /// Per running stage: name, total, last logged units and time.
    running: Vec<(String, u64, u64, Instant)>,
}

impl BuildLog {
    /// Logs one event.
    pub fn event(&mut self, event: &BuildEvent) {
        match event {
            BuildEvent::StageStarted { name, total } => {
                tracing::info!(stage = %name, total, "stage started");
                self.running.retain(|r| r.0 != *name);
                self.running.push((name.clone(), *total, 0, Instant::now()));
            }
            BuildEvent::StageProgress { done, message } => {
                if let Some(i) = self.running.len().checked_sub(1) {
                    self.progress(i, *done, message);
                }
            }
            BuildEvent::StageProgressOf {
                name,
                done,
                message,
            } => {
                if let Some(i) = self.running.iter().position(|r| r.0 == *name) {
                    self.progress(i, *done, message);
                }
            }
            BuildEvent::StageFinished {
                name,
                seconds,
                skipped,
            } => {
                self.running.retain(|r| r.0 != *name);
                if *skipped {
                    tracing::info!(stage = %name, "stage done earlier, skipped");
                } else {
                    tracing::info!(stage = %name, seconds, "stage finished");
                }
            }
        }
    }

    fn progress(&mut self, i: usize, done: u64, message: &str) {
        let (name, total, last, at) = &mut self.running[i];
        let step = (*total / 10).max(1);
        if done >= *last + step || at.elapsed().as_secs_f64() >= 30.0 {
            tracing::info!(stage = %name, done, total = *total, "{message}");
            *last = done;
            *at = Instant::now();
        } else {
            tracing::debug!(stage = %name, done, total = *total, "{message}");
        }
    }
}

/// The work of one stage: gets the map and the progress sink.
pub(crate) type StageBody<'a> =
    dyn FnMut(&mut MapDir, &mut dyn FnMut(&BuildEvent)) -> Result<(), PipelineError> + 'a;

/// Runs a stage unless the manifest says it is done.
pub(crate) fn stage(
    map: &mut MapDir,
    name: &str,
    total: u64,
    progress: &mut dyn FnMut(&BuildEvent),
    body: &mut StageBody<'_>,
) -> Result<(), PipelineError> {
    if map.stage_done(name) {
        progress(&BuildEvent::StageFinished {
            name: name.into(),
            seconds: 0.0,
            skipped: true,
        });
        return Ok(());
    }
    let t = Instant::now();
    progress(&BuildEvent::StageStarted {
        name: name.into(),
        total,
    });
    body(map, progress)?;
    let secs = t.elapsed().as_secs_f64();
    map.complete_stage(name, secs)?;
    progress(&BuildEvent::StageFinished {
        name: name.into(),
        seconds: secs,
        skipped: false,
    });
    Ok(())
}

/// Lists every file under `dir` (relative to the map root) in the manifest.
pub(crate) fn register_dir(map: &mut MapDir, dir: &str) -> Result<(), PipelineError> {
    let path = map.path_of(dir)?;
    let entries = std::fs::read_dir(&path).map_err(|e| PipelineError::Io {
        path: path.clone(),
        source: e,
    })?;
    for entry in entries {
        let entry = entry.map_err(|e| PipelineError::Io {
            path: path.clone(),
            source: e,
        })?;
        let file = entry.file_name().to_string_lossy().to_string();
        if entry.path().is_file() && !file.ends_with(".tmp") {
            map.register_file(&format!("{dir}/{file}"))?;
        }
    }
    Ok(())
}

/// A training view of a block, with its frame index in the dataset.
pub(crate) fn views_of_block(
    dataset: &Dataset,
    partition: &Partition,
    b: usize,
    holdout_every: usize,
) -> (Vec<TrainingView>, Vec<TrainingView>) {
    let train = dataset.split_indices(Split::Train);
    let mut fit = Vec::new();
    let mut held = Vec::new();
    for (k, &id) in partition.blocks[b].pose_ids.iter().enumerate() {
        let Some(&i) = train.get(id) else { continue };
        let f = &dataset.frames[i];
        let v = TrainingView {
            index: i,
            camera: f.camera,
            cam_from_world: f.cam_from_world,
        };
        if holdout_every > 0 && k % holdout_every == holdout_every - 1 {
            held.push(v);
        } else {
            fit.push(v);
        }
    }
    (fit, held)
}

/// At most `n` evenly spaced elements.
pub(crate) fn spaced<T: Clone>(v: &[T], n: usize) -> Vec<T> {
    matloc_core::subset::evenly_spaced(v.len(), n)
        .into_iter()
        .map(|i| v[i].clone())
        .collect()
}

pub(crate) fn load_image(
    dataset: &Dataset,
    index: usize,
) -> Result<(Image<f32>, Camera), PipelineError> {
    let f = &dataset.frames[index];
    Ok(matloc_data::images::load_frame_image(dataset, f, 1)?)
}

/// The dataset restricted to one block: its training frames, plus the test frames whose camera
/// centre lies inside the block's bounds (for evaluation), with the block's bounds as the scene
/// box.
pub fn block_dataset(dataset: &Dataset, partition: &Partition, block: usize) -> Dataset {
    let b = &partition.blocks[block];
    let train = dataset.split_indices(Split::Train);
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
