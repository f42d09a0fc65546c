//! Query input: hloc's query list with intrinsics (`NAME MODEL WIDTH HEIGHT PARAMS...`), image
//! paths with intrinsics from a JSON file, a dataset or the map, and loading one query at the
//! map's resolution. A problem with one query is kept with that query, so a batch goes on.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use matloc_core::{Camera, Image, Pose};

use super::camera::{CameraSpecError, colmap_camera, colmap_model, parse_camera_json};
use super::image::{QueryError, fit_to_image, to_map_resolution};
use crate::dataset::Frame;
use crate::images::ImageLoadError;
use crate::{Dataset, Split};

/// Why a query cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum QueryInputError {
    /// The query has no usable intrinsics (the message names the list line or the reason).
    #[error("{0}")]
    Camera(String),
    /// Its image file cannot be read.
    #[error("reading query image {path}: {source}")]
    Read {
        /// The image file.
        path: PathBuf,
        /// The loader's error.
        source: ImageLoadError,
    },
    /// The image does not fit its intrinsics or the map's images.
    #[error(transparent)]
    Image(#[from] QueryError),
    /// A file (intrinsics, query list) cannot be read.
    #[error("reading {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// An intrinsics file holds no usable camera.
    #[error("{path}: invalid intrinsics: {source}")]
    Intrinsics {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        source: CameraSpecError,
    },
}

/// One query ready to localize.
pub struct Query {
    /// Name (the image path as given).
    pub name: String,
    /// The image file.
    pub path: PathBuf,
    /// RGB image at the map's resolution.
    pub image: Image<f32>,
    /// Its camera at the map's resolution.
    pub camera: Camera,
    /// Its camera at the image file's size (what pose files record).
    pub file_camera: Camera,
    /// Ground truth, when known.
    pub cam_from_world: Option<Pose>,
}

/// A query before its image is read: what a list line or a command-line path says.
#[derive(Clone, Debug, PartialEq)]
pub struct QuerySpec {
    /// Name written in the output.
    pub name: String,
    /// The image file.
    pub path: PathBuf,
    /// Intrinsics for the image size they state, or why there are none.
    pub camera: Result<Camera, String>,
    /// Ground truth, when a dataset gives it.
    pub cam_from_world_gt: Option<Pose>,
}

/// Reads and parses an hloc query list file (see [`parse_query_list`]).
pub fn read_query_list(
    list: &Path,
    images: &Path,
    dataset: Option<&Dataset>,
) -> Result<Vec<QuerySpec>, QueryInputError> {
    let text = std::fs::read_to_string(list).map_err(|source| QueryInputError::Io {
        path: list.to_path_buf(),
        source,
    })?;
    Ok(parse_query_list(&text, list, images, dataset))
}

/// Parses an hloc query list (`queries_with_intrinsics.txt`): one query per line,
/// `NAME MODEL WIDTH HEIGHT PARAMS...` with COLMAP's model names and parameter orders; blank
/// lines and `#` comments are skipped. NAME is relative to `images`. A line that cannot be used
/// (unsupported model, wrong parameter count) keeps its error in [`QuerySpec::camera`].
/// `dataset`, when given, supplies ground truth for the names that are its frames.
pub fn parse_query_list(
    text: &str,
    list: &Path,
    images: &Path,
    dataset: Option<&Dataset>,
) -> Vec<QuerySpec> {
    let index = dataset.map(FrameIndex::new);
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .map(|(i, line)| {
            let name = line
                .split_whitespace()
                .next()
                .unwrap_or_default()
                .to_string();
            let path = images.join(&name);
            let camera = parse_list_camera(line)
                .map_err(|e| format!("{} line {}: {e}", list.display(), i + 1));
            let cam_from_world_gt = index
                .as_ref()
                .and_then(|ix| ix.frame_of(&path))
                .map(|f| f.cam_from_world);
            QuerySpec {
                name,
                path,
                camera,
                cam_from_world_gt,
            }
        })
        .collect()
}

/// The camera of one query-list line.
fn parse_list_camera(line: &str) -> Result<Camera, String> {
    let fields: Vec<&str> = line.split_whitespace().collect();
    if fields.len() < 4 {
        return Err(format!(
            "expected `NAME MODEL WIDTH HEIGHT PARAMS...`, got {} field(s)",
            fields.len()
        ));
    }
    // The model first: an unsupported one is named whatever its parameters.
    colmap_model(fields[1]).map_err(|e| e.to_string())?;
    let size = |field: &str, what: &str| -> Result<u32, String> {
        field
            .parse::<u32>()
            .ok()
            .filter(|&v| v > 0)
            .ok_or_else(|| format!("{what} `{field}` is not a positive whole number"))
    };
    let width = size(fields[2], "WIDTH")?;
    let height = size(fields[3], "HEIGHT")?;
    let params = fields[4..]
        .iter()
        .map(|p| {
            p.parse::<f64>()
                .map_err(|_| format!("parameter `{p}` is not a number"))
        })
        .collect::<Result<Vec<f64>, String>>()?;
    colmap_camera(fields[1], width, height, &params).map_err(|e| e.to_string())
}

/// Query specs for image paths named on the command line. The camera comes from the image's
/// frame in `dataset` (an image that is not one of its frames is that query's error), else
/// from `fixed`, else from the map's `map_camera`.
pub fn specs_from_paths(
    paths: &[PathBuf],
    dataset: Option<&Dataset>,
    fixed: Option<Camera>,
    map_camera: Option<Camera>,
) -> Vec<QuerySpec> {
    let index = dataset.map(FrameIndex::new);
    paths
        .iter()
        .map(|path| {
            let name = path.display().to_string();
            let (camera, gt) = if let Some(ix) = &index {
                match ix.frame_of(path) {
                    Some(f) => {
                        if f.split == Split::Train {
                            tracing::warn!(query = %name, "the query is a training frame of the dataset");
                        }
                        (Ok(f.camera), Some(f.cam_from_world))
                    }
                    None => (
                        Err(format!(
                            "{name} is not an image of dataset {}",
                            ix.dataset.root.display()
                        )),
                        None,
                    ),
                }
            } else if let Some(c) = fixed.or(map_camera) {
                (Ok(c), None)
            } else {
                (
                    Err(format!(
                        "{name}: no intrinsics (pass --intrinsics FILE, --queries LIST or --data DIR)"
                    )),
                    None,
                )
            };
            QuerySpec {
                name,
                path: path.clone(),
                camera,
                cam_from_world_gt: gt,
            }
        })
        .collect()
}

/// A dataset's frames by image file, to find the frame of a query path.
struct FrameIndex<'a> {
    dataset: &'a Dataset,
    by_file: HashMap<PathBuf, usize>,
}

impl<'a> FrameIndex<'a> {
    fn new(dataset: &'a Dataset) -> Self {
        let by_file = dataset
            .frames
            .iter()
            .enumerate()
            .filter_map(|(i, f)| Some((std::fs::canonicalize(dataset.image_path(f)).ok()?, i)))
            .collect();
        FrameIndex { dataset, by_file }
    }

    /// The frame whose image is `path` (the same file, or a frame path ending in it).
    fn frame_of(&self, path: &Path) -> Option<&'a Frame> {
        let ds = self.dataset;
        if let Some(&i) = std::fs::canonicalize(path)
            .ok()
            .and_then(|p| self.by_file.get(&p))
        {
            return Some(&ds.frames[i]);
        }
        ds.frames.iter().find(|f| ds.image_path(f).ends_with(path))
    }
}

/// Reads the query's image and brings it to the map's resolution (`target`).
pub fn load_query(spec: &QuerySpec, target: Option<&Camera>) -> Result<Query, QueryInputError> {
    let camera = spec.camera.clone().map_err(QueryInputError::Camera)?;
    load_at(
        &spec.name,
        &spec.path,
        camera,
        spec.cam_from_world_gt,
        target,
    )
}

/// Reads an image with its intrinsics and ground truth, brought to `target`'s size.
fn load_at(
    name: &str,
    path: &Path,
    camera: Camera,
    cam_from_world: Option<Pose>,
    target: Option<&Camera>,
) -> Result<Query, QueryInputError> {
    let image = crate::images::load_rgb(path).map_err(|source| QueryInputError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let (w, h, _) = image.shape();
    let file_camera = fit_to_image(camera, w as u32, h as u32, name)?;
    let (image, camera) = to_map_resolution(image, file_camera, target, name)?;
    Ok(Query {
        name: name.to_string(),
        path: path.to_path_buf(),
        image,
        camera,
        file_camera,
        cam_from_world,
    })
}

/// Reads an intrinsics file (nerfstudio keys with optional `camera_model`, a COLMAP `model` +
/// `params` object, or a matloc camera).
pub fn read_intrinsics(path: &Path) -> Result<Camera, QueryInputError> {
    let text = std::fs::read_to_string(path).map_err(|source| QueryInputError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_camera_json(&text).map_err(|source| QueryInputError::Intrinsics {
        path: path.to_path_buf(),
        source,
    })
}

/// The first `limit` test frames of a dataset (all when 0) as queries at `target`'s size,
/// with their ground truth; the first that cannot be read is the error.
pub fn dataset_queries(
    dataset: &Dataset,
    target: Option<&Camera>,
    limit: usize,
) -> Result<Vec<Query>, QueryInputError> {
    dataset
        .split(Split::Test)
        .take(if limit == 0 { usize::MAX } else { limit })
        .map(|f| {
            let name = f.image_path.display().to_string();
            load_at(
                &name,
                &dataset.image_path(f),
                f.camera,
                Some(f.cam_from_world),
                target,
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera_of(line: &str) -> Result<Camera, String> {
        let specs = parse_query_list(line, Path::new("q.txt"), Path::new("imgs"), None);
        assert_eq!(specs.len(), 1);
        specs[0].camera.clone()
    }

    #[test]
    fn hloc_lines_read_in_colmap_parameter_order() {
        let text = "# hloc queries\n\
                    a.jpg SIMPLE_PINHOLE 640 480 500 320 240\n\
                    \n\
                    sub/b.jpg PINHOLE 640 480 500 510 321 241\n\
                    c.jpg SIMPLE_RADIAL 640 480 500 320 240 0.1\n\
                    d.jpg RADIAL 640 480 500 320 240 0.1 -0.02\n\
                    e.jpg OPENCV 640 480 500 510 320 240 0.1 -0.02 0.001 0.002\n";
        let specs = parse_query_list(text, Path::new("q.txt"), Path::new("/imgs"), None);
        let names: Vec<&str> = specs.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["a.jpg", "sub/b.jpg", "c.jpg", "d.jpg", "e.jpg"]);
        assert_eq!(specs[1].path, Path::new("/imgs/sub/b.jpg"));
        let cams: Vec<Camera> = specs.iter().map(|s| s.camera.clone().unwrap()).collect();
        assert_eq!(
            (cams[0].fx, cams[0].fy, cams[0].cx, cams[0].cy),
            (500.0, 500.0, 320.0, 240.0)
        );
        assert_eq!(
            (cams[1].fx, cams[1].fy, cams[1].cx, cams[1].cy),
            (500.0, 510.0, 321.0, 241.0)
        );
        assert_eq!(cams[2].distortion.k1, 0.1);
        assert_eq!((cams[3].distortion.k1, cams[3].distortion.k2), (0.1, -0.02));
        let d = cams[4].distortion;
        assert_eq!(
            (d.k1, d.k2, d.p1, d.p2, d.k3),
            (0.1, -0.02, 0.001, 0.002, 0.0)
        );
        assert_eq!((cams[4].width, cams[4].height), (640, 480));
    }

    #[test]
    fn other_colmap_models_are_rejected_by_name() {
        for (model, n) in [
            ("OPENCV_FISHEYE", 8),
            ("FULL_OPENCV", 12),
            ("THIN_PRISM_FISHEYE", 12),
            ("FOV", 5),
        ] {
            let params = vec!["0.1"; n].join(" ");
            let e = camera_of(&format!("x.jpg {model} 640 480 {params}")).unwrap_err();
            assert!(e.contains(model) && e.contains("not supported"), "{e}");
            assert!(e.contains("q.txt line 1"), "{e}");
        }
        let e = camera_of("x.jpg NOPE 640 480 1 2 3").unwrap_err();
        assert!(e.contains("NOPE is not a COLMAP model"), "{e}");
    }

    #[test]
    fn bad_lines_keep_their_name_and_say_why() {
        let e = camera_of("x.jpg PINHOLE 640 480 500 500 320").unwrap_err();
        assert!(e.contains("PINHOLE takes 4 parameters, got 3"), "{e}");
        let e = camera_of("x.jpg PINHOLE 640").unwrap_err();
        assert!(e.contains("expected `NAME MODEL WIDTH HEIGHT"), "{e}");
        let e = camera_of("x.jpg PINHOLE 0 480 1 1 1 1").unwrap_err();
        assert!(e.contains("WIDTH"), "{e}");
        let e = camera_of("x.jpg PINHOLE 640 480 -5 500 320 240").unwrap_err();
        assert!(e.contains("focal"), "{e}");
        let e = camera_of("x.jpg PINHOLE 640 480 a 500 320 240").unwrap_err();
        assert!(e.contains("`a`"), "{e}");
        let specs = parse_query_list("x.jpg PINHOLE 640", Path::new("q"), Path::new("i"), None);
        assert_eq!(specs[0].name, "x.jpg");
    }

    #[test]
    fn intrinsics_json_honours_camera_model() {
        let base = r#""w": 640, "h": 480, "fl_x": 500, "fl_y": 500, "cx": 320, "cy": 240"#;
        let c = parse_camera_json(&format!(
            r#"{{{base}, "camera_model": "OPENCV", "k1": 0.1}}"#
        ))
        .unwrap();
        assert_eq!(c.distortion.k1, 0.1);
        let e = parse_camera_json(&format!(
            r#"{{{base}, "camera_model": "OPENCV_FISHEYE", "k1": 0.1, "k4": 0.01}}"#
        ))
        .unwrap_err();
        assert!(format!("{e:#}").contains("OPENCV_FISHEYE"), "{e:#}");
        let e = parse_camera_json(&format!(r#"{{{base}, "k4": 0.01}}"#)).unwrap_err();
        assert!(format!("{e:#}").contains("k4"), "{e:#}");
        let c = parse_camera_json(
            r#"{"width": 64, "height": 48, "fx": 50, "fy": 50, "cx": 32, "cy": 24}"#,
        )
        .unwrap();
        assert_eq!(c.width, 64);
    }

    #[test]
    fn a_dataset_gives_ground_truth_to_its_frames() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("images")).unwrap();
        std::fs::write(dir.path().join("images/a.png"), b"").unwrap();
        let cam = Camera::pinhole(64, 48, 50.0, 50.0, 32.0, 24.0).unwrap();
        let gt = Pose::translation(1.0, 2.0, 3.0);
        let ds = Dataset {
            root: dir.path().to_path_buf(),
            frames: vec![Frame {
                image_path: "images/a.png".into(),
                depth_path: None,
                camera: cam,
                cam_from_world: gt,
                split: Split::Test,
            }],
            metadata: Default::default(),
            points: None,
        };
        let list =
            "images/a.png PINHOLE 32 24 25 25 16 12\nimages/b.png PINHOLE 32 24 25 25 16 12\n";
        let specs = parse_query_list(list, Path::new("q"), dir.path(), Some(&ds));
        assert_eq!(specs[0].cam_from_world_gt, Some(gt));
        assert_eq!(specs[0].camera.as_ref().unwrap().width, 32);
        assert_eq!(specs[1].cam_from_world_gt, None);
        assert!(specs[1].camera.is_ok());

        let paths = [dir.path().join("images/a.png"), PathBuf::from("b.png")];
        let specs = specs_from_paths(&paths, Some(&ds), None, None);
        assert_eq!(
            (specs[0].camera.clone(), specs[0].cam_from_world_gt),
            (Ok(cam), Some(gt))
        );
        assert!(
            specs[1]
                .camera
                .as_ref()
                .unwrap_err()
                .contains("not an image of dataset")
        );
    }

    #[test]
    fn paths_without_intrinsics_fail_per_query() {
        let specs = specs_from_paths(&[PathBuf::from("a.png")], None, None, None);
        assert!(
            specs[0]
                .camera
                .as_ref()
                .unwrap_err()
                .contains("no intrinsics")
        );
        let cam = Camera::pinhole(64, 48, 50.0, 50.0, 32.0, 24.0).unwrap();
        let specs = specs_from_paths(&[PathBuf::from("a.png")], None, None, Some(cam));
        assert_eq!(specs[0].camera, Ok(cam));
    }
}
