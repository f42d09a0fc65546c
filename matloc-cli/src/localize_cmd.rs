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
use matloc_data::query::{QuerySpec, read_intrinsics, read_query_list, specs_from_paths};
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::Method;
use matloc_pipeline::query::poses::{NamesOnce, header, omission, record_text, summary};
use matloc_pipeline::query::{
    OutputWorld, PoseFormat, QueryRecord, WorldKind, batch_status, localize_batch, write_poses,
};

use crate::method_options::MethodOptionsArgs;
use crate::pose_args::{FormatArg, WorldArg};
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
    format: FormatArg,
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
    PoseFormat::from(args.format).check_destination(args.out.as_deref())?;
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
        return Ok((read_query_list(list, images, dataset)?, images.clone()));
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
    let world = OutputWorld::new(WorldKind::from(args.world), applied)?;
    let format = PoseFormat::from(args.format);
    let target = map.camera();
    let (specs, root) = query_specs(args, dataset.as_ref(), target)?;
    if specs.is_empty() {
        bail!("no queries to localize");
    }

    let stream = args.out.is_none();
    let mut names = NamesOnce::default();
    if stream && let Some(h) = header(format) {
        out!("{h}")?;
    }
    let options = args.method_options.load()?;
    let records = localize_batch(
        &map,
        &args.method,
        &options,
        &specs,
        |record| -> Result<()> {
            // A failure has been logged already.
            let left_out = match record {
                QueryRecord::Done(_) => {
                    omission(format, record).or_else(|| names.later(format, record))
                }
                QueryRecord::Failed { .. } => None,
            };
            if let Some(why) = &left_out {
                tracing::warn!(
                    query = record.name(),
                    "left out of the {} output: {why}",
                    format.name()
                );
            }
            if stream
                && left_out.is_none()
                && let Some(text) = record_text(format, record, &world)?
            {
                out!("{text}")?;
            }
            Ok(())
        },
    )?;
    if let Some(out) = &args.out {
        write_poses(format, &records, &world, &root, out)?;
    }
    tracing::info!("{}", summary(&records));
    Ok(batch_status(&records)?)
}
