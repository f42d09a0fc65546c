//! `matloc match`: ground-truth pair generation and the paper's Table 3 (feature sets × matching
//! time, match precision, pose error after PnP) on the synthetic world.
//!
//! The map side is the synthetic world's exact geometry seen through the analytic feature field
//! of `matloc_match::synth_view` (47 dims laid out like the NeRF's 32 positional + 15 MLP
//! features), so the table isolates matching, selection and the query encoder from NeRF quality.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand, ValueEnum};
use matloc_core::metrics::{median, rotation_error_deg, translation_error_m};
use matloc_core::{Camera, FeatureMap, Image, Pose};
use matloc_data::dataset::Split;
use matloc_data::synth::{RenderOptions, SynthConfig, World, plan_survey};
use matloc_match::encoder::{
    ENCODER_STRIDE, EncoderSample, EncoderTrainConfig, QueryEncoder, train_encoder,
};
use matloc_match::featuremetric::{FeatureMetricConfig, refine_pose};
use matloc_match::gt::{
    GtConfig, GtPairSet, PerturbKind, Perturbation, TrainingView, ViewRenderer, generate_pairs,
};
use matloc_match::localize::{
    correct_matches, render_map_points, solve_pose, solve_pose_within, timed_match,
};
use matloc_match::synth_view::{SynthFeatureField, SynthFeatureRenderer, SynthFieldConfig};
use matloc_match::{
    FeatureStats, Matcher, MnnConfig, MnnMatcher, QueryFeatures, SubcellConfig, SubcellSide,
};
use matloc_pnp::LoRansacPnp;
use matloc_select::{FeatureSelector, MatchingSelector, PairSet, PaperBipSelector, RandomSelector};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

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

    fn name(self) -> &'static str {
        match self {
            SubcellArg::Map => "map",
            SubcellArg::Query => "query",
            SubcellArg::Off => "off",
        }
    }
}

struct Scene {
    renderer: SynthFeatureRenderer,
    train: Vec<TrainingView>,
    test: Vec<TrainingView>,
    render_opts: RenderOptions,
}

fn scene(args: &SceneArgs) -> Result<Scene> {
    let cfg = SynthConfig::preset(&args.preset)?.with_seed(args.seed);
    let world = World::generate(&cfg.world, cfg.seed)?;
    let plan = plan_survey(&world, &cfg.survey, cfg.seed)?;
    let views = |split: Split| -> Vec<TrainingView> {
        plan.frames
            .iter()
            .enumerate()
            .filter(|(_, f)| f.split == split)
            .map(|(i, f)| TrainingView {
                index: i,
                camera: f.camera,
                cam_from_world: f.cam_from_world,
            })
            .collect()
    };
    let all_train = views(Split::Train);
    let n = args.train_views.clamp(1, all_train.len().max(1));
    let step = all_train.len() as f64 / n as f64;
    let train = (0..n)
        .map(|k| all_train[((k as f64 + 0.5) * step) as usize].clone())
        .collect();
    let field = SynthFeatureField::new(SynthFieldConfig::default());
    Ok(Scene {
        renderer: SynthFeatureRenderer::new(world, field),
        train,
        test: views(Split::Test),
        render_opts: cfg.render,
    })
}

fn gt_config(args: &SceneArgs) -> GtConfig {
    GtConfig {
        perturbation: Perturbation {
            kind: PerturbKind::UniformBall,
            translation_m: args.pair_translation_m,
            rotation_deg: args.pair_rotation_deg,
        },
        ..GtConfig::default()
    }
}

/// Runs `matloc match`.
pub fn run(args: &MatchArgs, quiet: bool) -> Result<()> {
    match &args.command {
        MatchCommand::Pairs { scene: s, out } => {
            let sc = scene(s)?;
            let t0 = Instant::now();
            let set = generate_pairs(&sc.renderer, &sc.train, &gt_config(s), s.seed)?;
            set.save(out)?;
            let kept: usize = set.provenance.renders.iter().map(|r| r.counts.kept).sum();
            let surface: usize = set
                .provenance
                .renders
                .iter()
                .map(|r| r.counts.surface)
                .sum();
            println!(
                "{} pairs from {} views ({:.0} % of rendered surface cells) in {:.1} s -> {}",
                set.len(),
                sc.train.len(),
                100.0 * kept as f64 / surface.max(1) as f64,
                t0.elapsed().as_secs_f64(),
                out.display()
            );
            Ok(())
        }
        MatchCommand::Eval(e) => match (&e.map, &e.data) {
            (Some(map), Some(data)) => eval_map(e, map, data, quiet),
            _ => eval(e, quiet),
        },
    }
}

/// Table 3 on a built map ([`matloc_pipeline::table3`]).
fn eval_map(
    args: &EvalArgs,
    map: &std::path::Path,
    data: &std::path::Path,
    quiet: bool,
) -> Result<()> {
    let dataset = matloc_data::read_dataset(data)
        .with_context(|| format!("reading the dataset {}", data.display()))?;
    let loaded = matloc_pipeline::stages::LoadedMap::open(map)
        .with_context(|| format!("opening the map {}", map.display()))?;
    let config = matloc_pipeline::table3::Table3Config {
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
                    matloc_pipeline::render_select::RenderScore::MatchF1 { tol_px: 4.0 }
                }
                RenderSelectArg::Pnp => matloc_pipeline::render_select::RenderScore::SinglePass,
            })
            .collect(),
        ..Default::default()
    };
    let t0 = Instant::now();
    let bar = progress::bar(0, "", quiet);
    let table = matloc_pipeline::table3::evaluate(
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
    println!(
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
    );
    for r in &table.rows {
        println!("{}: dims per block {:?}", r.name, r.dims);
    }
    print!("{}", matloc_pipeline::table3::markdown(&table));
    println!();
    print!("{}", matloc_pipeline::table3::paired_markdown(&table));
    if let Some(path) = &args.json {
        matloc_data::fsutil::write_atomic(path, serde_json::to_string_pretty(&table)?.as_bytes())?;
    }
    Ok(())
}

fn rgb(sc: &Scene, v: &TrainingView) -> Image<f32> {
    sc.renderer
        .world()
        .render(&v.camera, &v.cam_from_world, &sc.render_opts)
        .rgb
}

/// Query feature maps (all dims) of views: the encoder's output or the oracle render.
fn query_maps(
    sc: &Scene,
    views: &[TrainingView],
    encoder: Option<&QueryEncoder>,
    dims: &[usize],
) -> Result<Vec<FeatureMap>> {
    views
        .iter()
        .map(|v| match encoder {
            Some(enc) => Ok(enc.encode(&rgb(sc, v))?),
            None => {
                let r = sc
                    .renderer
                    .render_view(&v.camera, &v.cam_from_world, ENCODER_STRIDE, dims)
                    .map_err(|e| anyhow::anyhow!(e))?;
                Ok(FeatureMap::from_vec(
                    r.cols,
                    r.rows,
                    dims.len(),
                    r.features,
                )?)
            }
        })
        .collect()
}

struct Row {
    name: String,
    dims: Vec<usize>,
    match_ms: Vec<f64>,
    precision: Vec<f64>,
    matches: Vec<f64>,
    t_err: Vec<f64>,
    r_err: Vec<f64>,
    /// Errors after feature-metric refinement of the PnP pose on all dims (the pipeline's
    /// step after PnP; matching still uses the row's dims).
    t_ref: Vec<f64>,
    r_ref: Vec<f64>,
    failures: usize,
}

fn eval(args: &EvalArgs, quiet: bool) -> Result<()> {
    let sc = scene(&args.scene)?;
    if sc.test.is_empty() {
        bail!("preset {} has no test views", args.scene.preset);
    }
    let nd = sc.renderer.num_features();
    let all: Vec<usize> = (0..nd).collect();
    println!(
        "scene: preset {} seed {}, {} train views, {} test views, {} feature dims",
        args.scene.preset,
        args.scene.seed,
        sc.train.len(),
        sc.test.len(),
        nd
    );

    // Map statistics: features rendered at the training poses.
    let mut targets = Vec::new();
    let mut stat_rows = Vec::new();
    for v in &sc.train {
        let r = sc
            .renderer
            .render_view(&v.camera, &v.cam_from_world, ENCODER_STRIDE, &all)
            .map_err(|e| anyhow::anyhow!(e))?;
        for i in 0..r.cols * r.rows {
            if r.has_surface(i, 0.5) {
                stat_rows.extend_from_slice(&r.features[i * nd..(i + 1) * nd]);
            }
        }
        targets.push(r);
    }
    let stats = FeatureStats::from_features(&stat_rows, nd);

    // Query encoder.
    let encoder = match args.query {
        QuerySource::Oracle => None,
        QuerySource::Encoder => {
            let (w_reg, w_nce) = args
                .encoder_loss
                .split_once(',')
                .and_then(|(a, b)| Some((a.trim().parse().ok()?, b.trim().parse().ok()?)))
                .context("--encoder-loss must be `w_reg,w_nce`")?;
            let samples: Vec<EncoderSample> = sc
                .train
                .iter()
                .zip(targets)
                .map(|(v, t)| EncoderSample {
                    image: rgb(&sc, v),
                    target: t,
                })
                .collect();
            let base: EncoderTrainConfig = match &args.encoder_config {
                Some(j) => serde_json::from_str(j).context("--encoder-config")?,
                None => EncoderTrainConfig::default(),
            };
            let cfg = EncoderTrainConfig {
                steps: args.encoder_steps,
                w_reg,
                w_nce,
                seed: args.scene.seed,
                ..base
            };
            let bar = progress::bar(cfg.total_steps() as u64, "encoder", quiet);
            let t0 = Instant::now();
            let mut last = None;
            let enc = train_encoder(&samples, all.clone(), stats.clone(), &cfg, &mut |p| {
                bar.set_position(p.step as u64);
                bar.set_message(format!("loss {:.3}", p.loss));
                last = Some(*p);
            })?;
            bar.finish_and_clear();
            if let Some(p) = last {
                println!(
                    "encoder: {} + {} head steps (w_reg {w_reg}, w_nce {w_nce}) in {:.0} s, final loss {:.3} (mse {:.3}, nce {:.3})",
                    cfg.steps,
                    cfg.head_phase.steps,
                    t0.elapsed().as_secs_f64(),
                    p.loss,
                    p.mse,
                    p.nce
                );
            }
            if let Some(path) = &args.encoder_out {
                enc.save(path)?;
            }
            Some(enc)
        }
    };

    // Ground-truth pairs and selection on the encoder's features at the pairs' query cells.
    let t0 = Instant::now();
    let gt: GtPairSet = generate_pairs(&sc.renderer, &sc.train, &gt_config(&args.scene), 1)?;
    println!(
        "GT pairs: {} from {} perturbed renders ({:.1} s)",
        gt.len(),
        gt.provenance.renders.len(),
        t0.elapsed().as_secs_f64()
    );
    let train_maps = query_maps(&sc, &sc.train, encoder.as_ref(), &all)?;
    let mut qf = Vec::with_capacity(gt.len() * nd);
    for p in 0..gt.len() {
        let r = &gt.provenance.renders[gt.render[p] as usize];
        let k = sc
            .train
            .iter()
            .position(|v| v.index == r.view.index)
            .context("render of an unknown view")?;
        let q = gt.query_index[p] as usize;
        let m = &train_maps[k];
        qf.extend_from_slice(m.pixel(q % m.width(), q / m.width()));
    }
    let pairs = PairSet::from_gt(&gt, Some(qf))?;
    let mut rng = ChaCha8Rng::seed_from_u64(args.scene.seed);
    let greedy = MatchingSelector::default();
    let mut sets: Vec<(String, Vec<usize>)> = vec![
        ("all-47".into(), all.clone()),
        ("pos-32".into(), (0..32.min(nd)).collect()),
        ("mlp-15".into(), (32.min(nd)..nd).collect()),
    ];
    for (name, sel, n_s) in [
        ("greedy N_s=10", &greedy as &dyn FeatureSelector, 10),
        ("greedy N_s=5", &greedy, 5),
        ("paper-BIP N_s=10", &PaperBipSelector::default(), 10),
        ("random-5", &RandomSelector::default(), 5),
    ] {
        let t = Instant::now();
        let s = sel.select(&pairs, n_s, &mut rng)?;
        println!(
            "{name}: dims {:?} ({:.1} s, objective {:.4})",
            s.dims,
            t.elapsed().as_secs_f64(),
            s.report.objective
        );
        sets.push((name.into(), s.dims));
    }

    // Test queries from perturbed true poses.
    let perturb = Perturbation {
        kind: PerturbKind::UniformBall,
        translation_m: args.query_translation_m,
        rotation_deg: args.query_rotation_deg,
    };
    let matcher = MnnMatcher::new(MnnConfig {
        stats: Some(stats.clone()),
        subcell: SubcellConfig {
            side: args.subcell.side(),
            ..Default::default()
        },
        window_px: args.window_px,
        ..Default::default()
    });
    let solver = LoRansacPnp::default();
    let fm = FeatureMetricConfig::default();
    let test_maps = query_maps(&sc, &sc.test, encoder.as_ref(), &all)?;
    let mut rows: Vec<Row> = sets
        .iter()
        .map(|(n, d)| Row {
            name: n.clone(),
            dims: d.clone(),
            match_ms: vec![],
            precision: vec![],
            matches: vec![],
            t_err: vec![],
            r_err: vec![],
            t_ref: vec![],
            r_ref: vec![],
            failures: 0,
        })
        .collect();
    let mut start_t = Vec::new();
    let mut start_r = Vec::new();
    let bar = progress::bar((sc.test.len() * args.starts) as u64, "queries", quiet);
    for (v, qmap) in sc.test.iter().zip(&test_maps) {
        let query = QueryFeatures::new(qmap.clone(), ENCODER_STRIDE as f64);
        for s in 0..args.starts {
            let mut prng = ChaCha8Rng::seed_from_u64(1000 + args.scene.seed);
            prng.set_stream((v.index * 64 + s) as u64);
            let coarse: Pose = perturb.apply(&v.cam_from_world, &mut prng);
            start_t.push(translation_error_m(&coarse, &v.cam_from_world));
            start_r.push(rotation_error_deg(&coarse, &v.cam_from_world));
            let map =
                render_map_points(&sc.renderer, &v.camera, &coarse, ENCODER_STRIDE, &all, 0.5)?;
            for row in rows.iter_mut() {
                let tm = timed_match(&matcher, &query, &map, Some(&row.dims))?;
                row.match_ms.push(tm.elapsed.as_secs_f64() * 1e3);
                let n = tm.matches.len();
                row.matches.push(n as f64);
                let ok = correct_matches(&tm.matches, &v.camera, &v.cam_from_world, 2.0);
                row.precision
                    .push(if n == 0 { 0.0 } else { ok as f64 / n as f64 });
                let mut srng = ChaCha8Rng::seed_from_u64(7);
                let threshold_px = args.pnp_threshold_cells * ENCODER_STRIDE as f64;
                let solved = solve_pose_within(
                    &tm.matches,
                    &v.camera,
                    &solver,
                    Some(threshold_px),
                    &mut srng,
                );
                // A failed solve keeps the coarse pose: its error counts.
                let pnp = solved.as_ref().map_or(coarse, |r| r.cam_from_world);
                if solved.is_err() {
                    row.failures += 1;
                }
                row.t_err.push(translation_error_m(&pnp, &v.cam_from_world));
                row.r_err.push(rotation_error_deg(&pnp, &v.cam_from_world));
                let refined = if solved.is_ok() {
                    let (stats, l2) = matcher.feature_space();
                    refine_pose(&query, &map, &v.camera, &pnp, None, stats, l2, &fm)
                        .map_or(pnp, |o| o.cam_from_world)
                } else {
                    pnp
                };
                row.t_ref
                    .push(translation_error_m(&refined, &v.cam_from_world));
                row.r_ref
                    .push(rotation_error_deg(&refined, &v.cam_from_world));
            }
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    let med = |v: &[f64]| median(v).unwrap_or(f64::NAN);
    let cam: &Camera = &sc.test[0].camera;
    println!(
        "queries: {} test views x {} starts; query {}x{} px, grid {}x{}; sub-cell refinement {}, window {}; start perturbation uniform ball {} m / {} deg (median start error {:.2} m / {:.2} deg)",
        sc.test.len(),
        args.starts,
        cam.width,
        cam.height,
        cam.width / ENCODER_STRIDE,
        cam.height / ENCODER_STRIDE,
        args.subcell.name(),
        args.window_px
            .map_or("whole image".to_string(), |w| format!("{w} px")),
        args.query_translation_m,
        args.query_rotation_deg,
        med(&start_t),
        med(&start_r)
    );
    println!(
        "PnP inlier threshold {} cells; refined = feature-metric refinement of the PnP pose on all {nd} dims",
        args.pnp_threshold_cells
    );
    println!(
        "| feature set | dims | matching time (ms, median) | matches | precision (<= 2 px) | median t err (m) | median R err (deg) | refined: median t / R | PnP failures |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut json = Vec::new();
    for r in &rows {
        println!(
            "| {} | {} | {:.2} | {:.0} | {:.3} | {:.3} | {:.3} | {:.3} / {:.3} | {}/{} |",
            r.name,
            r.dims.len(),
            med(&r.match_ms),
            med(&r.matches),
            r.precision.iter().sum::<f64>() / r.precision.len().max(1) as f64,
            med(&r.t_err),
            med(&r.r_err),
            med(&r.t_ref),
            med(&r.r_ref),
            r.failures,
            r.t_err.len()
        );
        json.push(serde_json::json!({
            "set": r.name, "dims": r.dims, "match_ms_median": med(&r.match_ms),
            "matches_median": med(&r.matches),
            "precision_mean": r.precision.iter().sum::<f64>() / r.precision.len().max(1) as f64,
            "t_err_median_m": med(&r.t_err), "r_err_median_deg": med(&r.r_err),
            "refined_t_err_median_m": med(&r.t_ref), "refined_r_err_median_deg": med(&r.r_ref),
            "failures": r.failures, "queries": r.t_err.len(),
        }));
    }
    // Fit vs generalisation: matching from the true pose on training and test views.
    println!(
        "from the true pose (fit vs generalisation): | feature set | train precision | train inliers | test precision | test inliers |"
    );
    println!("|---|---|---|---|---|");
    let mut truth_json = Vec::new();
    let truth_maps = |views: &[TrainingView]| -> Result<Vec<_>> {
        views
            .iter()
            .map(|v| {
                Ok(render_map_points(
                    &sc.renderer,
                    &v.camera,
                    &v.cam_from_world,
                    ENCODER_STRIDE,
                    &all,
                    0.5,
                )?)
            })
            .collect()
    };
    let train_truth = truth_maps(&sc.train)?;
    let test_truth = truth_maps(&sc.test)?;
    for r in &rows {
        let mut cells = Vec::new();
        for (views, qmaps, maps) in [
            (&sc.train, &train_maps, &train_truth),
            (&sc.test, &test_maps, &test_truth),
        ] {
            let (mut prec, mut inl) = (Vec::new(), Vec::new());
            for ((v, q), m) in views.iter().zip(qmaps).zip(maps) {
                let query = QueryFeatures::new(q.clone(), ENCODER_STRIDE as f64);
                let tm = timed_match(&matcher, &query, m, Some(&r.dims))?;
                let n = tm.matches.len();
                let ok = correct_matches(&tm.matches, &v.camera, &v.cam_from_world, 2.0);
                prec.push(if n == 0 { 0.0 } else { ok as f64 / n as f64 });
                let mut srng = ChaCha8Rng::seed_from_u64(7);
                inl.push(
                    solve_pose(&tm.matches, &v.camera, &solver, &mut srng)
                        .map_or(0.0, |res| res.inliers.iter().filter(|&&b| b).count() as f64),
                );
            }
            let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
            cells.push((mean(&prec), med(&inl)));
        }
        println!(
            "| {} | {:.3} | {:.0} | {:.3} | {:.0} |",
            r.name, cells[0].0, cells[0].1, cells[1].0, cells[1].1
        );
        truth_json.push(serde_json::json!({
            "set": r.name, "train_precision_mean": cells[0].0, "train_inliers_median": cells[0].1,
            "test_precision_mean": cells[1].0, "test_inliers_median": cells[1].1,
        }));
    }
    if let Some(path) = &args.json {
        let doc = serde_json::json!({
            "preset": args.scene.preset, "seed": args.scene.seed,
            "query_source": match args.query { QuerySource::Oracle => "oracle", QuerySource::Encoder => "encoder" },
            "subcell": args.subcell.name(), "window_px": args.window_px,
            "pnp_threshold_cells": args.pnp_threshold_cells,
            "start_t_median_m": med(&start_t), "start_r_median_deg": med(&start_r),
            "rows": json, "from_true_pose": truth_json,
        });
        matloc_data::fsutil::write_atomic(path, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    }
    Ok(())
}
