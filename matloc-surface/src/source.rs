//! Which surface a dataset offers, and per-frame depth maps from it.

use matloc_core::image::Image;
use matloc_data::images::load_frame_depth;
use matloc_data::points::{SparsePoints, read_points};
use matloc_data::{Dataset, PointSource};
use serde::{Deserialize, Serialize};

use crate::config::{SurfaceChoice, SurfaceConfig};
use crate::densify::densify;
use crate::error::SurfaceError;
use crate::kind::SurfaceKind;
use crate::triangulate::{TriangulateProgress, triangulate};

/// What a build will use, decided without reading any image or point.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfacePlan {
    /// Source of frames without a depth file (`DepthMaps` when every frame has one).
    pub kind: SurfaceKind,
    /// Frames considered.
    pub frames: usize,
    /// Of those, frames with a depth file (they always use it).
    pub frames_with_depth: usize,
    /// One line for people, e.g. the file the points come from.
    pub detail: String,
}

/// Decides the surface source for the frames `frames` (see [`SurfaceChoice`]): depth files
/// when every frame has one, else the dataset's point cloud, else triangulation.
pub fn plan(
    dataset: &Dataset,
    frames: &[usize],
    choice: SurfaceChoice,
) -> Result<SurfacePlan, SurfaceError> {
    let mut with_depth = 0;
    for &i in frames {
        let f = dataset.frames.get(i).ok_or(SurfaceError::NoFrame(i))?;
        with_depth += usize::from(f.depth_path.is_some());
    }
    let all_depth = with_depth == frames.len();
    let points = |choice: SurfaceChoice| -> Result<(SurfaceKind, String), SurfaceError> {
        if let Some(src) = &dataset.points
            && !src.path().is_file()
        {
            return Err(SurfaceError::Unavailable {
                requested: choice.name(),
                reason: format!(
                    "the dataset's point cloud {} does not exist (nerfstudio ply_file_path or \
                     COLMAP points3D)",
                    src.path().display()
                ),
            });
        }
        match &dataset.points {
            Some(PointSource::Colmap { path, .. }) => Ok((
                SurfaceKind::ColmapPoints,
                format!("points and tracks from {}", path.display()),
            )),
            Some(PointSource::Ply { path }) => Ok((
                SurfaceKind::PlyPoints,
                format!(
                    "points from {} (no tracks: visibility by projection)",
                    path.display()
                ),
            )),
            None if choice == SurfaceChoice::Auto => Ok((
                SurfaceKind::Triangulated,
                "no depth files or point cloud: points triangulated from the posed images".into(),
            )),
            None => Err(SurfaceError::Unavailable {
                requested: choice.name(),
                reason: "the dataset names no point cloud (COLMAP points3D, nerfstudio \
                         ply_file_path or sparse_pc.ply)"
                    .into(),
            }),
        }
    };
    let (kind, detail) = match choice {
        SurfaceChoice::Auto if all_depth => (SurfaceKind::DepthMaps, "depth files".into()),
        SurfaceChoice::Depth if all_depth => (SurfaceKind::DepthMaps, "depth files".into()),
        SurfaceChoice::Depth => {
            return Err(SurfaceError::Unavailable {
                requested: "depth",
                reason: format!(
                    "{} of {} frames have no depth file",
                    frames.len() - with_depth,
                    frames.len()
                ),
            });
        }
        SurfaceChoice::Auto | SurfaceChoice::Points => points(choice)?,
        SurfaceChoice::Triangulate => (
            SurfaceKind::Triangulated,
            "points triangulated from the posed images".into(),
        ),
    };
    Ok(SurfacePlan {
        kind,
        frames: frames.len(),
        frames_with_depth: with_depth,
        detail,
    })
}

/// Depth maps for a set of frames: the depth file where a frame has one (unless a point or
/// triangulation source was asked for explicitly), else a coarse map densified from the chosen point source. Points are read
/// or triangulated once; depth maps are made on demand, one frame at a time.
pub struct FrameSurfaces {
    plan: SurfacePlan,
    config: SurfaceConfig,
    points: Option<SparsePoints>,
}

impl FrameSurfaces {
    /// Plans and reads (or triangulates) the points the frames `frames` need.
    pub fn prepare(
        dataset: &Dataset,
        frames: &[usize],
        config: &SurfaceConfig,
        progress: TriangulateProgress<'_>,
    ) -> Result<FrameSurfaces, SurfaceError> {
        config.validate()?;
        let plan = plan(dataset, frames, config.source)?;
        let points = match plan.kind {
            SurfaceKind::DepthMaps => None,
            SurfaceKind::ColmapPoints | SurfaceKind::PlyPoints => read_points(dataset)?,
            SurfaceKind::Triangulated => {
                Some(triangulate(dataset, frames, &config.triangulate, progress)?)
            }
        };
        if let Some(p) = &points {
            tracing::info!(points = p.len(), source = %plan.kind, "surface points ready");
        }
        Ok(FrameSurfaces {
            plan,
            config: config.clone(),
            points,
        })
    }

    /// What was chosen.
    pub fn plan(&self) -> &SurfacePlan {
        &self.plan
    }

    /// The sparse points, when the surface comes from points.
    pub fn points(&self) -> Option<&SparsePoints> {
        self.points.as_ref()
    }

    /// z-depth map of frame `index` (metres, `0` = no surface); a densified map is coarser
    /// than the image, with the image's aspect.
    pub fn depth(&self, dataset: &Dataset, index: usize) -> Result<Image<f32>, SurfaceError> {
        let frame = dataset
            .frames
            .get(index)
            .ok_or(SurfaceError::NoFrame(index))?;
        // An explicit point or triangulation source applies to every frame.
        let use_file = frame.depth_path.is_some()
            && matches!(
                self.config.source,
                SurfaceChoice::Auto | SurfaceChoice::Depth
            );
        if use_file && let Some(d) = load_frame_depth(dataset, frame, 1)? {
            let data = d.data();
            if !data.iter().any(|v| v.is_finite() && *v > 0.0) {
                return Err(SurfaceError::BadDepth {
                    frame: index,
                    path: dataset.depth_path(frame).unwrap_or_default(),
                    nan: data.iter().filter(|v| !v.is_finite()).count(),
                    negative: data.iter().filter(|v| **v < 0.0).count(),
                    zero: data.iter().filter(|v| **v == 0.0).count(),
                    total: data.len(),
                });
            }
            return Ok(d);
        }
        let Some(points) = &self.points else {
            return Err(SurfaceError::Unavailable {
                requested: self.config.source.name(),
                reason: format!("frame {index} has no depth file and no point source was read"),
            });
        };
        // A frame outside the tracks (not in the reconstruction or the triangulation, e.g. a
        // query) sees whatever projects into it, as with a cloud without tracks.
        let tracked = points
            .by_frame
            .as_ref()
            .and_then(|b| b.get(index))
            .filter(|ids| !ids.is_empty());
        let (gw, gh) = crate::densify::grid_size(&frame.camera, self.config.grid_max_side);
        matloc_core::limits::check_memory(&crate::densify::densify_request(gw, gh))?;
        let d = match tracked {
            Some(ids) => densify(
                &frame.camera,
                &frame.cam_from_world,
                ids.iter().map(|&k| &points.xyz[k as usize]),
                self.config.grid_max_side,
                self.config.fill_radius,
            ),
            None => densify(
                &frame.camera,
                &frame.cam_from_world,
                &points.xyz,
                self.config.grid_max_side,
                self.config.fill_radius,
            ),
        };
        if d.points_in_view < self.config.min_points {
            return Err(SurfaceError::TooFewPoints {
                frame: index,
                image: dataset.image_path(frame),
                source_kind: self.plan.kind,
                found: d.points_in_view,
                needed: self.config.min_points,
            });
        }
        Ok(d.depth)
    }
}
