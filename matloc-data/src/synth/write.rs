//! Rendering a planned survey into a nerfstudio dataset on disk.

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use super::survey::{SurveyPlan, plan_survey};
use super::world::World;
use super::{SynthConfig, SynthError};
use crate::dataset::{Dataset, SceneMetadata};

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
    let bytes: Vec<u8> = img
        .data()
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        .collect();
    let mut out = Vec::new();
    let enc = image::codecs::png::PngEncoder::new(&mut out);
    image::ImageEncoder::write_image(
        enc,
        &bytes,
        img.width() as u32,
        img.height() as u32,
        image::ExtendedColorType::Rgb8,
    )
    .map_err(|e| SynthError::Encode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    crate::fsutil::write_atomic(path, &out).map_err(io_err(path))
}

fn write_npy(depth: &matloc_core::Image<f32>, path: &Path) -> Result<(), SynthError> {
    let mut header = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, {}), }}",
        depth.height(),
        depth.width()
    );
    // Magic (6) + version (2) + header length (2) + header, padded to a multiple of 64.
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + 4 * depth.data().len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in depth.data() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    crate::fsutil::write_atomic(path, &out).map_err(io_err(path))
}

fn write_transforms(dataset: &Dataset, path: &Path) -> Result<(), SynthError> {
    let frames: Vec<serde_json::Value> = dataset
        .frames
        .iter()
        .map(|f| {
            let m = matloc_core::pose::opengl_from_cam_from_world(&f.cam_from_world);
            let rows: Vec<Vec<f64>> = (0..4)
                .map(|r| (0..4).map(|c| m[(r, c)]).collect())
                .collect();
            serde_json::json!({
                "file_path": f.image_path,
                "depth_file_path": f.depth_path,
                "transform_matrix": rows,
                "split": f.split,
                "fl_x": f.camera.fx, "fl_y": f.camera.fy, "cx": f.camera.cx, "cy": f.camera.cy,
                "w": f.camera.width, "h": f.camera.height,
            })
        })
        .collect();
    let json = serde_json::json!({ "camera_model": "PINHOLE", "frames": frames, "metadata": dataset.metadata });
    let bytes = serde_json::to_vec_pretty(&json).map_err(|e| SynthError::Dataset(e.to_string()))?;
    crate::fsutil::write_atomic(path, &bytes).map_err(io_err(path))
}
