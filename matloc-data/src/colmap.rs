//! COLMAP sparse models (`cameras`, `images`, `points3D`) in text and binary form.
//!
//! Camera models SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV map onto
//! [`Camera`] (the radial models are OpenCV cameras with `p1 = p2 = 0`); every other COLMAP
//! model is a typed error naming the model and the file. COLMAP stores `cam_from_world` as
//! quaternion `(qw, qx, qy, qz)` + translation with OpenCV camera axes, and puts the centre of
//! the top-left pixel at `(0.5, 0.5)` — the same conventions as [`matloc_core`], so only the
//! quaternion is converted.
//!
//! Binary layout (little-endian), as documented by COLMAP:
//! - `cameras.bin`: `u64` count; per camera `u32` id, `i32` model id, `u64` width, `u64`
//!   height, `f64` × (number of model parameters).
//! - `images.bin`: `u64` count; per image `u32` id, `f64` × 4 quaternion, `f64` × 3
//!   translation, `u32` camera id, NUL-terminated name, `u64` point count, then per point
//!   `f64` x, `f64` y, `u64` point3D id (`u64::MAX` = none).
//! - `points3D.bin`: `u64` count; per point `u64` id, `f64` × 3 xyz, `u8` × 3 rgb, `f64`
//!   error, `u64` track length, then per element `u32` image id, `u32` point2D index.
//!
//! A missing `points3D` file reads as an empty point set (poses and intrinsics are what a
//! dataset needs); missing `cameras` or `images` files are errors.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io;
use std::path::{Path, PathBuf};

use matloc_core::pose::{cam_from_world_from_colmap, colmap_from_cam_from_world};
use matloc_core::{Camera, CameraError, Distortion, Pose, PoseError};
use thiserror::Error;

use crate::dataset::{Dataset, Frame, PointSource, SceneMetadata, Split};
use matloc_core::fsutil::write_atomic;

/// The COLMAP camera models this crate reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ColmapCameraModel {
    /// `f, cx, cy`.
    SimplePinhole,
    /// `fx, fy, cx, cy`.
    Pinhole,
    /// `f, cx, cy, k`.
    SimpleRadial,
    /// `f, cx, cy, k1, k2`.
    Radial,
    /// `fx, fy, cx, cy, k1, k2, p1, p2`.
    OpenCv,
}

/// Every model COLMAP defines: id, name, number of parameters.
const COLMAP_MODELS: [(i32, &str, usize); 12] = [
    (0, "SIMPLE_PINHOLE", 3),
    (1, "PINHOLE", 4),
    (2, "SIMPLE_RADIAL", 4),
    (3, "RADIAL", 5),
    (4, "OPENCV", 8),
    (5, "OPENCV_FISHEYE", 8),
    (6, "FULL_OPENCV", 12),
    (7, "FOV", 5),
    (8, "SIMPLE_RADIAL_FISHEYE", 4),
    (9, "RADIAL_FISHEYE", 5),
    (10, "THIN_PRISM_FISHEYE", 12),
    (11, "RAD_TAN_THIN_PRISM_FISHEYE", 16),
];

impl ColmapCameraModel {
    /// All supported models.
    pub const ALL: [ColmapCameraModel; 5] = [
        Self::SimplePinhole,
        Self::Pinhole,
        Self::SimpleRadial,
        Self::Radial,
        Self::OpenCv,
    ];

    /// COLMAP's numeric model id.
    pub fn id(self) -> i32 {
        match self {
            Self::SimplePinhole => 0,
            Self::Pinhole => 1,
            Self::SimpleRadial => 2,
            Self::Radial => 3,
            Self::OpenCv => 4,
        }
    }

    /// COLMAP's model name, e.g. `"SIMPLE_RADIAL"`.
    pub fn name(self) -> &'static str {
        COLMAP_MODELS[self.id() as usize].1
    }

    /// Number of parameters COLMAP stores for the model.
    pub fn num_params(self) -> usize {
        COLMAP_MODELS[self.id() as usize].2
    }

    /// The supported model with this id; `Err` carries a description of the unsupported one.
    pub fn from_id(id: i32) -> Result<Self, String> {
        Self::ALL.into_iter().find(|m| m.id() == id).ok_or_else(|| {
            match COLMAP_MODELS.iter().find(|(i, _, _)| *i == id) {
                Some((_, name, _)) => format!("{name} (id {id})"),
                None => format!("unknown model id {id}"),
            }
        })
    }

    /// The supported model with this name; `Err` carries a description of the unsupported one.
    pub fn from_name(name: &str) -> Result<Self, String> {
        Self::ALL
            .into_iter()
            .find(|m| m.name() == name)
            .ok_or_else(|| match COLMAP_MODELS.iter().find(|(_, n, _)| *n == name) {
                Some((id, _, _)) => format!("{name} (id {id})"),
                None => format!("unknown model {name}"),
            })
    }
}

/// One COLMAP camera: model, image size and raw parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    /// Camera id.
    pub id: u32,
    /// Camera model.
    pub model: ColmapCameraModel,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Parameters in COLMAP's order for the model.
    pub params: Vec<f64>,
}

impl ColmapCamera {
    /// The camera as a validated [`Camera`].
    pub fn to_camera(&self) -> Result<Camera, CameraError> {
        // A hand-built camera may lack parameters: missing ones read as NaN and fail
        // validation with the parameter's name instead of panicking.
        let mut p = [f64::NAN; 8];
        for (dst, src) in p.iter_mut().zip(&self.params) {
            *dst = *src;
        }
        let (fx, fy, cx, cy, d) = match self.model {
            ColmapCameraModel::SimplePinhole => (p[0], p[0], p[1], p[2], Distortion::NONE),
            ColmapCameraModel::Pinhole => (p[0], p[1], p[2], p[3], Distortion::NONE),
            ColmapCameraModel::SimpleRadial => (
                p[0],
                p[0],
                p[1],
                p[2],
                Distortion {
                    k1: p[3],
                    ..Distortion::NONE
                },
            ),
            ColmapCameraModel::Radial => (
                p[0],
                p[0],
                p[1],
                p[2],
                Distortion {
                    k1: p[3],
                    k2: p[4],
                    ..Distortion::NONE
                },
            ),
            ColmapCameraModel::OpenCv => (
                p[0],
                p[1],
                p[2],
                p[3],
                Distortion {
                    k1: p[4],
                    k2: p[5],
                    p1: p[6],
                    p2: p[7],
                    k3: 0.0,
                },
            ),
        };
        Camera::opencv(self.width, self.height, fx, fy, cx, cy, d)
    }

    /// The simplest COLMAP model that represents `camera` exactly (PINHOLE or OPENCV);
    /// `None` when `k3 ≠ 0`, which needs FULL_OPENCV.
    pub fn from_camera(id: u32, camera: &Camera) -> Option<ColmapCamera> {
        let d = &camera.distortion;
        if d.k3 != 0.0 {
            return None;
        }
        let (model, params) = if camera.is_pinhole() {
            (
                ColmapCameraModel::Pinhole,
                vec![camera.fx, camera.fy, camera.cx, camera.cy],
            )
        } else {
            (
                ColmapCameraModel::OpenCv,
                vec![
                    camera.fx, camera.fy, camera.cx, camera.cy, d.k1, d.k2, d.p1, d.p2,
                ],
            )
        };
        Some(ColmapCamera {
            id,
            model,
            width: camera.width,
            height: camera.height,
            params,
        })
    }
}

/// A 2D keypoint of an image and the 3D point it observes, if any.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Point2D {
    /// Pixel coordinates (top-left pixel centre at `(0.5, 0.5)`).
    pub xy: [f64; 2],
    /// Observed 3D point id; `None` for an unmatched keypoint (`-1` in text).
    pub point3d_id: Option<u64>,
}

/// One registered image.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    /// Image id.
    pub id: u32,
    /// File name relative to the image directory.
    pub name: String,
    /// Camera id.
    pub camera_id: u32,
    /// World → camera pose.
    pub cam_from_world: Pose,
    /// Keypoints.
    pub points2d: Vec<Point2D>,
}

/// One observation of a 3D point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TrackElement {
    /// Observing image.
    pub image_id: u32,
    /// Index into that image's [`ColmapImage::points2d`].
    pub point2d_idx: u32,
}

/// One triangulated 3D point.
#[derive(Clone, Debug, PartialEq)]
pub struct Point3D {
    /// Point id.
    pub id: u64,
    /// Position, world frame.
    pub xyz: [f64; 3],
    /// Colour.
    pub rgb: [u8; 3],
    /// Mean reprojection error, pixels.
    pub error: f64,
    /// Observations.
    pub track: Vec<TrackElement>,
}

/// A COLMAP sparse model, keyed by id.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColmapModel {
    /// Cameras by id.
    pub cameras: BTreeMap<u32, ColmapCamera>,
    /// Images by id.
    pub images: BTreeMap<u32, ColmapImage>,
    /// 3D points by id.
    pub points3d: BTreeMap<u64, Point3D>,
}

/// Text (`.txt`) or binary (`.bin`) model files.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColmapFormat {
    /// `cameras.txt`, `images.txt`, `points3D.txt`.
    Text,
    /// `cameras.bin`, `images.bin`, `points3D.bin`.
    Binary,
}

impl ColmapFormat {
    fn ext(self) -> &'static str {
        match self {
            Self::Text => "txt",
            Self::Binary => "bin",
        }
    }
}

/// Errors raised when reading or writing COLMAP models.
#[derive(Debug, Error)]
pub enum ColmapError {
    /// No COLMAP model (cameras.bin / cameras.txt) at or below the path.
    #[error(
        "no COLMAP model at {path} (looked for cameras.bin|txt in it, sparse/0, sparse, colmap/sparse/0)"
    )]
    NotFound {
        /// The path given.
        path: PathBuf,
    },
    /// A required model file is missing.
    #[error("COLMAP model file missing: {path}")]
    MissingFile {
        /// The missing file.
        path: PathBuf,
    },
    /// A point's track names an image the model does not have.
    #[error(
        "{path}: point3D {point_id} is observed by image {image_id}, which is not in the model"
    )]
    UnknownTrackImage {
        /// The `points3D` file.
        path: PathBuf,
        /// The point.
        point_id: u64,
        /// The missing image id.
        image_id: u32,
    },
    /// Reading or writing failed at the operating-system level.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// A text line that cannot be parsed.
    #[error("{path}:{line}: field `{field}`: {reason}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// The field being read.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// A binary file ends inside a record.
    #[error(
        "{path}: truncated at byte {offset} while reading {record} (needs {needed} more bytes)"
    )]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Which record and field, e.g. `image #3 name`.
        record: String,
        /// Byte offset where the read started.
        offset: usize,
        /// Bytes the read needed.
        needed: usize,
    },
    /// A binary record with an impossible value.
    #[error("{path}: {record}: {reason}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// Which record.
        record: String,
        /// What is wrong.
        reason: String,
    },
    /// A camera model this crate does not support (fisheye, FULL_OPENCV, ...).
    #[error(
        "{path}: camera {camera_id}: unsupported camera model {model} (supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV)"
    )]
    UnsupportedCameraModel {
        /// The file.
        path: PathBuf,
        /// Camera id.
        camera_id: u32,
        /// Model name and id as found.
        model: String,
    },
    /// Camera parameters that do not form a valid camera.
    #[error("{path}: camera {camera_id}: {source}")]
    BadCamera {
        /// The file.
        path: PathBuf,
        /// Camera id.
        camera_id: u32,
        /// What is wrong.
        source: CameraError,
    },
    /// An image pose that is not a finite rigid transform.
    #[error("{path}: image {image_id}: bad pose: {source}")]
    BadPose {
        /// The file.
        path: PathBuf,
        /// Image id.
        image_id: u32,
        /// What is wrong.
        source: PoseError,
    },
    /// An image refers to a camera id that the model does not have.
    #[error("{path}: image {image_id} refers to camera {camera_id}, which does not exist")]
    UnknownCamera {
        /// The images file.
        path: PathBuf,
        /// Image id.
        image_id: u32,
        /// The missing camera id.
        camera_id: u32,
    },
    /// A dataset frame that no supported COLMAP model can represent.
    #[error("frame {frame}: {reason}")]
    Unrepresentable {
        /// Frame index.
        frame: usize,
        /// Why.
        reason: String,
    },
}

fn io_error(path: &Path, source: io::Error) -> ColmapError {
    if source.kind() == io::ErrorKind::NotFound {
        ColmapError::MissingFile {
            path: path.to_path_buf(),
        }
    } else {
        ColmapError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Locating models

/// Finds the model directory at or below `path` and its format (binary preferred when both
/// exist). Looks in `path`, `path/sparse/0`, `path/sparse`, `path/colmap/sparse/0`, `path/0`;
/// a path to a model file means its directory.
pub fn find_model_dir(path: &Path) -> Option<(PathBuf, ColmapFormat)> {
    let base = if path.is_file() {
        path.parent().unwrap_or(Path::new(""))
    } else {
        path
    };
    let candidates = [
        base.to_path_buf(),
        base.join("sparse").join("0"),
        base.join("sparse"),
        base.join("colmap").join("sparse").join("0"),
        base.join("0"),
    ];
    candidates.into_iter().find_map(|dir| {
        if dir.join("cameras.bin").is_file() {
            Some((dir, ColmapFormat::Binary))
        } else if dir.join("cameras.txt").is_file() {
            Some((dir, ColmapFormat::Text))
        } else {
            None
        }
    })
}

/// The image directory of a model: the nearest `images/` folder among the model directory's
/// ancestors (`root/sparse/0` → `root/images`); when none exists, the folder above `sparse`
/// joined with `images` (so validation reports the missing files).
pub fn default_image_dir(model_dir: &Path) -> PathBuf {
    for anc in model_dir.ancestors().take(4) {
        let candidate = anc.join("images");
        if candidate.is_dir() {
            return candidate;
        }
    }
    let above_sparse = model_dir
        .ancestors()
        .find(|a| a.file_name().is_some_and(|n| n == "sparse"))
        .and_then(Path::parent);
    above_sparse
        .or_else(|| model_dir.parent())
        .unwrap_or(Path::new(""))
        .join("images")
}

/// Reads the COLMAP model at or below `path` (see [`find_model_dir`]), detecting text vs
/// binary.
pub fn read_colmap(path: &Path) -> Result<ColmapModel, ColmapError> {
    let (dir, format) = find_model_dir(path).ok_or_else(|| ColmapError::NotFound {
        path: path.to_path_buf(),
    })?;
    read_colmap_dir(&dir, format)
}

/// Reads one `points3D.txt` / `points3D.bin` file (format by extension).
pub fn read_points3d_file(path: &Path) -> Result<BTreeMap<u64, Point3D>, ColmapError> {
    let bytes = std::fs::read(path).map_err(|e| io_error(path, e))?;
    if path.extension().is_some_and(|e| e == "bin") {
        parse_points3d_binary(&bytes, path)
    } else {
        parse_points3d_text(&bytes, path)
    }
}

/// Reads a model directory in the given format.
pub fn read_colmap_dir(dir: &Path, format: ColmapFormat) -> Result<ColmapModel, ColmapError> {
    let ext = format.ext();
    let read = |name: &str| -> Result<Vec<u8>, ColmapError> {
        let p = dir.join(format!("{name}.{ext}"));
        std::fs::read(&p).map_err(|e| io_error(&p, e))
    };
    let cameras_path = dir.join(format!("cameras.{ext}"));
    let images_path = dir.join(format!("images.{ext}"));
    let points_path = dir.join(format!("points3D.{ext}"));
    let cameras_bytes = read("cameras")?;
    let images_bytes = read("images")?;
    let points_bytes = match read("points3D") {
        Ok(b) => Some(b),
        Err(ColmapError::MissingFile { .. }) => None,
        Err(e) => return Err(e),
    };
    let (cameras, images, points3d) = match format {
        ColmapFormat::Text => (
            parse_cameras_text(&cameras_bytes, &cameras_path)?,
            parse_images_text(&images_bytes, &images_path)?,
            match points_bytes {
                Some(b) => parse_points3d_text(&b, &points_path)?,
                None => BTreeMap::new(),
            },
        ),
        ColmapFormat::Binary => (
            parse_cameras_binary(&cameras_bytes, &cameras_path)?,
            parse_images_binary(&images_bytes, &images_path)?,
            match points_bytes {
                Some(b) => parse_points3d_binary(&b, &points_path)?,
                None => BTreeMap::new(),
            },
        ),
    };
    for p in points3d.values() {
        if let Some(t) = p.track.iter().find(|t| !images.contains_key(&t.image_id)) {
            return Err(ColmapError::UnknownTrackImage {
                path: points_path,
                point_id: p.id,
                image_id: t.image_id,
            });
        }
    }
    for image in images.values() {
        if !cameras.contains_key(&image.camera_id) {
            return Err(ColmapError::UnknownCamera {
                path: images_path,
                image_id: image.id,
                camera_id: image.camera_id,
            });
        }
    }
    Ok(ColmapModel {
        cameras,
        images,
        points3d,
    })
}

/// Reads the COLMAP model at or below `path` as a [`Dataset`] whose root is the default image
/// directory ([`default_image_dir`]). Every frame is a training frame.
pub fn read_colmap_dataset(path: &Path) -> Result<Dataset, ColmapError> {
    let (dir, format) = find_model_dir(path).ok_or_else(|| ColmapError::NotFound {
        path: path.to_path_buf(),
    })?;
    let model = read_colmap_dir(&dir, format)?;
    let mut dataset = model.to_dataset(&default_image_dir(&dir))?;
    // The points are re-read on demand (crate::points::read_points) rather than kept here.
    if !model.points3d.is_empty() {
        let mut names: Vec<(&str, u32)> = model
            .images
            .values()
            .map(|i| (i.name.as_str(), i.id))
            .collect();
        names.sort();
        dataset.points = Some(PointSource::Colmap {
            path: dir.join(format!("points3D.{}", format.ext())),
            frame_of_image: names
                .into_iter()
                .enumerate()
                .map(|(frame, (_, id))| (id, frame))
                .collect(),
        });
    }
    Ok(dataset)
}

impl ColmapModel {
    /// The model as a [`Dataset`] rooted at `image_dir`, frames sorted by image name (COLMAP
    /// ids carry no order), all in the train split.
    pub fn to_dataset(&self, image_dir: &Path) -> Result<Dataset, ColmapError> {
        let mut images: Vec<&ColmapImage> = self.images.values().collect();
        images.sort_by(|a, b| a.name.cmp(&b.name));
        let frames = images
            .into_iter()
            .map(|img| {
                let cam =
                    self.cameras
                        .get(&img.camera_id)
                        .ok_or_else(|| ColmapError::UnknownCamera {
                            path: image_dir.to_path_buf(),
                            image_id: img.id,
                            camera_id: img.camera_id,
                        })?;
                let camera = cam.to_camera().map_err(|source| ColmapError::BadCamera {
                    path: image_dir.to_path_buf(),
                    camera_id: cam.id,
                    source,
                })?;
                Ok(Frame {
                    image_path: PathBuf::from(&img.name),
                    depth_path: None,
                    camera,
                    cam_from_world: img.cam_from_world,
                    split: Split::Train,
                })
            })
            .collect::<Result<Vec<_>, ColmapError>>()?;
        Ok(Dataset {
            root: image_dir.to_path_buf(),
            frames,
            points: None,
            metadata: SceneMetadata::default(),
        })
    }

    /// A model holding the dataset's cameras (deduplicated, ids from 1) and images (ids from 1
    /// in frame order, named by their paths), without points.
    pub fn from_dataset(dataset: &Dataset) -> Result<ColmapModel, ColmapError> {
        let mut model = ColmapModel::default();
        let mut unique: Vec<Camera> = Vec::new();
        for (i, frame) in dataset.frames.iter().enumerate() {
            let camera_id = match unique.iter().position(|c| *c == frame.camera) {
                Some(k) => k as u32 + 1,
                None => {
                    unique.push(frame.camera);
                    let id = unique.len() as u32;
                    let cam = ColmapCamera::from_camera(id, &frame.camera).ok_or_else(|| {
                        ColmapError::Unrepresentable {
                            frame: i,
                            reason: "k3 ≠ 0 needs FULL_OPENCV, which is not written".into(),
                        }
                    })?;
                    model.cameras.insert(id, cam);
                    id
                }
            };
            // "./images/a.png" and "images/a.png" are the same image to COLMAP users.
            let clean: PathBuf = frame
                .image_path
                .components()
                .filter(|c| !matches!(c, std::path::Component::CurDir))
                .collect();
            let name = clean
                .to_str()
                .ok_or_else(|| ColmapError::Unrepresentable {
                    frame: i,
                    reason: "image path is not valid UTF-8".into(),
                })?
                .to_string();
            // Text models split on whitespace and rejoin with single spaces.
            let survives_text = name.split_whitespace().collect::<Vec<_>>().join(" ") == name;
            if name.is_empty() || name.contains('\0') || !survives_text {
                return Err(ColmapError::Unrepresentable {
                    frame: i,
                    reason: format!("image name {name:?} cannot be stored in a COLMAP model"),
                });
            }
            let id = i as u32 + 1;
            model.images.insert(
                id,
                ColmapImage {
                    id,
                    name,
                    camera_id,
                    cam_from_world: frame.cam_from_world,
                    points2d: Vec::new(),
                },
            );
        }
        Ok(model)
    }
}

// ---------------------------------------------------------------------------------------------
// Text

/// Non-comment lines with their 1-based line numbers. Blank lines are kept: in `images.txt` an
/// empty line is an image without keypoints.
fn text_lines(bytes: &[u8]) -> Vec<(usize, String)> {
    String::from_utf8_lossy(bytes)
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim_start().starts_with('#'))
        .map(|(i, l)| (i + 1, l.trim().to_string()))
        .collect()
}

struct Tokens<'a> {
    path: &'a Path,
    line: usize,
    it: std::str::SplitWhitespace<'a>,
}

impl<'a> Tokens<'a> {
    fn new(path: &'a Path, line: usize, text: &'a str) -> Self {
        Tokens {
            path,
            line,
            it: text.split_whitespace(),
        }
    }

    fn err(&self, field: &'static str, reason: impl Into<String>) -> ColmapError {
        ColmapError::Parse {
            path: self.path.to_path_buf(),
            line: self.line,
            field,
            reason: reason.into(),
        }
    }

    fn next_str(&mut self, field: &'static str) -> Result<&'a str, ColmapError> {
        self.it.next().ok_or_else(|| self.err(field, "missing"))
    }

    fn parse<T: std::str::FromStr>(&mut self, field: &'static str) -> Result<T, ColmapError> {
        let s = self.next_str(field)?;
        s.parse()
            .map_err(|_| self.err(field, format!("cannot parse `{s}`")))
    }

    fn end(&mut self) -> Result<(), ColmapError> {
        match self.it.next() {
            None => Ok(()),
            Some(s) => Err(self.err("(end of line)", format!("unexpected extra value `{s}`"))),
        }
    }
}

/// Parses `cameras.txt` content. `path` names the file in errors.
pub fn parse_cameras_text(
    bytes: &[u8],
    path: &Path,
) -> Result<BTreeMap<u32, ColmapCamera>, ColmapError> {
    let mut cameras = BTreeMap::new();
    for (line, text) in text_lines(bytes) {
        if text.is_empty() {
            continue;
        }
        let mut t = Tokens::new(path, line, &text);
        let id: u32 = t.parse("CAMERA_ID")?;
        let model_name = t.next_str("MODEL")?;
        let model = ColmapCameraModel::from_name(model_name).map_err(|model| {
            ColmapError::UnsupportedCameraModel {
                path: path.to_path_buf(),
                camera_id: id,
                model,
            }
        })?;
        let width: u32 = t.parse("WIDTH")?;
        let height: u32 = t.parse("HEIGHT")?;
        let mut params = Vec::with_capacity(model.num_params());
        for _ in 0..model.num_params() {
            params.push(t.parse::<f64>("PARAMS")?);
        }
        t.end()?;
        let cam = ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        };
        check_camera(&cam, path)?;
        if cameras.insert(id, cam).is_some() {
            return Err(t.err("CAMERA_ID", format!("duplicate camera id {id}")));
        }
    }
    Ok(cameras)
}

fn check_camera(cam: &ColmapCamera, path: &Path) -> Result<(), ColmapError> {
    cam.to_camera()
        .map(|_| ())
        .map_err(|source| ColmapError::BadCamera {
            path: path.to_path_buf(),
            camera_id: cam.id,
            source,
        })
}

/// Parses `images.txt` content (two lines per image; the second may be empty).
pub fn parse_images_text(
    bytes: &[u8],
    path: &Path,
) -> Result<BTreeMap<u32, ColmapImage>, ColmapError> {
    let lines = text_lines(bytes);
    let mut images = BTreeMap::new();
    let mut i = 0;
    while i < lines.len() {
        let (line, text) = &lines[i];
        i += 1;
        if text.is_empty() {
            continue;
        }
        let mut t = Tokens::new(path, *line, text);
        let id: u32 = t.parse("IMAGE_ID")?;
        let mut q = [0.0; 4];
        for (v, f) in q.iter_mut().zip(["QW", "QX", "QY", "QZ"]) {
            *v = t.parse(f)?;
        }
        let mut tv = [0.0; 3];
        for (v, f) in tv.iter_mut().zip(["TX", "TY", "TZ"]) {
            *v = t.parse(f)?;
        }
        let camera_id: u32 = t.parse("CAMERA_ID")?;
        // The name is the rest of the line, so names containing single spaces survive.
        let mut name = t.next_str("NAME")?.to_string();
        for part in t.it.by_ref() {
            name.push(' ');
            name.push_str(part);
        }
        let cam_from_world =
            cam_from_world_from_colmap(q, tv).map_err(|source| ColmapError::BadPose {
                path: path.to_path_buf(),
                image_id: id,
                source,
            })?;
        let mut points2d = Vec::new();
        // Some writers leave out the POINTS2D lines: a line that cannot be one (its tokens
        // are not (x, y, id) triples ending in an integer id) is the next image's, not ours.
        let looks_like_points = |text: &str| {
            let tokens: Vec<&str> = text.split_whitespace().collect();
            tokens.len().is_multiple_of(3) && tokens.last().is_none_or(|t| t.parse::<i64>().is_ok())
        };
        if i < lines.len() && looks_like_points(&lines[i].1) {
            let (pline, ptext) = &lines[i];
            i += 1;
            let mut pt = Tokens::new(path, *pline, ptext);
            while let Some(x) = pt.it.next() {
                let x: f64 = x
                    .parse()
                    .map_err(|_| pt.err("POINTS2D x", format!("cannot parse `{x}`")))?;
                let y: f64 = pt.parse("POINTS2D y")?;
                let id3: i64 = pt.parse("POINTS2D POINT3D_ID")?;
                let point3d_id = match id3 {
                    -1 => None,
                    v if v >= 0 => Some(v as u64),
                    v => return Err(pt.err("POINTS2D POINT3D_ID", format!("invalid id {v}"))),
                };
                points2d.push(Point2D {
                    xy: [x, y],
                    point3d_id,
                });
            }
        }
        let image = ColmapImage {
            id,
            name,
            camera_id,
            cam_from_world,
            points2d,
        };
        if images.insert(id, image).is_some() {
            return Err(ColmapError::Parse {
                path: path.to_path_buf(),
                line: *line,
                field: "IMAGE_ID",
                reason: format!("duplicate image id {id}"),
            });
        }
    }
    Ok(images)
}

/// Parses `points3D.txt` content.
pub fn parse_points3d_text(
    bytes: &[u8],
    path: &Path,
) -> Result<BTreeMap<u64, Point3D>, ColmapError> {
    let mut points = BTreeMap::new();
    for (line, text) in text_lines(bytes) {
        if text.is_empty() {
            continue;
        }
        let mut t = Tokens::new(path, line, &text);
        let id: u64 = t.parse("POINT3D_ID")?;
        let xyz: [f64; 3] = [t.parse("X")?, t.parse("Y")?, t.parse("Z")?];
        for (v, field) in xyz.iter().zip(["X", "Y", "Z"]) {
            if !v.is_finite() {
                return Err(t.err(field, format!("point {id}: coordinate {v} is not finite")));
            }
        }
        let rgb = [t.parse("R")?, t.parse("G")?, t.parse("B")?];
        let error: f64 = t.parse("ERROR")?;
        let mut track = Vec::new();
        while let Some(s) = t.it.next() {
            let image_id: u32 = s
                .parse()
                .map_err(|_| t.err("TRACK IMAGE_ID", format!("cannot parse `{s}`")))?;
            let point2d_idx: u32 = t.parse("TRACK POINT2D_IDX")?;
            track.push(TrackElement {
                image_id,
                point2d_idx,
            });
        }
        let p = Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        };
        if points.insert(id, p).is_some() {
            return Err(t.err("POINT3D_ID", format!("duplicate point id {id}")));
        }
    }
    Ok(points)
}

// ---------------------------------------------------------------------------------------------
// Binary

/// Which record a binary read belongs to, for error messages.
#[derive(Clone, Copy)]
struct Rec {
    kind: &'static str,
    index: u64,
}

struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8], path: &'a Path) -> Self {
        Reader {
            bytes,
            pos: 0,
            path,
        }
    }

    fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    fn take(&mut self, n: usize, rec: Rec, field: &str) -> Result<&'a [u8], ColmapError> {
        if self.remaining() < n {
            return Err(ColmapError::Truncated {
                path: self.path.to_path_buf(),
                record: describe(rec, field),
                offset: self.pos,
                needed: n,
            });
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn array<const N: usize>(&mut self, rec: Rec, field: &str) -> Result<[u8; N], ColmapError> {
        Ok(self
            .take(N, rec, field)?
            .try_into()
            .expect("take returns N bytes"))
    }

    fn u8(&mut self, rec: Rec, field: &str) -> Result<u8, ColmapError> {
        Ok(self.array::<1>(rec, field)?[0])
    }

    fn u32(&mut self, rec: Rec, field: &str) -> Result<u32, ColmapError> {
        Ok(u32::from_le_bytes(self.array(rec, field)?))
    }

    fn i32(&mut self, rec: Rec, field: &str) -> Result<i32, ColmapError> {
        Ok(i32::from_le_bytes(self.array(rec, field)?))
    }

    fn u64(&mut self, rec: Rec, field: &str) -> Result<u64, ColmapError> {
        Ok(u64::from_le_bytes(self.array(rec, field)?))
    }

    fn f64(&mut self, rec: Rec, field: &str) -> Result<f64, ColmapError> {
        Ok(f64::from_le_bytes(self.array(rec, field)?))
    }

    /// A record count. It is not trusted for allocation: see [`Reader::capacity`].
    fn count(&mut self, rec: Rec, field: &str) -> Result<u64, ColmapError> {
        self.u64(rec, field)
    }

    /// Capacity to reserve for `n` records of at least `min_size` bytes: never more than the
    /// remaining bytes can hold, so a corrupt count cannot trigger a huge allocation (the
    /// reads then fail at the field where the data ends).
    fn capacity(&self, n: u64, min_size: usize) -> usize {
        n.min((self.remaining() / min_size) as u64) as usize
    }

    fn cstring(&mut self, rec: Rec, field: &str) -> Result<String, ColmapError> {
        let rest = &self.bytes[self.pos..];
        let Some(len) = rest.iter().position(|&b| b == 0) else {
            return Err(ColmapError::Truncated {
                path: self.path.to_path_buf(),
                record: describe(rec, field),
                offset: self.pos,
                needed: rest.len() + 1,
            });
        };
        let s = String::from_utf8_lossy(&rest[..len]).into_owned();
        self.pos += len + 1;
        Ok(s)
    }

    fn finish(&self) -> Result<(), ColmapError> {
        if self.remaining() != 0 {
            return Err(ColmapError::Invalid {
                path: self.path.to_path_buf(),
                record: "end of file".into(),
                reason: format!("{} unexpected trailing bytes", self.remaining()),
            });
        }
        Ok(())
    }
}

fn describe(rec: Rec, field: &str) -> String {
    if rec.kind == "header" {
        field.to_string()
    } else {
        format!("{} #{} {}", rec.kind, rec.index, field)
    }
}

const HEADER: Rec = Rec {
    kind: "header",
    index: 0,
};

/// Parses `cameras.bin` content.
pub fn parse_cameras_binary(
    bytes: &[u8],
    path: &Path,
) -> Result<BTreeMap<u32, ColmapCamera>, ColmapError> {
    let mut r = Reader::new(bytes, path);
    let n = r.count(HEADER, "number of cameras")?;
    let mut cameras = BTreeMap::new();
    for index in 0..n {
        let rec = Rec {
            kind: "camera",
            index,
        };
        let id = r.u32(rec, "camera_id")?;
        let model_id = r.i32(rec, "model_id")?;
        let model = ColmapCameraModel::from_id(model_id).map_err(|model| {
            ColmapError::UnsupportedCameraModel {
                path: path.to_path_buf(),
                camera_id: id,
                model,
            }
        })?;
        let width = r.u64(rec, "width")?;
        let height = r.u64(rec, "height")?;
        let to_u32 = |v: u64, field: &str| {
            u32::try_from(v).map_err(|_| ColmapError::Invalid {
                path: path.to_path_buf(),
                record: describe(rec, field),
                reason: format!("{v} pixels is too large"),
            })
        };
        let (width, height) = (to_u32(width, "width")?, to_u32(height, "height")?);
        let params = (0..model.num_params())
            .map(|_| r.f64(rec, "params"))
            .collect::<Result<Vec<_>, _>>()?;
        let cam = ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        };
        check_camera(&cam, path)?;
        if cameras.insert(id, cam).is_some() {
            return Err(ColmapError::Invalid {
                path: path.to_path_buf(),
                record: describe(rec, "camera_id"),
                reason: format!("duplicate camera id {id}"),
            });
        }
    }
    r.finish()?;
    Ok(cameras)
}

/// Parses `images.bin` content.
pub fn parse_images_binary(
    bytes: &[u8],
    path: &Path,
) -> Result<BTreeMap<u32, ColmapImage>, ColmapError> {
    let mut r = Reader::new(bytes, path);
    let n = r.count(HEADER, "number of images")?;
    let mut images = BTreeMap::new();
    for index in 0..n {
        let rec = Rec {
            kind: "image",
            index,
        };
        let id = r.u32(rec, "image_id")?;
        let mut q = [0.0; 4];
        for v in &mut q {
            *v = r.f64(rec, "qvec")?;
        }
        let mut t = [0.0; 3];
        for v in &mut t {
            *v = r.f64(rec, "tvec")?;
        }
        let camera_id = r.u32(rec, "camera_id")?;
        let name = r.cstring(rec, "name")?;
        let num_points = r.count(rec, "number of points2D")?;
        let mut points2d = Vec::with_capacity(r.capacity(num_points, 24));
        for _ in 0..num_points {
            let x = r.f64(rec, "points2D x")?;
            let y = r.f64(rec, "points2D y")?;
            let pid = r.u64(rec, "points2D point3D_id")?;
            points2d.push(Point2D {
                xy: [x, y],
                point3d_id: (pid != u64::MAX).then_some(pid),
            });
        }
        let cam_from_world =
            cam_from_world_from_colmap(q, t).map_err(|source| ColmapError::BadPose {
                path: path.to_path_buf(),
                image_id: id,
                source,
            })?;
        let image = ColmapImage {
            id,
            name,
            camera_id,
            cam_from_world,
            points2d,
        };
        if images.insert(id, image).is_some() {
            return Err(ColmapError::Invalid {
                path: path.to_path_buf(),
                record: describe(rec, "image_id"),
                reason: format!("duplicate image id {id}"),
            });
        }
    }
    r.finish()?;
    Ok(images)
}

/// Parses `points3D.bin` content.
pub fn parse_points3d_binary(
    bytes: &[u8],
    path: &Path,
) -> Result<BTreeMap<u64, Point3D>, ColmapError> {
    let mut r = Reader::new(bytes, path);
    let n = r.count(HEADER, "number of points")?;
    let mut points = BTreeMap::new();
    for index in 0..n {
        let rec = Rec {
            kind: "point3D",
            index,
        };
        let id = r.u64(rec, "point3D_id")?;
        let xyz = [r.f64(rec, "xyz")?, r.f64(rec, "xyz")?, r.f64(rec, "xyz")?];
        if let Some(v) = xyz.iter().find(|v| !v.is_finite()) {
            return Err(ColmapError::Invalid {
                path: path.to_path_buf(),
                record: describe(rec, "xyz"),
                reason: format!("point {id}: coordinate {v} is not finite"),
            });
        }
        let rgb = [r.u8(rec, "rgb")?, r.u8(rec, "rgb")?, r.u8(rec, "rgb")?];
        let error = r.f64(rec, "error")?;
        let len = r.count(rec, "track length")?;
        let mut track = Vec::with_capacity(r.capacity(len, 8));
        for _ in 0..len {
            track.push(TrackElement {
                image_id: r.u32(rec, "track image_id")?,
                point2d_idx: r.u32(rec, "track point2D_idx")?,
            });
        }
        let p = Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        };
        if points.insert(id, p).is_some() {
            return Err(ColmapError::Invalid {
                path: path.to_path_buf(),
                record: describe(rec, "point3D_id"),
                reason: format!("duplicate point id {id}"),
            });
        }
    }
    r.finish()?;
    Ok(points)
}

// ---------------------------------------------------------------------------------------------
// Writers

/// Writes the model in text or binary form into `dir` (created if needed). Each file is
/// written atomically.
pub fn write_colmap(
    model: &ColmapModel,
    dir: &Path,
    format: ColmapFormat,
) -> Result<(), ColmapError> {
    std::fs::create_dir_all(dir).map_err(|e| io_error(dir, e))?;
    let files: [(&str, Vec<u8>); 3] = match format {
        ColmapFormat::Text => [
            ("cameras.txt", cameras_text(model).into_bytes()),
            ("images.txt", images_text(model).into_bytes()),
            ("points3D.txt", points3d_text(model).into_bytes()),
        ],
        ColmapFormat::Binary => [
            ("cameras.bin", cameras_binary(model)),
            ("images.bin", images_binary(model)?),
            ("points3D.bin", points3d_binary(model)),
        ],
    };
    for (name, bytes) in files {
        let p = dir.join(name);
        write_atomic(&p, &bytes).map_err(|e| io_error(&p, e))?;
    }
    Ok(())
}

fn cameras_text(model: &ColmapModel) -> String {
    let mut s = String::from("# Camera list with one line of data per camera:\n");
    s.push_str("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    let _ = writeln!(s, "# Number of cameras: {}", model.cameras.len());
    for c in model.cameras.values() {
        let _ = write!(s, "{} {} {} {}", c.id, c.model.name(), c.width, c.height);
        for p in &c.params {
            let _ = write!(s, " {p}");
        }
        s.push('\n');
    }
    s
}

fn images_text(model: &ColmapModel) -> String {
    let mut s = String::from("# Image list with two lines of data per image:\n");
    s.push_str("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    s.push_str("#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
    let _ = writeln!(s, "# Number of images: {}", model.images.len());
    for img in model.images.values() {
        let (q, t) = colmap_from_cam_from_world(&img.cam_from_world);
        let _ = writeln!(
            s,
            "{} {} {} {} {} {} {} {} {} {}",
            img.id, q[0], q[1], q[2], q[3], t[0], t[1], t[2], img.camera_id, img.name
        );
        let pts: Vec<String> = img
            .points2d
            .iter()
            .map(|p| {
                let id = p.point3d_id.map_or("-1".to_string(), |v| v.to_string());
                format!("{} {} {}", p.xy[0], p.xy[1], id)
            })
            .collect();
        s.push_str(&pts.join(" "));
        s.push('\n');
    }
    s
}

fn points3d_text(model: &ColmapModel) -> String {
    let mut s = String::from("# 3D point list with one line of data per point:\n");
    s.push_str("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n");
    let _ = writeln!(s, "# Number of points: {}", model.points3d.len());
    for p in model.points3d.values() {
        let _ = write!(
            s,
            "{} {} {} {} {} {} {} {}",
            p.id, p.xyz[0], p.xyz[1], p.xyz[2], p.rgb[0], p.rgb[1], p.rgb[2], p.error
        );
        for t in &p.track {
            let _ = write!(s, " {} {}", t.image_id, t.point2d_idx);
        }
        s.push('\n');
    }
    s
}

fn cameras_binary(model: &ColmapModel) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(&(model.cameras.len() as u64).to_le_bytes());
    for c in model.cameras.values() {
        b.extend_from_slice(&c.id.to_le_bytes());
        b.extend_from_slice(&c.model.id().to_le_bytes());
        b.extend_from_slice(&(c.width as u64).to_le_bytes());
        b.extend_from_slice(&(c.height as u64).to_le_bytes());
        for p in &c.params {
            b.extend_from_slice(&p.to_le_bytes());
        }
    }
    b
}

fn images_binary(model: &ColmapModel) -> Result<Vec<u8>, ColmapError> {
    let mut b = Vec::new();
    b.extend_from_slice(&(model.images.len() as u64).to_le_bytes());
    for (i, img) in model.images.values().enumerate() {
        if img.name.contains('\0') {
            return Err(ColmapError::Unrepresentable {
                frame: i,
                reason: format!("image name {:?} contains NUL", img.name),
            });
        }
        let (q, t) = colmap_from_cam_from_world(&img.cam_from_world);
        b.extend_from_slice(&img.id.to_le_bytes());
        for v in q.iter().chain(&t) {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&img.camera_id.to_le_bytes());
        b.extend_from_slice(img.name.as_bytes());
        b.push(0);
        b.extend_from_slice(&(img.points2d.len() as u64).to_le_bytes());
        for p in &img.points2d {
            b.extend_from_slice(&p.xy[0].to_le_bytes());
            b.extend_from_slice(&p.xy[1].to_le_bytes());
            b.extend_from_slice(&p.point3d_id.unwrap_or(u64::MAX).to_le_bytes());
        }
    }
    Ok(b)
}

fn points3d_binary(model: &ColmapModel) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(&(model.points3d.len() as u64).to_le_bytes());
    for p in model.points3d.values() {
        b.extend_from_slice(&p.id.to_le_bytes());
        for v in &p.xyz {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&p.rgb);
        b.extend_from_slice(&p.error.to_le_bytes());
        b.extend_from_slice(&(p.track.len() as u64).to_le_bytes());
        for t in &p.track {
            b.extend_from_slice(&t.image_id.to_le_bytes());
            b.extend_from_slice(&t.point2d_idx.to_le_bytes());
        }
    }
    b
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn model_table_is_consistent() {
        for m in ColmapCameraModel::ALL {
            assert_eq!(ColmapCameraModel::from_id(m.id()), Ok(m));
            assert_eq!(ColmapCameraModel::from_name(m.name()), Ok(m));
        }
        assert!(
            ColmapCameraModel::from_id(6)
                .unwrap_err()
                .contains("FULL_OPENCV")
        );
        assert!(
            ColmapCameraModel::from_name("FOV")
                .unwrap_err()
                .contains("id 7")
        );
        assert!(ColmapCameraModel::from_id(99).unwrap_err().contains("99"));
    }

    #[test]
    fn huge_counts_are_truncation_errors() {
        let mut b = u64::MAX.to_le_bytes().to_vec();
        b.extend_from_slice(&[0; 30]);
        let err = parse_points3d_binary(&b, Path::new("p.bin")).unwrap_err();
        assert!(matches!(err, ColmapError::Truncated { .. }), "{err}");
    }

    /// A point whose coordinates are not finite is an error naming the file, the point and
    /// the field, in both forms.
    #[test]
    fn non_finite_point_coordinates_are_errors() {
        for (text, field) in [
            ("1 nan 0 0 0 0 0 0.5\n", "X"),
            ("7 0 0 inf 0 0 0 0.5 3 4\n", "Z"),
        ] {
            let err = parse_points3d_text(text.as_bytes(), Path::new("points3D.txt")).unwrap_err();
            let msg = err.to_string();
            assert!(
                msg.contains("points3D.txt") && msg.contains(&format!("`{field}`")),
                "{msg}"
            );
        }
        let mut b = 1u64.to_le_bytes().to_vec();
        b.extend_from_slice(&5u64.to_le_bytes());
        for v in [0.0, f64::NAN, 1.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&[1, 2, 3]);
        b.extend_from_slice(&0.5f64.to_le_bytes());
        b.extend_from_slice(&0u64.to_le_bytes());
        let err = parse_points3d_binary(&b, Path::new("points3D.bin")).unwrap_err();
        let msg = err.to_string();
        assert!(
            matches!(err, ColmapError::Invalid { .. })
                && msg.contains("points3D.bin")
                && msg.contains("point 5"),
            "{msg}"
        );
    }
}
