//! The survey's sparse point cloud as structure from motion would give it: surface points seen
//! by the training views, each with its track (every view in which it is visible), written as
//! a COLMAP text model (`sparse/0`, with 2D observations) and as nerfstudio's `sparse_pc.ply`.
//! Points are exact (ray casts into the world), so a build from them tests the surface path,
//! not triangulation noise.

use std::path::{Path, PathBuf};

use matloc_data::colmap::{
    ColmapFormat, ColmapModel, Point2D, Point3D, TrackElement, write_colmap,
};
use matloc_data::ply::write_ply;
use matloc_data::points::SparsePoints;
use matloc_data::{Dataset, Split};
use nalgebra::{Point2, Point3};
use rayon::prelude::*;

use crate::error::SynthError;
use crate::world::World;

/// Surface points under every `stride_px`-th pixel of each training view; tracks over all
/// frames (indexed by dataset frame), a view counting when the point projects into it and is
/// the first surface along its ray there (within 1 % + 5 cm).
pub fn survey_points(world: &World, dataset: &Dataset, stride_px: usize) -> SparsePoints {
    let stride = stride_px.max(1);
    let seeds: Vec<Point3<f64>> = dataset
        .split_indices(Split::Train)
        .par_iter()
        .flat_map_iter(|&i| {
            let f = &dataset.frames[i];
            let world_from_cam = f.cam_from_world.inverse();
            let origin = f.center();
            let mut pts = Vec::new();
            for r in (stride / 2..f.camera.height as usize).step_by(stride) {
                for c in (stride / 2..f.camera.width as usize).step_by(stride) {
                    let px = Point2::new(c as f64 + 0.5, r as f64 + 0.5);
                    if let Some(b) = f.camera.unproject(px)
                        && let Some(hit) =
                            world.raycast(&origin, &world_from_cam.transform_vector(&b))
                    {
                        pts.push(hit.point);
                    }
                }
            }
            pts
        })
        .collect();
    let tracks: Vec<Vec<usize>> = seeds
        .par_iter()
        .map(|p| {
            (0..dataset.frames.len())
                .filter(|&j| visible(world, dataset, j, p))
                .collect()
        })
        .collect();
    let mut out = SparsePoints {
        xyz: Vec::new(),
        by_frame: Some(vec![Vec::new(); dataset.frames.len()]),
    };
    for (p, track) in seeds.into_iter().zip(tracks) {
        // A point needs two views, as a triangulated one would.
        if track.len() < 2 {
            continue;
        }
        let id = out.xyz.len() as u32;
        out.xyz.push(p);
        let by_frame = out.by_frame.as_mut().expect("set above");
        for j in track {
            by_frame[j].push(id);
        }
    }
    out
}

fn visible(world: &World, dataset: &Dataset, j: usize, p: &Point3<f64>) -> bool {
    let f = &dataset.frames[j];
    let Some(px) = f.camera.project_world(&f.cam_from_world, p) else {
        return false;
    };
    if !f.camera.contains(px) {
        return false;
    }
    let origin = f.center();
    let d = p - origin;
    let dist = d.norm();
    world
        .raycast(&origin, &d)
        .is_some_and(|h| (h.t - dist).abs() <= 0.01 * dist + 0.05)
}

/// Writes `points` as `out_dir/sparse_pc.ply` and as a COLMAP text model in
/// `out_dir/sparse/0` whose image names are relative to `out_dir/images` (COLMAP's image
/// folder beside `sparse/`). Returns the PLY path.
pub fn write_survey_points(
    dataset: &Dataset,
    points: &SparsePoints,
    out_dir: &Path,
) -> Result<PathBuf, SynthError> {
    let ply = out_dir.join("sparse_pc.ply");
    write_ply(&ply, &points.xyz, None).map_err(|e| SynthError::Ply(Box::new(e)))?;
    // Image names relative to images/.
    let mut named = dataset.clone();
    for f in &mut named.frames {
        if let Ok(rest) = f.image_path.strip_prefix("images") {
            f.image_path = rest.to_path_buf();
        }
    }
    let mut model =
        ColmapModel::from_dataset(&named).map_err(|e| SynthError::Colmap(Box::new(e)))?;
    // Frame i is image id i + 1 (ColmapModel::from_dataset).
    let empty = Vec::new();
    let by_frame = points.by_frame.as_ref().unwrap_or(&empty);
    let mut tracks: Vec<Vec<TrackElement>> = vec![Vec::new(); points.xyz.len()];
    for (i, ids) in by_frame.iter().enumerate() {
        let f = &dataset.frames[i];
        let Some(image) = model.images.get_mut(&(i as u32 + 1)) else {
            continue;
        };
        for &k in ids {
            let Some(px) = f
                .camera
                .project_world(&f.cam_from_world, &points.xyz[k as usize])
            else {
                continue;
            };
            tracks[k as usize].push(TrackElement {
                image_id: image.id,
                point2d_idx: image.points2d.len() as u32,
            });
            image.points2d.push(Point2D {
                xy: [px.x, px.y],
                point3d_id: Some(u64::from(k) + 1),
            });
        }
    }
    for (k, (p, track)) in points.xyz.iter().zip(tracks).enumerate() {
        let id = k as u64 + 1;
        model.points3d.insert(
            id,
            Point3D {
                id,
                xyz: [p.x, p.y, p.z],
                rgb: [128, 128, 128],
                error: 0.0,
                track,
            },
        );
    }
    write_colmap(&model, &out_dir.join("sparse/0"), ColmapFormat::Text)
        .map_err(|e| SynthError::Colmap(Box::new(e)))?;
    Ok(ply)
}
