//! The in-memory dataset every reader produces and every writer consumes.

use std::collections::BTreeMap;
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
    /// nerfstudio's `applied_transform`: the 3×4 `[R | t]` that maps a point of the original
    /// (COLMAP) world into this dataset's world, `x_world = R x_original + t` (see
    /// [`crate::nerfstudio::original_cam_from_world`]). nerfstudio keeps it as a top-level
    /// key of `transforms.json`, and so does [`crate::nerfstudio::write_nerfstudio`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub applied_transform: Option<[[f64; 4]; 3]>,
    /// Unit direction towards the sun in this world frame when the images were taken (the
    /// synthetic world writes it; a map's shadow lifting reads it, see `matloc_surface::sunlight`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sun_direction: Option<[f64; 3]>,
    /// The Mega-NeRF normalisation that [`crate::meganerf`] undid when reading.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mega_nerf: Option<MegaNerfCoordinates>,
}

/// Mega-NeRF's `coordinates.pt`: its files hold positions `(x − origin_drb) / pose_scale_factor`
/// where `x` is the metric position this dataset holds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MegaNerfCoordinates {
    /// Origin of the normalised world, metres, in this dataset's world.
    pub origin_drb: [f64; 3],
    /// Metres per normalised unit.
    pub pose_scale_factor: f64,
}

/// Where a dataset keeps a sparse point cloud of its scene, read on demand
/// ([`crate::points::read_points`]) by whatever needs a surface without depth maps.
#[derive(Clone, Debug, PartialEq)]
pub enum PointSource {
    /// A COLMAP `points3D.txt` / `points3D.bin` whose tracks name COLMAP image ids.
    Colmap {
        /// The `points3D` file.
        path: PathBuf,
        /// COLMAP image id → index in [`Dataset::frames`].
        frame_of_image: BTreeMap<u32, usize>,
    },
    /// A PLY point cloud without tracks (nerfstudio's `ply_file_path`, `sparse_pc.ply`).
    Ply {
        /// The `.ply` file.
        path: PathBuf,
    },
}

impl PointSource {
    /// The file the points are read from.
    pub fn path(&self) -> &Path {
        match self {
            PointSource::Colmap { path, .. } | PointSource::Ply { path } => path,
        }
    }
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
    /// The dataset's sparse point cloud, when it has one.
    pub points: Option<PointSource>,
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

    /// The scene's up direction (unit, world frame): the metadata's `up` when given, else the
    /// reverse of the cameras' mean viewing direction when they mostly look down at the scene
    /// (an aerial survey), else +z.
    pub fn up_direction(&self) -> Vector3<f64> {
        if let Some(u) = self.metadata.up.map(Vector3::from)
            && u.iter().all(|v| v.is_finite())
            && u.norm() > 1e-12
        {
            return u.normalize();
        }
        let sum: Vector3<f64> = self.frames.iter().map(Frame::viewing_direction).sum();
        let n = self.frames.len().max(1) as f64;
        if (sum / n).norm() > 0.5 {
            -sum.normalize()
        } else {
            Vector3::z()
        }
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
