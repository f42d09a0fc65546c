//! Settings of the surface stage.

use serde::{Deserialize, Serialize};

use crate::error::SurfaceError;

/// Which surface a build uses for frames without a depth map.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SurfaceChoice {
    /// Depth files, else the dataset's point cloud, else triangulated points.
    #[default]
    Auto,
    /// Depth files only (every frame must have one).
    Depth,
    /// The dataset's point cloud (COLMAP `points3D` or PLY).
    Points,
    /// Points triangulated from the posed images, even when a cloud exists.
    Triangulate,
}

impl SurfaceChoice {
    /// The name used in configs and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            SurfaceChoice::Auto => "auto",
            SurfaceChoice::Depth => "depth",
            SurfaceChoice::Points => "points",
            SurfaceChoice::Triangulate => "triangulate",
        }
    }
}

/// How points are triangulated from posed images (the bootstrap for data without depth or a
/// point cloud): ORB keypoints matched between each image and its nearest neighbours, rays
/// intersected with the known poses, tracks merged and re-triangulated over all their views.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TriangulateConfig {
    /// Images are box-downscaled by an integer factor until the longer side is at most this.
    pub max_side: u32,
    /// Each image is matched with this many nearest training images.
    pub neighbours: usize,
    /// Keypoints per image.
    pub max_keypoints: usize,
    /// Largest reprojection error of an observation, pixels at the detection size.
    pub max_reprojection_px: f64,
    /// Smallest angle between two rays of a point, degrees.
    pub min_angle_deg: f64,
    /// Two images are paired only when their viewing directions differ by less than this.
    pub max_view_angle_deg: f64,
    /// Views a point needs: a third view rejects the consistent false depth that a repeated
    /// texture matched with one shift gives in a pair.
    pub min_track_len: usize,
    /// Detect the keypoints on the images upsampled 2× (`KeypointConfig::upsample`): finer
    /// positions, more points, and more outliers in them; off for the surface, on for the
    /// map's keypoint structure.
    pub upsample: bool,
    /// The descriptor pairs of images are matched with (every keypoint keeps both kinds).
    pub pair_descriptor: matloc_keypoints::DescriptorKind,
    /// Move each point to minimise its reprojection errors with the poses fixed
    /// (structure-only bundle adjustment) after its rays' least-squares solution. Off: the
    /// rays' solution already reprojects within 0.15 px (median) on 320 × 240 surveys, and
    /// the refined points localized no query better.
    pub refine_points: bool,
}

impl Default for TriangulateConfig {
    fn default() -> Self {
        TriangulateConfig {
            max_side: 640,
            neighbours: 8,
            max_keypoints: 2000,
            max_reprojection_px: 2.0,
            min_angle_deg: 1.5,
            max_view_angle_deg: 75.0,
            min_track_len: 2,
            upsample: false,
            pair_descriptor: matloc_keypoints::DescriptorKind::Binary,
            refine_points: false,
        }
    }
}

/// Settings of the surface stage.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SurfaceConfig {
    /// Which source.
    pub source: SurfaceChoice,
    /// Longer side of a depth map made from points, cells.
    pub grid_max_side: usize,
    /// Empty cells take the depth of the nearest cell with a point up to this fraction of the
    /// longer side away; farther cells stay without a surface.
    pub fill_radius: f64,
    /// A frame needs at least this many points in view.
    pub min_points: usize,
    /// Triangulation settings.
    pub triangulate: TriangulateConfig,
}

impl Default for SurfaceConfig {
    fn default() -> Self {
        SurfaceConfig {
            source: SurfaceChoice::Auto,
            grid_max_side: 48,
            fill_radius: 0.2,
            min_points: 12,
            triangulate: TriangulateConfig::default(),
        }
    }
}

impl SurfaceConfig {
    /// Checks every value.
    pub fn validate(&self) -> Result<(), SurfaceError> {
        let bad = |field, reason: String| Err(SurfaceError::InvalidConfig { field, reason });
        if !(4..=4096).contains(&self.grid_max_side) {
            return bad(
                "grid_max_side",
                format!("must be in 4..=4096, got {}", self.grid_max_side),
            );
        }
        if !(self.fill_radius.is_finite() && (0.0..=2.0).contains(&self.fill_radius)) {
            return bad(
                "fill_radius",
                format!("must be in [0, 2], got {}", self.fill_radius),
            );
        }
        if self.min_points == 0 {
            return bad("min_points", "must be at least 1".into());
        }
        let t = &self.triangulate;
        if t.max_side < 32 {
            return bad(
                "triangulate.max_side",
                format!("must be at least 32, got {}", t.max_side),
            );
        }
        if t.min_track_len < 2 {
            return bad(
                "triangulate.min_track_len",
                format!("must be at least 2, got {}", t.min_track_len),
            );
        }
        if t.neighbours == 0 {
            return bad("triangulate.neighbours", "must be at least 1".into());
        }
        if t.max_keypoints < 8 {
            return bad(
                "triangulate.max_keypoints",
                format!("must be at least 8, got {}", t.max_keypoints),
            );
        }
        for (field, v, hi) in [
            (
                "triangulate.max_reprojection_px",
                t.max_reprojection_px,
                1e3,
            ),
            ("triangulate.min_angle_deg", t.min_angle_deg, 90.0),
            (
                "triangulate.max_view_angle_deg",
                t.max_view_angle_deg,
                180.0,
            ),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= hi) {
                return bad(field, format!("must be in (0, {hi}], got {v}"));
            }
        }
        Ok(())
    }
}
