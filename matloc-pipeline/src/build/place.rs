//! The place stage: pose groups (two-stage K-means) over all training poses and the ArcFace
//! place classifier, trained on the survey images plus views the sub-NeRFs render near them.

use matloc_core::Image;
use matloc_data::{Dataset, Split};
use matloc_match::ViewRenderer;
use matloc_match::nerf_view::NerfViewRenderer;
use matloc_partition::Partition;
use matloc_place::{ExtraViews, PlaceMethod, PlaceModel, PoseGroups, view_point_from_depth};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::build::common::{BuildEvent, CurveLog, load_image, register_dir, stage};
use crate::config::MapConfig;
use crate::error::PipelineError;
use crate::gt::{PerturbKind, Perturbation};
use crate::map::layout::PLACE_DIR;
use crate::map::load::load_nerf;
use crate::map::manifest::MapDir;

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
    stage(
        map,
        "place",
        config.place.train.epochs as u64,
        progress,
        &mut |map, progress| {
            let mut images = Vec::with_capacity(train_idx.len());
            let mut poses = Vec::with_capacity(train_idx.len());
            let mut view_points = Vec::with_capacity(train_idx.len());
            // Block NeRFs, loaded when a view without a depth file first needs one.
            let mut nerfs = Vec::new();
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
                        if nerfs.len() <= b {
                            nerfs.resize_with(b + 1, || None);
                        }
                        if nerfs[b].is_none() {
                            nerfs[b] = Some(load_nerf(map, b, 0)?);
                        }
                        let r = nerfs[b].as_ref().expect("loaded above");
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
                images.push(matloc_place::resize_area(
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
            let extra = rendered_place_views(
                map, dataset, &train_idx, partition, &groups, config, progress,
            )?;
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
            Ok(())
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
    let width = if rv.width == 0 {
        2 * config.place.train.net.input_width
    } else {
        rv.width
    };
    let mut nerfs: Vec<Option<NerfViewRenderer>> = Vec::new();
    let mut rng = ChaCha8Rng::seed_from_u64(rv.seed);
    for (k, &i) in train_idx.iter().enumerate() {
        let f = &dataset.frames[i];
        let cam = f.camera;
        let height = ((width as f64 * cam.height as f64 / cam.width as f64).round() as u32).max(1);
        let small = cam.rescaled(width as u32, height)?;
        let b = partition.block_of_member(k).unwrap_or(0);
        if nerfs.len() <= b {
            nerfs.resize_with(b + 1, || None);
        }
        if nerfs[b].is_none() {
            nerfs[b] = Some(load_nerf(map, b, 0)?);
        }
        let nerf = nerfs[b]
            .as_ref()
            .ok_or(PipelineError::Internal("NeRF not loaded"))?;
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
