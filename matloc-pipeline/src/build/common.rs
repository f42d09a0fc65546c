//! What every build stage shares: progress events, the resumable stage runner, the manifest
//! listing of a stage's files, and which training views a block's stages use.

use std::time::Instant;

use matloc_core::{Camera, Image};
use matloc_data::{Dataset, Split};
use matloc_partition::Partition;

use crate::error::PipelineError;
use crate::gt::TrainingView;
use crate::map::manifest::{MapDir, StageRecord, VirtualViewsRecord};

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
    /// Per running stage: name, total, last logged units and time, start time.
    running: Vec<(String, u64, u64, Instant, Instant)>,
}

impl BuildLog {
    /// Logs one event.
    pub fn event(&mut self, event: &BuildEvent) {
        match event {
            BuildEvent::StageStarted { name, total } => {
                tracing::info!(stage = %name, total, "stage started");
                self.running.retain(|r| r.0 != *name);
                let now = Instant::now();
                self.running.push((name.clone(), *total, 0, now, now));
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
        let (name, total, last, at, started) = &mut self.running[i];
        let step = (*total / 10).max(1);
        if done >= *last + step || at.elapsed().as_secs_f64() >= 30.0 {
            let elapsed = started.elapsed().as_secs_f64();
            // Remaining time at the stage's mean rate so far.
            let eta = (done > 0 && *total >= done)
                .then(|| elapsed / done as f64 * (*total - done) as f64);
            tracing::info!(
                stage = %name,
                done,
                total = *total,
                elapsed_s = elapsed.round(),
                eta_s = eta.map(f64::round),
                "{message}"
            );
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
    stage_recorded(map, name, total, progress, &mut |map, progress| {
        body(map, progress).map(|()| None)
    })
}

/// The work of a stage that records virtual viewpoints beside its time.
pub(crate) type RecordedStageBody<'a> = dyn FnMut(
        &mut MapDir,
        &mut dyn FnMut(&BuildEvent),
    ) -> Result<Option<VirtualViewsRecord>, PipelineError>
    + 'a;

/// [`stage`] whose body also returns what the stage's record keeps of its virtual viewpoints.
pub(crate) fn stage_recorded(
    map: &mut MapDir,
    name: &str,
    total: u64,
    progress: &mut dyn FnMut(&BuildEvent),
    body: &mut RecordedStageBody<'_>,
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
    let virtual_views = body(map, progress)?;
    let secs = t.elapsed().as_secs_f64();
    map.complete_stage_record(StageRecord {
        name: name.to_string(),
        seconds: secs,
        virtual_views,
    })?;
    progress(&BuildEvent::StageFinished {
        name: name.into(),
        seconds: secs,
        skipped: false,
    });
    Ok(())
}

/// A stage's training curve as JSON lines in `curves/<stage>.jsonl` inside the map (`/` in
/// the stage name becomes `_`; a block job's under `blocks/B/curves/`), one object per report: `step`, `t_s` (seconds since the log
/// was opened) and the stage's values (loss, ...). Appended while the stage runs, so a long
/// build can be followed and plotted; a resumed stage appends after the interrupted run. Not
/// one of the map's checksummed files, and a log that cannot be written only warns.
pub struct CurveLog {
    file: Option<std::io::BufWriter<std::fs::File>>,
    start: Instant,
}

impl CurveLog {
    /// Opens (appends to) the curve of `stage` in `map`.
    pub fn open(map: &MapDir, stage: &str) -> CurveLog {
        let name = map.curve_name(stage);
        let file = map.path_of(&name).ok().and_then(|path| {
            let opened = path
                .parent()
                .map_or(Ok(()), std::fs::create_dir_all)
                .and_then(|_| {
                    std::fs::OpenOptions::new()
                        .create(true)
                        .append(true)
                        .open(&path)
                });
            match opened {
                Ok(f) => Some(std::io::BufWriter::new(f)),
                Err(e) => {
                    tracing::warn!(path = %path.display(), error = %e, "training curve not written");
                    None
                }
            }
        });
        CurveLog {
            file,
            start: Instant::now(),
        }
    }

    /// Appends one point of the curve (non-finite values are written as `null`).
    pub fn record(&mut self, step: u64, values: &[(&str, f64)]) {
        use std::io::Write;
        let Some(f) = self.file.as_mut() else {
            return;
        };
        let mut obj = serde_json::Map::new();
        obj.insert("step".into(), step.into());
        let t = (self.start.elapsed().as_secs_f64() * 1e3).round() / 1e3;
        for (k, v) in std::iter::once(&("t_s", t)).chain(values) {
            let v = serde_json::Number::from_f64(*v).map_or(serde_json::Value::Null, Into::into);
            obj.insert((*k).into(), v);
        }
        let line = serde_json::Value::Object(obj).to_string();
        if writeln!(f, "{line}").and_then(|_| f.flush()).is_err() {
            tracing::warn!("training curve: write failed, no further points");
            self.file = None;
        }
    }
}

/// Lists every file directly under `dir` (relative to the map root) in the manifest (a block
/// job: in its record), the block record itself excepted.
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
        // The block record describes the files; it is not one of them.
        if entry.path().is_file()
            && !file.ends_with(".tmp")
            && file != crate::map::layout::BLOCK_RECORD_FILE
        {
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
        points: None,
        metadata,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn curve_log_appends_json_lines_per_stage() {
        let dir = tempfile::tempdir().unwrap();
        let map = MapDir::create_or_resume(dir.path(), serde_json::json!({})).unwrap();
        let mut c = CurveLog::open(&map, "nerf/3");
        c.record(1, &[("loss", 0.5), ("psnr", f64::NAN)]);
        c.record(2, &[("loss", 0.25), ("psnr", 20.0)]);
        // A resumed stage appends.
        CurveLog::open(&map, "nerf/3").record(3, &[("loss", 0.125)]);
        let text = std::fs::read_to_string(dir.path().join("curves/nerf_3.jsonl")).unwrap();
        let lines: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        assert_eq!(lines.len(), 3);
        assert_eq!(lines[0]["step"], 1);
        assert!(lines[0]["psnr"].is_null());
        assert_eq!(lines[1]["loss"], 0.25);
        assert_eq!(lines[2]["step"], 3);
        assert!(lines[2]["t_s"].as_f64().unwrap() >= 0.0);
    }
}
