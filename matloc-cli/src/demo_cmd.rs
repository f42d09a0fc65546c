//! `matloc demo`: synthesise the `small` world, build its map, localize the test queries with
//! every method and write the report. Every step resumes: running the demo again after an
//! interruption continues where it stopped.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use matloc_pipeline::build::MapConfig;
use matloc_pipeline::methods::Method;

use crate::eval_cmd::{self, EvalArgs};
use crate::method_options::MethodOptionsArgs;
use crate::pose_args::WorldArg;
use crate::split_args::SplitArgs;
use crate::{map_cmd, synth_cmd};

/// Arguments of `matloc demo`.
#[derive(Args)]
pub struct DemoArgs {
    /// Working directory (dataset, map, report).
    #[arg(long, default_value = "demo")]
    out: PathBuf,
    /// Synthetic preset.
    #[arg(long, default_value = "small")]
    preset: String,
    /// Map build configuration (JSON) instead of the demo's.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Test queries for the iNeRF baselines (5–10 s each on 2 cores): 20, so that their rows
    /// rest on enough queries to compare.
    #[arg(long, default_value_t = 20)]
    inerf_queries: usize,
}

/// The demo's map configuration: sized so synthesis + build + evaluation of `small` fit in
/// about 16 minutes on 2 cores.
pub fn demo_config() -> MapConfig {
    let mut c = MapConfig::default();
    // 600 steps per block: the two blocks' NeRFs, trained side by side, take ~4 of the 16
    // minutes.
    c.nerf.steps = 600;
    c.nerf.checkpoint_every = 200;
    c.place.train.epochs = 30;
    c
}

/// Runs the demo.
pub fn run(args: &DemoArgs, quiet: bool) -> Result<()> {
    let t0 = Instant::now();
    let data = args.out.join("data");
    let map = args.out.join("map");
    let report = args.out.join("report");
    if matloc_data::read_dataset(&data).is_ok() {
        outln!("[1/3] dataset {} exists, reusing it", data.display())?;
    } else {
        outln!(
            "[1/3] synthesising preset `{}` into {}",
            args.preset,
            data.display()
        )?;
        synth_cmd::render(
            &args.preset,
            &data,
            None,
            None,
            &Default::default(),
            None,
            quiet,
        )?;
    }
    let config = match &args.config {
        Some(p) => map_cmd::read_config(p)?,
        None => demo_config(),
    };
    outln!("[2/3] building the map in {}", map.display())?;
    map_cmd::build(&data, &map, &config, &SplitArgs::default(), quiet).context("map build")?;
    outln!("[3/3] localizing the test queries with every method")?;
    let path = eval_cmd::run(
        &EvalArgs {
            map,
            data,
            methods: Method::ALL.to_vec(),
            queries: 0,
            inerf_queries: args.inerf_queries,
            out: report,
            format: None,
            world: WorldArg::Data,
            split: SplitArgs::default(),
            thresholds: Vec::new(),
            method_options: MethodOptionsArgs::default(),
        },
        quiet,
    )?;
    let text = std::fs::read_to_string(&path).unwrap_or_default();
    if let Some(i) = text.find("## Table 1") {
        let end = text.find("## Plots").unwrap_or(text.len());
        outln!("\n{}", text[i..end].trim_end())?;
    }
    outln!(
        "\ndemo finished in {:.1} min; report: {}",
        t0.elapsed().as_secs_f64() / 60.0,
        path.display()
    )?;
    Ok(())
}
