//! `matloc`: the command-line front end of matloc-nerf. It only parses arguments, shows progress
//! and prints reports; all work happens in the library crates.

#[macro_use]
mod output;

mod dataset_cmd;
mod demo_cmd;
mod eval_cmd;
mod import_cmd;
mod localize_cmd;
mod logging;
mod map_cmd;
mod match_cmd;
mod method_options;
mod nerf_cmd;
mod partition_cmd;
mod place_cmd;
mod plot;
mod pose_args;
mod progress;
mod serve_cmd;
mod split_args;
mod synth_cmd;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "matloc",
    version,
    about = "Localize camera images against NeRF maps on the CPU"
)]
struct Cli {
    /// Hide progress bars.
    #[arg(long, global = true)]
    quiet: bool,
    /// More log output on stderr (-v info, -vv debug, -vvv trace). Without it stderr shows
    /// warnings when it is a terminal (the progress bars show progress) and info otherwise.
    /// `RUST_LOG` (e.g. `matloc_pipeline=debug`) overrides both.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    /// Also write the log (info and above, or as `-v` / `RUST_LOG` say) to this file, appended.
    #[arg(long, global = true, value_name = "FILE")]
    log_file: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Synthesise a dataset of the procedural aerial world (nerfstudio layout).
    Synth(synth_cmd::SynthArgs),
    /// Inspect datasets.
    Dataset {
        #[command(subcommand)]
        command: DatasetCommand,
    },
    /// Train a NeRF on a dataset, or render its test views with metrics.
    Nerf(nerf_cmd::NerfArgs),
    /// Split the scene into sub-NeRF blocks (pose-aware or Mega-NeRF grid) and plot them.
    Partition(partition_cmd::PartitionArgs),
    /// Pose groups and the place predictor (coarse pose of a query image).
    Place {
        #[command(subcommand)]
        command: place_cmd::PlaceCommand,
    },
    /// Ground-truth 2D-3D pairs, and the Table 3 evaluation of matching with selected features.
    Match(match_cmd::MatchArgs),
    /// Build a map (all stages, resumable) or summarise one.
    Map {
        #[command(subcommand)]
        command: map_cmd::MapCommand,
    },
    /// Localize query images against a map; write their poses (JSON lines, hloc, TUM, COLMAP,
    /// nerfstudio).
    Localize(localize_cmd::LocalizeArgs),
    /// Serve localization over HTTP: POST /v1/localize, GET /healthz, GET /metrics.
    Serve(serve_cmd::ServeArgs),
    /// Localize a dataset's test views with each method; write a report with tables and plots.
    Eval(eval_cmd::EvalArgs),
    /// Synthesise the `small` world, build its map, evaluate every method, write the report.
    Demo(demo_cmd::DemoArgs),
}

#[derive(Subcommand)]
enum DatasetCommand {
    /// Validate a dataset (nerfstudio, COLMAP, Mega-NeRF) and print a summary: every image
    /// and depth map is decoded in full (in parallel, with a progress bar), and each file
    /// that does not decode is a problem on stderr naming it and what is wrong.
    Info {
        /// Dataset directory, transforms.json file, or COLMAP model directory.
        path: PathBuf,
        /// Print the summary as JSON instead of text.
        #[arg(long)]
        json: bool,
        /// Read only the headers of the images and depth maps (sizes), not decode them in
        /// full: fast, but a truncated or corrupt file passes.
        #[arg(long)]
        quick: bool,
    },
    /// Refine a survey's poses as a GPS/IMU gave them (about 0.3 m and 1° off): points
    /// triangulated through a wide gate, then poses and points bundle-adjusted with the given
    /// poses as priors; writes a nerfstudio transforms.json with the refined poses (its
    /// frames refer to the same images) and prints how far they moved.
    RefinePoses(dataset_cmd::RefinePosesArgs),
    /// Convert another dataset layout into a nerfstudio transforms.json.
    Import {
        #[command(subcommand)]
        format: import_cmd::ImportCommand,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Err(err) = logging::init(cli.verbose, cli.log_file.as_deref()) {
        errln!("error: {}", output::error_chain(&err));
        return ExitCode::FAILURE;
    }
    let result = match cli.command {
        Command::Synth(args) => synth_cmd::run(&args, cli.quiet),
        Command::Dataset {
            command: DatasetCommand::Info { path, json, quick },
        } => dataset_cmd::info(&path, json, quick, cli.quiet),
        Command::Dataset {
            command: DatasetCommand::Import { format },
        } => import_cmd::run(&format),
        Command::Dataset {
            command: DatasetCommand::RefinePoses(args),
        } => dataset_cmd::refine_poses(&args, cli.quiet),
        Command::Nerf(args) => nerf_cmd::run(&args, cli.quiet),
        Command::Partition(args) => partition_cmd::run(&args, cli.quiet),
        Command::Place { command } => place_cmd::run(&command, cli.quiet),
        Command::Match(args) => match_cmd::run(&args, cli.quiet),
        Command::Map { command } => map_cmd::run(&command, cli.quiet),
        Command::Localize(args) => localize_cmd::run(&args),
        Command::Serve(args) => serve_cmd::run(&args),
        Command::Eval(args) => {
            eval_cmd::run(&args, cli.quiet).and_then(|p| outln!("report: {}", p.display()))
        }
        Command::Demo(args) => demo_cmd::run(&args, cli.quiet),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        // The reader of stdout went away (`matloc … | head`): done, as far as it cares.
        Err(err) if output::is_closed_stdout(&err) => ExitCode::SUCCESS,
        Err(err) => {
            tracing::debug!(error = ?err, "command failed");
            errln!("error: {}", output::error_chain(&err));
            ExitCode::FAILURE
        }
    }
}
