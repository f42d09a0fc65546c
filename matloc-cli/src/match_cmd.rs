//! `matloc match`: ground-truth pair generation and the paper's Table 3 (feature sets × matching
//! time, match precision, pose error after PnP), on the synthetic world's analytic feature field
//! ([`matloc_pipeline::eval::table3_field`]) or on a built map
//! ([`matloc_pipeline::eval::table3`]). This module only parses arguments, draws progress and
//! prints or writes what those return.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use matloc_encoder::EncoderTrainConfig;
use matloc_match::SubcellSide;
use matloc_pipeline::eval::table3_field::{self, FieldTable3Config};
use matloc_pipeline::gt::{PerturbKind, Perturbation};

use crate::progress;

/// `matloc match ...`
#[derive(Args)]
pub struct MatchArgs {
    #[command(subcommand)]
    command: MatchCommand,
}

#[derive(Subcommand)]
enum MatchCommand {
    /// Generate ground-truth 2D–3D pairs from perturbed training poses (safetensors).
    Pairs {
        #[command(flatten)]
        scene: SceneArgs,
        /// Output file.
        #[arg(long)]
        out: PathBuf,
    },
    /// Print the paper's Table 3 on the synthetic world.
    Eval(Box<EvalArgs>),
}

#[derive(Args, Clone)]
struct SceneArgs {
    /// Synthetic preset.
    #[arg(long, default_value = "tiny")]
    preset: String,
    /// World and survey seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Use at most this many training views (evenly spaced).
    #[arg(long, default_value_t = 24)]
    train_views: usize,
    /// Pair-generation perturbation: translation radius, metres (uniform ball).
    #[arg(long, default_value_t = 2.0)]
    pair_translation_m: f64,
    /// Pair-generation perturbation: rotation radius, degrees (uniform ball).
    #[arg(long, default_value_t = 3.0)]
    pair_rotation_deg: f64,
}

/// Criterion of `--render-select`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum RenderSelectArg {
    /// F1 of windowed matches within one cell of the true projection.
    F1,
    /// One render–match–PnP pass.
    Pnp,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum QuerySource {
    /// Features rendered at the query's true pose (upper bound: a perfect encoder).
    Oracle,
    /// A CNN encoder trained on the training views.
    Encoder,
}

#[derive(Args)]
struct EvalArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// Evaluate on this built map (its NeRFs, encoders and localizer) instead of the analytic
    /// field; needs `--data`. The scene, encoder and sub-cell options do not apply.
    #[arg(long, requires = "data")]
    map: Option<PathBuf>,
    /// The map's dataset (test views are the queries; the GT pairs' images).
    #[arg(long, requires = "map")]
    data: Option<PathBuf>,
    /// With `--map`: also evaluate this feature set (e.g. `"greedy N_s=5"`) with encoders
    /// trained on only its dims (one per block, the map's recipe; minutes each). Repeatable.
    #[arg(long, requires = "map")]
    own_encoder: Vec<String>,
    /// With `--map`: Lowe ratio test for every feature set's matcher (default: none, as the
    /// map's localizer).
    #[arg(long, requires = "map")]
    ratio: Option<f32>,
    /// With `--map`: also select N_s = 5 dims per block on held-out renders, scored the way
    /// the localizer uses them: `f1` = windowed-match F1 within one cell, `pnp` = one PnP
    /// pass from perturbed poses. Repeatable; adds a row each.
    #[arg(long, requires = "map", value_enum)]
    render_select: Vec<RenderSelectArg>,
    /// Where query features come from.
    #[arg(long, value_enum, default_value = "encoder")]
    query: QuerySource,
    /// Encoder training steps.
    #[arg(long, default_value_t = 300)]
    encoder_steps: usize,
    /// Encoder loss weights `w_reg,w_nce`.
    #[arg(long, default_value = "1,0.5")]
    encoder_loss: String,
    /// Further encoder training settings as `EncoderTrainConfig` JSON (missing fields: the
    /// defaults; `--encoder-steps`, `--encoder-loss` and the seed override it), e.g.
    /// `'{"net":{"width":64},"head_phase":{"steps":2000}}'`.
    #[arg(long)]
    encoder_config: Option<String>,
    /// Save the trained encoder here.
    #[arg(long)]
    encoder_out: Option<PathBuf>,
    /// Test-query perturbation: translation radius, metres (uniform ball).
    #[arg(long, default_value_t = 3.0)]
    query_translation_m: f64,
    /// Test-query perturbation: rotation radius, degrees (uniform ball).
    #[arg(long, default_value_t = 5.0)]
    query_rotation_deg: f64,
    /// Perturbed starts per test view.
    #[arg(long, default_value_t = 3)]
    starts: usize,
    /// Sub-cell refinement of the matches (`matloc_match::subcell`).
    #[arg(long, value_enum, default_value = "map")]
    subcell: SubcellArg,
    /// Match only cells within this many pixels of each other (beyond the paper; default: the
    /// whole image).
    #[arg(long)]
    window_px: Option<f64>,
    /// RANSAC inlier threshold of the test-query PnP, in query cells (the pipeline's first
    /// pass uses 3: learned-encoder matches are often a cell off).
    #[arg(long, default_value_t = 3.0)]
    pnp_threshold_cells: f64,
    /// Write the table as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum SubcellArg {
    /// Move the 3D point (rendered neighbours; the matcher's default).
    Map,
    /// Move the query pixel (query neighbours).
    Query,
    /// No refinement (cell centres).
    Off,
}

impl SubcellArg {
    fn side(self) -> SubcellSide {
        match self {
            SubcellArg::Map => SubcellSide::Map,
            SubcellArg::Query => SubcellSide::Query,
            SubcellArg::Off => SubcellSide::Off,
        }
    }
}

impl SceneArgs {
    /// The evaluator's settings with this scene.
    fn config(&self) -> FieldTable3Config {
        FieldTable3Config {
            preset: self.preset.clone(),
            seed: self.seed,
            train_views: self.train_views,
            pair_perturbation: Perturbation {
                kind: PerturbKind::UniformBall,
                translation_m: self.pair_translation_m,
                rotation_deg: self.pair_rotation_deg,
            },
            ..FieldTable3Config::default()
        }
    }
}

/// Runs `matloc match`.
pub fn run(args: &MatchArgs, quiet: bool) -> Result<()> {
    match &args.command {
        MatchCommand::Pairs { scene: s, out } => {
            let config = s.config();
            let sc = table3_field::field_scene(&config)?;
            let t0 = Instant::now();
            let set = table3_field::field_pairs(&sc, &config, s.seed)?;
            set.save(out)?;
            let kept: usize = set.provenance.renders.iter().map(|r| r.counts.kept).sum();
            let surface: usize = set
                .provenance
                .renders
                .iter()
                .map(|r| r.counts.surface)
                .sum();
            outln!(
                "{} pairs from {} views ({:.0} % of rendered surface cells) in {:.1} s -> {}",
                set.len(),
                sc.train.len(),
                100.0 * kept as f64 / surface.max(1) as f64,
                t0.elapsed().as_secs_f64(),
                out.display()
            )?;
            Ok(())
        }
        MatchCommand::Eval(e) => match (&e.map, &e.data) {
            (Some(map), Some(data)) => eval_map(e, map, data, quiet),
            _ => eval(e, quiet),
        },
    }
}

/// Table 3 on a built map ([`matloc_pipeline::eval::table3`]).
fn eval_map(
    args: &EvalArgs,
    map: &std::path::Path,
    data: &std::path::Path,
    quiet: bool,
) -> Result<()> {
    let dataset = matloc_data::read_dataset(data)
        .with_context(|| format!("reading the dataset {}", data.display()))?;
    let loaded = matloc_pipeline::LoadedMap::open(map)
        .with_context(|| format!("opening the map {}", map.display()))?;
    let config = matloc_pipeline::eval::table3::Table3Config {
        start: Perturbation {
            kind: PerturbKind::UniformBall,
            translation_m: args.query_translation_m,
            rotation_deg: args.query_rotation_deg,
        },
        starts_per_query: args.starts,
        seed: args.scene.seed,
        own_encoder_sets: args.own_encoder.clone(),
        ratio: args.ratio,
        render_scores: args
            .render_select
            .iter()
            .map(|r| match r {
                RenderSelectArg::F1 => {
                    matloc_pipeline::config::RenderScore::MatchF1 { tol_px: 4.0 }
                }
                RenderSelectArg::Pnp => matloc_pipeline::config::RenderScore::SinglePass,
            })
            .collect(),
        ..Default::default()
    };
    let t0 = Instant::now();
    let bar = progress::bar(0, "", quiet);
    let table = matloc_pipeline::eval::table3::evaluate(
        &loaded,
        &dataset,
        &config,
        &mut |stage, done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
            bar.set_message(stage.to_string());
        },
    )?;
    bar.finish_and_clear();
    outln!(
        "map {}: {} test queries x {} starts ({} in all), start perturbation uniform ball {} m / {} deg (median start error {:.2} m / {:.2} deg); the map's encoder, matching window and localizer options, every pose kept ({:.0} s)",
        map.display(),
        table.queries,
        config.starts_per_query,
        table.starts,
        config.start.translation_m,
        config.start.rotation_deg,
        table.start_t_m,
        table.start_r_deg,
        t0.elapsed().as_secs_f64()
    )?;
    for r in &table.rows {
        outln!("{}: dims per block {:?}", r.name, r.dims)?;
    }
    out!("{}", matloc_pipeline::eval::table3::markdown(&table))?;
    outln!()?;
    out!("{}", matloc_pipeline::eval::table3::paired_markdown(&table))?;
    if let Some(path) = &args.json {
        matloc_core::fsutil::write_atomic(path, serde_json::to_string_pretty(&table)?.as_bytes())?;
    }
    Ok(())
}

/// Table 3 on the analytic feature field ([`matloc_pipeline::eval::table3_field`]).
fn eval(args: &EvalArgs, quiet: bool) -> Result<()> {
    let (w_reg, w_nce) = args
        .encoder_loss
        .split_once(',')
        .and_then(|(a, b)| Some((a.trim().parse().ok()?, b.trim().parse().ok()?)))
        .context("--encoder-loss must be `w_reg,w_nce`")?;
    let base: EncoderTrainConfig = match &args.encoder_config {
        Some(j) => serde_json::from_str(j).context("--encoder-config")?,
        None => EncoderTrainConfig::default(),
    };
    let config = FieldTable3Config {
        query_source: match args.query {
            QuerySource::Oracle => table3_field::QuerySource::Oracle,
            QuerySource::Encoder => table3_field::QuerySource::Encoder,
        },
        encoder_train: EncoderTrainConfig {
            steps: args.encoder_steps,
            w_reg,
            w_nce,
            ..base
        },
        start: Perturbation {
            kind: PerturbKind::UniformBall,
            translation_m: args.query_translation_m,
            rotation_deg: args.query_rotation_deg,
        },
        starts: args.starts,
        subcell: args.subcell.side(),
        window_px: args.window_px,
        pnp_threshold_cells: args.pnp_threshold_cells,
        ..args.scene.config()
    };
    let bar = progress::bar(0, "", quiet);
    let (table, encoder) = table3_field::evaluate(&config, &mut |stage, done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        bar.set_message(stage.to_string());
    })?;
    bar.finish_and_clear();
    if let (Some(path), Some(enc)) = (&args.encoder_out, &encoder) {
        enc.save(path)?;
    }
    out!("{}", table3_field::markdown(&table))?;
    if let Some(path) = &args.json {
        matloc_core::fsutil::write_atomic(path, serde_json::to_string_pretty(&table)?.as_bytes())?;
    }
    Ok(())
}
