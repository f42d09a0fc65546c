//! The query-encoder stage: per block, a CNN trained to map the block's training images to the
//! features its sub-NeRF renders at their true poses ([`matloc_encoder`]).

use matloc_data::Dataset;
use matloc_encoder::{
    ENCODER_STRIDE, EncoderProgress, EncoderSample, EncoderTrainConfig, QueryEncoder, SampleView,
    train_encoder,
};
use matloc_match::{FeatureStats, ViewRenderer};
use matloc_partition::Partition;

use crate::build::common::{BuildEvent, CurveLog, load_image, spaced, stage, views_of_block};
use crate::config::MapConfig;
use crate::error::PipelineError;
use crate::gt::TrainingView;
use crate::map::layout::encoder_file;
use crate::map::load::load_nerf;
use crate::map::manifest::MapDir;

/// Block `b`'s encoder training views: its training views less the hold-out, evenly spaced
/// down to the configured count.
pub fn encoder_views(
    dataset: &Dataset,
    partition: &Partition,
    config: &MapConfig,
    b: usize,
) -> Vec<TrainingView> {
    let (fit, _) = views_of_block(dataset, partition, b, config.calibration.holdout_every);
    spaced(&fit, config.encoder.views_per_block)
}

/// Trains block `b`'s query encoder on `views` into the `dims` of its sub-NeRF's features
/// (targets rendered at the views' true poses; statistics from the rendered surface cells).
pub fn train_block_encoder(
    map: &MapDir,
    dataset: &Dataset,
    config: &MapConfig,
    b: usize,
    views: &[TrainingView],
    dims: &[usize],
    progress: &mut dyn FnMut(&EncoderProgress),
) -> Result<QueryEncoder, PipelineError> {
    let renderer = load_nerf(map, b, 0)?;
    let up_world = dataset.up_direction();
    let mut samples = Vec::with_capacity(views.len());
    let mut rows = Vec::new();
    let nd = dims.len();
    for v in views {
        let (image, _) = load_image(dataset, v.index)?;
        let target = renderer
            .render_view(&v.camera, &v.cam_from_world, ENCODER_STRIDE, dims)
            .map_err(PipelineError::ViewRender)?;
        for i in 0..target.cols * target.rows {
            if target.has_surface(i, config.encoder.train.min_accumulation) {
                rows.extend_from_slice(&target.features[i * nd..(i + 1) * nd]);
            }
        }
        let up = v.cam_from_world.rotation * up_world;
        samples.push(EncoderSample {
            image,
            target,
            view: Some(SampleView {
                camera: v.camera,
                up_cam: [up.x, up.y, up.z],
            }),
        });
    }
    if rows.is_empty() {
        return Err(PipelineError::Config(format!(
            "block {b}: the sub-NeRF renders no surface at its training views"
        )));
    }
    let stats = FeatureStats::from_features(&rows, nd);
    let cfg = EncoderTrainConfig {
        seed: config.encoder.train.seed.wrapping_add(b as u64),
        ..config.encoder.train.clone()
    };
    Ok(train_encoder(
        &samples,
        dims.to_vec(),
        stats,
        &cfg,
        progress,
    )?)
}

/// Trains and stores block `b`'s query encoder on all the field's dims.
pub fn run(
    dataset: &Dataset,
    partition: &Partition,
    b: usize,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    let all_dims: Vec<usize> = (0..matloc_nerf_field::FEATURE_DIM).collect();
    let enc_views = encoder_views(dataset, partition, config, b);
    let steps = config.encoder.train.total_steps() as u64;
    stage(
        map,
        &format!("encoder/{b}"),
        steps,
        progress,
        &mut |map, progress| {
            let mut curve = CurveLog::open(map, &format!("encoder/{b}"));
            let enc =
                train_block_encoder(map, dataset, config, b, &enc_views, &all_dims, &mut |p| {
                    curve.record(
                        p.step as u64,
                        &[
                            ("loss", f64::from(p.loss)),
                            ("mse", f64::from(p.mse)),
                            ("nce", f64::from(p.nce)),
                        ],
                    );
                    progress(&BuildEvent::StageProgress {
                        done: p.step as u64,
                        message: format!("loss {:.3} (mse {:.3}, nce {:.3})", p.loss, p.mse, p.nce),
                    })
                })?;
            let path = map.path_of(&encoder_file(b))?;
            enc.save(&path)?;
            map.register_file(&encoder_file(b))?;
            Ok(())
        },
    )
}
