//! The sunlight stage (only with `sunlight.enabled`): the cast shadows of the map's sun are
//! found in every training image from the per-frame surfaces and lifted
//! ([`matloc_surface::sunlight`]); the lifted images (`sunlight/frame_NNNNN.png`, at the working
//! resolution) are what the NeRF stage fits, while the encoders, place predictor and
//! calibration keep the images as they were taken. `sunlight.json` records the sun, the
//! measured gain and each image's shadowed fraction.

use std::path::Path;

use matloc_core::Image;
use matloc_data::images::{downscale_depth, encode_png_rgb, load_frame_image};
use matloc_data::{Dataset, Split};
use matloc_surface::FrameSurfaces;
use matloc_surface::sunlight::{DepthView, ShadowEdges, lift_shadows, shadow_mask};
use nalgebra::Vector3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::build::common::{BuildEvent, stage};
use crate::config::MapConfig;
use crate::error::PipelineError;
use crate::map::layout::{SUNLIGHT_FILE, sunlight_image};
use crate::map::manifest::MapDir;

/// What the sunlight stage did (`sunlight.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SunlightRecord {
    /// Unit direction towards the sun, world frame.
    pub sun_direction: [f64; 3],
    /// Where it came from: `"config"` or `"dataset metadata"`.
    pub sun_source: String,
    /// Light a shadow took away, per channel (linear light, lit ÷ shadowed).
    pub gain: [f32; 3],
    /// Pixel pairs across mask edges the gain was measured on.
    pub edge_pairs: u64,
    /// Per lifted training image: its frame index, map file and shadowed fraction.
    pub images: Vec<LiftedImage>,
}

/// One lifted training image.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LiftedImage {
    /// Frame index in the working dataset.
    pub frame: usize,
    /// File in the map.
    pub file: String,
    /// Fraction of its mask's cells in shadow.
    pub shadowed: f64,
}

/// The sun direction the stage uses: the config's, else the dataset's metadata; unit length.
fn sun_direction(
    dataset: &Dataset,
    config: &MapConfig,
) -> Result<(Vector3<f64>, &'static str), PipelineError> {
    let (d, source) = match (
        config.sunlight.sun_direction,
        dataset.metadata.sun_direction,
    ) {
        (Some(d), _) => (d, "config"),
        (None, Some(d)) => (d, "dataset metadata"),
        (None, None) => {
            return Err(PipelineError::Config(
                "sunlight.enabled needs the sun's direction: set `sunlight.sun_direction` (world \
                 frame, towards the sun) or give the dataset a `sun_direction` in its metadata"
                    .into(),
            ));
        }
    };
    let v = Vector3::from(d);
    let n = v.norm();
    if !(n.is_finite() && n > 1e-9) {
        return Err(PipelineError::Config(format!(
            "sun direction from the {source} must be a finite non-zero vector, got {d:?}"
        )));
    }
    Ok((v / n, source))
}

/// Finds and lifts the shadows of the training images, unless disabled or done earlier.
pub fn run(
    dataset: &Dataset,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    if !config.sunlight.enabled {
        return Ok(());
    }
    let train = dataset.split_indices(Split::Train);
    stage(
        map,
        "sunlight",
        train.len() as u64,
        progress,
        &mut |map, progress| lift(dataset, &train, map, config, progress),
    )
}

/// The stage's work: masks, gain, lifted images and `sunlight.json`.
fn lift(
    dataset: &Dataset,
    train: &[usize],
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    config.sunlight.validate()?;
    let (sun, sun_source) = sun_direction(dataset, config)?;
    let surfaces =
        FrameSurfaces::prepare(dataset, train, &config.surface, &|phase, done, total| {
            if done == total || done % (total / 10).max(1) == 0 {
                tracing::info!(phase, done, total, "sunlight: triangulating the surface");
            }
        })?;
    let max_side = config.sunlight.max_side;
    // Each training view's surface, no finer than the mask grid.
    let depths = train
        .par_iter()
        .map(|&i| {
            let d = surfaces.depth(dataset, i)?;
            let k = (d.width().max(d.height()) / max_side.max(1)) as u32;
            Ok(if k >= 2 { downscale_depth(&d, k) } else { d })
        })
        .collect::<Result<Vec<Image<f32>>, PipelineError>>()?;
    let frames: Vec<_> = train.iter().map(|&i| &dataset.frames[i]).collect();
    let views: Vec<DepthView> = frames
        .iter()
        .zip(&depths)
        .map(|(f, d)| DepthView {
            camera: &f.camera,
            cam_from_world: &f.cam_from_world,
            depth: d,
        })
        .collect();
    let k = config.sunlight.neighbours;
    let masks: Vec<Image<f32>> = (0..views.len())
        .into_par_iter()
        .map(|v| {
            let c = frames[v].center();
            let mut order: Vec<usize> = (0..views.len()).filter(|&o| o != v).collect();
            order.sort_by(|&a, &b| {
                (frames[a].center() - c)
                    .norm()
                    .total_cmp(&(frames[b].center() - c).norm())
            });
            let others: Vec<DepthView> = order.iter().take(k).map(|&o| views[o]).collect();
            shadow_mask(&views[v], &others, &sun, max_side)
        })
        .collect();
    // Each image is read twice (the gain needs every mask edge before any image is lifted)
    // rather than all held at once.
    let load = |pos: usize| -> Result<Image<f32>, PipelineError> {
        Ok(load_frame_image(dataset, frames[pos], 1)?.0)
    };
    let edges = (0..frames.len())
        .into_par_iter()
        .map(|pos| {
            let mut e = ShadowEdges::default();
            e.add(&load(pos)?, &masks[pos]);
            Ok::<ShadowEdges, PipelineError>(e)
        })
        .try_reduce(ShadowEdges::default, |mut a, b| {
            a.merge(&b);
            Ok(a)
        })?;
    let gain = edges.gain().ok_or_else(|| {
        PipelineError::Config(format!(
            "sunlight: the shadows found along the sun direction {:?} ({sun_source}) have too \
             few clear edges ({} pixel pairs) to measure the light they take away; check the \
             direction (towards the sun, world frame) or disable `sunlight`",
            sun.as_slice(),
            edges.pairs()
        ))
    })?;
    tracing::info!(?gain, pairs = edges.pairs(), "sunlight: shadow gain");
    let mut images = Vec::with_capacity(frames.len());
    for (pos, &i) in train.iter().enumerate() {
        let lifted = lift_shadows(&load(pos)?, &masks[pos], gain, config.sunlight.edge_blur_px);
        let file = sunlight_image(i);
        map.write_file(&file, &encode_png_rgb(&lifted, Path::new(&file))?)?;
        let m = masks[pos].data();
        images.push(LiftedImage {
            frame: i,
            file,
            shadowed: m.iter().filter(|&&v| v > 0.5).count() as f64 / m.len().max(1) as f64,
        });
        progress(&BuildEvent::StageProgress {
            done: pos as u64 + 1,
            message: format!("{} of {} images lifted", pos + 1, frames.len()),
        });
    }
    map.write_json(
        SUNLIGHT_FILE,
        &SunlightRecord {
            sun_direction: [sun.x, sun.y, sun.z],
            sun_source: sun_source.into(),
            gain,
            edge_pairs: edges.pairs(),
            images,
        },
    )?;
    Ok(())
}

/// `dataset` with its training images replaced by the map's lifted ones when the sunlight
/// stage ran (the NeRF stage fits these); otherwise `None`.
pub fn lifted_dataset(dataset: &Dataset, map: &MapDir) -> Result<Option<Dataset>, PipelineError> {
    if !map.stage_done("sunlight") {
        return Ok(None);
    }
    let record: SunlightRecord = map.read_json(SUNLIGHT_FILE)?;
    let mut out = dataset.clone();
    for img in &record.images {
        let frame = out.frames.get_mut(img.frame).ok_or_else(|| {
            PipelineError::Config(format!(
                "{SUNLIGHT_FILE} names frame {} but the dataset has {} frames",
                img.frame,
                dataset.frames.len()
            ))
        })?;
        // Absolute, so the dataset's root does not prefix a map given by a relative path.
        let path = map.path_of(&img.file)?;
        frame.image_path = std::path::absolute(&path).map_err(|source| PipelineError::Io {
            path: path.clone(),
            source,
        })?;
    }
    Ok(Some(out))
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_data::dataset::SceneMetadata;

    fn dataset(sun: Option<[f64; 3]>) -> Dataset {
        Dataset {
            root: "d".into(),
            frames: Vec::new(),
            points: None,
            metadata: SceneMetadata {
                sun_direction: sun,
                ..SceneMetadata::default()
            },
        }
    }

    #[test]
    fn the_sun_comes_from_the_config_else_the_metadata_and_is_required() {
        let mut config = MapConfig::default();
        config.sunlight.enabled = true;
        let e = sun_direction(&dataset(None), &config)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("sunlight.sun_direction") && e.contains("metadata"),
            "{e}"
        );
        let (d, source) = sun_direction(&dataset(Some([0.0, 3.0, 4.0])), &config).unwrap();
        assert_eq!(source, "dataset metadata");
        assert!((d - Vector3::new(0.0, 0.6, 0.8)).norm() < 1e-12);
        config.sunlight.sun_direction = Some([0.0, 0.0, 2.0]);
        let (d, source) = sun_direction(&dataset(Some([0.0, 3.0, 4.0])), &config).unwrap();
        assert_eq!((source, d), ("config", Vector3::z()));
        config.sunlight.sun_direction = Some([0.0, 0.0, 0.0]);
        let e = sun_direction(&dataset(None), &config)
            .unwrap_err()
            .to_string();
        assert!(e.contains("non-zero"), "{e}");
    }
}
