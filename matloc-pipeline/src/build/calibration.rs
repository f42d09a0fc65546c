//! The calibration stage: held-out training views (every `holdout_every`-th view of a block,
//! kept out of its pairs and encoder, not of its NeRF) — or views rendered halfway from each
//! to its nearest neighbour ([`CalibrationQueries`]) — are localized with the
//! finished map; the attempts fit the confidence model and the bound on an accepted pose's
//! rotation.

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::pose::{Pose, camera_center};
use matloc_core::{Camera, Image};
use matloc_data::Dataset;
use matloc_partition::Partition;

use crate::build::common::{BuildEvent, load_image, spaced, stage, views_of_block};
use crate::config::{CalibrationConfig, CalibrationQueries, MapConfig};
use crate::error::PipelineError;
use crate::gt::TrainingView;
use crate::localizer::FixedPlace;
use crate::localizer::confidence::{ConfidenceModel, Evidence};
use crate::localizer::options::LocalizeOptions;
use crate::map::layout::{CONFIDENCE_FILE, CalibrationRecord};
use crate::map::load::{LoadedBlocks, MapComponents, NerfMapComponents};
use crate::map::manifest::MapDir;

/// Localizes the held-out views and stores the fitted confidence.
pub fn run(
    dataset: &Dataset,
    partition: &Partition,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    let nb = partition.blocks.len();
    let holdout = config.calibration.holdout_every;
    // Each calibration query: its block, its view, and the pose it is localized at.
    let mut held = Vec::new();
    for b in 0..nb {
        let (fit, block_held) = views_of_block(dataset, partition, b, holdout);
        for v in &block_held {
            let truth = match config.calibration.queries {
                CalibrationQueries::HeldOut => v.cam_from_world,
                CalibrationQueries::Rendered => nearest_other(v, fit.iter().chain(&block_held))
                    .map_or(v.cam_from_world, |w| halfway(&v.cam_from_world, &w)),
            };
            held.push((b, v.clone(), truth));
        }
    }
    let held = spaced(&held, config.calibration.max_views);
    stage(
        map,
        "calibration",
        held.len() as u64,
        progress,
        &mut |map, progress| {
            let components = NerfMapComponents;
            let loaded = LoadedBlocks::load(map, nb, &config.localize, &components)?;
            let place = components.place(map, config)?;
            let solver = components.solver(&config.localize);
            let mut samples = Vec::new();
            let mut corrections = Vec::new();
            for (done, (b, v, truth)) in held.iter().enumerate() {
                let (image, camera) = match config.calibration.queries {
                    CalibrationQueries::HeldOut => load_image(dataset, v.index)?,
                    CalibrationQueries::Rendered => {
                        (render_rgb(&loaded, *b, &v.camera, truth)?, v.camera)
                    }
                };
                let hyps = place.predict(
                    &image,
                    &camera,
                    config.calibration.hypotheses_per_view.max(1),
                )?;
                for h in hyps {
                    let h_coarse = h.cam_from_world;
                    let fixed = FixedPlace(vec![h]);
                    let options = LocalizeOptions {
                        top_k: 1,
                        confidence: ConfidenceModel {
                            accept_threshold: 0.0,
                            ..config.localize.confidence.clone()
                        },
                        ..config.localize.clone()
                    };
                    let localizer = loaded.localizer(&fixed, solver.as_ref(), options);
                    let out = localizer.localize(&image, &camera)?;
                    let Some(rep) = out.hypotheses.first() else {
                        continue;
                    };
                    let evidence = Evidence {
                        inliers: rep.inliers,
                        inlier_ratio: if rep.matches == 0 {
                            0.0
                        } else {
                            rep.inliers as f64 / rep.matches as f64
                        },
                        matches: rep.matches,
                        alignment: rep.alignment,
                    };
                    let (te, re) = match &out.cam_from_world {
                        Some(p) => (translation_error_m(p, truth), rotation_error_deg(p, truth)),
                        None => (f64::INFINITY, f64::INFINITY),
                    };
                    let ok = te <= config.calibration.correct_translation_m
                        && re <= config.calibration.correct_rotation_deg;
                    samples.push((evidence, ok, te, re));
                    corrections.push(
                        out.cam_from_world
                            .as_ref()
                            .map_or(f64::INFINITY, |p| rotation_error_deg(p, &h_coarse)),
                    );
                }
                progress(&BuildEvent::StageProgress {
                    done: done as u64 + 1,
                    message: format!(
                        "{} attempts, {} correct",
                        samples.len(),
                        samples.iter().filter(|s| s.1).count()
                    ),
                });
            }
            let labelled: Vec<(Evidence, bool)> = samples.iter().map(|s| (s.0, s.1)).collect();
            let model = ConfidenceModel::fit(&labelled, config.calibration.accept_threshold)?;
            let right = labelled
                .iter()
                .filter(|(e, ok)| model.accept(e) == *ok)
                .count();
            let accuracy = right as f64 / labelled.len().max(1) as f64;
            let max_accept_rotation_deg = rotation_bound(
                samples
                    .iter()
                    .zip(&corrections)
                    .filter(|(s, _)| s.1)
                    .map(|(_, c)| *c),
                &config.calibration,
                config.localize.max_accept_rotation_deg,
            );
            // Infinite errors are not valid JSON numbers: store them as a large sentinel.
            let samples = samples
                .into_iter()
                .map(|(e, ok, t, r)| (e, ok, t.min(1e9), r.min(1e9)))
                .collect();
            map.write_json(
                CONFIDENCE_FILE,
                &CalibrationRecord {
                    model,
                    samples,
                    accuracy,
                    corrections_deg: corrections.iter().map(|c| c.min(1e9)).collect(),
                    max_accept_rotation_deg,
                    queries: config.calibration.queries,
                },
            )?;
            Ok(())
        },
    )
}

/// The pose of `other` nearest `v` by camera centre (not `v` itself), if any.
fn nearest_other<'a>(
    v: &TrainingView,
    others: impl Iterator<Item = &'a TrainingView>,
) -> Option<Pose> {
    let c = camera_center(&v.cam_from_world);
    others
        .filter(|w| w.index != v.index)
        .map(|w| {
            (
                (camera_center(&w.cam_from_world) - c).norm(),
                w.cam_from_world,
            )
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, p)| p)
}

/// The camera halfway between two poses: centres averaged, attitudes slerped.
fn halfway(a: &Pose, b: &Pose) -> Pose {
    matloc_core::pose::interpolate(a, b, 0.5)
}

/// Block `b`'s NeRF rendered in colour at `pose`.
fn render_rgb(
    loaded: &LoadedBlocks,
    b: usize,
    camera: &Camera,
    pose: &Pose,
) -> Result<Image<f32>, PipelineError> {
    let nerf = loaded
        .0
        .get(b)
        .and_then(|block| block.nerf.as_ref())
        .ok_or(PipelineError::Internal(
            "calibration renders need the block's NeRF",
        ))?;
    Ok(crate::baselines::render_colour(nerf.model(), camera, pose)?.1)
}

/// The calibrated rotation-correction bound: `margin ×` the 90th percentile of the corrections
/// of correct attempts, within `[min_rotation_bound_deg, configured]`; `None` when the margin
/// is 0 or no attempt was correct (the configured bound applies). A percentile, not the
/// largest: one correct attempt turned 4.1° on a map whose others stayed ≤ 2.1°, and the bound
/// it gave (10.2°) let through a wrong pose that had turned 8.2°.
pub fn rotation_bound(
    correct_corrections_deg: impl Iterator<Item = f64>,
    config: &CalibrationConfig,
    configured_deg: f64,
) -> Option<f64> {
    if config.rotation_bound_margin <= 0.0 {
        return None;
    }
    let mut c: Vec<f64> = correct_corrections_deg.filter(|c| c.is_finite()).collect();
    if c.is_empty() {
        return None;
    }
    c.sort_by(f64::total_cmp);
    let p90 = c[((c.len() - 1) as f64 * 0.9).round() as usize];
    Some(
        (config.rotation_bound_margin * p90)
            .max(config.min_rotation_bound_deg)
            .min(configured_deg),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::pose::look_at;
    use nalgebra::{Point3, Vector3};
    use proptest::prelude::*;

    fn view(index: usize, eye: [f64; 3], target: [f64; 3]) -> TrainingView {
        TrainingView {
            index,
            camera: Camera::pinhole(64, 48, 50.0, 50.0, 32.0, 24.0).unwrap(),
            cam_from_world: look_at(&Point3::from(eye), &Point3::from(target), &Vector3::y())
                .unwrap(),
        }
    }

    proptest! {
        /// The halfway camera sits at the centres' midpoint, its attitude half the turn from
        /// either end.
        #[test]
        fn halfway_averages_centres_and_splits_the_turn(
            a in prop::array::uniform3(-50.0f64..50.0),
            b in prop::array::uniform3(-50.0f64..50.0),
            ta in prop::array::uniform3(-5.0f64..5.0),
            tb in prop::array::uniform3(-5.0f64..5.0),
        ) {
            let pa = view(0, [a[0], a[1], a[2] + 100.0], ta).cam_from_world;
            let pb = view(1, [b[0], b[1], b[2] + 100.0], tb).cam_from_world;
            let h = halfway(&pa, &pb);
            let mid = nalgebra::center(&camera_center(&pa), &camera_center(&pb));
            prop_assert!((camera_center(&h) - mid).norm() < 1e-9);
            let (ra, rb) = (rotation_error_deg(&h, &pa), rotation_error_deg(&h, &pb));
            prop_assert!((ra - rb).abs() < 1e-6);
            prop_assert!((ra + rb - rotation_error_deg(&pa, &pb)).abs() < 1e-6);
        }
    }

    /// Two attitudes 0.3° apart, 150 m from the origin: the case where an unnormalised slerp
    /// moved the halfway centre off the midpoint.
    #[test]
    fn halfway_between_nearby_attitudes_keeps_the_midpoint() {
        let pa = view(
            0,
            [0.0, 48.72353728411438, 107.66800527267098],
            [2.0236833864540973, 0.0, 1.9670420981530095],
        )
        .cam_from_world;
        let pb = view(
            1,
            [-3.187369372660751, 48.82912256842869, 100.0],
            [-1.1666128644132898, 3.7582347752903944, 3.418699288362063],
        )
        .cam_from_world;
        let h = halfway(&pa, &pb);
        let mid = nalgebra::center(&camera_center(&pa), &camera_center(&pb));
        assert!((camera_center(&h) - mid).norm() < 1e-9);
        assert!((h.rotation.into_inner().norm() - 1.0).abs() < 1e-15);
    }

    #[test]
    fn the_nearest_other_view_is_never_the_view_itself() {
        let v = view(3, [0.0, 0.0, 10.0], [0.0, 0.0, 0.0]);
        let near = view(5, [1.0, 0.0, 10.0], [1.0, 0.0, 0.0]);
        let far = view(7, [9.0, 0.0, 10.0], [9.0, 0.0, 0.0]);
        let all = [v.clone(), far.clone(), near.clone()];
        assert_eq!(nearest_other(&v, all.iter()), Some(near.cam_from_world));
        assert_eq!(nearest_other(&v, [v.clone()].iter()), None);
    }

    #[test]
    fn rotation_bound_scales_the_p90_correct_correction_within_limits() {
        let cfg = CalibrationConfig::default();
        let b = |c: &[f64], cfg: &CalibrationConfig| rotation_bound(c.iter().copied(), cfg, 45.0);
        // 2.5 × the 90th percentile (4° among these); non-finite corrections (no pose) are
        // ignored.
        let mut c: Vec<f64> = (1..=10).map(|i| i as f64 * 0.4).collect();
        c.push(f64::INFINITY);
        assert_eq!(b(&c, &cfg), Some(2.5 * 3.6));
        // One outlier among many does not move it.
        let mut outlier = vec![2.0; 19];
        outlier.push(9.0);
        assert_eq!(b(&outlier, &cfg), Some(6.0));
        // Never below the floor, never above the configured bound.
        assert_eq!(b(&[0.5], &cfg), Some(cfg.min_rotation_bound_deg));
        assert_eq!(b(&[30.0], &cfg), Some(45.0));
        // No correct attempt, or the bound turned off: the configured bound applies.
        assert_eq!(b(&[], &cfg), None);
        assert_eq!(b(&[f64::INFINITY], &cfg), None);
        let off = CalibrationConfig {
            rotation_bound_margin: 0.0,
            ..cfg
        };
        assert_eq!(b(&[4.0], &off), None);
    }
}
