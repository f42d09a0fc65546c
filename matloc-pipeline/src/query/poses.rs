//! Pose output of a batch of queries: JSON lines, hloc's results file, a TUM trajectory, a
//! COLMAP text model (or its `images.txt` alone) and nerfstudio `transforms.json`, in the data's
//! world or the original one. Writers take finished [`QueryRecord`]s; they neither read images
//! nor localize.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use matloc_core::pose::{PoseError, cam_from_other_world, colmap_from_cam_from_world};
use matloc_core::{Camera, Pose};
use matloc_data::colmap::{
    ColmapCamera, ColmapError, ColmapFormat, ColmapImage, ColmapModel, write_colmap,
};
use matloc_data::dataset::{Dataset, Frame, SceneMetadata, Split};
use matloc_data::nerfstudio::{NerfstudioError, applied_transform_pose, write_nerfstudio};
use serde_json::Value;

use super::record::{error_record, localization_record};
use crate::methods::QueryResult;

/// Why poses cannot be written.
#[derive(Debug, thiserror::Error)]
pub enum PoseWriteError {
    /// The format cannot go where it was asked to.
    #[error("{0}")]
    Destination(String),
    /// The data's `applied_transform` is not a rigid transform.
    #[error("the data's applied_transform: {0}")]
    AppliedTransform(#[source] PoseError),
    /// A record cannot be serialised.
    #[error("serialising a record: {0}")]
    Json(#[from] serde_json::Error),
    /// A file cannot be written.
    #[error("writing {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The COLMAP model cannot be written.
    #[error("writing the COLMAP model {path}: {source}")]
    Colmap {
        /// The model directory.
        path: PathBuf,
        /// The writer's error.
        source: ColmapError,
    },
    /// The nerfstudio file cannot be written.
    #[error("writing {path}: {source}")]
    Nerfstudio {
        /// The file or directory.
        path: PathBuf,
        /// The writer's error.
        source: Box<NerfstudioError>,
    },
}

/// A pose output format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PoseFormat {
    /// One JSON object per query: pose (`qvec_wxyz`, `tvec`), confidence, times, errors.
    Jsonl,
    /// COLMAP text model directory (cameras, images, empty points3D), or `images.txt` alone
    /// on stdout or to a `.txt` file.
    Colmap,
    /// hloc / visuallocalization.net results: `NAME QW QX QY QZ TX TY TZ` (cam_from_world).
    Hloc,
    /// TUM trajectory for evo: `timestamp tx ty tz qx qy qz qw` (camera-to-world).
    Tum,
    /// nerfstudio `transforms.json` of the localized frames.
    Nerfstudio,
}

impl PoseFormat {
    /// Every format, in the order of [`PoseFormat::name`]'s listing.
    pub const ALL: [PoseFormat; 5] = [
        PoseFormat::Jsonl,
        PoseFormat::Colmap,
        PoseFormat::Hloc,
        PoseFormat::Tum,
        PoseFormat::Nerfstudio,
    ];

    /// Command-line name.
    pub fn name(self) -> &'static str {
        match self {
            PoseFormat::Jsonl => "jsonl",
            PoseFormat::Colmap => "colmap",
            PoseFormat::Hloc => "hloc",
            PoseFormat::Tum => "tum",
            PoseFormat::Nerfstudio => "nerfstudio",
        }
    }

    /// Whether `out` (or stdout, `None`) receives the format line by line; the others are
    /// written as a whole by [`write_poses`].
    pub fn is_line_based(self, out: Option<&Path>) -> bool {
        match self {
            PoseFormat::Jsonl | PoseFormat::Hloc | PoseFormat::Tum => true,
            PoseFormat::Colmap => out.is_none_or(is_txt),
            PoseFormat::Nerfstudio => false,
        }
    }

    /// Checks that the format can go to `out` (stdout when `None`).
    pub fn check_destination(self, out: Option<&Path>) -> Result<(), PoseWriteError> {
        if self == PoseFormat::Nerfstudio && out.is_none() {
            return Err(PoseWriteError::Destination(
                "--format nerfstudio writes a file: give --out FILE.json or --out DIR".into(),
            ));
        }
        Ok(())
    }

    /// File (or directory) name for one method's poses in an `eval` report.
    pub fn report_name(self, method: &str) -> String {
        match self {
            PoseFormat::Jsonl => format!("{method}.jsonl"),
            PoseFormat::Hloc => format!("{method}_hloc.txt"),
            PoseFormat::Tum => format!("{method}.tum"),
            PoseFormat::Colmap | PoseFormat::Nerfstudio => method.to_string(),
        }
    }
}

fn is_txt(p: &Path) -> bool {
    p.extension().is_some_and(|e| e.eq_ignore_ascii_case("txt"))
}

/// Which world written poses are in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum WorldKind {
    /// The world of the data the map was built from (and of `--data`).
    #[default]
    Data,
    /// The original (COLMAP) world before nerfstudio's `applied_transform`.
    Original,
}

impl WorldKind {
    /// Command-line name.
    pub fn name(self) -> &'static str {
        match self {
            WorldKind::Data => "data",
            WorldKind::Original => "original",
        }
    }
}

/// The world the written poses are in, and how to get there from the data's world.
#[derive(Clone, Debug, PartialEq)]
pub struct OutputWorld {
    kind: WorldKind,
    /// `world_from_original` when poses are re-expressed in the original world.
    world_from_original: Option<Pose>,
    /// The data's `applied_transform`, recorded in nerfstudio output in the data world.
    applied_transform: Option<[[f64; 4]; 3]>,
}

impl OutputWorld {
    /// The world `kind` for data whose `applied_transform` is `applied` (`None`: the data's
    /// world is its original world).
    pub fn new(kind: WorldKind, applied: Option<[[f64; 4]; 3]>) -> Result<Self, PoseWriteError> {
        let world_from_original = match (kind, &applied) {
            (WorldKind::Original, Some(a)) => {
                Some(applied_transform_pose(a).map_err(PoseWriteError::AppliedTransform)?)
            }
            _ => None,
        };
        Ok(OutputWorld {
            kind,
            world_from_original,
            applied_transform: applied,
        })
    }

    /// Name written in JSON records: `data` or `original`.
    pub fn name(&self) -> &'static str {
        self.kind.name()
    }

    /// A data-world `cam_from_world` in the output world.
    pub fn pose(&self, cam_from_world: &Pose) -> Pose {
        match &self.world_from_original {
            Some(world_from_original) => cam_from_other_world(cam_from_world, world_from_original),
            None => *cam_from_world,
        }
    }

    /// The `applied_transform` that maps the original world into the output world, if any.
    fn applied_transform(&self) -> Option<[[f64; 4]; 3]> {
        match self.kind {
            WorldKind::Data => self.applied_transform,
            WorldKind::Original => None,
        }
    }
}

/// A query whose method ran (it returned a pose or refused).
#[derive(Clone, Debug)]
pub struct Localized {
    /// Position in the batch (0-based).
    pub index: usize,
    /// The image file.
    pub path: PathBuf,
    /// Intrinsics at the image file's size.
    pub camera: Camera,
    /// The method's result (name, pose in the data's world, statistics).
    pub result: QueryResult,
    /// Ground truth in the data's world, when known.
    pub cam_from_world_gt: Option<Pose>,
}

/// One query of a batch, as the writers take it.
#[derive(Clone, Debug)]
pub enum QueryRecord {
    /// The method ran.
    Done(Box<Localized>),
    /// The query failed: its image, its camera or the method.
    Failed {
        /// Query name.
        name: String,
        /// The error with its causes.
        error: String,
    },
}

impl QueryRecord {
    /// Query name.
    pub fn name(&self) -> &str {
        match self {
            QueryRecord::Done(l) => &l.result.name,
            QueryRecord::Failed { name, .. } => name,
        }
    }

    /// The pose in the data's world, when the query was localized.
    pub fn cam_from_world(&self) -> Option<&Pose> {
        match self {
            QueryRecord::Done(l) => l.result.cam_from_world.as_ref(),
            QueryRecord::Failed { .. } => None,
        }
    }
}

/// Why `record` has no place in `format`'s output (only JSONL keeps refusals and failures).
pub fn omission(format: PoseFormat, record: &QueryRecord) -> Option<String> {
    if format == PoseFormat::Jsonl {
        return None;
    }
    let why = match record {
        QueryRecord::Failed { .. } => "it failed".to_string(),
        QueryRecord::Done(l) if l.result.cam_from_world.is_none() => "not localized".to_string(),
        QueryRecord::Done(l) => match format {
            PoseFormat::Hloc | PoseFormat::Colmap
                if l.result.name.chars().any(char::is_whitespace) =>
            {
                // Both formats separate fields by spaces; COLMAP's and pycolmap's text readers
                // cut a name at its first space, so it would name another file.
                "its name contains whitespace".to_string()
            }
            PoseFormat::Colmap if l.camera.distortion.k3 != 0.0 => {
                "its intrinsics have k3, which COLMAP's OPENCV model lacks".to_string()
            }
            _ => return None,
        },
    };
    Some(why)
}

/// COLMAP names each image once: of the queries given under one name, the first written
/// is kept and the later ones are left out (`later` says why). Other formats keep every one.
#[derive(Default)]
pub struct NamesOnce {
    seen: HashSet<String>,
}

impl NamesOnce {
    /// Why `record` is left out of `format` because its name was written before, if it is
    /// (only records that would be written count, so call it after [`omission`]).
    pub fn later(&mut self, format: PoseFormat, record: &QueryRecord) -> Option<String> {
        match record {
            QueryRecord::Done(l) if format == PoseFormat::Colmap => {
                (!self.seen.insert(l.result.name.clone()))
                    .then(|| "its name was given by an earlier query".to_string())
            }
            _ => None,
        }
    }
}

/// `[w, x, y, z]` (w ≥ 0) and translation of `pose`, COLMAP's order.
fn qvec_tvec(pose: &Pose) -> ([f64; 4], [f64; 3]) {
    colmap_from_cam_from_world(pose)
}

/// The JSON record of one query (schema in `matloc-cli/README.md`; built by
/// [`localization_record`], which `matloc serve` answers with too).
pub fn jsonl_record(record: &QueryRecord, world: &OutputWorld) -> Result<Value, PoseWriteError> {
    match record {
        QueryRecord::Failed { name, error, .. } => Ok(error_record(name, error)),
        QueryRecord::Done(l) => Ok(localization_record(
            &l.result,
            world.name(),
            &|p| world.pose(p),
            l.cam_from_world_gt.as_ref(),
        )?),
    }
}

/// The TUM timestamp of a query: its image's file stem when that is a number (TUM RGB-D names
/// images by time, `1305031102.175304.png`), else its position in the batch.
pub fn tum_timestamp(name: &str, index: usize) -> f64 {
    Path::new(name)
        .file_stem()
        .and_then(|s| s.to_str())
        .and_then(|s| s.parse::<f64>().ok())
        .filter(|t| t.is_finite())
        .unwrap_or(index as f64)
}

/// Text before the first record (`None`: nothing).
pub fn header(format: PoseFormat) -> Option<&'static str> {
    match format {
        PoseFormat::Tum => Some("# timestamp tx ty tz qx qy qz qw (camera-to-world)\n"),
        PoseFormat::Colmap => Some(
            "# Image list with two lines of data per image:\n\
             #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
             #   POINTS2D[] as (X, Y, POINT3D_ID)\n",
        ),
        PoseFormat::Jsonl | PoseFormat::Hloc | PoseFormat::Nerfstudio => None,
    }
}

/// The text of one record in a line-based format (with its newline), `None` when the record
/// is left out (see [`omission`]).
pub fn record_text(
    format: PoseFormat,
    record: &QueryRecord,
    world: &OutputWorld,
) -> Result<Option<String>, PoseWriteError> {
    if format == PoseFormat::Jsonl {
        return Ok(Some(format!(
            "{}\n",
            serde_json::to_string(&jsonl_record(record, world)?)?
        )));
    }
    if omission(format, record).is_some() {
        return Ok(None);
    }
    let (QueryRecord::Done(l), Some(p)) = (record, record.cam_from_world()) else {
        return Ok(None);
    };
    let cam_from_world = world.pose(p);
    let name = &l.result.name;
    Ok(Some(match format {
        PoseFormat::Hloc => {
            let (q, t) = qvec_tvec(&cam_from_world);
            format!(
                "{name} {} {} {} {} {} {} {}\n",
                q[0], q[1], q[2], q[3], t[0], t[1], t[2]
            )
        }
        PoseFormat::Tum => {
            // Camera-to-world: translation = camera centre, rotation = world_from_cam.
            let (q, t) = qvec_tvec(&cam_from_world.inverse());
            format!(
                "{} {} {} {} {} {} {} {}\n",
                tum_timestamp(name, l.index),
                t[0],
                t[1],
                t[2],
                q[1],
                q[2],
                q[3],
                q[0]
            )
        }
        PoseFormat::Colmap => {
            let (q, t) = qvec_tvec(&cam_from_world);
            let id = l.index + 1;
            format!(
                "{id} {} {} {} {} {} {} {} {id} {name}\n\n",
                q[0], q[1], q[2], q[3], t[0], t[1], t[2]
            )
        }
        PoseFormat::Jsonl | PoseFormat::Nerfstudio => return Ok(None),
    }))
}

/// The whole text of a line-based format.
pub fn render_text(
    format: PoseFormat,
    records: &[QueryRecord],
    world: &OutputWorld,
) -> Result<String, PoseWriteError> {
    let mut s = header(format).unwrap_or_default().to_string();
    let mut names = NamesOnce::default();
    for r in records {
        if omission(format, r).is_none() && names.later(format, r).is_some() {
            continue;
        }
        if let Some(line) = record_text(format, r, world)? {
            s.push_str(&line);
        }
    }
    Ok(s)
}

/// The localized queries as a COLMAP model: image and camera ids are the batch position + 1,
/// each query has its own camera (PINHOLE or OPENCV), and there are no points.
pub fn colmap_model(records: &[QueryRecord], world: &OutputWorld) -> ColmapModel {
    let mut model = ColmapModel::default();
    let mut names = NamesOnce::default();
    for r in records {
        if omission(PoseFormat::Colmap, r).is_some() || names.later(PoseFormat::Colmap, r).is_some()
        {
            continue;
        }
        let (QueryRecord::Done(l), Some(p)) = (r, r.cam_from_world()) else {
            continue;
        };
        let id = (l.index + 1) as u32;
        let Some(camera) = ColmapCamera::from_camera(id, &l.camera) else {
            continue;
        };
        model.cameras.insert(id, camera);
        model.images.insert(
            id,
            ColmapImage {
                id,
                name: l.result.name.clone(),
                camera_id: id,
                cam_from_world: world.pose(p),
                points2d: Vec::new(),
            },
        );
    }
    model
}

/// The localized queries as a nerfstudio dataset (test frames) with image paths relative to
/// `root` and the output world's `applied_transform`.
pub fn nerfstudio_dataset(records: &[QueryRecord], world: &OutputWorld, root: &Path) -> Dataset {
    let frames = records
        .iter()
        .filter(|r| omission(PoseFormat::Nerfstudio, r).is_none())
        .filter_map(|r| match (r, r.cam_from_world()) {
            (QueryRecord::Done(l), Some(p)) => Some(Frame {
                image_path: l.path.strip_prefix(root).unwrap_or(&l.path).to_path_buf(),
                depth_path: None,
                camera: l.camera,
                cam_from_world: world.pose(p),
                split: Split::Test,
            }),
            _ => None,
        })
        .collect();
    Dataset {
        root: root.to_path_buf(),
        frames,
        metadata: SceneMetadata {
            applied_transform: world.applied_transform(),
            ..SceneMetadata::default()
        },
        points: None,
    }
}

/// Writes `records` in `format` to `out`: a line-based format as one file, written atomically
/// from memory; COLMAP as a text model directory (unless `out` ends in `.txt`); nerfstudio as
/// `out` (a `.json` file) or `out/transforms.json`. `root` is the directory image paths are
/// relative to.
pub fn write_poses(
    format: PoseFormat,
    records: &[QueryRecord],
    world: &OutputWorld,
    root: &Path,
    out: &Path,
) -> Result<(), PoseWriteError> {
    if format.is_line_based(Some(out)) {
        let text = render_text(format, records, world)?;
        return matloc_core::fsutil::write_atomic(out, text.as_bytes()).map_err(|source| {
            PoseWriteError::Io {
                path: out.to_path_buf(),
                source,
            }
        });
    }
    match format {
        PoseFormat::Colmap => write_colmap(&colmap_model(records, world), out, ColmapFormat::Text)
            .map_err(|source| PoseWriteError::Colmap {
                path: out.to_path_buf(),
                source,
            }),
        _ => write_nerfstudio(&nerfstudio_dataset(records, world, root), out).map_err(|source| {
            PoseWriteError::Nerfstudio {
                path: out.to_path_buf(),
                source: Box::new(source),
            }
        }),
    }
}

/// One line saying what a batch gave: localized, not localized, failed.
pub fn summary(records: &[QueryRecord]) -> String {
    let failed = records
        .iter()
        .filter(|r| matches!(r, QueryRecord::Failed { .. }))
        .count();
    let localized = records
        .iter()
        .filter(|r| r.cam_from_world().is_some())
        .count();
    format!(
        "{} queries: {localized} localized, {} not localized, {failed} failed",
        records.len(),
        records.len() - localized - failed
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::pose::{cam_from_world_from_colmap, camera_center};
    use matloc_data::nerfstudio::{cam_from_world_from_original, read_nerfstudio};
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use serde_json::json;

    fn pose(i: usize) -> Pose {
        let a = 0.3 + i as f64;
        Pose::from_parts(
            Translation3::new(1.5 * a, -2.0 + a, 0.25 * a * a),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.4 * a, -0.7, 0.2 * a.sin())),
        )
    }

    fn result(name: &str, cam_from_world: Option<Pose>) -> QueryResult {
        QueryResult {
            name: name.into(),
            method: "matloc".into(),
            localized: cam_from_world.is_some(),
            cam_from_world,
            camera_center: cam_from_world.map(|p| camera_center(&p).coords.into()),
            confidence: Some(0.9),
            inliers: 42,
            iterations: 2,
            hypotheses: Vec::new(),
            stage_seconds: vec![("place".into(), 0.1)],
            total_seconds: 0.5,
        }
    }

    /// Five queries: 0, 1, 3 localized (1 with a numeric name), 2 refused, 4 failed.
    fn records(root: &Path) -> Vec<QueryRecord> {
        let cam = Camera::pinhole(64, 48, 50.0, 51.0, 32.0, 24.5).unwrap();
        let names = ["a.png", "seq/1305031102.175304.png", "c.png", "d.png"];
        let mut out: Vec<QueryRecord> = names
            .iter()
            .enumerate()
            .map(|(i, n)| {
                let p = (i != 2).then(|| pose(i));
                QueryRecord::Done(Box::new(Localized {
                    index: i,
                    path: root.join(n),
                    camera: cam,
                    result: result(n, p),
                    cam_from_world_gt: (i == 0).then(|| pose(7)),
                }))
            })
            .collect();
        out.push(QueryRecord::Failed {
            name: "e.png".into(),
            error: "reading query image e.png: corrupt".into(),
        });
        out
    }

    fn assert_same(a: &Pose, b: &Pose) {
        assert!(a.rotation.angle_to(&b.rotation) < 1e-9, "{a} vs {b}");
        assert!(
            (a.translation.vector - b.translation.vector).norm() < 1e-9,
            "{a} vs {b}"
        );
    }

    fn applied() -> [[f64; 4]; 3] {
        let r = UnitQuaternion::from_scaled_axis(Vector3::new(0.1, 0.2, -1.2))
            .to_rotation_matrix()
            .into_inner();
        let t = [3.0, -1.0, 0.5];
        std::array::from_fn(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)], t[i]])
    }

    /// The expected output-world poses of the localized records, by name.
    fn expected(records: &[QueryRecord], world: &OutputWorld) -> Vec<(String, Pose)> {
        records
            .iter()
            .filter_map(|r| {
                r.cam_from_world()
                    .map(|p| (r.name().to_string(), world.pose(p)))
            })
            .collect()
    }

    fn worlds() -> [OutputWorld; 2] {
        [
            OutputWorld::new(WorldKind::Data, Some(applied())).unwrap(),
            OutputWorld::new(WorldKind::Original, Some(applied())).unwrap(),
        ]
    }

    #[test]
    fn original_world_undoes_applied_transform() {
        let world = OutputWorld::new(WorldKind::Original, Some(applied())).unwrap();
        let p = pose(3);
        let back = cam_from_world_from_original(&applied(), &world.pose(&p)).unwrap();
        assert_same(&back, &p);
        // Same camera centre mapped by x_data = R x_original + t.
        let a = applied_transform_pose(&applied()).unwrap();
        let c_orig = camera_center(&world.pose(&p));
        assert!((a.transform_point(&c_orig) - camera_center(&p)).norm() < 1e-9);
        let none = OutputWorld::new(WorldKind::Original, None).unwrap();
        assert_same(&none.pose(&p), &p);
    }

    #[test]
    fn jsonl_round_trips_qvec_wxyz_and_tvec() {
        let dir = tempfile::tempdir().unwrap();
        for world in worlds() {
            let recs = records(dir.path());
            let text = render_text(PoseFormat::Jsonl, &recs, &world).unwrap();
            let lines: Vec<Value> = text
                .lines()
                .map(|l| serde_json::from_str(l).unwrap())
                .collect();
            assert_eq!(lines.len(), 5);
            let mut got = Vec::new();
            for v in &lines {
                if v["qvec_wxyz"].is_array() {
                    let q: [f64; 4] = serde_json::from_value(v["qvec_wxyz"].clone()).unwrap();
                    let t: [f64; 3] = serde_json::from_value(v["tvec"].clone()).unwrap();
                    assert!(q[0] >= 0.0);
                    let p = cam_from_world_from_colmap(q, t).unwrap();
                    let c: [f64; 3] = serde_json::from_value(v["camera_center"].clone()).unwrap();
                    assert!((camera_center(&p).coords - Vector3::from(c)).norm() < 1e-9);
                    assert_eq!(v["world"], world.name());
                    got.push((v["name"].as_str().unwrap().to_string(), p));
                }
                assert!(v.get("cam_from_world").is_none());
            }
            let want = expected(&recs, &world);
            assert_eq!(got.len(), want.len());
            for ((gn, gp), (wn, wp)) in got.iter().zip(&want) {
                assert_eq!(gn, wn);
                assert_same(gp, wp);
            }
            assert_eq!(lines[2]["localized"], false);
            assert!(lines[2]["qvec_wxyz"].is_null());
            assert_eq!(
                lines[4],
                json!({"name": "e.png", "error": "reading query image e.png: corrupt"})
            );
            let gq: [f64; 4] = serde_json::from_value(lines[0]["gt_qvec_wxyz"].clone()).unwrap();
            let gt: [f64; 3] = serde_json::from_value(lines[0]["gt_tvec"].clone()).unwrap();
            assert_same(
                &cam_from_world_from_colmap(gq, gt).unwrap(),
                &world.pose(&pose(7)),
            );
            assert!(lines[0]["error_translation_m"].as_f64().unwrap() > 0.0);
        }
    }

    #[test]
    fn hloc_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        for world in worlds() {
            let recs = records(dir.path());
            let text = render_text(PoseFormat::Hloc, &recs, &world).unwrap();
            let got: Vec<(String, Pose)> = text
                .lines()
                .map(|l| {
                    let f: Vec<&str> = l.split_whitespace().collect();
                    assert_eq!(f.len(), 8, "{l}");
                    let v: Vec<f64> = f[1..].iter().map(|x| x.parse().unwrap()).collect();
                    let p =
                        cam_from_world_from_colmap([v[0], v[1], v[2], v[3]], [v[4], v[5], v[6]])
                            .unwrap();
                    (f[0].to_string(), p)
                })
                .collect();
            let want = expected(&recs, &world);
            assert_eq!(got.len(), 3);
            for ((gn, gp), (wn, wp)) in got.iter().zip(&want) {
                assert_eq!(gn, wn);
                assert_same(gp, wp);
            }
        }
    }

    #[test]
    fn tum_round_trips_camera_to_world() {
        let dir = tempfile::tempdir().unwrap();
        for world in worlds() {
            let recs = records(dir.path());
            let text = render_text(PoseFormat::Tum, &recs, &world).unwrap();
            let rows: Vec<Vec<f64>> = text
                .lines()
                .filter(|l| !l.starts_with('#'))
                .map(|l| l.split_whitespace().map(|x| x.parse().unwrap()).collect())
                .collect();
            assert_eq!(rows.len(), 3);
            let want = expected(&recs, &world);
            for (row, (_, wp)) in rows.iter().zip(&want) {
                let world_from_cam = Pose::from_parts(
                    Translation3::new(row[1], row[2], row[3]),
                    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                        row[7], row[4], row[5], row[6],
                    )),
                );
                assert_same(&world_from_cam.inverse(), wp);
                assert!(
                    (Vector3::new(row[1], row[2], row[3]) - camera_center(wp).coords).norm() < 1e-9
                );
            }
            // Timestamps: batch position, or the numeric file stem.
            assert_eq!(rows[0][0], 0.0);
            assert_eq!(rows[1][0], 1305031102.175304);
            assert_eq!(rows[2][0], 3.0);
        }
        assert_eq!(tum_timestamp("x/17.png", 4), 17.0);
        assert_eq!(tum_timestamp("frame_17.png", 4), 4.0);
        assert_eq!(tum_timestamp("inf.png", 4), 4.0);
    }

    #[test]
    fn colmap_round_trips_as_model_directory_and_images_txt() {
        let dir = tempfile::tempdir().unwrap();
        for world in worlds() {
            let recs = records(dir.path());
            let want = expected(&recs, &world);
            let model_dir = dir.path().join(format!("model_{}", world.name()));
            write_poses(PoseFormat::Colmap, &recs, &world, dir.path(), &model_dir).unwrap();
            for f in ["cameras.txt", "images.txt", "points3D.txt"] {
                assert!(model_dir.join(f).is_file(), "{f}");
            }
            let model = matloc_data::colmap::read_colmap(&model_dir).unwrap();
            assert_eq!(model.images.len(), 3);
            assert!(model.points3d.is_empty());
            let ids: Vec<u32> = model.images.keys().copied().collect();
            assert_eq!(ids, [1, 2, 4]);
            for (img, (wn, wp)) in model.images.values().zip(&want) {
                assert_eq!(&img.name, wn);
                assert_same(&img.cam_from_world, wp);
                let cam = model.cameras[&img.camera_id].to_camera().unwrap();
                assert_eq!(
                    cam,
                    Camera::pinhole(64, 48, 50.0, 51.0, 32.0, 24.5).unwrap()
                );
            }

            let listing = dir.path().join(format!("images_{}.txt", world.name()));
            write_poses(PoseFormat::Colmap, &recs, &world, dir.path(), &listing).unwrap();
            let text = std::fs::read(&listing).unwrap();
            let images = matloc_data::colmap::parse_images_text(&text, &listing).unwrap();
            assert_eq!(images.len(), 3);
            for (img, (wn, wp)) in images.values().zip(&want) {
                assert_eq!(&img.name, wn);
                assert_same(&img.cam_from_world, wp);
                assert!(img.points2d.is_empty());
            }
        }
    }

    #[test]
    fn nerfstudio_round_trips_with_intrinsics_and_world() {
        let dir = tempfile::tempdir().unwrap();
        for world in worlds() {
            let recs = records(dir.path());
            let want = expected(&recs, &world);
            let out = dir.path().join(format!("ns_{}", world.name()));
            write_poses(PoseFormat::Nerfstudio, &recs, &world, dir.path(), &out).unwrap();
            let ds = read_nerfstudio(&out).unwrap();
            assert_eq!(ds.frames.len(), 3);
            assert_eq!(ds.metadata.applied_transform, world.applied_transform());
            for (f, (wn, wp)) in ds.frames.iter().zip(&want) {
                // Relative to the file, one directory below the images.
                assert_eq!(f.image_path, Path::new("..").join(wn));
                assert_eq!(ds.root, out);
                assert_same(&f.cam_from_world, wp);
                assert_eq!(
                    f.camera,
                    Camera::pinhole(64, 48, 50.0, 51.0, 32.0, 24.5).unwrap()
                );
                assert_eq!(f.split, Split::Test);
            }
        }
    }

    #[test]
    fn omissions_name_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let recs = records(dir.path());
        assert_eq!(
            omission(PoseFormat::Hloc, &recs[2]).unwrap(),
            "not localized"
        );
        assert_eq!(omission(PoseFormat::Tum, &recs[4]).unwrap(), "it failed");
        assert!(omission(PoseFormat::Jsonl, &recs[4]).is_none());
        assert!(omission(PoseFormat::Hloc, &recs[0]).is_none());
        // A name with a space is left out of COLMAP's text model too, not cut by its readers.
        let mut spaced = records(dir.path());
        if let QueryRecord::Done(l) = &mut spaced[0] {
            l.result.name = "edge/my query.png".into();
        }
        assert_eq!(
            omission(PoseFormat::Colmap, &spaced[0]).unwrap(),
            "its name contains whitespace"
        );
        let world = OutputWorld::new(WorldKind::Data, None).unwrap();
        let model = colmap_model(&spaced, &world);
        assert!(model.images.values().all(|i| !i.name.contains(' ')));
        assert_eq!(model.images.len(), 2);
        // A name given twice: COLMAP gets the first query only, hloc both.
        let mut twice = records(dir.path());
        if let QueryRecord::Done(l) = &mut twice[3] {
            l.result.name = "a.png".into();
        }
        let model = colmap_model(&twice, &world);
        assert_eq!(model.images.len(), 2);
        assert_eq!(model.images[&1].name, "a.png");
        let text = render_text(PoseFormat::Colmap, &twice, &world).unwrap();
        assert_eq!(text.lines().filter(|l| l.ends_with(" a.png")).count(), 1);
        let text = render_text(PoseFormat::Hloc, &twice, &world).unwrap();
        assert_eq!(text.lines().filter(|l| l.starts_with("a.png ")).count(), 2);
        assert_eq!(
            summary(&recs),
            "5 queries: 3 localized, 1 not localized, 1 failed"
        );
        assert!(PoseFormat::Nerfstudio.check_destination(None).is_err());
        assert!(PoseFormat::Colmap.is_line_based(None));
        assert!(PoseFormat::Colmap.is_line_based(Some(Path::new("x/images.txt"))));
        assert!(!PoseFormat::Colmap.is_line_based(Some(Path::new("x/model"))));
    }
}
