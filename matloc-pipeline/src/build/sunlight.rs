//! The sunlight stage (only with `sunlight.enabled`): the cast shadows of the map's sun are
//! found in every training image from the per-frame surfaces and lifted
//! ([`matloc_surface::sunlight`]); the lifted images (`sunlight/frame_NNNNN.png`, at the working
//! resolution) are what the NeRF stage fits, while the encoders, place predictor and
//! calibration keep the images as they were taken. The sun's direction is the config's, else
//! the dataset's metadata, else estimated from eight training views
//! ([`matloc_surface::sunlight::estimate_sun`]). `sunlight.json` records the sun and where it
//! came from, the measured gain and each image's shadowed fraction.

use std::path::Path;

use matloc_core::Image;
use matloc_data::images::{downscale_depth, encode_png_rgb, load_frame_image};
use matloc_data::{Dataset, Frame, Split};
use matloc_surface::FrameSurfaces;
use matloc_surface::sunlight::{
    DepthView, ShadowEdges, estimate_sun, lift_shadows, nearest_views, shadow_mask, sun_edges,
    sun_views,
};
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
    /// Where it came from: `"config"`, `"dataset metadata"` or `"estimated from the images"`.
    pub sun_source: String,
    /// How well the sun explains the images' shadows (absent in maps built before the check).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub check: Option<SunCheck>,
    /// Light a shadow took away, per channel (linear light, lit ÷ shadowed).
    pub gain: [f32; 3],
    /// Pixel pairs across mask edges the gain was measured on.
    pub edge_pairs: u64,
    /// Per lifted training image: its frame index, map file and shadowed fraction.
    pub images: Vec<LiftedImage>,
}

/// How well the sun explains the images' shadows, on the views checked.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SunCheck {
    /// Mean `ln(lit / shadowed)` brightness across its shadows' edges.
    pub contrast: f64,
    /// Pixel pairs across those edges.
    pub pairs: u64,
    /// When estimated: the best score of a sun at least 20° away, against the estimate's.
    pub rival: Option<f64>,
    /// Training views checked (and searched).
    pub views: usize,
}

/// Training views the sun is checked (or searched) on, spread over the training set.
const SUN_VIEWS: usize = 8;
/// Longest side of the mask grids the sun is checked on (the search's coarse pass uses half).
const SUN_SIDE: usize = 192;
/// Least mean `ln(lit / shadowed)` across the sun's shadow edges (a ratio of 1.35). With
/// depth files the synthetic worlds' true suns give 0.79 to 1.33; on triangulated points, under
/// 0.05.
const MIN_SUN_CONTRAST: f64 = 0.3;

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

/// The sun direction given to the stage: the config's, else the dataset's metadata (unit
/// length); `None` when neither gives one (the stage then estimates it).
fn given_sun_direction(
    dataset: &Dataset,
    config: &MapConfig,
) -> Result<Option<(Vector3<f64>, &'static str)>, PipelineError> {
    let (d, source) = match (
        config.sunlight.sun_direction,
        dataset.metadata.sun_direction,
    ) {
        (Some(d), _) => (d, "config"),
        (None, Some(d)) => (d, "dataset metadata"),
        (None, None) => return Ok(None),
    };
    let v = Vector3::from(d);
    let n = v.norm();
    if !(n.is_finite() && n > 1e-9) {
        return Err(PipelineError::Config(format!(
            "sun direction from the {source} must be a finite non-zero vector, got {d:?}"
        )));
    }
    Ok(Some((v / n, source)))
}

/// The sun the stage lifts: the given one, else estimated from `SUN_VIEWS` training views
/// spread over `views` (each with its neighbours voting). Either way its shadows must darken
/// the images across their edges by at least [`MIN_SUN_CONTRAST`], or the stage stops with an
/// error saying what to check (a direction pointing away from the sun, a surface too coarse to
/// trace shadows on, an overcast day).
fn choose_sun(
    given: Option<(Vector3<f64>, &'static str)>,
    views: &[DepthView],
    neighbours: &[Vec<usize>],
    dataset: &Dataset,
    frames: &[&Frame],
    surface: &str,
) -> Result<(Vector3<f64>, &'static str, SunCheck), PipelineError> {
    let picked = matloc_core::subset::evenly_spaced(views.len(), SUN_VIEWS);
    let images = picked
        .par_iter()
        .map(|&v| Ok(load_frame_image(dataset, frames[v], 1)?.0))
        .collect::<Result<Vec<Image<f32>>, PipelineError>>()?;
    let search = sun_views(views, neighbours, &picked, &images);
    let started = std::time::Instant::now();
    // The estimate measured its own edges on the same grid; a given sun is measured here.
    let (sun, source, rival, measured) = match given {
        Some((sun, source)) => {
            let measured = sun_edges(&search, &sun, SUN_SIDE)
                .contrast()
                .unwrap_or((0.0, 0));
            (sun, source, None, measured)
        }
        None => {
            let est = estimate_sun(&search, SUN_SIDE).ok_or_else(|| {
                PipelineError::Config(format!(
                    "sunlight: the sun's direction is not given, and no direction casts a shadow \
                     on the {surface} surface; set `sunlight.sun_direction` (world frame, towards \
                     the sun) or give the dataset a `sun_direction` in its metadata"
                ))
            })?;
            (
                est.direction,
                "estimated from the images",
                Some(est.rival),
                (est.contrast, est.pairs),
            )
        }
    };
    let (contrast, pairs) = measured;
    tracing::info!(
        direction = ?sun.as_slice(),
        source,
        contrast,
        pairs,
        ?rival,
        seconds = started.elapsed().as_secs_f64(),
        "sunlight: the sun's shadows against the images"
    );
    if contrast < MIN_SUN_CONTRAST {
        return Err(PipelineError::Config(format!(
            "sunlight: the shadows the sun direction {:?} ({source}) casts on the {surface} \
             surface do not fall where the images darken (lit / shadowed brightness across their \
             edges {:.2}, {pairs} pixel pairs, at least {:.2} needed). Check that the direction \
             points towards the sun in the dataset's world frame; shadows are traced well only on \
             depth files (triangulated points and sparse clouds are too coarse); an overcast day \
             has no shadows to lift: disable `sunlight`",
            sun.as_slice(),
            contrast.exp(),
            MIN_SUN_CONTRAST.exp()
        )));
    }
    Ok((
        sun,
        source,
        SunCheck {
            contrast,
            pairs,
            rival,
            views: search.len(),
        },
    ))
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
    let given = given_sun_direction(dataset, config)?;
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
        .map(|(f, d)| DepthView::of(f, d))
        .collect();
    // Each view's nearest views by camera centre: they vote on its shadows.
    let centres: Vec<_> = frames.iter().map(|f| f.center()).collect();
    let neighbours = nearest_views(&centres, config.sunlight.neighbours);
    let surface = surfaces.plan().kind.to_string();
    let (sun, sun_source, check) =
        choose_sun(given, &views, &neighbours, dataset, &frames, &surface)?;
    let masks: Vec<Image<f32>> = (0..views.len())
        .into_par_iter()
        .map(|v| {
            let others: Vec<DepthView> = neighbours[v].iter().map(|&o| views[o]).collect();
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
            check: Some(check),
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
    fn the_sun_comes_from_the_config_else_the_metadata_else_the_search() {
        let mut config = MapConfig::default();
        config.sunlight.enabled = true;
        assert_eq!(given_sun_direction(&dataset(None), &config).unwrap(), None);
        let (d, source) = given_sun_direction(&dataset(Some([0.0, 3.0, 4.0])), &config)
            .unwrap()
            .unwrap();
        assert_eq!(source, "dataset metadata");
        assert!((d - Vector3::new(0.0, 0.6, 0.8)).norm() < 1e-12);
        config.sunlight.sun_direction = Some([0.0, 0.0, 2.0]);
        let (d, source) = given_sun_direction(&dataset(Some([0.0, 3.0, 4.0])), &config)
            .unwrap()
            .unwrap();
        assert_eq!((source, d), ("config", Vector3::z()));
        config.sunlight.sun_direction = Some([0.0, 0.0, 0.0]);
        let e = given_sun_direction(&dataset(None), &config)
            .unwrap_err()
            .to_string();
        assert!(e.contains("non-zero"), "{e}");
    }
}
