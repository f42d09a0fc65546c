//! The place stage: pose groups (two-stage K-means) over all training poses and the ArcFace
//! place classifier, trained on the survey images plus views the sub-NeRFs render near them
//! and, with the map config's `virtual` on, views they render at virtual viewpoints beyond the
//! survey (`matloc_surface::viewpoints`), each labelled with the pose group that shares the
//! most ground with it ([`shared_ground_label`]).

use std::time::Instant;

use matloc_core::{Camera, Image, Pose};
use matloc_data::{Dataset, Split};
use matloc_match::ViewRenderer;
use matloc_match::nerf_view::NerfViewRenderer;
use matloc_partition::Partition;
use matloc_place::{ExtraViews, PlaceMethod, PlaceModel, PoseGroups, view_point_from_depth};
use matloc_surface::FrameSurfaces;
use matloc_surface::viewpoints::{
    GroundFrame, SceneBox, SurfaceGrid, ViewpointScene, footprint_cells, points_from_depth,
    sample_viewpoints, up_from_views,
};
use nalgebra::{Point3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::build::common::{BuildEvent, CurveLog, load_image, register_dir, stage_recorded};
use crate::config::MapConfig;
use crate::error::PipelineError;
use crate::gt::{PerturbKind, Perturbation};
use crate::map::layout::PLACE_DIR;
use crate::map::load::load_nerf;
use crate::map::manifest::{MapDir, VirtualViewsRecord};

/// Pixel stride of the NeRF depth render that stands in for a missing depth file.
const NERF_DEPTH_STRIDE: u32 = 8;

/// Builds the pose groups and trains the place classifier.
pub fn run(
    dataset: &Dataset,
    partition: &Partition,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    let train_idx = dataset.split_indices(Split::Train);
    stage_recorded(
        map,
        "place",
        config.place.train.epochs as u64,
        progress,
        &mut |map, progress| {
            let mut images = Vec::with_capacity(train_idx.len());
            let mut poses = Vec::with_capacity(train_idx.len());
            let mut view_points = Vec::with_capacity(train_idx.len());
            // Block NeRFs, loaded when a view without a depth file first needs one.
            let mut nerfs = BlockNerfs::default();
            for (k, &i) in train_idx.iter().enumerate() {
                let f = &dataset.frames[i];
                let (image, camera) = load_image(dataset, i)?;
                // The view point is a mean over the seen surface: every 4th depth pixel of a
                // depth file, or the block's NeRF rendered on a grid of every 8th pixel when
                // the dataset has no depth (a full-resolution render per view cost minutes).
                let (depth, stride) = match matloc_data::images::load_frame_depth(dataset, f, 1) {
                    Ok(Some(d)) => (d, 4),
                    _ => {
                        let b = partition.block_of_member(k).unwrap_or(0);
                        let r = nerfs.get(map, b)?;
                        let v = r
                            .render_view(&camera, &f.cam_from_world, NERF_DEPTH_STRIDE, &[])
                            .map_err(PipelineError::ViewRender)?;
                        let d = Image::from_vec(v.cols, v.rows, 1, v.depth_z)
                            .map_err(|_| PipelineError::Internal("depth image shape"))?;
                        (d, 1)
                    }
                };
                let vp = view_point_from_depth(&camera, &f.cam_from_world, &depth, stride)
                    .ok_or_else(|| PipelineError::ViewSeesNoSurface { frame: i })?;
                // Kept at the size training samples from (twice the network input), not the
                // working size: memory per image is then independent of the camera.
                let net = &config.place.train.net;
                images.push(matloc_core::image::resize_area(
                    &image,
                    2 * net.input_width,
                    2 * net.input_height,
                ));
                poses.push(f.cam_from_world);
                view_points.push(vp);
            }
            let mut groups = PoseGroups::build(&poses, &view_points, &config.place.groups)?;
            groups.attach_blocks(|k| partition.block_of_member(k));
            let mut curve = CurveLog::open(map, "place");
            let mut extra = rendered_place_views(
                map, dataset, &train_idx, partition, &groups, config, progress,
            )?;
            let record = virtual_place_views(
                map, dataset, &train_idx, partition, &groups, config, progress,
            )?
            .map(|(views, record)| {
                extra.images.extend(views.images);
                extra.poses.extend(views.poses);
                extra.labels.extend(views.labels);
                record
            });
            let model = PlaceModel::train_with_extra(
                PlaceMethod::ArcFace,
                &images,
                &poses,
                &groups,
                ExtraViews {
                    images: &extra.images,
                    poses: &extra.poses,
                    labels: &extra.labels,
                },
                &config.place.train,
                &mut |r| {
                    curve.record(r.epoch as u64 + 1, &[("loss", f64::from(r.loss))]);
                    progress(&BuildEvent::StageProgress {
                        done: r.epoch as u64 + 1,
                        message: format!("{} groups, loss {:.3}", groups.len(), r.loss),
                    })
                },
            )?;
            let dir = map.path_of(PLACE_DIR)?;
            model.save(&dir)?;
            register_dir(map, PLACE_DIR)?;
            Ok(record)
        },
    )
}

/// Owned images, poses and group labels of [`rendered_place_views`].
#[derive(Default)]
struct RenderedViews {
    images: Vec<Image<f32>>,
    poses: Vec<matloc_core::Pose>,
    labels: Vec<usize>,
}

/// Views rendered by the sub-NeRFs at perturbed training poses, labelled with the group their
/// pose falls in (the source view's group when it falls in none).
fn rendered_place_views(
    map: &MapDir,
    dataset: &Dataset,
    train_idx: &[usize],
    partition: &Partition,
    groups: &PoseGroups,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<RenderedViews, PipelineError> {
    let rv = &config.place.rendered;
    let mut out = RenderedViews::default();
    if rv.per_view == 0 || train_idx.is_empty() {
        return Ok(out);
    }
    let perturb = Perturbation {
        kind: PerturbKind::UniformBall,
        translation_m: rv.translation_m,
        rotation_deg: rv.rotation_deg,
    };
    let mut nerfs = BlockNerfs::default();
    let mut rng = ChaCha8Rng::seed_from_u64(rv.seed);
    for (k, &i) in train_idx.iter().enumerate() {
        let f = &dataset.frames[i];
        let small = render_camera(&f.camera, config)?;
        let nerf = nerfs.get(map, partition.block_of_member(k).unwrap_or(0))?;
        for _ in 0..rv.per_view {
            let pose = perturb.apply(&f.cam_from_world, &mut rng);
            let (_, image) = crate::baselines::render_colour(nerf.model(), &small, &pose)?;
            out.labels
                .push(groups.assign(&pose).unwrap_or(groups.labels[k]));
            out.images.push(image);
            out.poses.push(pose);
        }
        progress(&BuildEvent::StageProgress {
            done: 0,
            message: format!("rendered views {}/{}", k + 1, train_idx.len()),
        });
    }
    Ok(out)
}

/// `camera` at the size the place stage renders views: `place.rendered.width` (0: twice the
/// network's input width) wide, its aspect kept.
fn render_camera(camera: &Camera, config: &MapConfig) -> Result<Camera, PipelineError> {
    let rv = &config.place.rendered;
    let width = if rv.width == 0 {
        2 * config.place.train.net.input_width
    } else {
        rv.width
    };
    let height =
        ((width as f64 * camera.height as f64 / camera.width as f64).round() as u32).max(1);
    Ok(camera.rescaled(width as u32, height)?)
}

/// Depth cells per side of a training view lifted to surface points for the height field.
const SEEN_POINTS_PER_SIDE: usize = 64;

/// Views the sub-NeRFs render at virtual viewpoints (`None` while the map config's `virtual`
/// is off), with what the stage records of them.
///
/// Each training view's surface (as the partition has it: depth files, points, triangulated)
/// is lifted to world points on a grid of about 64 cells per side; the sampler draws poses
/// over each block's scene box with the world's up axis (the dataset's `up`, else minus the
/// training views' mean viewing direction) and the first training camera at the rendered
/// size; each accepted pose is labelled by [`shared_ground_label`] over the height-field cells
/// its footprint lands on and the cells each training view saw, then rendered by its block's
/// NeRF. A pose no group's views saw any of is left out (counted as `unlabelled`).
fn virtual_place_views(
    map: &MapDir,
    dataset: &Dataset,
    train_idx: &[usize],
    partition: &Partition,
    groups: &PoseGroups,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<Option<(RenderedViews, VirtualViewsRecord)>, PipelineError> {
    let vc = &config.virtual_views;
    if !vc.enabled {
        return Ok(None);
    }
    let t = Instant::now();
    let Some(&first) = train_idx.first() else {
        return Err(PipelineError::Config(
            "virtual viewpoints need training views".into(),
        ));
    };
    let surfaces = FrameSurfaces::prepare(
        dataset,
        train_idx,
        &config.surface,
        &|phase, done, total| {
            if done == total || done % (total / 10).max(1) == 0 {
                tracing::info!(
                    phase,
                    done,
                    total,
                    "virtual views: triangulating the surface"
                );
            }
        },
    )?;
    let seen = train_idx
        .par_iter()
        .map(|&i| {
            let f = &dataset.frames[i];
            let d = surfaces.depth(dataset, i)?;
            let stride = (d.width().max(d.height()) / SEEN_POINTS_PER_SIDE).max(1);
            Ok(points_from_depth(&f.camera, &f.cam_from_world, &d, stride))
        })
        .collect::<Result<Vec<Vec<Point3<f64>>>, PipelineError>>()?;
    let poses: Vec<Pose> = train_idx
        .iter()
        .map(|&i| dataset.frames[i].cam_from_world)
        .collect();
    let centres: Vec<Point3<f64>> = train_idx
        .iter()
        .map(|&i| dataset.frames[i].center())
        .collect();
    let up = match dataset.metadata.up {
        Some(u) => Vector3::from(u),
        None => up_from_views(&poses).ok_or_else(|| {
            PipelineError::Config(
                "virtual viewpoints: the dataset records no `up` and the training views' \
                 directions cancel out"
                    .into(),
            )
        })?,
    };
    let camera = render_camera(&dataset.frames[first].camera, config)?;
    let blocks: Vec<SceneBox> = partition
        .blocks
        .iter()
        .map(|b| SceneBox {
            min: b.bounds.min,
            max: b.bounds.max,
        })
        .collect();
    let sampled = sample_viewpoints(
        vc,
        &ViewpointScene {
            up,
            camera: &camera,
            training_centres: &centres,
            seen: &seen,
            blocks: &blocks,
        },
    )?;
    let frame = GroundFrame::new(up).ok_or_else(|| {
        PipelineError::Config(format!("virtual viewpoints: unusable up axis {up:?}"))
    })?;
    let grid = SurfaceGrid::build(frame, sampled.cell_m, &seen)?;
    let seen_cells: Vec<Vec<usize>> = seen.iter().map(|p| grid.cells_of(p)).collect();
    drop(seen);
    let members: Vec<&[usize]> = groups.groups.iter().map(|g| g.members.as_slice()).collect();
    let mut out = RenderedViews::default();
    let mut record = VirtualViewsRecord {
        views: 0,
        candidates: sampled.candidates,
        rejected: sampled.rejected,
        unlabelled: 0,
        per_block: vec![0; blocks.len()],
        per_group: vec![0; groups.len()],
        survey_height_m: sampled.survey_height_m,
        cell_m: sampled.cell_m,
        seconds: 0.0,
    };
    let mut nerfs = BlockNerfs::default();
    for (n, vp) in sampled.poses.iter().enumerate() {
        let footprint = footprint_cells(&grid, &camera, &vp.cam_from_world);
        let Some(label) = shared_ground_label(&footprint, &seen_cells, &members) else {
            record.unlabelled += 1;
            continue;
        };
        let nerf = nerfs.get(map, vp.block)?;
        let (_, image) =
            crate::baselines::render_colour(nerf.model(), &camera, &vp.cam_from_world)?;
        out.images.push(image);
        out.poses.push(vp.cam_from_world);
        out.labels.push(label);
        record.views += 1;
        if let Some(c) = record.per_block.get_mut(vp.block) {
            *c += 1;
        }
        if let Some(c) = record.per_group.get_mut(label) {
            *c += 1;
        }
        progress(&BuildEvent::StageProgress {
            done: 0,
            message: format!("virtual views {}/{}", n + 1, sampled.poses.len()),
        });
    }
    record.seconds = t.elapsed().as_secs_f64();
    tracing::info!(
        views = record.views,
        candidates = record.candidates,
        rejected = record.rejected.total(),
        unlabelled = record.unlabelled,
        seconds = record.seconds,
        "virtual views rendered for the place classifier"
    );
    Ok(Some((out, record)))
}

/// The pose group that shares the most ground with a view: the group whose member views saw,
/// on average, the largest part of the view's footprint. `footprint` holds the height-field
/// cell each footprint ray lands on (one entry per ray, [`footprint_cells`]); `seen_cells[m]`
/// the cells training view `m` saw (increasing, [`SurfaceGrid::cells_of`]); `members[g]` the
/// training views of group `g`. A group's score is the mean over its members of the number of
/// footprint rays landing on a cell the member saw — a mean, so a large group that spreads
/// over the area does not outvote a small one that looks at the same ground; where the camera
/// stands does not enter. Ties go to the lowest group id; `None` when no member of any group
/// saw any of the footprint.
pub(crate) fn shared_ground_label(
    footprint: &[usize],
    seen_cells: &[Vec<usize>],
    members: &[&[usize]],
) -> Option<usize> {
    // Best so far as the exact fraction (hits, members).
    let mut best: Option<(usize, u64, u64)> = None;
    for (g, ms) in members.iter().enumerate() {
        if ms.is_empty() {
            continue;
        }
        let hits: u64 = ms
            .iter()
            .filter_map(|&m| seen_cells.get(m))
            .map(|cells| {
                footprint
                    .iter()
                    .filter(|c| cells.binary_search(c).is_ok())
                    .count() as u64
            })
            .sum();
        let n = ms.len() as u64;
        let better = match best {
            None => hits > 0,
            Some((_, bh, bn)) => u128::from(hits) * u128::from(bn) > u128::from(bh) * u128::from(n),
        };
        if better {
            best = Some((g, hits, n));
        }
    }
    best.map(|(g, _, _)| g)
}

/// Block NeRFs loaded when first needed, kept for the stage.
#[derive(Default)]
struct BlockNerfs(Vec<Option<NerfViewRenderer>>);

impl BlockNerfs {
    /// Block `b`'s NeRF, loaded from `map` on first use.
    fn get(&mut self, map: &MapDir, b: usize) -> Result<&NerfViewRenderer, PipelineError> {
        if self.0.len() <= b {
            self.0.resize_with(b + 1, || None);
        }
        if self.0[b].is_none() {
            self.0[b] = Some(load_nerf(map, b, 0)?);
        }
        self.0[b]
            .as_ref()
            .ok_or(PipelineError::Internal("NeRF not loaded"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_surface::viewpoints::heading_pitch_pose;

    /// Flat ground at height 0 over `[0, 100] × [0, 40]`; a nadir training view at `(x, 20)`
    /// sees a 1 m lattice within 15 m of the point under it.
    fn nadir_view(x: f64) -> Vec<Point3<f64>> {
        let mut pts = Vec::new();
        for dx in -15..15 {
            for y in 0..40 {
                let px = x + dx as f64 + 0.5;
                if (0.0..100.0).contains(&px) {
                    pts.push(Point3::new(px, y as f64 + 0.5, 0.0));
                }
            }
        }
        pts
    }

    #[test]
    fn the_label_is_the_group_that_saw_the_footprint_not_the_nearest_cameras() {
        // Group 0 flew over the west (x = 30, 40), group 1 over the east (x = 70, 85), group
        // 2 is one view at the western edge (x = 15).
        let seen = vec![
            nadir_view(30.0),
            nadir_view(40.0),
            nadir_view(70.0),
            nadir_view(85.0),
            nadir_view(15.0),
        ];
        let frame = GroundFrame::new(Vector3::z()).unwrap();
        let grid = SurfaceGrid::build(frame, 2.0, &seen).unwrap();
        let cells: Vec<Vec<usize>> = seen.iter().map(|p| grid.cells_of(p)).collect();
        let members: Vec<&[usize]> = vec![&[0, 1], &[2, 3], &[4]];
        let camera = Camera::from_hfov(64, 48, 60.0).unwrap();
        // The footprint cells of the camera at `at` heading east, `pitch_deg` below the horizon.
        let footprint = |at: Point3<f64>, pitch_deg: f64| {
            let pose = heading_pitch_pose(&frame, &at, 0.0, pitch_deg.to_radians());
            footprint_cells(&grid, &camera, &pose)
        };
        // A camera 12 m up over x = 35 — between group 0's cameras — looking east 20° below
        // the horizon: most of its footprint rays land beyond x = 55, on ground group 1 saw.
        let fp = footprint(Point3::new(35.0, 20.0, 12.0), 20.0);
        assert!(!fp.is_empty());
        assert_eq!(shared_ground_label(&fp, &cells, &members), Some(1));
        // The same camera looking down sees group 0's ground.
        let down_fp = footprint(Point3::new(35.0, 20.0, 12.0), 90.0);
        assert_eq!(shared_ground_label(&down_fp, &cells, &members), Some(0));
        // Over x = 22 (x ∈ [17.7, 26.3] seen): the single view of group 2 saw all of it; of
        // group 0, x = 30 saw all and x = 40 a sliver. Their union covers it too, so a union
        // rule would tie and hand it to group 0; the mean gives it to group 2.
        let fp = footprint(Point3::new(22.0, 20.0, 10.0), 90.0);
        assert_eq!(shared_ground_label(&fp, &cells, &members), Some(2));
        // A footprint nobody saw, an empty one, and a tie (the lowest id wins).
        assert_eq!(shared_ground_label(&[usize::MAX], &cells, &members), None);
        assert_eq!(shared_ground_label(&[], &cells, &members), None);
        let twice: Vec<&[usize]> = vec![&[0], &[0], &[]];
        assert_eq!(shared_ground_label(&down_fp, &cells, &twice), Some(0));
    }
}
