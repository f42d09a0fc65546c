//! `matloc map build|info|verify|config`: build (or resume) a map, summarise or check one,
//! print the default build configuration.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use indicatif::{MultiProgress, ProgressBar};
use matloc_pipeline::MapDir;
use matloc_pipeline::build::{BuildEvent, MapConfig, build_map};
use matloc_pipeline::map::MapError;
use matloc_pipeline::map::layout::{
    CONFIDENCE_FILE, CalibrationRecord, SelectionRecord, required_stages, selection_file,
};

use crate::progress;
use crate::split_args::{self, SplitArgs};

/// `matloc map ...`
#[derive(Subcommand)]
pub enum MapCommand {
    /// Build a map: partition, sub-NeRFs, GT pairs, encoders, selection, place, calibration.
    /// A killed build resumes where it stopped when run again with the same config.
    Build(BuildArgs),
    /// Summarise a map: blocks, sizes, selected dims, stage times. Fails (after the summary)
    /// when the map is incomplete or damaged, with the reasons on stderr.
    Info {
        /// Map directory.
        map: PathBuf,
        /// Print the manifest summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Check a map: every listed file against its size and checksum, every stage a complete
    /// map has, and the files each stage writes. One line per problem; fails on any.
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
        MapCommand::Build(a) => {
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
            build(&a.data, &a.out, &config, &a.split, quiet)
        }
        MapCommand::Info { map, json } => info(map, *json),
        MapCommand::Verify { map } => verify(map),
        MapCommand::Config { .. } => {
            outln!(
                "{}",
                serde_json::to_string_pretty(&MapConfig::default()).context("map config")?
            )
        }
    }
}

/// Reads a map config file.
pub fn read_config(path: &Path) -> Result<MapConfig> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing map config {}", path.display()))
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
    let mut dataset = matloc_data::read_dataset(data)
        .with_context(|| format!("reading dataset {}", data.display()))?;
    // The same manifest config `build_map` opens the map with.
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
    drop(map_dir);
    let t0 = Instant::now();
    // Bars of the running stages (several while sub-NeRF blocks train side by side), by name;
    // `StageProgress` goes to the one started last.
    let bars = MultiProgress::new();
    let mut running: Vec<(String, ProgressBar)> = Vec::new();
    // A stdout that cannot be written does not stop the build; it is reported at the end.
    let mut out_err: Option<anyhow::Error> = None;
    let mut on_event = |e: &BuildEvent| match e {
        BuildEvent::StageStarted { name, total } => {
            let b = bars.add(progress::bar(*total, name, quiet));
            running.push((name.clone(), b));
        }
        BuildEvent::StageProgress { done, message } => {
            if let Some((_, b)) = running.last() {
                b.set_position(*done);
                b.set_message(message.clone());
            }
        }
        BuildEvent::StageProgressOf {
            name,
            done,
            message,
        } => {
            if let Some((_, b)) = running.iter().find(|(n, _)| n == name) {
                b.set_position(*done);
                b.set_message(format!("{name} {message}"));
            }
        }
        BuildEvent::StageFinished {
            name,
            seconds,
            skipped,
        } => {
            if let Some(i) = running.iter().position(|(n, _)| n == name) {
                let (_, b) = running.remove(i);
                b.finish_and_clear();
                bars.remove(&b);
            }
            let line = if *skipped {
                format!("{name:<14} done earlier")
            } else {
                format!("{name:<14} {seconds:>8.1} s")
            };
            // Printed with the live bars out of the way, not through them.
            if let Err(e) = bars.suspend(|| outln!("{line}")) {
                out_err.get_or_insert(e);
            }
        }
    };
    let map = build_map(&dataset, out, config, &mut on_event)
        .with_context(|| format!("building map {}", out.display()))?;
    if let Some(e) = out_err {
        return Err(e);
    }
    outln!(
        "map {} complete in {:.1} s ({} blocks, {:.1} MB)",
        out.display(),
        t0.elapsed().as_secs_f64(),
        map.manifest().blocks.len(),
        map.total_bytes() as f64 / 1e6
    )?;
    Ok(())
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
    let problems = map.problems();
    for p in &problems {
        outln!("{p}")?;
    }
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
    let problems = map.problems();
    let file_problems = problems
        .iter()
        .filter(|p| {
            !matches!(
                p,
                MapError::StageMissing { .. } | MapError::StageFileNotListed { .. }
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
    let calibration_summary = calibration.as_ref().map(|c| {
        serde_json::json!({
            "model": c.model,
            "attempts": c.samples.len(),
            "correct": c.samples.iter().filter(|s| s.1).count(),
            "accuracy": c.accuracy,
            "max_accept_rotation_deg": c.max_accept_rotation_deg,
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
            "stages": m.stages,
            "missing_stages": missing,
            "files": m.files.len(),
            "bytes": map.total_bytes(),
            "checksums": match &verified { Ok(()) => "ok".to_string(), Err(e) => e.clone() },
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
    if let Some(c) = &calibration {
        outln!(
            "  calibration  {} attempts ({} correct), rule accuracy {:.0} %, accept threshold {}, \
             accepted poses within {} of their coarse attitude",
            c.samples.len(),
            c.samples.iter().filter(|s| s.1).count(),
            100.0 * c.accuracy,
            c.model.accept_threshold,
            c.max_accept_rotation_deg
                .map_or("the configured bound".to_string(), |d| format!("{d:.1}°"))
        )?;
    }
    outln!("  stages:")?;
    for s in &m.stages {
        outln!("    {:<14} {:>8.1} s", s.name, s.seconds)?;
    }
    report_problems(&problems);
    fail_on(root, &problems)
}

/// One line per problem on stderr.
fn report_problems(problems: &[MapError]) {
    for p in problems {
        eprintln!("problem: {p}");
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

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
