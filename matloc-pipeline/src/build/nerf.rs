//! The sub-NeRF stage: one NeRF per block, trained on the block's training views,
//! [`NerfStageConfig::parallel_blocks`] blocks side by side, each in its own thread pool with
//! its share of the cores; a block interrupted mid-training resumes from its checkpoint.

use std::path::Path;
use std::time::Instant;

use matloc_data::Dataset;
use matloc_partition::Partition;
use matloc_render::{FitOptions, config_for_dataset, train_on_dataset};

use crate::build::common::{BuildEvent, CurveLog, block_dataset, register_dir};
use crate::config::{MapConfig, NerfStageConfig};
use crate::error::PipelineError;
use crate::map::layout::block_dir;
use crate::map::manifest::MapDir;

/// The sub-NeRF config of a block dataset: derived from the data, then the overrides.
pub fn block_model_config(
    dataset: &Dataset,
    nerf: &NerfStageConfig,
) -> Result<matloc_render::ModelConfig, PipelineError> {
    let base = config_for_dataset(dataset, nerf.steps);
    if nerf.model_overrides.is_null() {
        return Ok(base);
    }
    let field = "nerf.model_overrides";
    let mut v = serde_json::to_value(&base)
        .map_err(|source| PipelineError::ConfigJson { field, source })?;
    crate::config::overlay_json(&mut v, nerf.model_overrides.clone());
    let config: matloc_render::ModelConfig =
        serde_json::from_value(v).map_err(|source| PipelineError::ConfigJson { field, source })?;
    let read = serde_json::to_value(&config)
        .map_err(|source| PipelineError::ConfigJson { field, source })?;
    match crate::config::unknown_overlay_keys(&nerf.model_overrides, &read).first() {
        Some(key) => Err(PipelineError::Config(format!(
            "{field}: unknown field `{key}` (not a field of the NeRF model config)"
        ))),
        None => Ok(config),
    }
}

/// Trains the sub-NeRF of each of `blocks` the map does not record as done (on the lifted
/// training images when the map has them, [`crate::build::sunlight`]).
pub fn run(
    dataset: &Dataset,
    partition: &Partition,
    blocks: &[usize],
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    let mut pending = Vec::new();
    for &b in blocks {
        if b >= partition.blocks.len() {
            return Err(crate::map::MapError::NoSuchBlock {
                block: b,
                blocks: partition.blocks.len(),
            }
            .into());
        }
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
    if pending.is_empty() {
        return Ok(());
    }
    // With the sunlight stage done, the NeRFs fit the training images with the sun's shadows
    // lifted.
    let lifted = crate::build::sunlight::lifted_dataset(dataset, map)?;
    let dataset = lifted.as_ref().unwrap_or(dataset);
    let threads = rayon::current_num_threads();
    // No more blocks at once than threads: each gets at least one of its own.
    for group in pending.chunks(config.nerf.parallel_blocks.clamp(1, threads.max(1))) {
        train_blocks(dataset, partition, map, config, group, threads, progress)?;
    }
    Ok(())
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
    loss: f64,
    psnr: f64,
    rays_per_s: f64,
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
                                loss: f64::from(p.stats.loss),
                                psnr: f64::from(p.stats.psnr),
                                rays_per_s: p.rays_per_s,
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
        let mut curves: Vec<CurveLog> = group
            .iter()
            .map(|b| CurveLog::open(map, &format!("nerf/{b}")))
            .collect();
        for (slot, msg) in rx {
            let name = format!("nerf/{}", group[slot]);
            if let BlockMsg::Progress(p) = &msg {
                curves[slot].record(
                    p.done,
                    &[
                        ("loss", p.loss),
                        ("psnr", p.psnr),
                        ("rays_per_s", p.rays_per_s),
                    ],
                );
            }
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
    register_dir(map, &block_dir(b))
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_render::Background;
    use serde_json::json;

    /// An override naming another variant of an enum replaces the derived value whole (two
    /// variants merged key by key would be a map no enum reads), and a plain field keeps the
    /// rest of its section.
    #[test]
    fn an_override_of_another_enum_variant_replaces_the_derived_one() {
        let dataset = Dataset {
            root: "d".into(),
            frames: Vec::new(),
            points: None,
            metadata: matloc_data::dataset::SceneMetadata {
                bounds_min: Some([-10.0, -10.0, -2.0]),
                bounds_max: Some([10.0, 10.0, 5.0]),
                ..Default::default()
            },
        };
        let nerf = NerfStageConfig {
            model_overrides: json!({"train": {
                "background": {"Random": [0.5, 0.5, 0.5]},
                "batch_rays": 1024
            }}),
            ..NerfStageConfig::default()
        };
        let c = block_model_config(&dataset, &nerf).unwrap();
        assert_eq!(c.train.background, Background::Random([0.5; 3]));
        assert_eq!(c.train.batch_rays, 1024);
        let base = block_model_config(&dataset, &NerfStageConfig::default()).unwrap();
        assert_eq!(c.train.schedule, base.train.schedule);
        let typo = NerfStageConfig {
            model_overrides: json!({"train": {"batch_rayz": 1}}),
            ..NerfStageConfig::default()
        };
        assert!(block_model_config(&dataset, &typo).is_err());
    }
}
