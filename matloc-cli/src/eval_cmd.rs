//! `matloc eval`: localize a dataset's test queries with each method on one map and write a
//! report (markdown in the paper's Table 1/2 layouts, JSON, and PNG plots).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use matloc_core::Pose;
use matloc_data::query::{Query, dataset_queries};
use matloc_pipeline::LoadedMap;
use matloc_pipeline::config::CalibrationQueries;
use matloc_pipeline::eval::tables::RELIABILITY_BINS;
use matloc_pipeline::methods::{Method, MethodOptions, localize_with};
use matloc_pipeline::query::poses::jsonl_record;
use matloc_pipeline::query::{
    Localized, OutputWorld, PoseFormat, QueryRecord, WorldKind, write_poses,
};
use matloc_pipeline::{
    MethodSummary, QueryOutcome, RecallThreshold, accuracy_table, reliability_table,
    summarize_with, timing_table,
};

use crate::method_options::MethodOptionsArgs;
use crate::plot;
use crate::pose_args::{FormatArg, WorldArg};
use crate::progress;
use crate::split_args::{self, SplitArgs};

/// Arguments of `matloc eval`.
#[derive(Args, Clone)]
pub struct EvalArgs {
    /// Map directory.
    #[arg(long)]
    pub map: PathBuf,
    /// Dataset whose test split are the queries.
    #[arg(long)]
    pub data: PathBuf,
    /// Methods, comma-separated (structure, matloc, rgb-keypoints, curriculum-inerf, inerf).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "structure,matloc,rgb-keypoints,curriculum-inerf,inerf"
    )]
    pub methods: Vec<Method>,
    /// Use at most this many test queries (0 = all).
    #[arg(long, default_value_t = 0)]
    pub queries: usize,
    /// Use at most this many queries for the iNeRF baselines (0 = as many as the others): they
    /// take tens of seconds per query on the CPU.
    #[arg(long, default_value_t = 0)]
    pub inerf_queries: usize,
    /// Report directory (created).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write each method's poses in this format to OUT/poses/ (`results.jsonl` always
    /// has them).
    #[arg(long, value_enum)]
    pub format: Option<FormatArg>,
    /// World of the written poses: `data`, or `original` (undoes the dataset's nerfstudio
    /// `applied_transform`: the COLMAP world).
    #[arg(long, value_enum, default_value = "data")]
    pub world: WorldArg,
    /// Test split for data without one; by default the split the map was built with.
    #[command(flatten)]
    pub split: SplitArgs,
    /// Recall thresholds as METRES,DEGREES pairs (repeat or separate with spaces), e.g.
    /// `--thresholds 0.25,2 0.5,5 5,10`; the loosest also defines a false accept. Default:
    /// 0.25,2 0.5,5 1,5 5,10.
    #[arg(long, num_args = 1.., value_parser = parse_threshold)]
    pub thresholds: Vec<RecallThreshold>,
    /// The methods' settings.
    #[command(flatten)]
    pub method_options: MethodOptionsArgs,
}

fn parse_threshold(s: &str) -> Result<RecallThreshold, String> {
    RecallThreshold::parse(s)
}

/// One method's results.
struct MethodRun {
    method: Method,
    records: Vec<QueryRecord>,
    outcomes: Vec<QueryOutcome>,
    summary: MethodSummary,
}

/// Runs `matloc eval`; returns the path of the markdown report.
pub fn run(args: &EvalArgs, quiet: bool) -> Result<PathBuf> {
    if args.methods.is_empty() {
        bail!("no methods given");
    }
    let map = LoadedMap::open(&args.map)
        .with_context(|| format!("opening map {}", args.map.display()))?;
    let mut dataset = matloc_data::read_dataset(&args.data)
        .with_context(|| format!("reading dataset {}", args.data.display()))?;
    let split = args.split.for_map(map.dir.manifest().split.as_ref())?;
    split_args::apply(split.as_ref(), &mut dataset)
        .with_context(|| format!("splitting dataset {}", args.data.display()))?;
    let world = OutputWorld::new(args.world.into(), dataset.metadata.applied_transform)?;
    let queries = dataset_queries(&dataset, map.camera().as_ref(), args.queries)?;
    if queries.is_empty() {
        bail!("{} has no test views to localize", args.data.display());
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let options = args.method_options.load()?;
    let mut runs = Vec::new();
    for &method in &args.methods {
        let n = match method {
            Method::Inerf | Method::CurriculumInerf if args.inerf_queries > 0 => {
                args.inerf_queries.min(queries.len())
            }
            _ => queries.len(),
        };
        let subset = spaced(&queries, n);
        let bar = progress::bar(subset.len() as u64, method.name(), quiet);
        let t = Instant::now();
        let mut records = Vec::new();
        let mut outcomes = Vec::new();
        for (index, q) in subset {
            let r = localize_with(&map, &method, &q.name, &q.image, &q.camera, &options)
                .with_context(|| format!("{method} on {}", q.name))?;
            if let Some(gt) = q.cam_from_world {
                outcomes.push(r.outcome(gt));
            }
            bar.inc(1);
            records.push(QueryRecord::Done(Box::new(Localized {
                index,
                path: q.path.clone(),
                camera: q.file_camera,
                result: r,
                cam_from_world_gt: q.cam_from_world,
            })));
        }
        bar.finish_and_clear();
        let summary = summarize_with(method.name(), &outcomes, &args.thresholds);
        outln!(
            "{:<17} {} queries in {:>6.1} s: median {:.3} m / {:.3}°, refused {:.0} %, {:.3} s/query",
            method.name(),
            records.len(),
            t.elapsed().as_secs_f64(),
            summary.median_translation_m,
            summary.median_rotation_deg,
            100.0 * summary.refusal_rate,
            summary.mean_seconds
        )?;
        runs.push(MethodRun {
            method,
            records,
            outcomes,
            summary,
        });
    }

    // Files.
    let mut lines = String::new();
    for r in &runs {
        for record in &r.records {
            lines.push_str(&serde_json::to_string(&jsonl_record(record, &world)?)?);
            lines.push('\n');
        }
    }
    write(&args.out.join("results.jsonl"), lines.as_bytes())?;
    if let Some(format) = args.format.map(PoseFormat::from) {
        let dir = args.out.join("poses");
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        for r in &runs {
            let out = dir.join(format.report_name(r.method.name()));
            write_poses(format, &r.records, &world, &dataset.root, &out)?;
        }
    }
    let summaries: Vec<&MethodSummary> = runs.iter().map(|r| &r.summary).collect();
    write(
        &args.out.join("summary.json"),
        serde_json::to_string_pretty(&summaries)?.as_bytes(),
    )?;
    plot_cdf(&runs, &args.out.join("error_cdf.png"))?;
    plot_topdown(&runs, &dataset, &map, &args.out.join("topdown.png"))?;
    plot_stage_times(&runs, &args.out.join("stage_times.png"))?;
    let report = report(&runs, &map, &dataset, args, &options)?;
    let path = args.out.join("report.md");
    write(&path, report.as_bytes())?;
    Ok(path)
}

/// What each row's method was given and when it refuses, from the options this run used.
fn differences(runs: &[MethodRun], map: &LoadedMap, method_options: &MethodOptions) -> String {
    let options = map.options();
    let structure = &method_options.structure;
    let mut s = String::new();
    for r in runs {
        let text = match r.method {
            Method::Structure => format!(
                "the place predictor's top {} hypotheses (MatLoc gets the first {}), tried in order; refuses unless a pose has ≥ {} PnP inliers, NFA ≤ 10^{} (false alarms counted over the starts tried) and a training image looking within {}° of its direction; confidence 1 − NFA (not fitted)",
                structure.hypotheses_to_try(options.top_k),
                options.top_k.max(1),
                structure.min_inliers,
                structure.max_log10_nfa,
                structure.max_view_angle_deg
            ),
            Method::Matloc => format!(
                "the place predictor's top {} hypotheses, tried in order; refuses below a calibrated confidence of {:.2} (fitted at build time on {}) or a correction beyond {:.1}°",
                options.top_k.max(1),
                options.confidence.accept_threshold,
                match map.calibrated_on {
                    CalibrationQueries::HeldOut =>
                        "held-out training views: kept out of their block's encoder, not out of the place predictor",
                    CalibrationQueries::Rendered =>
                        "views rendered halfway between neighbouring training views, which neither the encoder nor the place predictor trained on",
                },
                options.max_accept_rotation_deg
            ),
            Method::RgbKeypoints => format!(
                "the top-1 hypothesis only (as the paper's comparison), {}; refuses when PnP finds no consensus of {} inliers{}, or no training image looks within {}° of the pose's direction; confidence 1 − NFA of the last consensus (not fitted)",
                match method_options.keypoints.passes {
                    1 => "one render at it (the paper's)".to_string(),
                    n => format!(
                        "{n} passes, each after the first rendering at the pose the last one solved"
                    ),
                },
                method_options.keypoints.pnp.ransac.min_inliers,
                if method_options.keypoints.passes > 1 {
                    " in any pass, when a pass moves the pose further than the one before"
                } else {
                    ""
                },
                structure.max_view_angle_deg
            ),
            Method::Inerf | Method::CurriculumInerf => {
                "the top-1 hypothesis only; never refuses; no confidence".to_string()
            }
        };
        let _ = writeln!(
            s,
            "- `{}` ({} queries): {text}.",
            r.method,
            r.outcomes.len()
        );
    }
    s.push('\n');
    s
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    matloc_core::fsutil::write_atomic(path, bytes)
        .with_context(|| format!("writing {}", path.display()))
}

/// `n` evenly spaced queries with their positions in `v`.
fn spaced(v: &[Query], n: usize) -> Vec<(usize, &Query)> {
    matloc_core::subset::evenly_spaced(v.len(), n)
        .into_iter()
        .map(|i| (i, &v[i]))
        .collect()
}

fn center(p: &Pose) -> [f64; 3] {
    matloc_core::pose::camera_center(p).coords.into()
}

/// Translation and rotation error CDFs per method; refused queries never count as localized.
fn plot_cdf(runs: &[MethodRun], path: &Path) -> Result<()> {
    let errors: Vec<(Vec<f64>, Vec<f64>)> = runs
        .iter()
        .map(|r| r.outcomes.iter().filter_map(|o| o.errors()).unzip())
        .collect();
    let series: Vec<plot::ErrorSeries<'_>> = runs
        .iter()
        .zip(&errors)
        .map(|(r, (t, rot))| plot::ErrorSeries {
            name: r.method.name(),
            translation_m: t,
            rotation_deg: rot,
            queries: r.outcomes.len(),
        })
        .collect();
    plot::error_cdfs(
        path,
        "Localization error CDF (refused queries never count as localized)",
        &series,
    )
}

/// Top-down map: training cameras, block bounds, ground-truth query positions and each method's
/// estimates joined to their truth.
fn plot_topdown(
    runs: &[MethodRun],
    dataset: &matloc_data::Dataset,
    map: &LoadedMap,
    path: &Path,
) -> Result<()> {
    let xy = |p: [f64; 3]| [p[0], p[1]];
    let train: Vec<[f64; 2]> = dataset
        .split(matloc_data::Split::Train)
        .map(|f| {
            let c = f.center();
            [c.x, c.y]
        })
        .collect();
    let boxes: Vec<plot::MapBox> = map
        .partition
        .blocks
        .iter()
        .map(|b| plot::MapBox {
            min: [b.bounds.min[0], b.bounds.min[1]],
            max: [b.bounds.max[0], b.bounds.max[1]],
            color: b.id + 6,
            label: format!("block {}", b.id),
        })
        .collect();
    let truth: Vec<[f64; 2]> = runs.first().map_or_else(Vec::new, |r| {
        r.outcomes
            .iter()
            .map(|o| xy(center(&o.cam_from_world_gt)))
            .collect()
    });
    let pairs: Vec<Vec<([f64; 2], [f64; 2])>> = runs
        .iter()
        .map(|r| {
            r.outcomes
                .iter()
                .filter_map(|o| {
                    let est = o.cam_from_world_est.as_ref()?;
                    Some((xy(center(&o.cam_from_world_gt)), xy(center(est))))
                })
                .collect()
        })
        .collect();
    let estimates: Vec<plot::EstimateSeries<'_>> = runs
        .iter()
        .zip(&pairs)
        .map(|(r, p)| plot::EstimateSeries {
            name: r.method.name(),
            pairs: p,
        })
        .collect();
    plot::topdown(
        path,
        &plot::TopDown {
            title: "Top-down: query ground truth and each method's estimates",
            train_cameras: &train,
            boxes: &boxes,
            boxes_legend: "sub-NeRF block bounds",
            truth: &truth,
            estimates: &estimates,
        },
    )
}

/// Mean seconds per query and stage, one stacked bar per method.
fn plot_stage_times(runs: &[MethodRun], path: &Path) -> Result<()> {
    let bars: Vec<plot::StackedBar<'_>> = runs
        .iter()
        .map(|r| plot::StackedBar {
            label: r.method.name(),
            parts: &r.summary.stage_mean_seconds,
        })
        .collect();
    plot::stage_bars(
        path,
        "Mean time per query by stage",
        "mean time per query (s)",
        "s",
        &bars,
    )
}

fn report(
    runs: &[MethodRun],
    map: &LoadedMap,
    dataset: &matloc_data::Dataset,
    args: &EvalArgs,
    method_options: &MethodOptions,
) -> Result<String> {
    let mut s = String::new();
    writeln!(s, "# matloc evaluation report\n")?;
    writeln!(
        s,
        "Map `{}`, queries: test split of `{}`.\n",
        args.map.display(),
        args.data.display()
    )?;
    if let Some(p) = &args.method_options.method_options {
        writeln!(
            s,
            "Method options from `{}`: `{}`.\n",
            p.display(),
            serde_json::to_string(method_options)?
        )?;
    }
    // Scene facts.
    let (mut min, mut max) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for f in &dataset.frames {
        let p = f.center();
        for k in 0..3 {
            min[k] = min[k].min(p[k]);
            max[k] = max[k].max(p[k]);
        }
    }
    if let Some(f) = dataset.split(matloc_data::Split::Train).next() {
        let ground = dataset.metadata.bounds_min.map_or(0.0, |b| b[2]);
        let altitude = f.center()[2] - ground;
        writeln!(
            s,
            "Scene: cameras span {:.0} × {:.0} m at {:.0}–{:.0} m height; {}×{} px images, focal {:.0} px; ground sampling distance ≈ {:.2} m/px at nadir from {:.0} m.\n",
            max[0] - min[0],
            max[1] - min[1],
            min[2],
            max[2],
            f.camera.width,
            f.camera.height,
            f.camera.fx,
            altitude / f.camera.fx,
            altitude
        )?;
    }
    let m = map.dir.manifest();
    writeln!(s, "## Map\n")?;
    writeln!(s, "| block | poses | selected dims |\n|---|---|---|")?;
    for (b, e) in m.blocks.iter().enumerate() {
        writeln!(s, "| {b} | {} | {:?} |", e.num_poses, e.selected_dims)?;
    }
    writeln!(s, "\nBuild stages (s): {}\n", {
        let v: Vec<String> = m
            .stages
            .iter()
            .map(|st| format!("{} {:.0}", st.name, st.seconds))
            .collect();
        v.join(", ")
    })?;
    writeln!(s, "## Table 1 — accuracy\n")?;
    let summaries: Vec<MethodSummary> = runs.iter().map(|r| r.summary.clone()).collect();
    writeln!(s, "{}", accuracy_table(&summaries))?;
    writeln!(
        s,
        "Medians over all queries count a refused query as ∞; \"accepted\" medians are over returned poses only. A false accept is a returned pose outside 5 m / 10°.\n"
    )?;
    writeln!(s, "## Table 2 — iterations and time\n")?;
    writeln!(s, "{}", timing_table(&summaries))?;
    for name in [Method::DEFAULT.name(), Method::Matloc.name()] {
        let Some(base) = summaries.iter().find(|x| x.method == name) else {
            continue;
        };
        for o in summaries.iter().filter(|x| x.method != name) {
            let ratio = o.mean_seconds / base.mean_seconds.max(1e-9);
            let (factor, word) = if ratio >= 1.0 {
                (ratio, "faster")
            } else {
                (1.0 / ratio.max(1e-9), "slower")
            };
            writeln!(
                s,
                "- {name} is {factor:.1}× {word} than {} per query.",
                o.method
            )?;
        }
        writeln!(s)?;
    }
    let reliability = reliability_table(&summaries);
    if !reliability.is_empty() {
        writeln!(s, "## Confidence reliability\n")?;
        writeln!(
            s,
            "How well each method's confidence predicts a correct answer (a returned pose within the loosest threshold; a refused query is wrong), on these test queries: none of them was used to fit or choose a confidence. ECE: expected calibration error over {RELIABILITY_BINS} equal-width bins.\n"
        )?;
        writeln!(s, "{reliability}")?;
    }
    writeln!(s, "## What differs between the rows\n")?;
    write!(s, "{}", differences(runs, map, method_options))?;
    writeln!(s, "## Plots\n")?;
    writeln!(
        s,
        "- `error_cdf.png`: translation and rotation error CDFs per method"
    )?;
    writeln!(
        s,
        "- `topdown.png`: truth and estimated camera positions, block bounds"
    )?;
    writeln!(s, "- `stage_times.png`: mean time per query and stage\n")?;
    writeln!(
        s,
        "Per-query results: `results.jsonl`; summaries: `summary.json`."
    )?;
    if let Some(format) = args.format.map(PoseFormat::from) {
        writeln!(
            s,
            "Poses of each method ({}, {} world): `poses/`.",
            format.name(),
            WorldKind::from(args.world).name()
        )?;
    }
    Ok(s)
}
