//! What finding a surface can fail with.

use std::path::PathBuf;

use matloc_data::DataError;
use matloc_data::images::ImageLoadError;
use thiserror::Error;

use crate::kind::SurfaceKind;

/// Errors of the surface stage.
#[derive(Debug, Error)]
pub enum SurfaceError {
    /// Reading the dataset's point cloud failed.
    #[error(transparent)]
    Data(#[from] DataError),
    /// Loading a training image or depth map failed.
    #[error(transparent)]
    Image(#[from] ImageLoadError),
    /// The requested source is not available in the dataset.
    #[error("surface source `{requested}` is not available: {reason}")]
    Unavailable {
        /// The source asked for.
        requested: &'static str,
        /// Why not.
        reason: String,
    },
    /// A frame sees too few surface points to stand in for its depth.
    #[error(
        "frame {frame} ({image}): the {source_kind} surface gives {found} points in this view, \
         fewer than the {needed} needed (surface.min_points); {}",
        too_few_points_remedy(*.source_kind)
    )]
    TooFewPoints {
        /// Frame index in the dataset.
        frame: usize,
        /// The frame's image.
        image: PathBuf,
        /// Where the points came from.
        source_kind: SurfaceKind,
        /// Points that project into the view.
        found: usize,
        /// The configured minimum.
        needed: usize,
    },
    /// A frame's depth file holds no usable value.
    #[error(
        "frame {frame}: depth map {path} has no finite positive value ({nan} NaN or infinite, \
         {negative} negative, {zero} zero of {total})"
    )]
    BadDepth {
        /// Frame index in the dataset.
        frame: usize,
        /// The depth file.
        path: PathBuf,
        /// Non-finite values.
        nan: usize,
        /// Negative values.
        negative: usize,
        /// Zero values (no surface).
        zero: usize,
        /// All values.
        total: usize,
    },
    /// A densified depth map does not fit in memory.
    #[error("{0}")]
    Limit(Box<matloc_core::limits::LimitError>),
    /// A setting is out of range.
    #[error("surface config: `{field}` {reason}")]
    InvalidConfig {
        /// The setting.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// An observation given to bundle adjustment is unusable.
    #[error("bundle adjustment: observation {index}: {reason}")]
    BadObservation {
        /// Index into the observations.
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// The training cameras saw no surface point to sample virtual viewpoints over.
    #[error("virtual viewpoints: the training cameras saw no finite surface point")]
    NoSurfaceSeen,
    /// A frame index outside the dataset.
    #[error("no frame {0} in the dataset")]
    NoFrame(usize),
}

impl From<matloc_core::limits::LimitError> for SurfaceError {
    fn from(e: matloc_core::limits::LimitError) -> Self {
        SurfaceError::Limit(Box::new(e))
    }
}

/// What to do about [`SurfaceError::TooFewPoints`] from a surface of `kind`.
fn too_few_points_remedy(kind: SurfaceKind) -> &'static str {
    match kind {
        SurfaceKind::Triangulated => {
            "with poses off by a degree or more (as GPS/IMU give them) few points' views agree \
             within surface.triangulate.max_reprojection_px: refine the poses by structure from \
             motion first, or raise that gate (and structure.triangulate.max_reprojection_px, \
             about 5 px per degree at 320 px wide); else add depth maps or a point cloud"
        }
        _ => "add depth maps or a denser point cloud, or choose another source with --surface",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn too_few_points_says_what_to_change_for_its_source() {
        let e = |kind| {
            SurfaceError::TooFewPoints {
                frame: 87,
                image: PathBuf::from("survey/images/survey_00087.png"),
                source_kind: kind,
                found: 3,
                needed: 12,
            }
            .to_string()
        };
        let triangulated = e(SurfaceKind::Triangulated);
        assert!(
            triangulated.contains("survey_00087.png") && triangulated.contains("gives 3 points")
        );
        assert!(triangulated.contains("surface.triangulate.max_reprojection_px"));
        assert!(e(SurfaceKind::ColmapPoints).contains("--surface"));
    }
}
