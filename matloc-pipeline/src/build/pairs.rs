//! The ground-truth pair stage: per block, 2D–3D pairs from perturbed training poses rendered
//! by the block's sub-NeRF ([`crate::gt`]), the input of encoder training and selection.

use matloc_encoder::ENCODER_STRIDE;

use crate::build::common::{BuildEvent, spaced, stage};
use crate::config::MapConfig;
use crate::error::PipelineError;
use crate::gt::{GtConfig, TrainingView, generate_pairs};
use crate::map::layout::pairs_file;
use crate::map::load::load_nerf;
use crate::map::manifest::MapDir;

/// Generates block `b`'s pairs from its training views `fit` (hold-out excluded).
pub fn run(
    b: usize,
    fit: &[TrainingView],
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    let pair_views = spaced(fit, config.pairs.views_per_block);
    stage(
        map,
        &format!("pairs/{b}"),
        pair_views.len() as u64,
        progress,
        &mut |map, _| {
            let renderer = load_nerf(map, b, 0)?;
            let gt_cfg = GtConfig {
                stride: ENCODER_STRIDE,
                perturbation: config.pairs.perturbation.clone(),
                perturbations_per_view: config.pairs.perturbations_per_view,
                ..GtConfig::default()
            };
            let set = generate_pairs(&renderer, &pair_views, &gt_cfg, b as u64)
                .map_err(|e| PipelineError::in_block(b, e))?;
            let bytes = set.to_bytes().map_err(|e| PipelineError::in_block(b, e))?;
            map.write_file(&pairs_file(b), &bytes)?;
            Ok(())
        },
    )
}
