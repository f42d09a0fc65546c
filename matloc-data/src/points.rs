//! A dataset's sparse point cloud ([`PointSource`]) read into one type: positions, and for
//! COLMAP models the frames that observed each point (its track), indexed by frame.

use nalgebra::Point3;

use crate::colmap::{ColmapError, read_points3d_file};
use crate::dataset::{Dataset, PointSource};
use crate::error::DataError;
use crate::ply::read_ply;

/// Sparse 3D points of a scene.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SparsePoints {
    /// Positions, world frame.
    pub xyz: Vec<Point3<f64>>,
    /// Per frame of the dataset, the points it observed (indices into `xyz`); `None` when the
    /// source has no tracks (a PLY cloud), so visibility must be worked out by projection.
    pub by_frame: Option<Vec<Vec<u32>>>,
}

impl SparsePoints {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.xyz.len()
    }

    /// True when there are no points.
    pub fn is_empty(&self) -> bool {
        self.xyz.is_empty()
    }
}

/// Reads the dataset's point cloud, if it names one.
pub fn read_points(dataset: &Dataset) -> Result<Option<SparsePoints>, DataError> {
    match &dataset.points {
        None => Ok(None),
        Some(PointSource::Ply { path }) => {
            let cloud = read_ply(path)?;
            Ok(Some(SparsePoints {
                xyz: cloud.xyz,
                by_frame: None,
            }))
        }
        Some(PointSource::Colmap {
            path,
            frame_of_image,
        }) => {
            let points = read_points3d_file(path)?;
            let mut by_frame = vec![Vec::new(); dataset.frames.len()];
            let mut xyz = Vec::with_capacity(points.len());
            for p in points.values() {
                let k = xyz.len() as u32;
                for t in &p.track {
                    let seen = frame_of_image
                        .get(&t.image_id)
                        .and_then(|&f| by_frame.get_mut(f))
                        .ok_or_else(|| ColmapError::UnknownTrackImage {
                            path: path.to_path_buf(),
                            point_id: p.id,
                            image_id: t.image_id,
                        })?;
                    // A point observed twice by one image counts once.
                    if seen.last() != Some(&k) {
                        seen.push(k);
                    }
                }
                if !p.xyz.iter().all(|v| v.is_finite()) {
                    return Err(ColmapError::Invalid {
                        path: path.to_path_buf(),
                        record: format!("point3D {}", p.id),
                        reason: format!("non-finite position {:?}", p.xyz),
                    }
                    .into());
                }
                xyz.push(Point3::from(p.xyz));
            }
            Ok(Some(SparsePoints {
                xyz,
                by_frame: Some(by_frame),
            }))
        }
    }
}
