//! `matloc map build|plan|block|finish|slurm|info|verify|config`: build (or resume) a map in
//! one process or as independent jobs (plan, one job per block, finish) with Slurm scripts for
//! them, summarise or check a map, print the default build configuration.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use indicatif::{MultiProgress, ProgressBar};
use matloc_pipeline::build::jobs::{
    SlurmOptions, read_plan, shell_line, shell_quote, write_slurm_scripts,
};
use matloc_pipeline::build::{
    BuildEvent, JobCommands, MapConfig, build_map, plan_map, run_block_job, run_finish_job,
};
use matloc_pipeline::config::CalibrationQueries;
use matloc_pipeline::map::MapError;
use matloc_pipeline::map::check::{content_problems, structure_summary};
use matloc_pipeline::map::layout::{
    CONFIDENCE_FILE, CalibrationRecord, PLAN_FILE, SelectionRecord, block_stages, required_stages,
    selection_file,
};
use matloc_pipeline::{MapDir, VirtualViewsRecord};

use crate::progress;
use crate::split_args::{self, SplitArgs};

/// `matloc map ...`
#[derive(Subcommand)]
pub enum MapCommand {
    /// Build a map: partition, sub-NeRFs, GT pairs, encoders, selection, place, calibration.
    /// A killed build resumes where it stopped when run again with the same config.
    Build(BuildArgs),
    /// First step of a build as independent jobs: check the dataset, find the surface,
    /// partition, and write the job list (MAP/plan.json: block ids and each job's command).
    /// Same options as `map build`.
    Plan(BuildArgs),
    /// One block's job of a planned map: its sub-NeRF, pairs, encoder and selection. Writes
    /// only under MAP/blocks/B (jobs of different blocks run side by side); rerun after a
    /// kill, it resumes.
    Block {
        /// Map directory (planned with `map plan`).
        map: PathBuf,
        /// Block id.
        #[arg(long)]
        block: usize,
        /// Dataset directory (default: the one in the plan).
        #[arg(long)]
        data: Option<PathBuf>,
    },
    /// Last job of a planned map: merges the blocks' records into the manifest, trains the
    /// place predictor and calibrates. Refuses, naming them, while blocks are missing.
    Finish {
        /// Map directory.
        map: PathBuf,
        /// Dataset directory (default: the one in the plan).
        #[arg(long)]
        data: Option<PathBuf>,
    },
    /// Write Slurm batch scripts for a planned map: a job array over the blocks, a finish job
    /// that runs after all of them succeeded, and submit.sh that submits both.
    Slurm(SlurmArgs),
    /// Summarise a map: blocks, sizes, selected dims, stage times, and the checks of `map
    /// verify`. Fails (after the summary) when the map is incomplete or damaged, with the
    /// reasons on stderr.
    Info {
        /// Map directory.
        map: PathBuf,
        /// Print the manifest summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Check a map: every listed file against its size and checksum, every stage a complete
    /// map has and the files each stage writes; then every file parsed and loaded as
    /// localization loads it: safetensors headers, dtypes and shapes against the map's configs
    /// with every value finite, JSON files into their types, the partition against the block
    /// count, each selection's dims below the feature dimension and produced by its encoder.
    /// One line per problem (naming file and field, on stdout and stderr); fails on any.
    Verify {
        /// Map directory.
        map: PathBuf,
    },
    /// Build configuration.
    Config {
        /// Print the full default configuration as JSON (a starting point for `--config`).
        #[arg(long, required = true)]
        print_default: bool,
    },
}

/// Arguments of `matloc map build`.
#[derive(Args)]
pub struct BuildArgs {
    /// Dataset directory (nerfstudio transforms.json or COLMAP model).
    #[arg(long)]
    pub data: PathBuf,
    /// Output map directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Test split for data without one (recorded in the map).
    #[command(flatten)]
    pub split: SplitArgs,
    /// Build configuration (JSON; missing fields take their defaults, unknown fields are an
    /// error; `matloc map config --print-default` prints all of them).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override the sub-NeRF training steps per block.
    #[arg(long)]
    pub nerf_steps: Option<u64>,
    /// Scene surface for views without depth files: auto (depth files, else the dataset's
    /// point cloud, else points triangulated from the posed images), depth, points,
    /// triangulate. Overrides the config's `surface.source`.
    #[arg(long, value_enum)]
    pub surface: Option<SurfaceArg>,
    /// Working resolution: images (and queries) are box-downscaled by the smallest integer
    /// factor that brings the longer side to at most this many pixels. Overrides the config's
    /// `images.max_side`.
    #[arg(long)]
    pub max_side: Option<u32>,
}

/// Arguments of `matloc map slurm`.
#[derive(Args)]
pub struct SlurmArgs {
    /// Map directory (planned with `map plan`).
    pub map: PathBuf,
    /// Slurm partition (default: the cluster's).
    #[arg(long)]
    pub partition: Option<String>,
    /// CPUs per block job (also the job's worker threads).
    #[arg(long, default_value_t = 4)]
    pub cpus_per_task: u32,
    /// CPUs of the finish job (place classifier and calibration, once for the whole map;
    /// default: --cpus-per-task).
    #[arg(long)]
    pub finish_cpus: Option<u32>,
    /// Memory per job, as Slurm writes it (e.g. 8G).
    #[arg(long, default_value = "8G")]
    pub mem: String,
    /// Time limit per job, as Slurm writes it (e.g. 02:00:00).
    #[arg(long, default_value = "02:00:00")]
    pub time: String,
    /// Slurm account to charge.
    #[arg(long)]
    pub account: Option<String>,
    /// Block jobs running at once at most (`--array=…%N`; default: no limit).
    #[arg(long)]
    pub max_running: Option<u32>,
    /// The matloc executable the jobs run (default: the one that planned the map).
    #[arg(long)]
    pub matloc: Option<PathBuf>,
    /// Directory for the scripts (default: MAP/slurm); job logs go to its logs/.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// `--surface` on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SurfaceArg {
    /// Depth files, else the dataset's point cloud, else triangulated points.
    Auto,
    /// Depth files only.
    Depth,
    /// The dataset's point cloud (COLMAP points3D, nerfstudio ply_file_path / sparse_pc.ply).
    Points,
    /// Points triangulated from the posed images.
    Triangulate,
}

impl From<SurfaceArg> for matloc_surface::SurfaceChoice {
    fn from(a: SurfaceArg) -> Self {
        match a {
            SurfaceArg::Auto => Self::Auto,
            SurfaceArg::Depth => Self::Depth,
            SurfaceArg::Points => Self::Points,
            SurfaceArg::Triangulate => Self::Triangulate,
        }
    }
}

/// Runs `matloc map ...`.
pub fn run(cmd: &MapCommand, quiet: bool) -> Result<()> {
    match cmd {
        MapCommand::Build(a) => build(&a.data, &a.out, &build_config(a)?, &a.split, quiet),
        MapCommand::Plan(a) => plan(&a.data, &a.out, &build_config(a)?, &a.split, quiet),
        MapCommand::Block { map, block, data } => {
            let dataset = job_dataset(map, data.as_deref())?;
            let mut bars = StageBars::new(quiet);
            let t0 = Instant::now();
            let dir = run_block_job(&dataset, map, *block, &mut |e| bars.event(e))
                .with_context(|| format!("building block {block} of map {}", map.display()))?;
            bars.finish()?;
            let bytes: u64 = dir
                .manifest()
                .files
                .iter()
                .filter(|(k, _)| k.starts_with(&format!("blocks/{block}/")))
                .map(|(_, f)| f.bytes)
                .sum::<u64>()
                + block_record_bytes(&dir, *block);
            outln!(
                "block {block} of map {} done in {:.1} s ({:.1} MB)",
                map.display(),
                t0.elapsed().as_secs_f64(),
                bytes as f64 / 1e6
            )
        }
        MapCommand::Finish { map, data } => {
            let dataset = job_dataset(map, data.as_deref())?;
            let mut bars = StageBars::new(quiet);
            let t0 = Instant::now();
            let dir = run_finish_job(&dataset, map, &mut |e| bars.event(e))
                .with_context(|| format!("finishing map {}", map.display()))?;
            bars.finish()?;
            outln!(
                "map {} complete in {:.1} s ({} blocks, {:.1} MB)",
                map.display(),
                t0.elapsed().as_secs_f64(),
                dir.manifest().blocks.len(),
                dir.total_bytes() as f64 / 1e6
            )
        }
        MapCommand::Slurm(a) => slurm(a),
        MapCommand::Info { map, json } => info(map, *json),
        MapCommand::Verify { map } => verify(map),
        MapCommand::Config { .. } => {
            outln!(
                "{}",
                serde_json::to_string_pretty(&MapConfig::documented_default())
                    .context("map config")?
            )
        }
    }
}

/// The build config of `map build` / `map plan`: the file or the defaults, then the flags.
fn build_config(a: &BuildArgs) -> Result<MapConfig> {
    let mut config = match &a.config {
        Some(p) => read_config(p)?,
        None => MapConfig::default(),
    };
    if let Some(s) = a.nerf_steps {
        config.nerf.steps = s;
    }
    if let Some(s) = a.surface {
        config.surface.source = s.into();
    }
    if let Some(m) = a.max_side {
        anyhow::ensure!(m >= 16, "--max-side must be at least 16, got {m}");
        config.images.max_side = Some(m);
    }
    Ok(config)
}

/// Reads a map config file ([`MapConfig::from_path`]).
pub fn read_config(path: &Path) -> Result<MapConfig> {
    Ok(MapConfig::from_path(path)?)
}

/// Runs `step`, which creates or resumes the map in `out`. When `out` held no map before and
/// the step fails before any stage finished (the dataset or config refused), the manifest it
/// created, and `out` itself if it was made for it and is empty, are removed: a refused build
/// leaves nothing behind. A map with a finished stage is kept, to be resumed.
fn leaving_nothing_if_refused<T>(out: &Path, step: impl FnOnce() -> Result<T>) -> Result<T> {
    let manifest = out.join(matloc_pipeline::map::manifest::MANIFEST_FILE);
    let (had_dir, had_map) = (out.exists(), manifest.exists());
    let result = step();
    if result.is_err() && !had_map && no_stage_finished(&manifest) {
        let _ = std::fs::remove_file(&manifest);
        if !had_dir {
            let _ = std::fs::remove_dir(out);
        }
    }
    result
}

/// Whether the manifest at `path` records no finished stage (or cannot be read).
fn no_stage_finished(path: &Path) -> bool {
    std::fs::read(path)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .is_none_or(|v| v["stages"].as_array().is_none_or(Vec::is_empty))
}

/// Reads the dataset, opens (or creates) the map, applies the split rule from the flags (or,
/// without flags, the one the map records) and records it in the manifest.
fn open_for_build(
    data: &Path,
    out: &Path,
    config: &MapConfig,
    split: &SplitArgs,
) -> Result<matloc_data::Dataset> {
    let mut dataset = matloc_data::read_dataset(data)
        .with_context(|| format!("reading dataset {}", data.display()))?;
    // The same manifest config the build opens the map with.
    let config_json = serde_json::to_value(config).context("map config")?;
    let mut map_dir = MapDir::create_or_resume(out, config_json)
        .with_context(|| format!("opening map {}", out.display()))?;
    let spec = match split.spec()? {
        Some(s) => Some(s),
        None => map_dir.manifest().split.clone(),
    };
    split_args::apply(spec.as_ref(), &mut dataset)
        .with_context(|| format!("splitting dataset {}", data.display()))?;
    map_dir.record_split(spec.as_ref())?;
    Ok(dataset)
}

/// Builds (or resumes) a map with progress bars per stage. A split rule from the flags (or,
/// without flags, the one the map records) is applied to the dataset and recorded in the
/// manifest before any stage runs.
pub fn build(
    data: &Path,
    out: &Path,
    config: &MapConfig,
    split: &SplitArgs,
    quiet: bool,
) -> Result<()> {
    let t0 = Instant::now();
    let mut bars = StageBars::new(quiet);
    let map = leaving_nothing_if_refused(out, || {
        let dataset = open_for_build(data, out, config, split)?;
        build_map(&dataset, out, config, &mut |e| bars.event(e))
            .with_context(|| format!("building map {}", out.display()))
    })?;
    bars.finish()?;
    outln!(
        "map {} complete in {:.1} s ({} blocks, {:.1} MB)",
        out.display(),
        t0.elapsed().as_secs_f64(),
        map.manifest().blocks.len(),
        map.total_bytes() as f64 / 1e6
    )?;
    Ok(())
}

/// `matloc map plan`: the plan step, then the job list in MAP/plan.json.
fn plan(data: &Path, out: &Path, config: &MapConfig, split: &SplitArgs, quiet: bool) -> Result<()> {
    let mut bars = StageBars::new(quiet);
    let program = std::env::current_exe()
        .map(|p| std::fs::canonicalize(&p).unwrap_or(p))
        .unwrap_or_else(|_| PathBuf::from("matloc"));
    let jobs = JobCommands {
        program: program.clone(),
        data: data.to_path_buf(),
    };
    let planned = leaving_nothing_if_refused(out, || {
        let dataset = open_for_build(data, out, config, split)?;
        plan_map(&dataset, out, config, &jobs, &mut |e| bars.event(e))
            .with_context(|| format!("planning map {}", out.display()))
    })?;
    bars.finish()?;
    let record = read_plan(&planned.map)?;
    let root = std::fs::canonicalize(out).unwrap_or_else(|_| out.to_path_buf());
    outln!(
        "map {} planned: {} blocks; run each block job, then the finish job:",
        out.display(),
        record.blocks.len()
    )?;
    for c in &record.block_commands {
        outln!("  {}", shell_line(c))?;
    }
    outln!("  {}", shell_line(&record.finish_command))?;
    outln!(
        "or write Slurm scripts: {} map slurm {}",
        shell_quote(&program.display().to_string()),
        shell_quote(&root.display().to_string())
    )
}

/// The dataset of a block or finish job: `data`, else the plan's, else the one the manifest
/// records, with the map's split rule applied.
fn job_dataset(root: &Path, data: Option<&Path>) -> Result<matloc_data::Dataset> {
    let map =
        MapDir::open_manifest(root).with_context(|| format!("opening map {}", root.display()))?;
    let data = match data {
        Some(d) => d.to_path_buf(),
        None => match map.manifest().files.contains_key(PLAN_FILE) {
            true => PathBuf::from(read_plan(&map)?.data),
            false => map
                .manifest()
                .scene
                .get("dataset")
                .and_then(|d| d.as_str())
                .map(PathBuf::from)
                .with_context(|| {
                    format!(
                        "{}: no plan and no `scene.dataset`; pass --data",
                        root.join("manifest.json").display()
                    )
                })?,
        },
    };
    let mut dataset = matloc_data::read_dataset(&data)
        .with_context(|| format!("reading dataset {}", data.display()))?;
    split_args::apply(map.manifest().split.as_ref(), &mut dataset)
        .with_context(|| format!("splitting dataset {}", data.display()))?;
    Ok(dataset)
}

/// Bytes of block `b`'s record file (0 when absent).
fn block_record_bytes(map: &MapDir, b: usize) -> u64 {
    map.read_block_record(b)
        .ok()
        .flatten()
        .map_or(0, |r| r.files.values().map(|f| f.bytes).sum())
}

/// `matloc map slurm`: writes the scripts and prints how to submit them.
fn slurm(a: &SlurmArgs) -> Result<()> {
    let map = MapDir::open_manifest(&a.map)
        .with_context(|| format!("opening map {}", a.map.display()))?;
    let plan = read_plan(&map)?;
    let options = SlurmOptions {
        partition: a.partition.clone(),
        cpus_per_task: a.cpus_per_task,
        finish_cpus: a.finish_cpus,
        mem: a.mem.clone(),
        time: a.time.clone(),
        account: a.account.clone(),
        max_running: a.max_running,
        program: a.matloc.clone(),
    };
    let out = a.out.clone().unwrap_or_else(|| a.map.join("slurm"));
    let out = write_slurm_scripts(&plan, &options, &out)?;
    let dir = shell_quote(&out.display().to_string());
    outln!(
        "wrote {dir}/blocks.sbatch ({} blocks), {dir}/finish.sbatch, {dir}/submit.sh; submit with\n  \
         {dir}/submit.sh\nor by hand:\n  \
         A=$(sbatch --parsable {dir}/blocks.sbatch)\n  \
         sbatch --parsable --dependency=afterok:${{A%%;*}} {dir}/finish.sbatch",
        plan.blocks.len()
    )
}

/// Progress bars of the running stages (several while sub-NeRF blocks train side by side), by
/// name; `StageProgress` goes to the one started last. A line per finished stage on stdout.
struct StageBars {
    bars: MultiProgress,
    running: Vec<(String, ProgressBar)>,
    quiet: bool,
    /// A stdout that cannot be written does not stop the build; it is reported at the end.
    out_err: Option<anyhow::Error>,
}

impl StageBars {
    fn new(quiet: bool) -> Self {
        Self {
            bars: MultiProgress::new(),
            running: Vec::new(),
            quiet,
            out_err: None,
        }
    }

    fn event(&mut self, e: &BuildEvent) {
        match e {
            BuildEvent::StageStarted { name, total } => {
                let b = self.bars.add(progress::bar(*total, name, self.quiet));
                self.running.push((name.clone(), b));
            }
            BuildEvent::StageProgress { done, message } => {
                if let Some((_, b)) = self.running.last() {
                    b.set_position(*done);
                    b.set_message(message.clone());
                }
            }
            BuildEvent::StageProgressOf {
                name,
                done,
                message,
            } => {
                if let Some((_, b)) = self.running.iter().find(|(n, _)| n == name) {
                    b.set_position(*done);
                    b.set_message(format!("{name} {message}"));
                }
            }
            BuildEvent::StageFinished {
                name,
                seconds,
                skipped,
            } => {
                if let Some(i) = self.running.iter().position(|(n, _)| n == name) {
                    let (_, b) = self.running.remove(i);
                    b.finish_and_clear();
                    self.bars.remove(&b);
                }
                let line = if *skipped {
                    format!("{name:<14} done earlier")
                } else {
                    format!("{name:<14} {seconds:>8.1} s")
                };
                // Printed with the live bars out of the way, not through them.
                if let Err(e) = self.bars.suspend(|| outln!("{line}")) {
                    self.out_err.get_or_insert(e);
                }
            }
        }
    }

    /// The first stdout error, if any.
    fn finish(self) -> Result<()> {
        self.out_err.map_or(Ok(()), Err)
    }
}

/// Fails naming the count when `problems` is not empty.
fn fail_on(root: &Path, problems: &[MapError]) -> Result<()> {
    match problems.len() {
        0 => Ok(()),
        n => anyhow::bail!(
            "map {}: {n} problem{}",
            root.display(),
            if n == 1 { "" } else { "s" }
        ),
    }
}

fn verify(root: &Path) -> Result<()> {
    let map =
        MapDir::open_manifest(root).with_context(|| format!("opening map {}", root.display()))?;
    let mut problems = map.problems();
    problems.extend(content_problems(&map));
    for p in &problems {
        outln!("{p}")?;
    }
    report_problems(&problems);
    fail_on(root, &problems)?;
    outln!(
        "map {}: ok ({} files, {} stages)",
        root.display(),
        map.manifest().files.len(),
        map.manifest().stages.len()
    )
}

fn info(root: &Path, json: bool) -> Result<()> {
    let map =
        MapDir::open_manifest(root).with_context(|| format!("opening map {}", root.display()))?;
    let m = map.manifest();
    let missing: Vec<String> = required_stages(m.blocks.len())
        .into_iter()
        .filter(|s| !map.stage_done(s))
        .collect();
    let mut problems = map.problems();
    let contents = content_problems(&map);
    let contents_summary = match contents.as_slice() {
        [] => "ok".to_string(),
        [only] => format!("FAILED: {only}"),
        [first, ..] => format!("FAILED on {} parts, first: {first}", contents.len()),
    };
    problems.extend(contents);
    let file_problems = problems
        .iter()
        .filter(|p| {
            !matches!(
                p,
                MapError::StageMissing { .. }
                    | MapError::StageFileNotListed { .. }
                    | MapError::Content { .. }
            )
        })
        .count();
    let unlisted = problems
        .iter()
        .filter(|p| matches!(p, MapError::StageFileNotListed { .. }))
        .count();
    let verified = match problems.first() {
        Some(p) if file_problems > 0 => Err(p.to_string()),
        _ => Ok(()),
    };
    let selections: Vec<Option<SelectionRecord>> = (0..m.blocks.len())
        .map(|b| map.read_json(&selection_file(b)).ok())
        .collect();
    let calibration: Option<CalibrationRecord> = map.read_json(CONFIDENCE_FILE).ok();
    let structure = structure_summary(&map);
    let calibration_summary = calibration.as_ref().map(|c| {
        serde_json::json!({
            "model": c.model,
            "attempts": c.samples.len(),
            "correct": c.samples.iter().filter(|s| s.1).count(),
            "accuracy": c.accuracy,
            "max_accept_rotation_deg": c.max_accept_rotation_deg,
            "queries": c.queries,
        })
    });
    if json {
        let doc = serde_json::json!({
            "map": root.display().to_string(),
            "version": m.version,
            "created_by": m.created_by,
            "scene": m.scene,
            "blocks": m.blocks,
            "selections": selections,
            "calibration": calibration_summary,
            "structure": structure,
            "stages": m.stages,
            "missing_stages": missing,
            "files": m.files.len(),
            "bytes": map.total_bytes(),
            "checksums": match &verified { Ok(()) => "ok".to_string(), Err(e) => e.clone() },
            "contents": contents_summary,
            "problems": problems.iter().map(|p| p.to_string()).collect::<Vec<_>>(),
        });
        outln!("{}", serde_json::to_string_pretty(&doc)?)?;
        report_problems(&problems);
        return fail_on(root, &problems);
    }
    outln!(
        "map {} (format v{}, {})",
        root.display(),
        m.version,
        m.created_by
    )?;
    if let Some(d) = m.scene.get("dataset") {
        outln!("  dataset      {}", d.as_str().unwrap_or("?"))?;
    }
    outln!(
        "  files        {} ({:.1} MB), checksums {}",
        m.files.len(),
        map.total_bytes() as f64 / 1e6,
        match &verified {
            Ok(()) => "ok".to_string(),
            Err(e) if file_problems == 1 => format!("FAILED: {e}"),
            Err(e) => format!("FAILED on {file_problems} files, first: {e}"),
        }
    )?;
    outln!("  contents     {contents_summary}")?;
    outln!(
        "  status       {}",
        if !missing.is_empty() {
            format!("incomplete, next stage {}", missing[0])
        } else if unlisted > 0 {
            format!("incomplete, {unlisted} files of completed stages not listed")
        } else {
            "complete".to_string()
        }
    )?;
    // Blocks built by `map block` jobs and not yet merged by `map finish`.
    let jobs: Vec<String> = (0..m.blocks.len())
        .filter(|&b| !block_stages(b).iter().all(|s| map.stage_done(s)))
        .map(|b| match map.read_block_record(b) {
            Ok(Some(r)) => format!("{b}: {}/4 stages", r.stages.len()),
            Ok(None) => format!("{b}: not started"),
            Err(e) => format!("{b}: {e}"),
        })
        .collect();
    if !jobs.is_empty() && m.files.contains_key(PLAN_FILE) {
        outln!("  block jobs   {}", jobs.join(", "))?;
    }
    outln!("  blocks:")?;
    for (b, e) in m.blocks.iter().enumerate() {
        let bytes: u64 = m
            .files
            .iter()
            .filter(|(k, _)| k.starts_with(&format!("blocks/{b}/")))
            .map(|(_, f)| f.bytes)
            .sum();
        let ext = [
            e.bounds_max[0] - e.bounds_min[0],
            e.bounds_max[1] - e.bounds_min[1],
            e.bounds_max[2] - e.bounds_min[2],
        ];
        outln!(
            "    {b}: {} poses, box {:.0}×{:.0}×{:.0} m, {:.1} MB, selected dims {:?}",
            e.num_poses,
            ext[0],
            ext[1],
            ext[2],
            bytes as f64 / 1e6,
            e.selected_dims
        )?;
    }
    if let Some(s) = &structure {
        outln!(
            "  structure    {} points, {} observations in {} images, {} descriptors{}",
            s.points,
            s.observations,
            s.images,
            s.descriptors,
            s.reprojection.as_ref().map_or(String::new(), |r| format!(
                ", reprojection error median {:.2} px, 95 % {:.2} px, max {:.2} px",
                r.median_px, r.p95_px, r.max_px
            ))
        )?;
    }
    if let Some(c) = &calibration {
        outln!(
            "  calibration  {} attempts on {} ({} correct), rule accuracy {:.0} %, accept \
             threshold {}, accepted poses within {} of their coarse attitude",
            c.samples.len(),
            match c.queries {
                CalibrationQueries::HeldOut => "held-out views",
                CalibrationQueries::Rendered => "rendered views",
            },
            c.samples.iter().filter(|s| s.1).count(),
            100.0 * c.accuracy,
            c.model.accept_threshold,
            c.max_accept_rotation_deg
                .map_or("the configured bound".to_string(), |d| format!("{d:.1}°"))
        )?;
    }
    if let Some(v) = m
        .stages
        .iter()
        .find(|s| s.name == "place")
        .and_then(|s| s.virtual_views.as_ref())
    {
        outln!("  virtual      {}", virtual_views_line(v))?;
    }
    outln!("  stages:")?;
    for s in &m.stages {
        outln!("    {:<14} {:>8.1} s", s.name, s.seconds)?;
    }
    report_problems(&problems);
    fail_on(root, &problems)
}

/// What `map info` shows of the place stage's virtual viewpoints.
fn virtual_views_line(v: &VirtualViewsRecord) -> String {
    let r = &v.rejected;
    format!(
        "{} views in the place classifier ({} groups), {} of {} candidates rejected ({} no \
         ground below, {} clearance, {} axis misses ground, {} target outside block, {} axis \
         not covered, {} low coverage), {} unlabelled; survey {:.1} m up, cells {:.2} m, \
         {:.1} s",
        v.views,
        v.per_group.iter().filter(|&&n| n > 0).count(),
        r.total(),
        v.candidates,
        r.no_ground_below,
        r.clearance,
        r.axis_misses_ground,
        r.target_outside_block,
        r.axis_not_covered,
        r.low_coverage,
        v.unlabelled,
        v.survey_height_m,
        v.cell_m,
        v.seconds
    )
}

/// One line per problem on stderr.
fn report_problems(problems: &[MapError]) {
    for p in problems {
        errln!("problem: {p}");
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    #[test]
    fn map_info_shows_the_virtual_views_with_their_rejections() {
        let v = matloc_pipeline::VirtualViewsRecord {
            views: 12,
            candidates: 15,
            rejected: matloc_surface::viewpoints::Rejections {
                axis_misses_ground: 2,
                target_outside_block: 1,
                ..Default::default()
            },
            unlabelled: 0,
            per_block: vec![12],
            per_group: vec![2, 0, 10],
            survey_height_m: 29.89,
            cell_m: 2.989,
            seconds: 1.96,
        };
        assert_eq!(
            super::virtual_views_line(&v),
            "12 views in the place classifier (2 groups), 3 of 15 candidates rejected (0 no \
             ground below, 0 clearance, 2 axis misses ground, 1 target outside block, 0 axis \
             not covered, 0 low coverage), 0 unlabelled; survey 29.9 m up, cells 2.99 m, 2.0 s"
        );
    }

    /// The shipped quality config is a partial file: what it names changes, the rest stays
    /// the default.
    #[test]
    fn shipped_quality_config_parses_onto_the_defaults() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/quality.json");
        let c = super::read_config(&path).unwrap();
        let d = matloc_pipeline::build::MapConfig::default();
        assert_eq!(c.nerf.steps, 2000);
        assert_eq!(c.encoder.train.steps, 2400);
        assert_eq!(c.encoder.train.head_phase.steps, 12000);
        assert_eq!(c.place, d.place);
        assert_eq!(c.localize, d.localize);
        assert_eq!(c.encoder.views_per_block, d.encoder.views_per_block);
    }
}
