//! The Mega-NeRF / Mill-19 dataset layout: reader and writer.
//!
//! ```text
//! DIR/coordinates.pt                 {'origin_drb': tensor(3), 'pose_scale_factor': float}
//! DIR/train/metadata/NAME.pt         {'W', 'H', 'intrinsics', 'c2w', ['distortion']}
//! DIR/train/rgbs/NAME.{jpg,JPG,png,PNG}
//! DIR/val/metadata/NAME.pt, DIR/val/rgbs/NAME.*
//! ```
//!
//! Conventions, as `scripts/colmap_to_mega_nerf.py` writes them and `mega_nerf/ray_utils.py`
//! reads them:
//!
//! - **World axes.** The script treats the COLMAP world as (right, down, forward) and
//!   re-expresses it in (down, right, back) "drb" axes: `x_drb = y_colmap`, `y_drb = x_colmap`,
//!   `z_drb = −z_colmap` ([`DRB_FROM_COLMAP`]). For a model whose y axis is gravity (as COLMAP's
//!   gravity alignment leaves it), x then points down: Mega-NeRF bounds rays by planes of
//!   constant x and gives its altitudes along x. The reader keeps these axes, so the dataset's
//!   up is −x.
//! - **Normalisation.** `origin_drb` is the centre of the camera positions' bounding box and
//!   the files hold `(x_drb − origin_drb) / pose_scale_factor` (`pose_scale_factor` metres per
//!   unit). The reader undoes it, so positions are metric again, and records the two numbers
//!   in [`SceneMetadata::mega_nerf`] (and the COLMAP axes in
//!   [`SceneMetadata::applied_transform`]) so poses can be given back in either frame.
//! - **Camera axes.** `c2w` is camera-to-world, 3×4. The script first builds it with camera
//!   axes (down, right, back), then reorders the columns to `[right, −down, back, t]`, so the
//!   file holds (right, up, back) camera axes: the OpenGL / nerfstudio convention, which is what
//!   `get_ray_directions` assumes (`(x − cx)/fx, −(y − cy)/fy, −1`).
//! - **Intrinsics.** `intrinsics` is `[fx, fy, cx, cy]` in pixels for the `W × H` image, with
//!   pixel centres at `+0.5` (Mega-NeRF's default `center_pixels`), as here.
//! - **Distortion.** `distortion` is OpenCV's `[k1, k2, p1, p2(, k3)]` of the original photo.
//!   The images in `rgbs/` were already undistorted with it (`cv2.undistort` with the same
//!   camera matrix), and Mega-NeRF renders them as pinhole images; so the reader returns
//!   pinhole cameras unless [`MegaNerfOptions::images_distorted`] says the `rgbs/` hold the
//!   original photos.
//! - **Splits.** `train/` becomes [`Split::Train`], `val/` [`Split::Test`]: Mega-NeRF's val
//!   images are the held-out views its paper evaluates on. `val/` may be absent.
//!
//! Every metadata file needs its image (Mega-NeRF looks for `.jpg`, `.JPG`, `.png`, `.PNG`, in
//! that order) with exactly the stated `W × H`; anything missing or malformed is a
//! [`MegaNerfError`] naming the file and the key.

use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use matloc_core::fsutil::write_atomic;
use matloc_core::pose::{Pose, cam_from_world_from_opengl, opengl_from_cam_from_world};
use matloc_core::{Camera, CameraError, Distortion, PoseError};
use nalgebra::{Matrix3x4, Matrix4, Point3, Vector3};
use thiserror::Error;

use crate::dataset::{Dataset, Frame, MegaNerfCoordinates, SceneMetadata, Split};
use crate::images::{ImageLoadError, image_size};
use crate::torch_pt::{PtValue, Tensor, TorchError, read_pt, write_pt};

/// The file that marks a Mega-NeRF dataset and holds its normalisation.
pub const COORDINATES_FILE: &str = "coordinates.pt";

/// Split folders in the order they are read, and the split each becomes.
pub const SPLIT_DIRS: [(&str, Split); 2] = [("train", Split::Train), ("val", Split::Test)];

/// Image extensions Mega-NeRF looks for, in its order.
pub const IMAGE_EXTENSIONS: [&str; 4] = ["jpg", "JPG", "png", "PNG"];

/// `colmap_to_mega_nerf.py`'s world axes as an `applied_transform` `[R | t]`:
/// `x_drb = R x_colmap`.
pub const DRB_FROM_COLMAP: [[f64; 4]; 3] = [
    [0.0, 1.0, 0.0, 0.0],
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 0.0, -1.0, 0.0],
];

/// Errors raised when reading or writing a Mega-NeRF dataset.
#[derive(Debug, Error)]
pub enum MegaNerfError {
    /// The directory lacks the layout (`coordinates.pt`, `train/metadata/`).
    #[error("{path} is not a Mega-NeRF dataset: {reason}")]
    NotMegaNerf {
        /// The directory.
        path: PathBuf,
        /// What is missing.
        reason: String,
    },
    /// Listing, reading or writing failed at the operating-system level.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// A `.pt` file could not be read.
    #[error(transparent)]
    Torch(#[from] TorchError),
    /// A required key is absent.
    #[error("{file}: missing key `{key}`")]
    MissingKey {
        /// The `.pt` file.
        file: PathBuf,
        /// The key.
        key: String,
    },
    /// A key has the wrong type, shape or value.
    #[error("{file}: key `{key}`: {reason}")]
    BadField {
        /// The `.pt` file.
        file: PathBuf,
        /// The key.
        key: String,
        /// What is wrong.
        reason: String,
    },
    /// `c2w` is not a finite rigid transform.
    #[error("{file}: key `c2w`: {source}")]
    BadPose {
        /// The metadata file.
        file: PathBuf,
        /// What is wrong.
        source: PoseError,
    },
    /// The intrinsics are invalid.
    #[error("{file}: keys `W`, `H`, `intrinsics`: {source}")]
    BadCamera {
        /// The metadata file.
        file: PathBuf,
        /// What is wrong.
        source: CameraError,
    },
    /// A metadata file has no image.
    #[error("{metadata}: no image {looked_for} (.jpg, .JPG, .png or .PNG)")]
    MissingImage {
        /// The metadata file.
        metadata: PathBuf,
        /// The image path without extension.
        looked_for: PathBuf,
    },
    /// An image header could not be read.
    #[error("{metadata}: {source}")]
    Image {
        /// The metadata file.
        metadata: PathBuf,
        /// What went wrong.
        source: ImageLoadError,
    },
    /// An image's size differs from the metadata's `W × H`.
    #[error(
        "{image} is {width}x{height} but {metadata} says W = {expected_width}, H = {expected_height}"
    )]
    ImageSize {
        /// The image file.
        image: PathBuf,
        /// The metadata file.
        metadata: PathBuf,
        /// Width of the image.
        width: u32,
        /// Height of the image.
        height: u32,
        /// `W` in the metadata.
        expected_width: u32,
        /// `H` in the metadata.
        expected_height: u32,
    },
    /// The dataset cannot be written as asked.
    #[error("cannot write {path}: {reason}")]
    Unwritable {
        /// The file or directory.
        path: PathBuf,
        /// Why.
        reason: String,
    },
}

/// How to read a Mega-NeRF dataset.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MegaNerfOptions {
    /// The `rgbs/` hold the original, distorted photos: cameras get the files' `distortion`.
    /// Off by default, since Mega-NeRF's `rgbs/` are undistorted.
    pub images_distorted: bool,
}

/// True when `dir` has the Mega-NeRF layout (`coordinates.pt` and `train/metadata/`).
pub fn is_mega_nerf_dir(dir: &Path) -> bool {
    dir.join(COORDINATES_FILE).is_file() && dir.join("train").join("metadata").is_dir()
}

/// Reads a Mega-NeRF dataset directory (or its `coordinates.pt`) with default options.
pub fn read_mega_nerf(path: &Path) -> Result<Dataset, MegaNerfError> {
    read_mega_nerf_with(path, &MegaNerfOptions::default())
}

/// Reads a Mega-NeRF dataset directory (or its `coordinates.pt`): metric poses in the drb
/// world, OpenCV camera axes, image paths relative to the directory.
pub fn read_mega_nerf_with(
    path: &Path,
    options: &MegaNerfOptions,
) -> Result<Dataset, MegaNerfError> {
    let dir = if path.file_name().is_some_and(|n| n == COORDINATES_FILE) && path.is_file() {
        path.parent().unwrap_or(Path::new("."))
    } else {
        path
    };
    let coordinates_file = dir.join(COORDINATES_FILE);
    if !coordinates_file.is_file() {
        return Err(MegaNerfError::NotMegaNerf {
            path: dir.to_path_buf(),
            reason: format!("no {COORDINATES_FILE}"),
        });
    }
    let coordinates = read_coordinates(&coordinates_file)?;
    if !dir.join("train").join("metadata").is_dir() {
        return Err(MegaNerfError::NotMegaNerf {
            path: dir.to_path_buf(),
            reason: "no train/metadata folder".into(),
        });
    }
    let mut frames = Vec::new();
    for (name, split) in SPLIT_DIRS {
        let metadata_dir = dir.join(name).join("metadata");
        if split == Split::Test && !metadata_dir.exists() {
            continue;
        }
        for file in metadata_files(&metadata_dir)? {
            frames.push(read_frame(dir, name, &file, split, &coordinates, options)?);
        }
    }
    Ok(Dataset {
        root: dir.to_path_buf(),
        frames,
        points: None,
        metadata: SceneMetadata {
            up: Some([-1.0, 0.0, 0.0]),
            applied_transform: Some(DRB_FROM_COLMAP),
            mega_nerf: Some(coordinates),
            ..SceneMetadata::default()
        },
    })
}

/// The `.pt` files of a metadata folder, sorted by name (as Mega-NeRF sorts them).
fn metadata_files(dir: &Path) -> Result<Vec<PathBuf>, MegaNerfError> {
    let io_err = |source| MegaNerfError::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut files = Vec::new();
    for entry in fs::read_dir(dir).map_err(io_err)? {
        let path = entry.map_err(io_err)?.path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if name.ends_with(".pt") && !name.starts_with('.') {
            // A `.pt` entry that is not a file (a directory, a device, a dangling link) is a
            // broken frame, not one to skip silently.
            if !path.is_file() {
                return Err(MegaNerfError::Io {
                    path,
                    source: std::io::Error::new(
                        std::io::ErrorKind::InvalidInput,
                        "not a regular file",
                    ),
                });
            }
            files.push(path);
        }
    }
    files.sort();
    Ok(files)
}

/// Reads `coordinates.pt`.
pub fn read_coordinates(file: &Path) -> Result<MegaNerfCoordinates, MegaNerfError> {
    let v = read_pt(file)?;
    let f = Fields { file, value: &v };
    f.dict()?;
    let origin = f.numbers("origin_drb", &[3])?;
    let scale = f.number("pose_scale_factor")?;
    if !(scale.is_finite() && scale > 0.0) {
        return Err(f.bad(
            "pose_scale_factor",
            format!("must be positive, got {scale}"),
        ));
    }
    if origin.iter().any(|x| !x.is_finite()) {
        return Err(f.bad("origin_drb", format!("not finite: {origin:?}")));
    }
    Ok(MegaNerfCoordinates {
        origin_drb: [origin[0], origin[1], origin[2]],
        pose_scale_factor: scale,
    })
}

/// `cam_from_world` (metric, OpenCV axes) of a metadata file's `c2w`.
pub fn cam_from_world_from_metadata(
    coordinates: &MegaNerfCoordinates,
    c2w: &Matrix3x4<f64>,
) -> Result<Pose, PoseError> {
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 4>(0, 0).copy_from(c2w);
    let t = Vector3::from(coordinates.origin_drb)
        + Vector3::from(c2w.column(3)) * coordinates.pose_scale_factor;
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&t);
    // The file's camera axes are (right, up, back): OpenGL's.
    cam_from_world_from_opengl(&m)
}

/// The `c2w` a metadata file holds for a metric `cam_from_world` pose (inverse of
/// [`cam_from_world_from_metadata`]).
pub fn metadata_c2w(coordinates: &MegaNerfCoordinates, cam_from_world: &Pose) -> Matrix3x4<f64> {
    let m = opengl_from_cam_from_world(cam_from_world);
    let mut c2w: Matrix3x4<f64> = m.fixed_view::<3, 4>(0, 0).into_owned();
    let t = (Vector3::from(c2w.column(3)) - Vector3::from(coordinates.origin_drb))
        / coordinates.pose_scale_factor;
    c2w.set_column(3, &t);
    c2w
}

fn read_frame(
    dir: &Path,
    split_dir: &str,
    file: &Path,
    split: Split,
    coordinates: &MegaNerfCoordinates,
    options: &MegaNerfOptions,
) -> Result<Frame, MegaNerfError> {
    let v = read_pt(file)?;
    let f = Fields { file, value: &v };
    f.dict()?;
    let width = f.pixels("W")?;
    let height = f.pixels("H")?;
    let k = f.numbers("intrinsics", &[4])?;
    f.get("c2w")?;
    let c2w = match f.numbers("c2w", &[3, 4]) {
        Ok(m) => m,
        Err(_) => {
            let m = f.numbers("c2w", &[4, 4]).map_err(|_| {
                f.bad(
                    "c2w",
                    format!("expected a 3x4 (or 4x4) tensor, got {}", f.kind("c2w")),
                )
            })?;
            if m[12..] != [0.0, 0.0, 0.0, 1.0] {
                return Err(f.bad(
                    "c2w",
                    "the 4th row of a 4x4 c2w must be [0, 0, 0, 1]".into(),
                ));
            }
            m[..12].to_vec()
        }
    };
    let c2w = Matrix3x4::from_row_slice(&c2w);
    let cam_from_world = cam_from_world_from_metadata(coordinates, &c2w).map_err(|source| {
        MegaNerfError::BadPose {
            file: file.to_path_buf(),
            source,
        }
    })?;
    let distortion = match v.get("distortion") {
        None | Some(PtValue::None) => Distortion::NONE,
        Some(_) => f.distortion()?,
    };
    let distortion = if options.images_distorted {
        distortion
    } else {
        Distortion::NONE
    };
    let camera =
        Camera::opencv(width, height, k[0], k[1], k[2], k[3], distortion).map_err(|source| {
            MegaNerfError::BadCamera {
                file: file.to_path_buf(),
                source,
            }
        })?;

    let stem = file.file_stem().unwrap_or_default();
    let rgbs = Path::new(split_dir).join("rgbs");
    let image_path = IMAGE_EXTENSIONS
        .iter()
        .map(|ext| rgbs.join(stem).with_extension(ext))
        .find(|p| dir.join(p).is_file())
        .ok_or_else(|| MegaNerfError::MissingImage {
            metadata: file.to_path_buf(),
            looked_for: dir.join(&rgbs).join(stem),
        })?;
    let image = dir.join(&image_path);
    let (w, h) = image_size(&image).map_err(|source| MegaNerfError::Image {
        metadata: file.to_path_buf(),
        source,
    })?;
    if (w, h) != (width, height) {
        return Err(MegaNerfError::ImageSize {
            image,
            metadata: file.to_path_buf(),
            width: w,
            height: h,
            expected_width: width,
            expected_height: height,
        });
    }
    Ok(Frame {
        image_path,
        depth_path: None,
        camera,
        cam_from_world,
        split,
    })
}

/// Typed access to the keys of one `.pt` dict.
struct Fields<'a> {
    file: &'a Path,
    value: &'a PtValue,
}

impl Fields<'_> {
    fn bad(&self, key: &str, reason: String) -> MegaNerfError {
        MegaNerfError::BadField {
            file: self.file.to_path_buf(),
            key: key.to_string(),
            reason,
        }
    }

    fn dict(&self) -> Result<(), MegaNerfError> {
        match self.value {
            PtValue::Dict(_) => Ok(()),
            other => Err(self.bad("(file)", format!("expected a dict, got {}", other.kind()))),
        }
    }

    fn get(&self, key: &str) -> Result<&PtValue, MegaNerfError> {
        self.value
            .get(key)
            .ok_or_else(|| MegaNerfError::MissingKey {
                file: self.file.to_path_buf(),
                key: key.to_string(),
            })
    }

    fn kind(&self, key: &str) -> String {
        self.value.get(key).map_or("nothing".into(), PtValue::kind)
    }

    fn number(&self, key: &str) -> Result<f64, MegaNerfError> {
        let v = self.get(key)?;
        v.as_f64()
            .ok_or_else(|| self.bad(key, format!("expected a number, got {}", v.kind())))
    }

    /// A positive whole number of pixels.
    fn pixels(&self, key: &str) -> Result<u32, MegaNerfError> {
        let x = self.number(key)?;
        if !(x.is_finite() && x >= 1.0 && x.fract() == 0.0 && x <= f64::from(u32::MAX)) {
            return Err(self.bad(key, format!("expected a positive whole number, got {x}")));
        }
        Ok(x as u32)
    }

    /// A tensor (or list) of exactly `shape`, as row-major f64.
    fn numbers(&self, key: &str, shape: &[usize]) -> Result<Vec<f64>, MegaNerfError> {
        let v = self.get(key)?;
        let wrong = || {
            self.bad(
                key,
                format!("expected a tensor of shape {shape:?}, got {}", v.kind()),
            )
        };
        let (s, data) = v.as_f64_array().ok_or_else(wrong)?;
        if s != shape {
            return Err(wrong());
        }
        Ok(data)
    }

    /// OpenCV's `[k1, k2, p1, p2(, k3(, k4, k5, k6))]`; k4..k6 (the rational model) must be 0.
    fn distortion(&self) -> Result<Distortion, MegaNerfError> {
        let key = "distortion";
        let v = self.get(key)?;
        let (_, d) = v
            .as_f64_array()
            .filter(|(s, _)| s.len() == 1 && matches!(s[0], 4 | 5 | 8))
            .ok_or_else(|| {
                self.bad(
                    key,
                    format!(
                        "expected OpenCV coefficients [k1, k2, p1, p2(, k3)] (4, 5 or 8 values), got {}",
                        v.kind()
                    ),
                )
            })?;
        if d.iter().any(|x| !x.is_finite()) {
            return Err(self.bad(key, format!("not finite: {d:?}")));
        }
        if d.len() == 8 && d[5..] != [0.0, 0.0, 0.0] {
            return Err(self.bad(key, "k4..k6 (the rational model) are not supported".into()));
        }
        Ok(Distortion {
            k1: d[0],
            k2: d[1],
            p1: d[2],
            p2: d[3],
            k3: d.get(4).copied().unwrap_or(0.0),
        })
    }
}

/// The normalisation [`write_mega_nerf`] uses for a dataset that carries none: the centre of
/// the camera positions' bounding box, and the largest distance from it (as Mega-NeRF's
/// script does, so every position lands in `[−1, 1]`).
pub fn fit_coordinates(dataset: &Dataset) -> MegaNerfCoordinates {
    let centres: Vec<Point3<f64>> = dataset.frames.iter().map(Frame::center).collect();
    let Some(first) = centres.first() else {
        return MegaNerfCoordinates {
            origin_drb: [0.0; 3],
            pose_scale_factor: 1.0,
        };
    };
    let (mut lo, mut hi) = (first.coords, first.coords);
    for c in &centres {
        lo = lo.inf(&c.coords);
        hi = hi.sup(&c.coords);
    }
    let origin = (lo + hi) * 0.5;
    let radius = centres
        .iter()
        .map(|c| (c.coords - origin).norm())
        .fold(0.0, f64::max);
    MegaNerfCoordinates {
        origin_drb: [origin.x, origin.y, origin.z],
        pose_scale_factor: if radius > 0.0 && radius.is_finite() {
            radius
        } else {
            1.0
        },
    }
}

/// Writes `dataset` in the Mega-NeRF layout into `dir` (created; one that already holds a
/// `coordinates.pt` is refused): `train/` for train frames, `val/` for test and val frames,
/// named by frame index (`000000.pt`, `000000.jpg`), images copied, float64 tensors (so poses
/// survive exactly), `distortion` for distorted cameras, and `coordinates.pt` written last.
/// The normalisation is the dataset's own ([`SceneMetadata::mega_nerf`]) or
/// [`fit_coordinates`]. Poses stay in the dataset's world axes; Mega-NeRF expects x down.
pub fn write_mega_nerf(
    dataset: &Dataset,
    dir: &Path,
) -> Result<MegaNerfCoordinates, MegaNerfError> {
    let coordinates_file = dir.join(COORDINATES_FILE);
    if coordinates_file.exists() {
        return Err(MegaNerfError::Unwritable {
            path: dir.to_path_buf(),
            reason: format!("it already holds a Mega-NeRF dataset ({COORDINATES_FILE})"),
        });
    }
    let coordinates = dataset
        .metadata
        .mega_nerf
        .unwrap_or_else(|| fit_coordinates(dataset));
    for (name, _) in SPLIT_DIRS {
        for sub in ["metadata", "rgbs"] {
            let d = dir.join(name).join(sub);
            fs::create_dir_all(&d).map_err(|source| MegaNerfError::Io { path: d, source })?;
        }
    }
    for (i, frame) in dataset.frames.iter().enumerate() {
        let split_dir = if frame.split == Split::Train {
            "train"
        } else {
            "val"
        };
        let source = dataset.image_path(frame);
        let ext = source
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        let ext = match ext.as_deref() {
            Some("jpg" | "jpeg") => "jpg",
            Some("png") => "png",
            _ => {
                return Err(MegaNerfError::Unwritable {
                    path: source,
                    reason: "Mega-NeRF reads only .jpg and .png images".into(),
                });
            }
        };
        let stem = format!("{i:06}");
        let image = dir
            .join(split_dir)
            .join("rgbs")
            .join(format!("{stem}.{ext}"));
        let bytes = fs::read(&source).map_err(|e| MegaNerfError::Io {
            path: source.clone(),
            source: e,
        })?;
        write_atomic(&image, &bytes).map_err(|source| MegaNerfError::Io {
            path: image.clone(),
            source,
        })?;

        let cam = &frame.camera;
        let c2w = metadata_c2w(&coordinates, &frame.cam_from_world);
        let c2w_rows: Vec<f64> = (0..3)
            .flat_map(|r| (0..4).map(move |c| (r, c)))
            .map(|(r, c)| c2w[(r, c)])
            .collect();
        if c2w_rows.iter().any(|x| !x.is_finite()) {
            return Err(MegaNerfError::Unwritable {
                path: image,
                reason: format!("frame {i}: pose is not finite"),
            });
        }
        let mut items = vec![
            ("H".to_string(), PtValue::Int(i64::from(cam.height))),
            ("W".to_string(), PtValue::Int(i64::from(cam.width))),
            (
                "c2w".to_string(),
                PtValue::Tensor(Tensor::f64(vec![3, 4], c2w_rows)),
            ),
            (
                "intrinsics".to_string(),
                PtValue::Tensor(Tensor::f64(vec![4], vec![cam.fx, cam.fy, cam.cx, cam.cy])),
            ),
        ];
        if !cam.is_pinhole() {
            let d = &cam.distortion;
            items.push((
                "distortion".to_string(),
                PtValue::Tensor(Tensor::f64(vec![5], vec![d.k1, d.k2, d.p1, d.p2, d.k3])),
            ));
        }
        let file = dir
            .join(split_dir)
            .join("metadata")
            .join(format!("{stem}.pt"));
        write_pt(&file, &PtValue::Dict(items))?;
    }
    let c = PtValue::Dict(vec![
        (
            "origin_drb".into(),
            PtValue::Tensor(Tensor::f64(vec![3], coordinates.origin_drb.to_vec())),
        ),
        (
            "pose_scale_factor".into(),
            PtValue::Float(coordinates.pose_scale_factor),
        ),
    ]);
    write_pt(&coordinates_file, &c)?;
    Ok(coordinates)
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::pose::look_at;

    #[test]
    fn metadata_pose_round_trips_and_uses_opengl_camera_axes() {
        let coordinates = MegaNerfCoordinates {
            origin_drb: [10.0, -20.0, 5.0],
            pose_scale_factor: 50.0,
        };
        // A file c2w with identity rotation at normalised (0.1, 0.2, -0.2): camera looks down
        // its −z (back) axis, image up is world +y, centre 10 + 5, −20 + 10, 5 − 10.
        let c2w = Matrix3x4::new(
            1.0, 0.0, 0.0, 0.1, //
            0.0, 1.0, 0.0, 0.2, //
            0.0, 0.0, 1.0, -0.2,
        );
        let pose = cam_from_world_from_metadata(&coordinates, &c2w).unwrap();
        let c = pose.inverse_transform_point(&Point3::origin());
        assert!((c - Point3::new(15.0, -10.0, -5.0)).norm() < 1e-12);
        let forward = pose.inverse_transform_vector(&Vector3::z());
        assert!((forward - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        let down = pose.inverse_transform_vector(&Vector3::y());
        assert!((down - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
        let back = metadata_c2w(&coordinates, &pose);
        assert!((back - c2w).norm() < 1e-12);
    }

    #[test]
    fn fitted_coordinates_put_every_centre_in_the_unit_ball() {
        let cam = Camera::pinhole(4, 3, 5.0, 5.0, 2.0, 1.5).unwrap();
        let frames = [[0.0, 0.0, 10.0], [100.0, 20.0, 12.0], [50.0, -40.0, 11.0]]
            .iter()
            .map(|&[x, y, z]| Frame {
                image_path: "a.png".into(),
                depth_path: None,
                camera: cam,
                cam_from_world: look_at(
                    &Point3::new(x, y, z),
                    &Point3::new(x, y + 1.0, 0.0),
                    &Vector3::z(),
                )
                .unwrap(),
                split: Split::Train,
            })
            .collect();
        let ds = Dataset {
            root: PathBuf::new(),
            frames,
            metadata: SceneMetadata::default(),
            points: None,
        };
        let c = fit_coordinates(&ds);
        let expected = Vector3::new(50.0, -10.0, 11.0);
        assert!((Vector3::from(c.origin_drb) - expected).norm() < 1e-9);
        for f in &ds.frames {
            let t = metadata_c2w(&c, &f.cam_from_world).column(3).into_owned();
            assert!(t.amax() <= 1.0 + 1e-12);
        }
    }
}
