//! nerfstudio `transforms.json`: reader and writer.
//!
//! Reading accepts what `ns-process-data` writes and the Blender (NeRF-synthetic) layout:
//!
//! - intrinsics `fl_x fl_y cx cy w h` at the top level (shared) or in each frame (a frame's
//!   keys override the shared ones); `fl_y` defaults to `fl_x`; `camera_angle_x` (Blender)
//!   stands in for `fl_x`; missing `w`/`h` are read from the image header; missing `cx`/`cy`
//!   default to the image centre;
//! - `camera_model` `PINHOLE`, `OPENCV` (also `SIMPLE_PINHOLE`, `SIMPLE_RADIAL`, `RADIAL`)
//!   with `k1 k2 p1 p2` and optional `k3`; when `camera_model` is absent the distortion keys
//!   decide. Fisheye and equirectangular models are rejected with a typed error;
//! - `transform_matrix`: OpenGL camera-to-world (x right, y up, z back), 4×4 or 3×4,
//!   converted to the internal `cam_from_world`; non-finite or non-rigid matrices are errors;
//!   Python's `NaN`/`Infinity` literals are read so that they are reported as such;
//! - relative `file_path` and optional `depth_file_path` (Blender paths without an extension
//!   get `.png` when that file exists);
//! - splits from `train_filenames` / `val_filenames` / `test_filenames` lists, or from separate
//!   `transforms_{train,val,test}.json` files; frames named in no list are train. A frame in
//!   several lists gets the last of train, val, test;
//! - `ply_file_path` (nerfstudio's sparse point cloud), else a `sparse_pc.ply` beside the file,
//!   recorded as the dataset's [`PointSource::Ply`];
//! - `applied_transform`, the 3×4 `[R | t]` that `ns-process-data` applied to the COLMAP world
//!   (`x_here = R x_colmap + t`), kept in [`SceneMetadata::applied_transform`]. nerfstudio
//!   inverts it as a general matrix; here it must be finite with a rotation `R` (what every
//!   nerfstudio converter writes), since only a rigid map keeps a pose a pose.
//!   [`original_cam_from_world`] gives a pose back in the COLMAP world;
//! - our own `"matloc"` object ([`SceneMetadata`]). Every other key is ignored.
//!
//! The writer emits one `transforms.json` with split lists, shared intrinsics when every frame
//! has the same camera (else per-frame), `ply_file_path`, `applied_transform` (top level, as
//! nerfstudio has it), and the `"matloc"` object; it writes atomically.

use std::collections::HashMap;
use std::fmt;
use std::io;
use std::path::{Component, Path, PathBuf};

use matloc_core::pose::{
    Pose, cam_from_world_from_opengl, opengl_from_cam_from_world, rotation_from_matrix,
};
use matloc_core::{Camera, CameraError, Distortion, PoseError};
use nalgebra::{Matrix3, Matrix4, Vector3};
use serde_json::{Map, Value};
use thiserror::Error;

use crate::dataset::{Dataset, Frame, PointSource, SceneMetadata, Split};
use crate::images::{ImageLoadError, image_size};
use matloc_core::fsutil::write_atomic;

/// File name of the single-file layout.
pub const TRANSFORMS_JSON: &str = "transforms.json";

/// Per-split files of the Blender layout, in the order they are read.
pub const BLENDER_SPLIT_FILES: [(Split, &str); 3] = [
    (Split::Train, "transforms_train.json"),
    (Split::Val, "transforms_val.json"),
    (Split::Test, "transforms_test.json"),
];

/// Where in the file a problem is: a frame index, or the top level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct At(pub Option<usize>);

impl fmt::Display for At {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some(i) => write!(f, "frame {i}"),
            None => write!(f, "top level"),
        }
    }
}

/// The `transforms.json` keys a camera error is about (`fl_x` for the camera's `fx`).
fn ns_keys(e: &CameraError) -> &'static str {
    match e {
        CameraError::NonFinite { field, .. } | CameraError::NonPositiveFocal { field, .. } => {
            match *field {
                "fx" => "`fl_x`",
                "fy" => "`fl_y`",
                "cx" => "`cx`",
                "cy" => "`cy`",
                _ => "`k1` `k2` `k3` `p1` `p2`",
            }
        }
        CameraError::EmptyImage { .. } => "`w` `h`",
        _ => "`fl_x` `fl_y` `cx` `cy` `w` `h`",
    }
}

/// Errors raised when reading or writing nerfstudio datasets.
#[derive(Debug, Error)]
pub enum NerfstudioError {
    /// Neither a transforms file nor a directory holding one.
    #[error(
        "no nerfstudio dataset at {path} (looked for transforms.json or transforms_{{train,val,test}}.json)"
    )]
    NotFound {
        /// The path given.
        path: PathBuf,
    },
    /// Reading or writing failed at the operating-system level.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// The file is not valid JSON.
    #[error("malformed JSON in {path} at line {line}, column {column}: {message}")]
    Json {
        /// The file.
        path: PathBuf,
        /// 1-based line of the error.
        line: usize,
        /// 1-based column of the error.
        column: usize,
        /// serde_json's description.
        message: String,
    },
    /// A required key is absent.
    #[error("{path}: {at}: missing field `{field}`")]
    MissingField {
        /// The file.
        path: PathBuf,
        /// Frame or top level.
        at: At,
        /// The key.
        field: String,
    },
    /// A key has the wrong type or an impossible value.
    #[error("{path}: {at}: field `{field}`: {reason}")]
    InvalidField {
        /// The file.
        path: PathBuf,
        /// Frame or top level.
        at: At,
        /// The key.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// A `camera_model` this crate cannot represent.
    #[error(
        "{path}: {at}: unsupported camera_model `{model}` (supported: PINHOLE, OPENCV, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL)"
    )]
    UnsupportedCameraModel {
        /// The file.
        path: PathBuf,
        /// Frame or top level.
        at: At,
        /// The model named in the file.
        model: String,
    },
    /// `transform_matrix` is not a finite rigid transform.
    #[error("{path}: frame {frame}: field `transform_matrix`: {source}")]
    BadTransform {
        /// The file.
        path: PathBuf,
        /// Frame index.
        frame: usize,
        /// What is wrong with it.
        source: PoseError,
    },
    /// The intrinsics are invalid (non-finite, non-positive focal length, empty image).
    #[error("{path}: {at}: invalid intrinsics ({}): {source}", ns_keys(source))]
    BadCamera {
        /// The file.
        path: PathBuf,
        /// Frame or top level.
        at: At,
        /// What is wrong.
        source: CameraError,
    },
    /// `w`/`h` are absent and the image header that would give them cannot be read.
    #[error("{path}: frame {frame}: no `w`/`h` and the image size is unknown: {source}")]
    ImageSize {
        /// The transforms file.
        path: PathBuf,
        /// Frame index.
        frame: usize,
        /// Why the image header could not be read.
        source: ImageLoadError,
    },
    /// A split list names a file that no frame has.
    #[error("{path}: `{list}` names `{entry}`, which is not the file_path of any frame")]
    UnknownSplitEntry {
        /// The file.
        path: PathBuf,
        /// The list key, e.g. `test_filenames`.
        list: String,
        /// The entry.
        entry: String,
    },
    /// The dataset cannot be written as given (non-finite pose, non-UTF-8 path, ...).
    #[error("cannot write {path}: frame {frame}: {reason}")]
    Unwritable {
        /// The file that was to be written.
        path: PathBuf,
        /// Frame index.
        frame: usize,
        /// Why.
        reason: String,
    },
}

/// Reads a nerfstudio dataset from a `transforms.json`-style file or from a directory holding
/// `transforms.json` or the Blender split files `transforms_{train,val,test}.json`.
///
/// Frame paths stay relative to the returned [`Dataset::root`], the directory of the file.
pub fn read_nerfstudio(path: &Path) -> Result<Dataset, NerfstudioError> {
    if path.is_dir() {
        let single = path.join(TRANSFORMS_JSON);
        if single.is_file() {
            return read_transforms_file(&single, Split::Train);
        }
        let mut merged: Option<Dataset> = None;
        for (split, name) in BLENDER_SPLIT_FILES {
            let file = path.join(name);
            if !file.is_file() {
                continue;
            }
            let part = read_transforms_file(&file, split)?;
            match merged.as_mut() {
                None => merged = Some(part),
                Some(all) => {
                    all.frames.extend(part.frames);
                    if all.metadata == SceneMetadata::default() {
                        all.metadata = part.metadata;
                    }
                    if all.points.is_none() {
                        all.points = part.points;
                    }
                }
            }
        }
        return merged.ok_or_else(|| NerfstudioError::NotFound {
            path: path.to_path_buf(),
        });
    }
    if !path.exists() {
        return Err(NerfstudioError::NotFound {
            path: path.to_path_buf(),
        });
    }
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
    let default_split = BLENDER_SPLIT_FILES
        .iter()
        .find(|(_, n)| *n == name)
        .map_or(Split::Train, |(s, _)| *s);
    read_transforms_file(path, default_split)
}

fn read_transforms_file(file: &Path, default_split: Split) -> Result<Dataset, NerfstudioError> {
    let bytes = std::fs::read(file).map_err(|source| {
        if source.kind() == io::ErrorKind::NotFound {
            NerfstudioError::NotFound {
                path: file.to_path_buf(),
            }
        } else {
            NerfstudioError::Io {
                path: file.to_path_buf(),
                source,
            }
        }
    })?;
    let root = file.parent().unwrap_or(Path::new("")).to_path_buf();
    parse_transforms(&bytes, file, &root, default_split)
}

/// Parses the bytes of a transforms file. `file` names the file in errors, `root` is the
/// directory frame paths are relative to, `default_split` applies to frames in no split list.
///
/// Touches the file system only to read image headers when `w`/`h` are missing.
pub fn parse_transforms(
    bytes: &[u8],
    file: &Path,
    root: &Path,
    default_split: Split,
) -> Result<Dataset, NerfstudioError> {
    let value = parse_json_lenient(bytes, file)?;
    let p = Ctx { path: file };
    let top = value
        .as_object()
        .ok_or_else(|| p.invalid(None, "(document)", "expected a JSON object"))?;
    let frames_json = top
        .get("frames")
        .ok_or_else(|| p.missing(None, "frames"))?
        .as_array()
        .ok_or_else(|| p.invalid(None, "frames", "expected an array"))?;

    let mut frames = Vec::with_capacity(frames_json.len());
    let mut raw_paths = Vec::with_capacity(frames_json.len());
    for (i, fv) in frames_json.iter().enumerate() {
        let fo = fv
            .as_object()
            .ok_or_else(|| p.invalid(Some(i), "frames", "expected an object"))?;
        let raw = p.string(fo, Some(i), "file_path")?;
        let image_path = resolve_image_path(root, raw);
        let matrix = p.matrix(fo, i)?;
        let cam_from_world = cam_from_world_from_opengl(&matrix).map_err(|source| {
            NerfstudioError::BadTransform {
                path: file.to_path_buf(),
                frame: i,
                source,
            }
        })?;
        let camera = p.camera(top, fo, i, root, &image_path)?;
        let depth_path = match fo.get("depth_file_path") {
            None | Some(Value::Null) => None,
            Some(_) => Some(PathBuf::from(p.string(fo, Some(i), "depth_file_path")?)),
        };
        raw_paths.push(raw.to_string());
        frames.push(Frame {
            image_path,
            depth_path,
            camera,
            cam_from_world,
            split: default_split,
        });
    }

    let by_name: HashMap<String, usize> = raw_paths
        .iter()
        .enumerate()
        .map(|(i, r)| (normalize(r), i))
        .collect();
    for (split, key) in [
        (Split::Train, "train_filenames"),
        (Split::Val, "val_filenames"),
        (Split::Test, "test_filenames"),
    ] {
        let Some(list) = top.get(key) else { continue };
        let list = list
            .as_array()
            .ok_or_else(|| p.invalid(None, key, "expected an array of file paths"))?;
        for entry in list {
            let entry = entry
                .as_str()
                .ok_or_else(|| p.invalid(None, key, "expected an array of file paths"))?;
            let &i = by_name.get(&normalize(entry)).ok_or_else(|| {
                NerfstudioError::UnknownSplitEntry {
                    path: file.to_path_buf(),
                    list: key.to_string(),
                    entry: entry.to_string(),
                }
            })?;
            frames[i].split = split;
        }
    }

    let mut metadata = match top.get("matloc") {
        None | Some(Value::Null) => SceneMetadata::default(),
        Some(v) => serde_json::from_value(v.clone())
            .map_err(|e| p.invalid(None, "matloc", &e.to_string()))?,
    };
    match top.get("applied_transform") {
        None | Some(Value::Null) => {}
        Some(v) => metadata.applied_transform = Some(p.applied_transform(v)?),
    }
    // nerfstudio's point cloud: `ply_file_path`, else a `sparse_pc.ply` beside the file.
    let points = match top.get("ply_file_path") {
        None | Some(Value::Null) => {
            let default = root.join("sparse_pc.ply");
            default
                .is_file()
                .then_some(PointSource::Ply { path: default })
        }
        Some(_) => Some(PointSource::Ply {
            path: root.join(p.string(top, None, "ply_file_path")?),
        }),
    };
    Ok(Dataset {
        root: root.to_path_buf(),
        frames,
        points,
        metadata,
    })
}

/// A file path as nerfstudio writes it, for comparing split-list entries with frame paths.
fn normalize(raw: &str) -> String {
    let parts: Vec<String> = Path::new(raw)
        .components()
        .filter(|c| !matches!(c, Component::CurDir))
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    parts.join("/")
}

/// Blender's `file_path` omits the extension (nerfstudio appends `.png`).
fn resolve_image_path(root: &Path, raw: &str) -> PathBuf {
    let p = PathBuf::from(raw);
    if p.extension().is_none() && !root.join(&p).exists() {
        let png = PathBuf::from(format!("{raw}.png"));
        if root.join(&png).exists() {
            return png;
        }
    }
    p
}

/// Parses JSON, accepting Python's `NaN` / `Infinity` literals (which `json.dump` writes) so
/// that a NaN pose is reported as a NaN pose rather than as a syntax error.
fn parse_json_lenient(bytes: &[u8], path: &Path) -> Result<Value, NerfstudioError> {
    match serde_json::from_slice::<Value>(bytes) {
        Ok(v) => Ok(v),
        Err(first) => {
            if let Some(fixed) = quote_non_finite_literals(bytes)
                && let Ok(v) = serde_json::from_slice::<Value>(&fixed)
            {
                return Ok(v);
            }
            Err(NerfstudioError::Json {
                path: path.to_path_buf(),
                line: first.line(),
                column: first.column(),
                message: {
                    // serde_json appends the location, which the variant already carries.
                    let full = first.to_string();
                    let suffix = format!(" at line {} column {}", first.line(), first.column());
                    full.strip_suffix(&suffix).unwrap_or(&full).to_string()
                },
            })
        }
    }
}

/// Rewrites bare `NaN`, `Infinity`, `-Infinity` outside strings as JSON strings; `None` when
/// there are none.
fn quote_non_finite_literals(bytes: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::with_capacity(bytes.len() + 16);
    let (mut in_string, mut escaped, mut changed) = (false, false, false);
    let mut i = 0;
    while i < bytes.len() {
        let b = bytes[i];
        if in_string {
            out.push(b);
            if escaped {
                escaped = false;
            } else if b == b'\\' {
                escaped = true;
            } else if b == b'"' {
                in_string = false;
            }
            i += 1;
            continue;
        }
        if b == b'"' {
            in_string = true;
            out.push(b);
            i += 1;
            continue;
        }
        let mut matched = false;
        for lit in [&b"-Infinity"[..], b"Infinity", b"NaN"] {
            if bytes[i..].starts_with(lit) {
                out.push(b'"');
                out.extend_from_slice(lit);
                out.push(b'"');
                i += lit.len();
                matched = true;
                changed = true;
                break;
            }
        }
        if !matched {
            out.push(b);
            i += 1;
        }
    }
    changed.then_some(out)
}

/// The file being parsed, for building errors.
struct Ctx<'a> {
    path: &'a Path,
}

impl Ctx<'_> {
    fn missing(&self, frame: Option<usize>, field: &str) -> NerfstudioError {
        NerfstudioError::MissingField {
            path: self.path.to_path_buf(),
            at: At(frame),
            field: field.to_string(),
        }
    }

    fn invalid(&self, frame: Option<usize>, field: &str, reason: &str) -> NerfstudioError {
        NerfstudioError::InvalidField {
            path: self.path.to_path_buf(),
            at: At(frame),
            field: field.to_string(),
            reason: reason.to_string(),
        }
    }

    fn string<'v>(
        &self,
        obj: &'v Map<String, Value>,
        frame: Option<usize>,
        key: &str,
    ) -> Result<&'v str, NerfstudioError> {
        obj.get(key)
            .ok_or_else(|| self.missing(frame, key))?
            .as_str()
            .ok_or_else(|| self.invalid(frame, key, "expected a string"))
    }

    /// A number, or one of the strings `NaN`, `Infinity`, `-Infinity` (see
    /// [`quote_non_finite_literals`]).
    fn number(&self, v: &Value, frame: Option<usize>, key: &str) -> Result<f64, NerfstudioError> {
        match v {
            Value::Number(n) => n
                .as_f64()
                .ok_or_else(|| self.invalid(frame, key, "number out of range")),
            Value::String(s) if s == "NaN" => Ok(f64::NAN),
            Value::String(s) if s == "Infinity" => Ok(f64::INFINITY),
            Value::String(s) if s == "-Infinity" => Ok(f64::NEG_INFINITY),
            _ => Err(self.invalid(frame, key, "expected a number")),
        }
    }

    fn matrix(
        &self,
        fo: &Map<String, Value>,
        frame: usize,
    ) -> Result<Matrix4<f64>, NerfstudioError> {
        let key = "transform_matrix";
        let shape_err = || self.invalid(Some(frame), key, "expected 4 (or 3) rows of 4 numbers");
        let rows = fo
            .get(key)
            .ok_or_else(|| self.missing(Some(frame), key))?
            .as_array()
            .ok_or_else(shape_err)?;
        if rows.len() != 4 && rows.len() != 3 {
            return Err(shape_err());
        }
        let mut m = Matrix4::identity();
        for (r, row) in rows.iter().enumerate() {
            let row = row
                .as_array()
                .filter(|a| a.len() == 4)
                .ok_or_else(shape_err)?;
            for (c, v) in row.iter().enumerate() {
                m[(r, c)] = self.number(v, Some(frame), key)?;
            }
        }
        Ok(m)
    }

    /// `applied_transform`: 3 rows of 4 numbers (a 4th row `[0, 0, 0, 1]` is accepted), finite,
    /// with a rotation in the first three columns.
    fn applied_transform(&self, v: &Value) -> Result<[[f64; 4]; 3], NerfstudioError> {
        let key = "applied_transform";
        let shape_err = || self.invalid(None, key, "expected 3 rows of 4 numbers");
        let rows = v.as_array().ok_or_else(shape_err)?;
        if rows.len() != 3 && rows.len() != 4 {
            return Err(shape_err());
        }
        let mut m = [[0.0; 4]; 4];
        for (r, row) in rows.iter().enumerate() {
            let row = row
                .as_array()
                .filter(|a| a.len() == 4)
                .ok_or_else(shape_err)?;
            for (c, x) in row.iter().enumerate() {
                m[r][c] = self.number(x, None, key)?;
            }
        }
        if rows.len() == 4 && m[3] != [0.0, 0.0, 0.0, 1.0] {
            return Err(self.invalid(None, key, "the 4th row must be [0, 0, 0, 1]"));
        }
        let a = [m[0], m[1], m[2]];
        applied_transform_pose(&a).map_err(|e| self.invalid(None, key, &e.to_string()))?;
        Ok(a)
    }

    fn camera(
        &self,
        top: &Map<String, Value>,
        fo: &Map<String, Value>,
        frame: usize,
        root: &Path,
        image_path: &Path,
    ) -> Result<Camera, NerfstudioError> {
        // A frame's own key wins; the error names the frame when the value came from it.
        let get = |key: &str| -> Option<(&Value, Option<usize>)> {
            fo.get(key)
                .map(|v| (v, Some(frame)))
                .or_else(|| top.get(key).map(|v| (v, None)))
                .filter(|(v, _)| !v.is_null())
        };
        let num = |key: &str| -> Result<Option<f64>, NerfstudioError> {
            get(key).map(|(v, at)| self.number(v, at, key)).transpose()
        };
        let size = |key: &str| -> Result<Option<u32>, NerfstudioError> {
            let Some((v, at)) = get(key) else {
                return Ok(None);
            };
            let x = self.number(v, at, key)?;
            if !(x.is_finite() && x >= 1.0 && x.fract() == 0.0 && x <= u32::MAX as f64) {
                return Err(self.invalid(at, key, "expected a positive whole number of pixels"));
            }
            Ok(Some(x as u32))
        };

        let model = match get("camera_model") {
            None => None,
            Some((v, at)) => Some((
                v.as_str()
                    .ok_or_else(|| self.invalid(at, "camera_model", "expected a string"))?
                    .to_ascii_uppercase(),
                at,
            )),
        };
        if let Some((m, at)) = &model
            && !matches!(
                m.as_str(),
                "PINHOLE" | "SIMPLE_PINHOLE" | "OPENCV" | "SIMPLE_RADIAL" | "RADIAL"
            )
        {
            return Err(NerfstudioError::UnsupportedCameraModel {
                path: self.path.to_path_buf(),
                at: At(*at),
                model: m.clone(),
            });
        }

        let (width, height) = match (size("w")?, size("h")?) {
            (Some(w), Some(h)) => (w, h),
            _ => {
                image_size(&root.join(image_path)).map_err(|source| NerfstudioError::ImageSize {
                    path: self.path.to_path_buf(),
                    frame,
                    source,
                })?
            }
        };
        let fx = match num("fl_x")? {
            Some(f) => f,
            None => match get("camera_angle_x") {
                Some((v, at)) => {
                    let angle = self.number(v, at, "camera_angle_x")?;
                    // Blender's horizontal field of view in radians: blame it, not the focal
                    // length derived from it.
                    if !(angle.is_finite() && angle > 0.0 && angle < std::f64::consts::PI) {
                        return Err(self.invalid(
                            at,
                            "camera_angle_x",
                            &format!(
                                "{angle} is not a field of view in radians (expected 0 < angle < π)"
                            ),
                        ));
                    }
                    0.5 * width as f64 / (0.5 * angle).tan()
                }
                None => return Err(self.missing(Some(frame), "fl_x")),
            },
        };
        let fy = num("fl_y")?.unwrap_or(fx);
        let cx = num("cx")?.unwrap_or(0.5 * width as f64);
        let cy = num("cy")?.unwrap_or(0.5 * height as f64);
        let distortion = Distortion {
            k1: num("k1")?.unwrap_or(0.0),
            k2: num("k2")?.unwrap_or(0.0),
            p1: num("p1")?.unwrap_or(0.0),
            p2: num("p2")?.unwrap_or(0.0),
            k3: num("k3")?.unwrap_or(0.0),
        };
        if let Some(k4) = num("k4")?
            && k4 != 0.0
        {
            return Err(self.invalid(
                get("k4").and_then(|(_, at)| at),
                "k4",
                "k4 (fisheye / rational model) is not supported; use OPENCV with k1 k2 p1 p2 k3",
            ));
        }
        Camera::opencv(width, height, fx, fy, cx, cy, distortion).map_err(|source| {
            NerfstudioError::BadCamera {
                path: self.path.to_path_buf(),
                at: At(Some(frame)),
                source,
            }
        })
    }
}

/// The rigid transform `world_from_original` that an `applied_transform` `[R | t]` stands for
/// (`x_world = R x_original + t`); an error when it is not finite or `R` is not a rotation.
pub fn applied_transform_pose(applied: &[[f64; 4]; 3]) -> Result<Pose, PoseError> {
    for (row, r) in applied.iter().enumerate() {
        if !r[3].is_finite() {
            return Err(PoseError::NonFinite {
                row,
                col: 3,
                value: r[3],
            });
        }
    }
    let rotation = rotation_from_matrix(&Matrix3::from_fn(|r, c| applied[r][c]))?;
    let t = Vector3::new(applied[0][3], applied[1][3], applied[2][3]);
    Ok(Pose::from_parts(t.into(), rotation))
}

/// A `cam_from_world` pose of a dataset whose `applied_transform` is `applied`, expressed in
/// the original (COLMAP) world: `cam_from_original = cam_from_world · world_from_original`.
pub fn original_cam_from_world(
    applied: &[[f64; 4]; 3],
    cam_from_world: &Pose,
) -> Result<Pose, PoseError> {
    Ok(cam_from_world * applied_transform_pose(applied)?)
}

/// The inverse of [`original_cam_from_world`]: a pose in the original (COLMAP) world
/// expressed in the dataset's world, `cam_from_world = cam_from_original · world_from_original⁻¹`.
pub fn cam_from_world_from_original(
    applied: &[[f64; 4]; 3],
    cam_from_original: &Pose,
) -> Result<Pose, PoseError> {
    Ok(matloc_core::pose::cam_from_other_world(
        cam_from_original,
        &applied_transform_pose(applied)?.inverse(),
    ))
}

/// Writes `dataset` as nerfstudio `transforms.json`, atomically.
///
/// `path` is the file to write when it ends in `.json`, else a directory (created if needed)
/// that receives `transforms.json`. Frame paths are written as stored when the file lands in
/// [`Dataset::root`], otherwise relative to the written file's directory (with `..` where
/// needed), so the file and the images can move together; absolute only where no relative
/// path exists (another drive). Intrinsics shared by every frame are written once at the top
/// level (as `ns-process-data` does), else per frame. A split list is written when it names a
/// frame: a file of test frames has `test_filenames` and no empty `train_filenames`.
pub fn write_nerfstudio(dataset: &Dataset, path: &Path) -> Result<(), NerfstudioError> {
    let is_file = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("json"));
    let target = if is_file {
        path.to_path_buf()
    } else {
        path.join(TRANSFORMS_JSON)
    };
    let out_dir = target.parent().unwrap_or(Path::new("")).to_path_buf();
    let io_err = |p: &Path, source: io::Error| NerfstudioError::Io {
        path: p.to_path_buf(),
        source,
    };
    if !out_dir.as_os_str().is_empty() {
        std::fs::create_dir_all(&out_dir).map_err(|e| io_err(&out_dir, e))?;
    }
    let value = to_json(dataset, &target, &out_dir)?;
    let bytes = serde_json::to_vec_pretty(&value).map_err(|e| io_err(&target, e.into()))?;
    write_atomic(&target, &bytes).map_err(|e| io_err(&target, e))
}

/// The JSON document [`write_nerfstudio`] writes, with frame paths expressed for `out_dir`.
fn to_json(dataset: &Dataset, target: &Path, out_dir: &Path) -> Result<Value, NerfstudioError> {
    let unwritable = |frame: usize, reason: String| NerfstudioError::Unwritable {
        path: target.to_path_buf(),
        frame,
        reason,
    };
    let shared = dataset
        .frames
        .first()
        .map(|f| f.camera)
        .filter(|c| dataset.frames.iter().all(|f| f.camera == *c));
    let same_dir = same_directory(&dataset.root, out_dir);

    let mut top = Map::new();
    if let Some(cam) = &shared {
        put_camera(&mut top, cam);
    }
    let mut frames = Vec::with_capacity(dataset.frames.len());
    let mut lists: [(Split, &str, Vec<Value>); 3] = [
        (Split::Train, "train_filenames", Vec::new()),
        (Split::Val, "val_filenames", Vec::new()),
        (Split::Test, "test_filenames", Vec::new()),
    ];
    for (i, frame) in dataset.frames.iter().enumerate() {
        frame
            .camera
            .validate()
            .map_err(|e| unwritable(i, format!("invalid intrinsics: {e}")))?;
        let m = opengl_from_cam_from_world(&frame.cam_from_world);
        if m.iter().any(|v| !v.is_finite()) {
            return Err(unwritable(i, "pose is not finite".into()));
        }
        let rows: Vec<Value> = (0..4)
            .map(|r| Value::from((0..4).map(|c| m[(r, c)]).collect::<Vec<f64>>()))
            .collect();
        let file_path = path_for_json(&dataset.root, &frame.image_path, out_dir, same_dir)
            .ok_or_else(|| unwritable(i, "image path is not valid UTF-8".into()))?;
        let mut fo = Map::new();
        fo.insert("file_path".into(), Value::from(file_path.clone()));
        fo.insert("transform_matrix".into(), Value::from(rows));
        if let Some(d) = &frame.depth_path {
            let d = path_for_json(&dataset.root, d, out_dir, same_dir)
                .ok_or_else(|| unwritable(i, "depth path is not valid UTF-8".into()))?;
            fo.insert("depth_file_path".into(), Value::from(d));
        }
        if shared.is_none() {
            put_camera(&mut fo, &frame.camera);
        }
        frames.push(Value::Object(fo));
        if let Some((_, _, list)) = lists.iter_mut().find(|(s, _, _)| *s == frame.split) {
            list.push(Value::from(file_path));
        }
    }
    top.insert("frames".into(), Value::from(frames));
    for (_, key, list) in lists {
        if !list.is_empty() {
            top.insert(key.into(), Value::from(list));
        }
    }
    if let Some(PointSource::Ply { path }) = &dataset.points {
        // Relative to the written file, as the frames.
        let rel = path_for_json(Path::new(""), path, out_dir, false)
            .ok_or_else(|| unwritable(0, "ply_file_path is not valid UTF-8".into()))?;
        top.insert("ply_file_path".into(), Value::from(rel));
    }
    let mut matloc = dataset.metadata.clone();
    if let Some(a) = matloc.applied_transform.take() {
        applied_transform_pose(&a).map_err(|e| unwritable(0, format!("applied_transform: {e}")))?;
        let rows: Vec<Value> = a.iter().map(|r| Value::from(r.to_vec())).collect();
        top.insert("applied_transform".into(), Value::from(rows));
    }
    if matloc != SceneMetadata::default() {
        let meta =
            serde_json::to_value(&matloc).map_err(|e| unwritable(0, format!("metadata: {e}")))?;
        top.insert("matloc".into(), meta);
    }
    Ok(Value::Object(top))
}

fn put_camera(obj: &mut Map<String, Value>, cam: &Camera) {
    let model = if cam.is_pinhole() {
        "PINHOLE"
    } else {
        "OPENCV"
    };
    obj.insert("camera_model".into(), Value::from(model));
    obj.insert("w".into(), Value::from(cam.width));
    obj.insert("h".into(), Value::from(cam.height));
    obj.insert("fl_x".into(), Value::from(cam.fx));
    obj.insert("fl_y".into(), Value::from(cam.fy));
    obj.insert("cx".into(), Value::from(cam.cx));
    obj.insert("cy".into(), Value::from(cam.cy));
    if !cam.is_pinhole() {
        for (k, v) in cam.distortion.named() {
            obj.insert(k.into(), Value::from(v));
        }
    }
}

fn absolute(p: &Path) -> Option<PathBuf> {
    let p = if p.as_os_str().is_empty() {
        Path::new(".")
    } else {
        p
    };
    p.canonicalize()
        .ok()
        .or_else(|| std::path::absolute(p).ok())
}

fn same_directory(a: &Path, b: &Path) -> bool {
    match (absolute(a), absolute(b)) {
        (Some(a), Some(b)) => a == b,
        _ => false,
    }
}

/// A frame path as written in JSON: unchanged when the file lands in the dataset root,
/// otherwise relative to `out_dir` (absolute where no relative path exists). `None` for
/// non-UTF-8 paths.
fn path_for_json(root: &Path, p: &Path, out_dir: &Path, same_dir: bool) -> Option<String> {
    let p = if same_dir && !p.is_absolute() {
        p.to_path_buf()
    } else {
        let full = if p.is_absolute() {
            p.to_path_buf()
        } else {
            absolute(root).map_or_else(|| root.join(p), |r| r.join(p))
        };
        let full = absolute(&full).unwrap_or(full);
        absolute(out_dir)
            .and_then(|base| relative_path(&base, &full))
            .unwrap_or(full)
    };
    p.to_str().map(str::to_owned)
}

/// `target` relative to the directory `base`, both absolute and free of `.`/`..` components;
/// `None` when they share no root (another drive).
fn relative_path(base: &Path, target: &Path) -> Option<PathBuf> {
    let (b, t) = (lexical_components(base)?, lexical_components(target)?);
    if root_of(&b) != root_of(&t) || root_of(&b).is_empty() {
        return None;
    }
    let common = b.iter().zip(&t).take_while(|(x, y)| x == y).count();
    let mut rel = PathBuf::new();
    for _ in common..b.len() {
        rel.push("..");
    }
    for c in &t[common..] {
        rel.push(c.as_os_str());
    }
    Some(rel)
}

/// `p`'s components with `.` dropped and `..` applied; `None` when `..` climbs above the root.
fn lexical_components(p: &Path) -> Option<Vec<Component<'_>>> {
    let mut out: Vec<Component<'_>> = Vec::new();
    for c in p.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                if matches!(out.last(), Some(Component::Normal(_))) {
                    out.pop();
                } else {
                    return None;
                }
            }
            c => out.push(c),
        }
    }
    Some(out)
}

/// The leading prefix and root components of a path.
fn root_of<'a>(components: &[Component<'a>]) -> Vec<Component<'a>> {
    components
        .iter()
        .take_while(|c| matches!(c, Component::Prefix(_) | Component::RootDir))
        .copied()
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    proptest::proptest! {
        #[test]
        fn a_relative_path_leads_from_base_to_target(
            base in proptest::collection::vec("[a-c]{1,2}", 0..5),
            target in proptest::collection::vec("[a-c]{1,2}", 0..5),
        ) {
            let abs = |v: &[String]| v.iter().fold(PathBuf::from("/"), |p, c| p.join(c));
            let (b, t) = (abs(&base), abs(&target));
            let rel = relative_path(&b, &t).unwrap();
            proptest::prop_assert!(rel.is_relative());
            let joined = b.join(&rel);
            proptest::prop_assert_eq!(
                lexical_components(&joined).unwrap(),
                lexical_components(&t).unwrap()
            );
        }
    }

    #[test]
    fn no_relative_path_without_a_shared_root() {
        assert!(relative_path(Path::new("/a"), Path::new("b")).is_none());
        assert!(relative_path(Path::new("/a/../.."), Path::new("/b")).is_none());
        assert_eq!(
            relative_path(Path::new("/x/./y"), Path::new("/x/z/../w")).unwrap(),
            PathBuf::from("../w")
        );
    }

    #[test]
    fn non_finite_literals_are_quoted_outside_strings_only() {
        let src = br#"{"a": [NaN, -Infinity, Infinity], "s": "NaN \" Infinity"}"#;
        let fixed = quote_non_finite_literals(src).unwrap();
        let v: Value = serde_json::from_slice(&fixed).unwrap();
        assert_eq!(v["a"][0], "NaN");
        assert_eq!(v["a"][1], "-Infinity");
        assert_eq!(v["s"], "NaN \" Infinity");
        assert!(quote_non_finite_literals(br#"{"a": 1}"#).is_none());
    }

    #[test]
    fn split_names_are_normalized() {
        assert_eq!(normalize("./images/a.png"), "images/a.png");
        assert_eq!(normalize("images/a.png"), "images/a.png");
    }
}
