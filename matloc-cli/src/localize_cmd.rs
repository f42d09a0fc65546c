//! `matloc localize`: localize query images against a map and write their poses.
//!
//! A query that fails (unreadable image, unsupported camera, size mismatch, localization
//! error) becomes an error record and the batch goes on; the command fails only when every
//! query failed or the output cannot be written.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use matloc_core::Camera;
use matloc_data::Dataset;
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::{Method, QueryResult, localize_with};

use crate::method_options::MethodOptionsArgs;
use crate::pose_formats::{
    Localized, NamesOnce, OutputWorld, PoseFormat, QueryRecord, WorldArg, header, omission,
    record_text, summary, write_poses,
};
use crate::queries::{
    Query, QuerySpec, load_query, parse_query_list, read_intrinsics, specs_from_paths,
};
use crate::split_args::{self, SplitArgs};

/// Arguments of `matloc localize`.
#[derive(Args)]
pub struct LocalizeArgs {
    /// Map directory (from `matloc map build`).
    #[arg(long)]
    map: PathBuf,
    /// Query images (PNG/JPEG); with --queries, the one directory the list's names are
    /// relative to.
    #[arg(long, num_args = 1.., required = true)]
    images: Vec<PathBuf>,
    /// Query list with intrinsics, as hloc's `queries_with_intrinsics.txt`: one line per query,
    /// `NAME MODEL WIDTH HEIGHT PARAMS...` (COLMAP SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL,
    /// RADIAL or OPENCV; any other model fails that query).
    #[arg(long, value_name = "LIST", conflicts_with = "intrinsics")]
    queries: Option<PathBuf>,
    /// Intrinsics of the queries: a JSON file with nerfstudio keys (`w`, `h`, `fl_x`, `fl_y`,
    /// `cx`, `cy`, optional `camera_model`, `k1 k2 p1 p2 k3`) or a matloc camera (`width`,
    /// `height`, `fx`, ...).
    #[arg(long, conflicts_with = "data")]
    intrinsics: Option<PathBuf>,
    /// Dataset the queries belong to: gives each image its intrinsics (with --queries the list
    /// does), ground truth for the errors when it has poses, and its world for --world.
    #[arg(long)]
    data: Option<PathBuf>,
    /// Method: `structure` (the default: keypoints against the map's triangulated points),
    /// `matloc` (the paper's NeRF-feature pipeline) or a baseline.
    #[arg(long, default_value_t = Method::DEFAULT)]
    method: Method,
    /// Output format.
    #[arg(long, value_enum, default_value = "jsonl")]
    format: PoseFormat,
    /// Write the output here (atomically, once every query is done) instead of stdout; a
    /// directory for --format colmap (unless it ends in .txt) and for nerfstudio (unless it
    /// ends in .json).
    #[arg(long)]
    out: Option<PathBuf>,
    /// World of the written poses: `data` (the dataset's and map's) or `original` (undoes
    /// the --data dataset's nerfstudio `applied_transform`: the COLMAP world).
    #[arg(long, value_enum, default_value = "data")]
    world: WorldArg,
    /// Test split of the --data dataset when it has none; by default the map's.
    #[command(flatten)]
    split: SplitArgs,
    /// The methods' settings.
    #[command(flatten)]
    method_options: MethodOptionsArgs,
}

/// Localizes every query in order: a query whose camera, image or localization fails becomes
/// [`QueryRecord::Failed`] and the batch goes on. `target` is the map's camera (queries are
/// brought to its resolution); `emit` sees each record as it is made.
pub fn localize_batch(
    specs: &[QuerySpec],
    target: Option<&Camera>,
    mut localize: impl FnMut(&Query) -> Result<QueryResult>,
    mut emit: impl FnMut(&QueryRecord) -> Result<()>,
) -> Result<Vec<QueryRecord>> {
    let mut records = Vec::with_capacity(specs.len());
    for (index, spec) in specs.iter().enumerate() {
        let record = match load_query(spec, target).and_then(|q| {
            let result = localize(&q).with_context(|| format!("localizing {}", q.name))?;
            Ok((q, result))
        }) {
            Ok((q, result)) => QueryRecord::Done(Box::new(Localized {
                index,
                path: q.path,
                camera: q.file_camera,
                result,
                cam_from_world_gt: q.cam_from_world,
            })),
            Err(e) => {
                let error = format!("{e:#}");
                tracing::warn!(query = %spec.name, "{error}");
                QueryRecord::Failed {
                    name: spec.name.clone(),
                    error,
                }
            }
        };
        emit(&record)?;
        records.push(record);
    }
    Ok(records)
}

/// The batch's outcome: an error when there were queries and every one failed.
pub fn batch_status(records: &[QueryRecord]) -> Result<()> {
    if records.is_empty() {
        bail!("no queries to localize");
    }
    if records
        .iter()
        .all(|r| matches!(r, QueryRecord::Failed { .. }))
    {
        bail!("every query failed ({})", records.len());
    }
    Ok(())
}

/// The --data dataset, split as the map was.
fn read_data(args: &LocalizeArgs, map: &LoadedMap) -> Result<Option<Dataset>> {
    let Some(d) = &args.data else {
        if args.split.spec()?.is_some() {
            bail!("--test-every / --test-list need --data");
        }
        return Ok(None);
    };
    let mut ds =
        matloc_data::read_dataset(d).with_context(|| format!("reading dataset {}", d.display()))?;
    let split = args.split.for_map(map.dir.manifest().split.as_ref())?;
    split_args::apply(split.as_ref(), &mut ds)
        .with_context(|| format!("splitting dataset {}", d.display()))?;
    Ok(Some(ds))
}

/// With --queries: the one directory --images names.
fn list_image_dir(args: &LocalizeArgs) -> Result<&PathBuf> {
    let [images] = args.images.as_slice() else {
        bail!("with --queries, --images takes one directory (the list's names are relative to it)");
    };
    if !images.is_dir() {
        bail!(
            "--images {}: not a directory (with --queries, --images is the directory the list's names are relative to)",
            images.display()
        );
    }
    Ok(images)
}

/// Argument checks that need no map, so mistakes show before the map loads.
fn check_args(args: &LocalizeArgs) -> Result<()> {
    args.format.check_destination(args.out.as_deref())?;
    if args.world == WorldArg::Original && args.data.is_none() {
        bail!("--world original needs --data (the dataset whose applied_transform to undo)");
    }
    if args.queries.is_some() {
        list_image_dir(args)?;
    }
    Ok(())
}

/// The queries the arguments name, and the directory their paths are relative to.
fn query_specs(
    args: &LocalizeArgs,
    dataset: Option<&Dataset>,
    map_camera: Option<Camera>,
) -> Result<(Vec<QuerySpec>, PathBuf)> {
    if let Some(list) = &args.queries {
        let images = list_image_dir(args)?;
        let text = std::fs::read_to_string(list)
            .with_context(|| format!("reading query list {}", list.display()))?;
        return Ok((
            parse_query_list(&text, list, images, dataset),
            images.clone(),
        ));
    }
    let fixed = match &args.intrinsics {
        Some(p) => Some(read_intrinsics(p)?),
        None => None,
    };
    Ok((
        specs_from_paths(&args.images, dataset, fixed, map_camera),
        PathBuf::new(),
    ))
}

/// Runs `matloc localize`.
pub fn run(args: &LocalizeArgs) -> Result<()> {
    check_args(args)?;
    let map = LoadedMap::open(&args.map)
        .with_context(|| format!("opening map {}", args.map.display()))?;
    let dataset = read_data(args, &map)?;
    let applied = dataset.as_ref().and_then(|d| d.metadata.applied_transform);
    if args.world == WorldArg::Original && applied.is_none() {
        tracing::info!("the dataset has no applied_transform: its world is the original world");
    }
    let world = OutputWorld::new(args.world, applied)?;
    let target = map.camera();
    let (specs, root) = query_specs(args, dataset.as_ref(), target)?;
    if specs.is_empty() {
        bail!("no queries to localize");
    }

    let stream = args.out.is_none();
    let mut names = NamesOnce::default();
    if stream && let Some(h) = header(args.format) {
        out!("{h}")?;
    }
    let options = args.method_options.load()?;
    let records = localize_batch(
        &specs,
        target.as_ref(),
        |q| {
            Ok(localize_with(
                &map,
                args.method,
                &q.name,
                &q.image,
                &q.camera,
                &options,
            )?)
        },
        |record| {
            // A failure has been logged already.
            let left_out = match record {
                QueryRecord::Done(_) => {
                    omission(args.format, record).or_else(|| names.later(args.format, record))
                }
                QueryRecord::Failed { .. } => None,
            };
            if let Some(why) = &left_out {
                tracing::warn!(
                    query = record.name(),
                    "left out of the {} output: {why}",
                    args.format.name()
                );
            }
            if stream
                && left_out.is_none()
                && let Some(text) = record_text(args.format, record, &world)?
            {
                out!("{text}")?;
            }
            Ok(())
        },
    )?;
    if let Some(out) = &args.out {
        write_poses(args.format, &records, &world, &root, out)?;
    }
    tracing::info!("{}", summary(&records));
    batch_status(&records)
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use matloc_core::Pose;
    use matloc_core::pose::camera_center;
    use matloc_pipeline::PipelineError;

    fn write_png(path: &Path, w: u32, h: u32) {
        image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 4) as u8, (y * 4) as u8, 90]))
            .save(path)
            .unwrap();
    }

    fn result(q: &Query) -> QueryResult {
        let p = Pose::translation(q.image.shape().0 as f64, 0.0, 1.0);
        QueryResult {
            name: q.name.clone(),
            method: Method::Matloc,
            localized: true,
            cam_from_world: Some(p),
            camera_center: Some(camera_center(&p).coords.into()),
            confidence: Some(1.0),
            inliers: 10,
            iterations: 1,
            hypotheses: Vec::new(),
            stage_seconds: Vec::new(),
            total_seconds: 0.0,
        }
    }

    #[test]
    fn failing_queries_become_error_records_and_the_rest_localize() {
        let dir = tempfile::tempdir().unwrap();
        let images = dir.path();
        write_png(&images.join("good.png"), 32, 24);
        write_png(&images.join("small.png"), 16, 12);
        write_png(&images.join("wide.png"), 40, 24);
        write_png(&images.join("boom.png"), 32, 24);
        std::fs::write(images.join("corrupt.png"), b"\x89PNG\r\n\x1a\nnot really").unwrap();
        let list = "good.png PINHOLE 32 24 30 30 16 12\n\
                    missing.png PINHOLE 32 24 30 30 16 12\n\
                    corrupt.png PINHOLE 32 24 30 30 16 12\n\
                    fisheye.png OPENCV_FISHEYE 32 24 30 30 16 12 0.1 0.01 0 0\n\
                    small.png SIMPLE_RADIAL 32 24 30 16 12 0.01\n\
                    wide.png PINHOLE 32 24 30 30 16 12\n\
                    boom.png PINHOLE 32 24 30 30 16 12\n";
        let specs = parse_query_list(list, Path::new("q.txt"), images, None);
        let target = Camera::pinhole(32, 24, 30.0, 30.0, 16.0, 12.0).unwrap();
        let mut emitted = Vec::new();
        let records = localize_batch(
            &specs,
            Some(&target),
            |q| {
                if q.name == "boom.png" {
                    return Err(PipelineError::NoPlaceHypothesis.into());
                }
                assert_eq!((q.camera.width, q.camera.height), (32, 24));
                Ok(result(q))
            },
            |r| {
                emitted.push(r.name().to_string());
                Ok(())
            },
        )
        .unwrap();
        assert_eq!(
            emitted,
            [
                "good.png",
                "missing.png",
                "corrupt.png",
                "fisheye.png",
                "small.png",
                "wide.png",
                "boom.png"
            ]
        );
        let error = |i: usize| match &records[i] {
            QueryRecord::Failed { error, .. } => error.clone(),
            QueryRecord::Done(_) => panic!("{} should have failed", records[i].name()),
        };
        assert!(error(1).contains("missing.png"), "{}", error(1));
        assert!(error(2).contains("corrupt.png"), "{}", error(2));
        assert!(error(3).contains("OPENCV_FISHEYE"), "{}", error(3));
        assert!(
            error(5).contains("40×24") && error(5).contains("32×24"),
            "{}",
            error(5)
        );
        assert!(error(6).contains("localizing boom.png"), "{}", error(6));
        for i in [0, 4] {
            let QueryRecord::Done(l) = &records[i] else {
                panic!("{i} failed: {records:?}")
            };
            assert_eq!(l.index, i);
            assert_eq!(images.join(&l.result.name), l.path);
        }
        // The 16×12 image keeps its own-size intrinsics for the output.
        let QueryRecord::Done(small) = &records[4] else {
            unreachable!()
        };
        assert_eq!((small.camera.width, small.camera.fx), (16, 15.0));
        assert!(batch_status(&records).is_ok());

        let text = crate::pose_formats::render_text(
            PoseFormat::Jsonl,
            &records,
            &OutputWorld::new(WorldArg::Data, None).unwrap(),
        )
        .unwrap();
        let lines: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        assert_eq!(lines.len(), 7);
        assert!(
            lines[3]["error"]
                .as_str()
                .unwrap()
                .contains("OPENCV_FISHEYE")
        );
        assert_eq!(lines[0]["localized"], true);
    }

    #[test]
    fn the_batch_fails_only_when_every_query_failed() {
        let failed = |i| QueryRecord::Failed {
            name: format!("q{i}"),
            error: "x".into(),
        };
        let e = batch_status(&[failed(0), failed(1)]).unwrap_err();
        assert!(e.to_string().contains("every query failed (2)"), "{e}");
        assert!(batch_status(&[]).is_err());
    }
}
