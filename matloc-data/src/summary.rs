//! Format detection, dataset summaries and validation (what `matloc dataset info` prints).

use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::path::{Path, PathBuf};

use nalgebra::{Point3, Vector3};
use serde::Serialize;

use crate::colmap::{find_model_dir, read_colmap_dataset};
use crate::dataset::{Dataset, SceneMetadata, Split};
use crate::error::DataError;
use crate::images::{ImageLoadError, check_depth, check_image, depth_size, image_size};
use crate::meganerf::{COORDINATES_FILE, is_mega_nerf_dir, read_mega_nerf};
use crate::nerfstudio::{BLENDER_SPLIT_FILES, TRANSFORMS_JSON, read_nerfstudio};

/// The on-disk formats [`read_dataset`] recognises.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DatasetFormat {
    /// nerfstudio `transforms.json` (or the Blender split files).
    Nerfstudio,
    /// A COLMAP sparse model.
    Colmap,
    /// The Mega-NeRF / Mill-19 layout (`coordinates.pt`, `{train,val}/metadata`).
    #[serde(rename = "mega-nerf")]
    MegaNerf,
}

/// Decides which format `path` holds without parsing it.
pub fn detect_format(path: &Path) -> Result<DatasetFormat, DataError> {
    if !path.exists() {
        return Err(DataError::NotFound {
            path: path.to_path_buf(),
        });
    }
    if path.is_file() {
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if name.ends_with(".json") {
            return Ok(DatasetFormat::Nerfstudio);
        }
        if name == COORDINATES_FILE && path.parent().is_some_and(is_mega_nerf_dir) {
            return Ok(DatasetFormat::MegaNerf);
        }
        if find_model_dir(path).is_some() {
            return Ok(DatasetFormat::Colmap);
        }
    } else {
        let nerfstudio = path.join(TRANSFORMS_JSON).is_file()
            || BLENDER_SPLIT_FILES
                .iter()
                .any(|(_, n)| path.join(n).is_file());
        if nerfstudio {
            return Ok(DatasetFormat::Nerfstudio);
        }
        if is_mega_nerf_dir(path) {
            return Ok(DatasetFormat::MegaNerf);
        }
        if find_model_dir(path).is_some() {
            return Ok(DatasetFormat::Colmap);
        }
    }
    Err(DataError::UnknownFormat {
        path: path.to_path_buf(),
    })
}

/// Reads a dataset in whichever supported format `path` holds: a nerfstudio directory or
/// transforms file, a Mega-NeRF dataset directory, or a COLMAP model directory / dataset root
/// (images in the `images/` folder beside `sparse/`).
pub fn read_dataset(path: &Path) -> Result<Dataset, DataError> {
    match detect_format(path)? {
        DatasetFormat::Nerfstudio => Ok(read_nerfstudio(path)?),
        DatasetFormat::Colmap => Ok(read_colmap_dataset(path)?),
        DatasetFormat::MegaNerf => Ok(read_mega_nerf(path)?),
    }
}

/// Number of frames per split.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct SplitCounts {
    /// Training frames.
    pub train: usize,
    /// Validation frames.
    pub val: usize,
    /// Test frames.
    pub test: usize,
}

/// How many frames have one image size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct ResolutionCount {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Frames with this size.
    pub count: usize,
}

/// One distinct set of intrinsics and how many frames use it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct CameraSummary {
    /// Frames with these intrinsics.
    pub count: usize,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// True when any distortion coefficient is non-zero.
    pub distorted: bool,
    /// Horizontal field of view, degrees.
    pub hfov_deg: f64,
}

/// Bounds of the camera centres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct CenterBounds {
    /// Minimum per axis, metres.
    pub min: [f64; 3],
    /// Maximum per axis, metres.
    pub max: [f64; 3],
    /// `max − min` per axis, metres.
    pub extent_m: [f64; 3],
    /// Length of the bounding-box diagonal, metres.
    pub diagonal_m: f64,
}

/// Camera heights along the up axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AltitudeRange {
    /// The unit up axis used.
    pub up: [f64; 3],
    /// True when `up` came from the dataset metadata (else world +z was assumed).
    pub from_metadata: bool,
    /// Lowest camera, metres along `up`.
    pub min_m: f64,
    /// Highest camera, metres along `up`.
    pub max_m: f64,
}

/// How spread out the viewing directions are.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ViewingSpread {
    /// Unit mean viewing direction (world frame).
    pub mean_direction: [f64; 3],
    /// Mean angle between a frame's viewing direction and the mean direction, degrees.
    pub mean_angle_deg: f64,
    /// Largest such angle, degrees.
    pub max_angle_deg: f64,
}

/// Everything `matloc dataset info` reports about a dataset.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DatasetSummary {
    /// Directory frame paths resolve against.
    pub root: PathBuf,
    /// Number of frames.
    pub num_frames: usize,
    /// Frames per split.
    pub splits: SplitCounts,
    /// Frames with a depth map.
    pub with_depth: usize,
    /// Image sizes stated by the intrinsics, most common first.
    pub resolutions: Vec<ResolutionCount>,
    /// Distinct intrinsics, most common first.
    pub cameras: Vec<CameraSummary>,
    /// Bounds of the camera centres (none for an empty dataset).
    pub centers: Option<CenterBounds>,
    /// Median distance from each camera centre to its nearest neighbour, metres.
    pub median_nn_spacing_m: Option<f64>,
    /// Camera heights along the up axis.
    pub altitude: Option<AltitudeRange>,
    /// Spread of viewing directions.
    pub viewing: Option<ViewingSpread>,
    /// Scene metadata carried by the dataset (bounds, up, generator, preset, seed).
    pub metadata: SceneMetadata,
}

/// Computes the summary of a dataset (poses and intrinsics only; no file is read).
pub fn summarize(dataset: &Dataset) -> DatasetSummary {
    let frames = &dataset.frames;
    let mut splits = SplitCounts::default();
    for f in frames {
        match f.split {
            Split::Train => splits.train += 1,
            Split::Val => splits.val += 1,
            Split::Test => splits.test += 1,
        }
    }

    let mut sizes: BTreeMap<(u32, u32), usize> = BTreeMap::new();
    let mut cameras: Vec<CameraSummary> = Vec::new();
    for f in frames {
        *sizes.entry((f.camera.width, f.camera.height)).or_default() += 1;
        let c = &f.camera;
        match cameras.iter_mut().find(|s| {
            (s.width, s.height, s.fx, s.fy, s.cx, s.cy)
                == (c.width, c.height, c.fx, c.fy, c.cx, c.cy)
                && s.distorted != c.is_pinhole()
        }) {
            Some(s) => s.count += 1,
            None => cameras.push(CameraSummary {
                count: 1,
                width: c.width,
                height: c.height,
                fx: c.fx,
                fy: c.fy,
                cx: c.cx,
                cy: c.cy,
                distorted: !c.is_pinhole(),
                hfov_deg: c.hfov_deg(),
            }),
        }
    }
    let mut resolutions: Vec<ResolutionCount> = sizes
        .into_iter()
        .map(|((width, height), count)| ResolutionCount {
            width,
            height,
            count,
        })
        .collect();
    resolutions.sort_by_key(|r| std::cmp::Reverse(r.count));
    cameras.sort_by_key(|c| std::cmp::Reverse(c.count));

    let centers: Vec<Point3<f64>> = frames.iter().map(|f| f.center()).collect();
    let center_bounds = (!centers.is_empty()).then(|| {
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        for c in &centers {
            for k in 0..3 {
                min[k] = min[k].min(c[k]);
                max[k] = max[k].max(c[k]);
            }
        }
        let extent_m = [max[0] - min[0], max[1] - min[1], max[2] - min[2]];
        CenterBounds {
            min,
            max,
            extent_m,
            diagonal_m: Vector3::from(extent_m).norm(),
        }
    });

    let (up, from_metadata) = match dataset.metadata.up.map(Vector3::from) {
        Some(u) if u.norm() > 1e-12 && u.iter().all(|v| v.is_finite()) => (u.normalize(), true),
        _ => (Vector3::z(), false),
    };
    let altitude = (!centers.is_empty()).then(|| {
        let heights = centers.iter().map(|c| c.coords.dot(&up));
        let (min_m, max_m) = heights.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), h| {
            (lo.min(h), hi.max(h))
        });
        AltitudeRange {
            up: [up.x, up.y, up.z],
            from_metadata,
            min_m,
            max_m,
        }
    });

    DatasetSummary {
        root: dataset.root.clone(),
        num_frames: frames.len(),
        splits,
        with_depth: frames.iter().filter(|f| f.depth_path.is_some()).count(),
        resolutions,
        cameras,
        centers: center_bounds,
        median_nn_spacing_m: median_nearest_neighbour(&centers),
        altitude,
        viewing: viewing_spread(frames.iter().map(|f| f.viewing_direction())),
        metadata: dataset.metadata.clone(),
    }
}

/// Median nearest-neighbour distance; O(n²), which is fine for the thousands of frames a
/// dataset holds and needs no spatial index.
fn median_nearest_neighbour(centers: &[Point3<f64>]) -> Option<f64> {
    if centers.len() < 2 {
        return None;
    }
    let mut nn: Vec<f64> = centers
        .iter()
        .enumerate()
        .map(|(i, a)| {
            centers
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, b)| (a - b).norm_squared())
                .fold(f64::INFINITY, f64::min)
                .sqrt()
        })
        .collect();
    nn.sort_by(f64::total_cmp);
    let n = nn.len();
    Some(if n % 2 == 1 {
        nn[n / 2]
    } else {
        0.5 * (nn[n / 2 - 1] + nn[n / 2])
    })
}

fn viewing_spread(dirs: impl Iterator<Item = Vector3<f64>>) -> Option<ViewingSpread> {
    let dirs: Vec<Vector3<f64>> = dirs.collect();
    let sum: Vector3<f64> = dirs.iter().sum();
    // Directions that cancel out (e.g. cameras looking inwards from all sides) have no mean.
    let mean = sum.try_normalize(1e-9 * dirs.len().max(1) as f64)?;
    let angles: Vec<f64> = dirs
        .iter()
        .map(|d| d.dot(&mean).clamp(-1.0, 1.0).acos().to_degrees())
        .collect();
    Some(ViewingSpread {
        mean_direction: [mean.x, mean.y, mean.z],
        mean_angle_deg: angles.iter().sum::<f64>() / angles.len() as f64,
        max_angle_deg: angles.iter().copied().fold(0.0, f64::max),
    })
}

fn fmt3(v: &[f64; 3]) -> String {
    // `+ 0.0` turns -0.0 into 0.0 so a rounded zero never prints as "-0.000".
    let [x, y, z] = v.map(|c| c + 0.0);
    format!("({x:.3}, {y:.3}, {z:.3})")
}

impl fmt::Display for DatasetSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "root: {}", self.root.display())?;
        writeln!(
            f,
            "frames: {} (train {}, val {}, test {}), with depth: {}",
            self.num_frames, self.splits.train, self.splits.val, self.splits.test, self.with_depth
        )?;
        let res: Vec<String> = self
            .resolutions
            .iter()
            .map(|r| format!("{}x{} ×{}", r.width, r.height, r.count))
            .collect();
        writeln!(f, "resolutions: {}", res.join(", "))?;
        writeln!(f, "intrinsics ({} distinct):", self.cameras.len())?;
        for c in self.cameras.iter().take(8) {
            writeln!(
                f,
                "  ×{} {}x{} fx {:.2} fy {:.2} cx {:.2} cy {:.2} hfov {:.1}° distortion {}",
                c.count,
                c.width,
                c.height,
                c.fx,
                c.fy,
                c.cx,
                c.cy,
                c.hfov_deg,
                if c.distorted { "yes" } else { "no" }
            )?;
        }
        if self.cameras.len() > 8 {
            writeln!(f, "  ... {} more", self.cameras.len() - 8)?;
        }
        if let Some(c) = &self.centers {
            writeln!(
                f,
                "camera centres: min {} max {} extent {} m (diagonal {:.2} m)",
                fmt3(&c.min),
                fmt3(&c.max),
                fmt3(&c.extent_m),
                c.diagonal_m
            )?;
        }
        if let Some(s) = self.median_nn_spacing_m {
            writeln!(f, "median nearest-neighbour camera spacing: {s:.3} m")?;
        }
        if let Some(a) = &self.altitude {
            writeln!(
                f,
                "altitude along {} ({}): {:.2} .. {:.2} m",
                fmt3(&a.up),
                if a.from_metadata {
                    "metadata up"
                } else {
                    "assumed +z"
                },
                a.min_m,
                a.max_m
            )?;
        }
        if let Some(v) = &self.viewing {
            writeln!(
                f,
                "viewing direction: mean {} spread mean {:.1}° max {:.1}°",
                fmt3(&v.mean_direction),
                v.mean_angle_deg,
                v.max_angle_deg
            )?;
        }
        let m = &self.metadata;
        if let (Some(lo), Some(hi)) = (&m.bounds_min, &m.bounds_max) {
            writeln!(f, "scene bounds: {} .. {}", fmt3(lo), fmt3(hi))?;
        }
        if m.generator.is_some() || m.preset.is_some() || m.seed.is_some() {
            writeln!(
                f,
                "generator: {} preset: {} seed: {}",
                m.generator.as_deref().unwrap_or("-"),
                m.preset.as_deref().unwrap_or("-"),
                m.seed.map_or("-".to_string(), |s| s.to_string())
            )?;
        }
        Ok(())
    }
}

/// A problem found by [`validate`].
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Problem {
    /// The dataset has no frames.
    NoFrames,
    /// A frame's intrinsics are physically impossible (see [`plausibility`]).
    ImplausibleCamera {
        /// Frame index.
        frame: usize,
        /// The field (`fx`, `cx`, `width`, `distortion`, ...).
        field: &'static str,
        /// The bound it breaks and the value.
        reason: String,
    },
    /// A frame's pose is not usable (non-finite, or farther than the stated scene scale).
    ImplausiblePose {
        /// Frame index.
        frame: usize,
        /// What is wrong.
        reason: String,
    },
    /// A frame's image file does not exist.
    MissingImage {
        /// Frame index.
        frame: usize,
        /// Resolved path.
        path: PathBuf,
    },
    /// An image file exists but its header cannot be read.
    UnreadableImage {
        /// Frame index.
        frame: usize,
        /// Resolved path.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The image size differs from the intrinsics' size with a different aspect ratio.
    ImageSizeMismatch {
        /// Frame index.
        frame: usize,
        /// Resolved path.
        path: PathBuf,
        /// Size the intrinsics are for.
        intrinsics: (u32, u32),
        /// Size of the file.
        image: (u32, u32),
    },
    /// A frame's depth file does not exist.
    MissingDepth {
        /// Frame index.
        frame: usize,
        /// Resolved path.
        path: PathBuf,
    },
    /// A depth file exists but its header cannot be read.
    UnreadableDepth {
        /// Frame index.
        frame: usize,
        /// Resolved path.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The dataset's point cloud (COLMAP `points3D`, PLY) cannot be read.
    UnreadablePoints {
        /// Why, with the file.
        reason: String,
    },
    /// The depth map's aspect ratio differs from the intrinsics'.
    DepthSizeMismatch {
        /// Frame index.
        frame: usize,
        /// Resolved path.
        path: PathBuf,
        /// Size the intrinsics are for.
        intrinsics: (u32, u32),
        /// Size of the depth map.
        depth: (u32, u32),
    },
    /// Two frames use the same image file.
    DuplicateImage {
        /// Frame index.
        frame: usize,
        /// The earlier frame with the same file.
        first: usize,
        /// Resolved path.
        path: PathBuf,
    },
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Problem::NoFrames => write!(f, "the dataset has no frames"),
            Problem::ImplausibleCamera {
                frame,
                field,
                reason,
            } => write!(f, "frame {frame}: intrinsics `{field}`: {reason}"),
            Problem::ImplausiblePose { frame, reason } => {
                write!(f, "frame {frame}: pose: {reason}")
            }
            Problem::MissingImage { frame, path } => {
                write!(f, "frame {frame}: image not found: {}", path.display())
            }
            Problem::UnreadableImage {
                frame,
                path,
                reason,
            } => write!(
                f,
                "frame {frame}: cannot read image {}: {reason}",
                path.display()
            ),
            Problem::ImageSizeMismatch {
                frame,
                path,
                intrinsics,
                image,
            } => write!(
                f,
                "frame {frame}: image {} is {}x{} but intrinsics are for {}x{} (aspect differs)",
                path.display(),
                image.0,
                image.1,
                intrinsics.0,
                intrinsics.1
            ),
            Problem::MissingDepth { frame, path } => {
                write!(f, "frame {frame}: depth not found: {}", path.display())
            }
            Problem::UnreadableDepth {
                frame,
                path,
                reason,
            } => write!(
                f,
                "frame {frame}: cannot read depth {}: {reason}",
                path.display()
            ),
            Problem::UnreadablePoints { reason } => {
                write!(f, "cannot read the point cloud: {reason}")
            }
            Problem::DepthSizeMismatch {
                frame,
                path,
                intrinsics,
                depth,
            } => write!(
                f,
                "frame {frame}: depth {} is {}x{} but intrinsics are for {}x{} (aspect differs)",
                path.display(),
                depth.0,
                depth.1,
                intrinsics.0,
                intrinsics.1
            ),
            Problem::DuplicateImage { frame, first, path } => write!(
                f,
                "frame {frame}: uses the same image as frame {first}: {}",
                path.display()
            ),
        }
    }
}

pub use matloc_core::camera::{FOV_RANGE_DEG, MAX_IMAGE_SIDE};

/// Farthest camera centre from the world origin accepted, metres (ECEF coordinates fit).
pub const MAX_SCENE_M: f64 = 1.0e7;

/// Physically impossible intrinsics and poses, without touching the files: the camera bounds
/// of [`matloc_core::Camera::plausibility`] (image sides in `1..=`[`MAX_IMAGE_SIDE`], a field
/// of view inside [`FOV_RANGE_DEG`], the principal point within a quarter of the image outside
/// its borders, lens distortion invertible at the image's corners and edge midpoints and
/// changing the ray radius there by at most 4×, `|p1|, |p2| ≤ 0.1`); finite rigid poses with
/// the camera within [`MAX_SCENE_M`] of the origin. Empty = plausible.
pub fn plausibility(dataset: &Dataset) -> Vec<Problem> {
    let mut problems = Vec::new();
    for (i, f) in dataset.frames.iter().enumerate() {
        for p in f.camera.plausibility() {
            problems.push(Problem::ImplausibleCamera {
                frame: i,
                field: p.field(),
                reason: p.reason(),
            });
        }
        let centre = f.center();
        let finite = f
            .cam_from_world
            .translation
            .vector
            .iter()
            .all(|v| v.is_finite())
            && f.cam_from_world
                .rotation
                .coords
                .iter()
                .all(|v| v.is_finite());
        if !finite {
            problems.push(Problem::ImplausiblePose {
                frame: i,
                reason: "not finite".into(),
            });
        } else if centre.coords.norm() > MAX_SCENE_M {
            problems.push(Problem::ImplausiblePose {
                frame: i,
                reason: format!(
                    "camera centre {:.3e} m from the origin, beyond {MAX_SCENE_M:.0e} m",
                    centre.coords.norm()
                ),
            });
        }
    }
    problems
}

/// Which file of a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FrameFile {
    /// The frame's image.
    Image,
    /// The frame's depth map.
    Depth,
}

/// A frame's image or depth map that does not decode in full.
#[derive(Debug)]
pub struct DecodeFailure {
    /// Frame index.
    pub frame: usize,
    /// Which of its files.
    pub file: FrameFile,
    /// Resolved path.
    pub path: PathBuf,
    /// What is wrong: [`ImageLoadError::Truncated`], a codec error (bad compressed data, an
    /// impossible header), [`ImageLoadError::Limit`] (decoding would exceed the memory
    /// budget), [`ImageLoadError::NotDepthPng`] / [`ImageLoadError::Npy`] (a depth map that is
    /// not 16-bit grey PNG or float `.npy`), [`ImageLoadError::NotFound`].
    pub error: ImageLoadError,
}

impl DecodeFailure {
    /// The failure as a dataset [`Problem`].
    pub fn problem(&self) -> Problem {
        let (frame, path, reason) = (self.frame, self.path.clone(), self.error.to_string());
        match self.file {
            FrameFile::Image => Problem::UnreadableImage {
                frame,
                path,
                reason,
            },
            FrameFile::Depth => Problem::UnreadableDepth {
                frame,
                path,
                reason,
            },
        }
    }
}

/// Files [`decode_failures`] decodes: every frame's image and each depth map.
pub fn decoded_file_count(dataset: &Dataset) -> usize {
    dataset.frames.len()
        + dataset
            .frames
            .iter()
            .filter(|f| f.depth_path.is_some())
            .count()
}

/// Decodes every frame's image ([`check_image`]) and depth map ([`check_depth`]) in full, in
/// parallel, each after the memory check of the size its header claims; `decoded` is called
/// once per file. Returns the files that fail, in frame order (image before depth). What both
/// `matloc dataset info` and the map build's plan step run.
pub fn decode_failures(dataset: &Dataset, decoded: &(dyn Fn() + Sync)) -> Vec<DecodeFailure> {
    use rayon::prelude::*;
    dataset
        .frames
        .par_iter()
        .enumerate()
        .flat_map_iter(|(i, frame)| {
            let mut out = Vec::new();
            let path = dataset.image_path(frame);
            if let Err(error) = check_image(&path) {
                out.push(DecodeFailure {
                    frame: i,
                    file: FrameFile::Image,
                    path,
                    error,
                });
            }
            decoded();
            if let Some(path) = dataset.depth_path(frame) {
                if let Err(error) = check_depth(&path) {
                    out.push(DecodeFailure {
                        frame: i,
                        file: FrameFile::Depth,
                        path,
                        error,
                    });
                }
                decoded();
            }
            out
        })
        .collect()
}

/// [`validate`], then every image and depth map decoded in full ([`decode_failures`]; a file
/// [`validate`] already reported is not reported again), then the point cloud read: a
/// truncated PNG / JPEG, bad compressed data, a header claiming more pixels than the memory
/// budget holds or a depth file of the wrong bit depth or dtype is found here. `decoded` is
/// called once per decoded file (a progress bar).
pub fn validate_deep(dataset: &Dataset, decoded: &(dyn Fn() + Sync)) -> Vec<Problem> {
    let mut problems = validate(dataset);
    let reported: std::collections::HashSet<PathBuf> = problems
        .iter()
        .filter_map(|p| match p {
            Problem::MissingImage { path, .. }
            | Problem::UnreadableImage { path, .. }
            | Problem::MissingDepth { path, .. }
            | Problem::UnreadableDepth { path, .. } => Some(path.clone()),
            _ => None,
        })
        .collect();
    problems.extend(
        decode_failures(dataset, decoded)
            .iter()
            .filter(|f| !reported.contains(&f.path))
            .map(DecodeFailure::problem),
    );
    // The point cloud a map build may take its surface from.
    if let Err(e) = crate::points::read_points(dataset) {
        problems.push(Problem::UnreadablePoints {
            reason: e.to_string(),
        });
    }
    problems
}

/// Checks that every referenced image and depth file exists and that its size matches the
/// intrinsics or differs only by a rescale (reading file headers only), and that intrinsics
/// and poses are plausible ([`plausibility`]). Empty = valid.
pub fn validate(dataset: &Dataset) -> Vec<Problem> {
    let mut problems = Vec::new();
    if dataset.frames.is_empty() {
        problems.push(Problem::NoFrames);
    }
    problems.extend(plausibility(dataset));
    let mut seen: HashMap<PathBuf, usize> = HashMap::new();
    for (i, frame) in dataset.frames.iter().enumerate() {
        let cam = &frame.camera;
        let intrinsics = (cam.width, cam.height);
        let fits = |(w, h): (u32, u32)| (w, h) == intrinsics || cam.rescaled(w, h).is_ok();
        let path = dataset.image_path(frame);
        if let Some(&first) = seen.get(&path) {
            problems.push(Problem::DuplicateImage {
                frame: i,
                first,
                path: path.clone(),
            });
        } else {
            seen.insert(path.clone(), i);
        }
        if !path.is_file() {
            problems.push(Problem::MissingImage { frame: i, path });
        } else {
            match image_size(&path) {
                Err(e) => problems.push(Problem::UnreadableImage {
                    frame: i,
                    path,
                    reason: e.to_string(),
                }),
                Ok(size) if !fits(size) => problems.push(Problem::ImageSizeMismatch {
                    frame: i,
                    path,
                    intrinsics,
                    image: size,
                }),
                Ok(_) => {}
            }
        }
        if let Some(path) = dataset.depth_path(frame) {
            if !path.is_file() {
                problems.push(Problem::MissingDepth { frame: i, path });
            } else {
                match depth_size(&path) {
                    Err(e) => problems.push(Problem::UnreadableDepth {
                        frame: i,
                        path,
                        reason: e.to_string(),
                    }),
                    Ok(size) if !fits(size) => problems.push(Problem::DepthSizeMismatch {
                        frame: i,
                        path,
                        intrinsics,
                        depth: size,
                    }),
                    Ok(_) => {}
                }
            }
        }
    }
    problems
}

/// Opens `path` (any supported format) and returns its summary and validation problems, with
/// every file decoded ([`validate_deep`], as `matloc dataset info` does by default).
pub fn inspect(path: &Path) -> Result<(DatasetSummary, Vec<Problem>), DataError> {
    let dataset = read_dataset(path)?;
    Ok((summarize(&dataset), validate_deep(&dataset, &|| {})))
}
