//! Rendering a planned survey into a nerfstudio dataset on disk.

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use super::config::SynthConfig;
use super::error::SynthError;
use super::survey::{SurveyPlan, plan_survey};
use super::world::World;
use matloc_data::dataset::{Dataset, SceneMetadata};

/// Progress of [`synthesize`], reported after each written frame (from worker threads).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Progress {
    /// Frames written so far.
    pub done: usize,
    /// Frames in total.
    pub total: usize,
}

/// Generates the world and plans the survey for `config` without rendering anything.
pub fn generate(config: &SynthConfig) -> Result<(World, SurveyPlan), SynthError> {
    config.validate()?;
    let world = World::generate(&config.world, config.seed)?;
    let plan = plan_survey(&world, &config.survey, config.seed)?;
    Ok((world, plan))
}

fn metadata(config: &SynthConfig, world: &World) -> SceneMetadata {
    let (lo, hi) = world.bounds();
    SceneMetadata {
        bounds_min: Some([lo.x, lo.y, lo.z]),
        bounds_max: Some([hi.x, hi.y, hi.z]),
        up: Some([0.0, 0.0, 1.0]),
        generator: Some("matloc-synth".into()),
        preset: Some(config.preset.clone()),
        seed: Some(config.seed),
    }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> SynthError + '_ {
    move |source| SynthError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Renders every planned frame (rayon) and writes a nerfstudio dataset into `out_dir`:
/// `images/frame_NNNNN.png` (8-bit RGB), `depth/frame_NNNNN.npy` (float32 z-depth in metres,
/// 0 = sky) and `transforms.json` with the scene metadata. Every file is written atomically;
/// `transforms.json` is written last, so a dataset that has one is complete.
pub fn synthesize(
    config: &SynthConfig,
    out_dir: &Path,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<Dataset, SynthError> {
    let (world, plan) = generate(config)?;
    for sub in ["images", "depth"] {
        let d = out_dir.join(sub);
        std::fs::create_dir_all(&d).map_err(io_err(&d))?;
    }
    let total = plan.frames.len();
    let done = AtomicUsize::new(0);
    progress(Progress { done: 0, total });
    plan.frames
        .par_iter()
        .try_for_each(|frame| -> Result<(), SynthError> {
            let r = world.render(&frame.camera, &frame.cam_from_world, &config.render);
            write_png(&r.rgb, &out_dir.join(&frame.image_path))?;
            if let Some(dp) = &frame.depth_path {
                write_npy(&r.depth, &out_dir.join(dp))?;
            }
            let d = done.fetch_add(1, Ordering::Relaxed) + 1;
            progress(Progress { done: d, total });
            Ok(())
        })?;
    let dataset = Dataset {
        root: out_dir.to_path_buf(),
        frames: plan.frames,
        metadata: metadata(config, &world),
    };
    write_transforms(&dataset, &out_dir.join("transforms.json"))?;
    Ok(dataset)
}

pub(crate) fn write_png(img: &matloc_core::Image<f32>, path: &Path) -> Result<(), SynthError> {
    matloc_data::images::write_png_rgb(img, path).map_err(|e| SynthError::Image(Box::new(e)))
}

fn write_npy(depth: &matloc_core::Image<f32>, path: &Path) -> Result<(), SynthError> {
    matloc_data::images::write_depth_npy(depth, path).map_err(|e| SynthError::Image(Box::new(e)))
}

fn write_transforms(dataset: &Dataset, path: &Path) -> Result<(), SynthError> {
    matloc_data::nerfstudio::write_nerfstudio(dataset, path)
        .map_err(|e| SynthError::Dataset(Box::new(e)))
}
