//! The kinds of surface source.

use std::fmt;

use serde::{Deserialize, Serialize};

/// Where a frame's surface comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceKind {
    /// The dataset's depth files.
    DepthMaps,
    /// COLMAP `points3D`, each point in the views of its track.
    ColmapPoints,
    /// A PLY cloud, each point in every view it projects into (nearest per cell).
    PlyPoints,
    /// Points triangulated from the posed images, with their tracks.
    Triangulated,
}

impl fmt::Display for SurfaceKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            SurfaceKind::DepthMaps => "depth-map",
            SurfaceKind::ColmapPoints => "COLMAP points3D",
            SurfaceKind::PlyPoints => "PLY point-cloud",
            SurfaceKind::Triangulated => "triangulated-point",
        })
    }
}
