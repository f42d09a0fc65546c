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

pub(crate) fn metadata(config: &SynthConfig, world: &World) -> SceneMetadata {
    let (lo, hi) = world.bounds();
    SceneMetadata {
        bounds_min: Some([lo.x, lo.y, lo.z]),
        bounds_max: Some([hi.x, hi.y, hi.z]),
        up: Some([0.0, 0.0, 1.0]),
        generator: Some("matloc-synth".into()),
        preset: Some(config.preset.clone()),
        seed: Some(config.seed),
        sun_direction: Some([world.sun.x, world.sun.y, world.sun.z]),
        ..SceneMetadata::default()
    }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> SynthError + '_ {
    move |source| SynthError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// What [`synthesize_with`] writes besides the images.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SynthOutput {
    /// Depth maps (`depth/`, `depth_file_path`), as the synthetic world always could.
    pub depth: bool,
    /// The sparse point cloud real data would have: a COLMAP model with points3D and tracks
    /// in `sparse/0` and nerfstudio's `sparse_pc.ply` (see [`crate::points`]).
    pub points: bool,
}

impl Default for SynthOutput {
    fn default() -> Self {
        SynthOutput {
            depth: true,
            points: false,
        }
    }
}

/// Pixel stride of the exported survey points (about one point per 8×8 pixels of each
/// training view, before keeping those seen twice).
const POINT_STRIDE_PX: usize = 8;

/// Renders every planned frame (rayon) and writes a nerfstudio dataset into `out_dir`:
/// `images/frame_NNNNN.png` (8-bit RGB), `depth/frame_NNNNN.npy` (float32 z-depth in metres,
/// 0 = sky) and `transforms.json` with the scene metadata. Every file is written atomically;
/// `transforms.json` is written last, so a dataset that has one is complete.
pub fn synthesize(
    config: &SynthConfig,
    out_dir: &Path,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<Dataset, SynthError> {
    synthesize_with(config, out_dir, &SynthOutput::default(), progress)
}

/// [`synthesize`] with a choice of what to write besides the images.
pub fn synthesize_with(
    config: &SynthConfig,
    out_dir: &Path,
    output: &SynthOutput,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<Dataset, SynthError> {
    let (world, mut plan) = generate(config)?;
    if !output.depth {
        for f in &mut plan.frames {
            f.depth_path = None;
        }
    }
    let subs: &[&str] = if output.depth {
        &["images", "depth"]
    } else {
        &["images"]
    };
    for sub in subs {
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
    let mut dataset = Dataset {
        root: out_dir.to_path_buf(),
        frames: plan.frames,
        points: None,
        metadata: metadata(config, &world),
    };
    if output.points {
        let points = crate::points::survey_points(&world, &dataset, POINT_STRIDE_PX);
        let ply = crate::points::write_survey_points(&dataset, &points, out_dir)?;
        dataset.points = Some(matloc_data::PointSource::Ply { path: ply });
    }
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
