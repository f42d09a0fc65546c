//! The structure stage: keypoints of every training image (at the working resolution) matched
//! with its neighbours and triangulated with the known poses; every keypoint that observes a
//! point is kept with its descriptor (`structure.safetensors`) for the structure localizer
//! ([`matloc_structure`]), the default method of `localize`, `serve` and `eval`.

use std::time::Instant;

use matloc_data::{Dataset, Split};
use matloc_structure::StructureMap;
use matloc_surface::triangulate::triangulate_tracks;

use crate::build::common::BuildEvent;
use crate::config::MapConfig;
use crate::error::PipelineError;
use crate::map::layout::STRUCTURE_FILE;
use crate::map::manifest::MapDir;

/// Triangulates the training images of `dataset` (at the working resolution) and stores the
/// structure, unless done earlier or disabled.
pub fn run(
    dataset: &Dataset,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    if !config.structure.enabled {
        return Ok(());
    }
    if map.stage_done("structure") {
        progress(&BuildEvent::StageFinished {
            name: "structure".into(),
            seconds: 0.0,
            skipped: true,
        });
        return Ok(());
    }
    let t = Instant::now();
    let train = dataset.split_indices(Split::Train);
    progress(&BuildEvent::StageStarted {
        name: "structure".into(),
        total: train.len() as u64,
    });
    let mut tri = config.structure.triangulate.clone();
    // The working images are already at the map's size: detect on them as they are.
    tri.max_side = dataset
        .frames
        .iter()
        .map(|f| f.camera.width.max(f.camera.height))
        .max()
        .unwrap_or(tri.max_side)
        .max(1);
    let tracks = triangulate_tracks(dataset, &train, &tri, &|phase, done, total| {
        if done == total || done % (total / 10).max(1) == 0 {
            tracing::info!(phase, done, total, "structure: triangulating");
        }
    })?;
    let structure = StructureMap::from_tracks(&tracks, |f| dataset.frames[f].cam_from_world);
    tracing::info!(
        points = structure.points().len(),
        observations = structure.observations(),
        images = structure.images().len(),
        "structure triangulated"
    );
    map.write_file(STRUCTURE_FILE, &structure.to_bytes()?)?;
    let secs = t.elapsed().as_secs_f64();
    map.complete_stage("structure", secs)?;
    progress(&BuildEvent::StageFinished {
        name: "structure".into(),
        seconds: secs,
        skipped: false,
    });
    Ok(())
}
