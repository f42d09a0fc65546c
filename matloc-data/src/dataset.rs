//! The in-memory dataset every reader produces and every writer consumes.

use std::path::{Path, PathBuf};

use matloc_core::Camera;
use matloc_core::pose::{Pose, camera_center, viewing_direction};
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

/// Which split a frame belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    /// Used to build the map.
    Train,
    /// Held out for validation during training.
    Val,
    /// Held out queries for evaluation.
    Test,
}

/// One posed image.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// Image path relative to [`Dataset::root`] (or absolute).
    pub image_path: PathBuf,
    /// Optional depth map path relative to [`Dataset::root`] (z-depth, see [`crate`] docs).
    pub depth_path: Option<PathBuf>,
    /// Intrinsics for the image size stated by the dataset.
    pub camera: Camera,
    /// World → camera pose (OpenCV camera axes).
    pub cam_from_world: Pose,
    /// Split membership.
    pub split: Split,
}

impl Frame {
    /// Camera centre in world coordinates.
    pub fn center(&self) -> Point3<f64> {
        camera_center(&self.cam_from_world)
    }

    /// Unit viewing direction in world coordinates.
    pub fn viewing_direction(&self) -> Vector3<f64> {
        viewing_direction(&self.cam_from_world)
    }
}

/// Facts about a scene that the poses alone do not give (written by the synthetic world, and
/// optional for real data).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneMetadata {
    /// Axis-aligned bounds of the scene content `[min, max]`, metres, world frame.
    pub bounds_min: Option<[f64; 3]>,
    /// See `bounds_min`.
    pub bounds_max: Option<[f64; 3]>,
    /// World "up" direction.
    pub up: Option<[f64; 3]>,
    /// Generator that made the scene, e.g. `"matloc-synth"`.
    pub generator: Option<String>,
    /// Preset name of a synthetic scene.
    pub preset: Option<String>,
    /// Seed of a synthetic scene.
    pub seed: Option<u64>,
}

/// A set of posed images with a root directory that relative paths resolve against.
#[derive(Clone, Debug, PartialEq)]
pub struct Dataset {
    /// Directory that frame paths are relative to.
    pub root: PathBuf,
    /// All frames in file order.
    pub frames: Vec<Frame>,
    /// Optional scene facts.
    pub metadata: SceneMetadata,
}

impl Dataset {
    /// Absolute (root-joined) path of a frame's image.
    pub fn image_path(&self, frame: &Frame) -> PathBuf {
        self.root.join(&frame.image_path)
    }

    /// Absolute (root-joined) path of a frame's depth map, if any.
    pub fn depth_path(&self, frame: &Frame) -> Option<PathBuf> {
        frame.depth_path.as_ref().map(|p| self.root.join(p))
    }

    /// Frames of one split, in file order.
    pub fn split(&self, split: Split) -> impl Iterator<Item = &Frame> {
        self.frames.iter().filter(move |f| f.split == split)
    }

    /// Indices of the frames of one split.
    pub fn split_indices(&self, split: Split) -> Vec<usize> {
        (0..self.frames.len())
            .filter(|&i| self.frames[i].split == split)
            .collect()
    }

    /// The dataset root.
    pub fn root(&self) -> &Path {
        &self.root
    }
}
