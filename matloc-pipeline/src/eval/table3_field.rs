//! The paper's Table 3 (feature sets × matching time, match precision, pose error after PnP)
//! on the synthetic world's analytic feature field.
//!
//! The map side is the synthetic world's exact geometry seen through
//! [`matloc_synth::oracle::SynthFeatureField`] (47 dims laid out like the NeRF's 32
//! positional and 15 MLP features), so the table isolates matching, selection and the query
//! encoder from NeRF quality; [`crate::eval::table3`] measures the same on a built map. Query
//! features are either rendered at the true pose (an oracle: a perfect encoder) or come from a
//! CNN encoder trained here on the training views.

use std::time::Instant;

use matloc_core::metrics::{median, rotation_error_deg, translation_error_m};
use matloc_core::{FeatureMap, Image, Pose};
use matloc_data::Split;
use matloc_encoder::{
    ENCODER_STRIDE, EncoderSample, EncoderTrainConfig, QueryEncoder, train_encoder,
};
use matloc_match::featuremetric::{FeatureMetricConfig, refine_pose};
use matloc_match::localize::{
    correct_matches, render_map_points, solve_pose, solve_pose_within, timed_match,
};
use matloc_match::{
    FeatureStats, Matcher, MnnConfig, MnnMatcher, QueryFeatures, RenderedPoints, SubcellConfig,
    SubcellSide, ViewRenderer,
};
use matloc_pnp::LoRansacPnp;
use matloc_select::{FeatureSelector, MatchingSelector, PaperBipSelector, RandomSelector};
use matloc_synth::oracle::{SynthFeatureField, SynthFeatureRenderer, SynthFieldConfig};
use matloc_synth::{RenderOptions, SynthConfig, World, plan_survey};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::error::PipelineError;
use crate::gt::{GtConfig, GtPairSet, PerturbKind, Perturbation, TrainingView, generate_pairs};

/// Where the query features come from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum QuerySource {
    /// Features rendered at the query's true pose (upper bound: a perfect encoder).
    Oracle,
    /// A CNN encoder trained on the training views.
    #[default]
    Encoder,
}

/// Settings of the evaluation: the scene, the query side and the matching/PnP options.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FieldTable3Config {
    /// Synthetic preset (`matloc_synth::PRESET_NAMES`).
    pub preset: String,
    /// World and survey seed; also seeds the encoder, the selection and the starts.
    pub seed: u64,
    /// Use at most this many training views (evenly spaced; at least 1).
    pub train_views: usize,
    /// Perturbation of the training poses for ground-truth pair generation.
    pub pair_perturbation: Perturbation,
    /// Where the query features come from.
    pub query_source: QuerySource,
    /// Encoder training (with [`QuerySource::Encoder`]); its `seed` is replaced by
    /// [`Self::seed`].
    pub encoder_train: EncoderTrainConfig,
    /// Start poses: the test views' true poses perturbed by this.
    pub start: Perturbation,
    /// Perturbed starts per test view (at least 1).
    pub starts: usize,
    /// Sub-cell refinement of the matches.
    pub subcell: SubcellSide,
    /// Match only cells within this many pixels of each other (`None`: the whole image).
    pub window_px: Option<f64>,
    /// RANSAC inlier threshold of the test-query PnP, in query cells.
    pub pnp_threshold_cells: f64,
}

impl Default for FieldTable3Config {
    fn default() -> Self {
        Self {
            preset: "tiny".into(),
            seed: 0,
            train_views: 24,
            pair_perturbation: Perturbation {
                kind: PerturbKind::UniformBall,
                translation_m: 2.0,
                rotation_deg: 3.0,
            },
            query_source: QuerySource::Encoder,
            encoder_train: EncoderTrainConfig::default(),
            start: Perturbation {
                kind: PerturbKind::UniformBall,
                translation_m: 3.0,
                rotation_deg: 5.0,
            },
            starts: 3,
            subcell: SubcellSide::Map,
            window_px: None,
            pnp_threshold_cells: 3.0,
        }
    }
}

/// The synthetic world behind the analytic feature field, with its training views (the
/// evenly spaced subset) and test views.
#[derive(Clone, Debug)]
pub struct FieldScene {
    /// The world seen through the analytic feature field.
    pub renderer: SynthFeatureRenderer,
    /// Training views used (map statistics, encoder training, GT pairs).
    pub train: Vec<TrainingView>,
    /// Test views (the queries).
    pub test: Vec<TrainingView>,
    /// RGB render settings of the preset.
    pub render_opts: RenderOptions,
}

impl FieldScene {
    /// The RGB image of a view (the encoder's input).
    pub fn rgb(&self, v: &TrainingView) -> Image<f32> {
        self.renderer
            .world()
            .render(&v.camera, &v.cam_from_world, &self.render_opts)
            .rgb
    }
}

/// Builds the scene of `config.preset` / `config.seed` with at most `config.train_views`
/// evenly spaced training views.
pub fn field_scene(config: &FieldTable3Config) -> Result<FieldScene, PipelineError> {
    let cfg = SynthConfig::preset(&config.preset)?.with_seed(config.seed);
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
    if all_train.is_empty() {
        return Err(PipelineError::Config(format!(
            "preset {} has no training views",
            config.preset
        )));
    }
    let n = config.train_views.clamp(1, all_train.len());
    let step = all_train.len() as f64 / n as f64;
    let train = (0..n)
        .map(|k| all_train[((k as f64 + 0.5) * step) as usize].clone())
        .collect();
    let field = SynthFeatureField::new(SynthFieldConfig::default());
    Ok(FieldScene {
        renderer: SynthFeatureRenderer::new(world, field),
        train,
        test: views(Split::Test),
        render_opts: cfg.render,
    })
}

/// Ground-truth pair settings: the defaults with `config.pair_perturbation`.
pub fn field_gt_config(config: &FieldTable3Config) -> GtConfig {
    GtConfig {
        perturbation: config.pair_perturbation.clone(),
        ..GtConfig::default()
    }
}

/// Ground-truth 2D–3D pairs from the scene's perturbed training poses.
pub fn field_pairs(
    scene: &FieldScene,
    config: &FieldTable3Config,
    seed: u64,
) -> Result<GtPairSet, PipelineError> {
    Ok(generate_pairs(
        &scene.renderer,
        &scene.train,
        &field_gt_config(config),
        seed,
    )?)
}

/// The scene the table was measured on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldSceneSummary {
    /// Training views used.
    pub train_views: usize,
    /// Test views.
    pub test_views: usize,
    /// Feature dims of the field.
    pub dims: usize,
    /// Query image width, pixels.
    pub image_width: u32,
    /// Query image height, pixels.
    pub image_height: u32,
    /// Query grid columns (stride [`ENCODER_STRIDE`]).
    pub grid_cols: u32,
    /// Query grid rows.
    pub grid_rows: u32,
}

/// The trained query encoder's run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EncoderSummary {
    /// End-to-end steps.
    pub steps: usize,
    /// Head-only steps.
    pub head_steps: usize,
    /// Regression weight.
    pub w_reg: f32,
    /// InfoNCE weight.
    pub w_nce: f32,
    /// Training wall time, seconds.
    pub seconds: f64,
    /// Total loss of the last step.
    pub loss: f32,
    /// Regression term of the last step.
    pub mse: f32,
    /// InfoNCE term of the last step.
    pub nce: f32,
}

/// The ground-truth pairs the selectors scored dims on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GtSummary {
    /// Pairs.
    pub pairs: usize,
    /// Perturbed renders they came from.
    pub renders: usize,
    /// Generation wall time, seconds.
    pub seconds: f64,
}

/// One selector's choice.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SelectionSummary {
    /// Feature set name.
    pub name: String,
    /// Selected dims.
    pub dims: Vec<usize>,
    /// Selection wall time, seconds.
    pub seconds: f64,
    /// The selector's objective.
    pub objective: f64,
}

/// One feature set matched from the perturbed starts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldTable3Row {
    /// Feature set name.
    #[serde(rename = "set")]
    pub name: String,
    /// Dims matched.
    pub dims: Vec<usize>,
    /// Median wall time of one match, milliseconds.
    pub match_ms_median: f64,
    /// Median matches.
    pub matches_median: f64,
    /// Mean fraction of matches within 2 px of their true projection.
    pub precision_mean: f64,
    /// Median translation error after PnP, metres (a failed solve keeps the start).
    pub t_err_median_m: f64,
    /// Median rotation error after PnP, degrees.
    pub r_err_median_deg: f64,
    /// Median translation error after feature-metric refinement of the PnP pose on all dims.
    pub refined_t_err_median_m: f64,
    /// Median rotation error after that refinement, degrees.
    pub refined_r_err_median_deg: f64,
    /// Starts where PnP found no pose.
    pub failures: usize,
    /// Starts in all.
    pub queries: usize,
}

/// One feature set matched from the true pose: how well matching fits the training views
/// against how it generalises to the test views.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FromTruePoseRow {
    /// Feature set name.
    #[serde(rename = "set")]
    pub name: String,
    /// Mean match precision on the training views.
    pub train_precision_mean: f64,
    /// Median PnP inliers on the training views.
    pub train_inliers_median: f64,
    /// Mean match precision on the test views.
    pub test_precision_mean: f64,
    /// Median PnP inliers on the test views.
    pub test_inliers_median: f64,
}

/// The table and the conditions it was measured under.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldTable3 {
    /// The settings.
    #[serde(flatten)]
    pub config: FieldTable3Config,
    /// The scene.
    pub scene: FieldSceneSummary,
    /// The encoder's run (`None` for oracle queries or when no step ran).
    pub encoder: Option<EncoderSummary>,
    /// The ground-truth pairs.
    pub gt: GtSummary,
    /// The selectors' choices, in row order.
    pub selections: Vec<SelectionSummary>,
    /// Median start translation error, metres.
    pub start_t_median_m: f64,
    /// Median start rotation error, degrees.
    pub start_r_median_deg: f64,
    /// Rows: all 47, positional 32, MLP 15, then the selections.
    pub rows: Vec<FieldTable3Row>,
    /// The same sets matched from the true pose.
    pub from_true_pose: Vec<FromTruePoseRow>,
}

/// Query feature maps (all dims) of views: the encoder's output or the oracle render.
fn query_maps(
    sc: &FieldScene,
    views: &[TrainingView],
    encoder: Option<&QueryEncoder>,
    dims: &[usize],
) -> Result<Vec<FeatureMap>, PipelineError> {
    views
        .iter()
        .map(|v| match encoder {
            Some(enc) => Ok(enc.encode(&sc.rgb(v))?),
            None => {
                let r = sc
                    .renderer
                    .render_view(&v.camera, &v.cam_from_world, ENCODER_STRIDE, dims)
                    .map_err(PipelineError::ViewRender)?;
                FeatureMap::from_vec(r.cols, r.rows, dims.len(), r.features)
                    .map_err(|e| PipelineError::ViewRender(Box::new(e)))
            }
        })
        .collect()
}

/// Per-start measurements of one feature set.
struct Acc {
    name: String,
    dims: Vec<usize>,
    match_ms: Vec<f64>,
    precision: Vec<f64>,
    matches: Vec<f64>,
    t_err: Vec<f64>,
    r_err: Vec<f64>,
    /// Errors after feature-metric refinement of the PnP pose on all dims (the pipeline's
    /// step after PnP; matching still uses the set's dims).
    t_ref: Vec<f64>,
    r_ref: Vec<f64>,
    failures: usize,
}

fn med(v: &[f64]) -> f64 {
    median(v).unwrap_or(f64::NAN)
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// Runs the evaluation. `progress(stage, done, total)` reports encoder training (stage
/// `"encoder, loss L"`, in steps), each selection, each start (stage `"queries"`) and each
/// feature set matched from the true pose. Returns the table and, with
/// [`QuerySource::Encoder`], the trained encoder.
pub fn evaluate(
    config: &FieldTable3Config,
    progress: &mut dyn FnMut(&str, usize, usize),
) -> Result<(FieldTable3, Option<QueryEncoder>), PipelineError> {
    if config.starts == 0 {
        return Err(PipelineError::Config(
            "at least one start per test view is needed".into(),
        ));
    }
    let sc = field_scene(config)?;
    if sc.test.is_empty() {
        return Err(PipelineError::Config(format!(
            "preset {} has no test views",
            config.preset
        )));
    }
    let nd = sc.renderer.num_features();
    let all: Vec<usize> = (0..nd).collect();
    let cam = &sc.test[0].camera;
    let scene = FieldSceneSummary {
        train_views: sc.train.len(),
        test_views: sc.test.len(),
        dims: nd,
        image_width: cam.width,
        image_height: cam.height,
        grid_cols: cam.width / ENCODER_STRIDE,
        grid_rows: cam.height / ENCODER_STRIDE,
    };

    // Map statistics: features rendered at the training poses.
    let mut targets = Vec::new();
    let mut stat_rows = Vec::new();
    for v in &sc.train {
        let r = sc
            .renderer
            .render_view(&v.camera, &v.cam_from_world, ENCODER_STRIDE, &all)
            .map_err(PipelineError::ViewRender)?;
        for i in 0..r.cols * r.rows {
            if r.has_surface(i, 0.5) {
                stat_rows.extend_from_slice(&r.features[i * nd..(i + 1) * nd]);
            }
        }
        targets.push(r);
    }
    let stats = FeatureStats::from_features(&stat_rows, nd);

    // Query encoder.
    let (encoder, encoder_summary) = match config.query_source {
        QuerySource::Oracle => (None, None),
        QuerySource::Encoder => {
            let samples: Vec<EncoderSample> = sc
                .train
                .iter()
                .zip(targets)
                .map(|(v, t)| EncoderSample {
                    image: sc.rgb(v),
                    target: t,
                    view: None,
                })
                .collect();
            let cfg = EncoderTrainConfig {
                seed: config.seed,
                ..config.encoder_train.clone()
            };
            let total = cfg.total_steps();
            let t0 = Instant::now();
            let mut last = None;
            let enc = train_encoder(&samples, all.clone(), stats.clone(), &cfg, &mut |p| {
                progress(&format!("encoder, loss {:.3}", p.loss), p.step, total);
                last = Some(*p);
            })?;
            let summary = last.map(|p| EncoderSummary {
                steps: cfg.steps,
                head_steps: cfg.head_phase.steps,
                w_reg: cfg.w_reg,
                w_nce: cfg.w_nce,
                seconds: t0.elapsed().as_secs_f64(),
                loss: p.loss,
                mse: p.mse,
                nce: p.nce,
            });
            (Some(enc), summary)
        }
    };

    // Ground-truth pairs and selection on the query features at the pairs' query cells.
    let t0 = Instant::now();
    let gt = field_pairs(&sc, config, 1)?;
    let gt_summary = GtSummary {
        pairs: gt.len(),
        renders: gt.provenance.renders.len(),
        seconds: t0.elapsed().as_secs_f64(),
    };
    let train_maps = query_maps(&sc, &sc.train, encoder.as_ref(), &all)?;
    let mut qf = Vec::with_capacity(gt.len() * nd);
    for p in 0..gt.len() {
        let r = &gt.provenance.renders[gt.render[p] as usize];
        let k = sc
            .train
            .iter()
            .position(|v| v.index == r.view.index)
            .ok_or(PipelineError::Internal(
                "GT pair rendered from an unknown view",
            ))?;
        let q = gt.query_index[p] as usize;
        let m = &train_maps[k];
        qf.extend_from_slice(m.pixel(q % m.width(), q / m.width()));
    }
    let pairs = gt.to_pair_set(Some(qf))?;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let greedy = MatchingSelector::default();
    let mut sets: Vec<(String, Vec<usize>)> = vec![
        ("all-47".into(), all.clone()),
        ("pos-32".into(), (0..32.min(nd)).collect()),
        ("mlp-15".into(), (32.min(nd)..nd).collect()),
    ];
    let selectors: [(&str, &dyn FeatureSelector, usize); 4] = [
        ("greedy N_s=10", &greedy, 10),
        ("greedy N_s=5", &greedy, 5),
        ("paper-BIP N_s=10", &PaperBipSelector::default(), 10),
        ("random-5", &RandomSelector::default(), 5),
    ];
    let n_selectors = selectors.len();
    let mut selections = Vec::with_capacity(n_selectors);
    for (k, (name, sel, n_s)) in selectors.into_iter().enumerate() {
        progress(&format!("select {name}"), k, n_selectors);
        let t = Instant::now();
        let s = sel.select(&pairs, n_s, &mut rng)?;
        selections.push(SelectionSummary {
            name: name.into(),
            dims: s.dims.clone(),
            seconds: t.elapsed().as_secs_f64(),
            objective: s.report.objective,
        });
        sets.push((name.into(), s.dims));
    }

    // Test queries from perturbed true poses.
    let matcher = MnnMatcher::new(MnnConfig {
        stats: Some(stats.clone()),
        subcell: SubcellConfig {
            side: config.subcell,
            ..Default::default()
        },
        window_px: config.window_px,
        ..Default::default()
    });
    let solver = LoRansacPnp::default();
    let fm = FeatureMetricConfig::default();
    let test_maps = query_maps(&sc, &sc.test, encoder.as_ref(), &all)?;
    let mut acc: Vec<Acc> = sets
        .iter()
        .map(|(n, d)| Acc {
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
    let total = sc.test.len() * config.starts;
    let mut done = 0;
    progress("queries", done, total);
    for (v, qmap) in sc.test.iter().zip(&test_maps) {
        let query = QueryFeatures::new(qmap.clone(), ENCODER_STRIDE as f64);
        for s in 0..config.starts {
            let mut prng = ChaCha8Rng::seed_from_u64(1000 + config.seed);
            prng.set_stream((v.index * 64 + s) as u64);
            let coarse: Pose = config.start.apply(&v.cam_from_world, &mut prng);
            start_t.push(translation_error_m(&coarse, &v.cam_from_world));
            start_r.push(rotation_error_deg(&coarse, &v.cam_from_world));
            let map =
                render_map_points(&sc.renderer, &v.camera, &coarse, ENCODER_STRIDE, &all, 0.5)?;
            for row in acc.iter_mut() {
                let tm = timed_match(&matcher, &query, &map, Some(&row.dims))?;
                row.match_ms.push(tm.elapsed.as_secs_f64() * 1e3);
                let n = tm.matches.len();
                row.matches.push(n as f64);
                let ok = correct_matches(&tm.matches, &v.camera, &v.cam_from_world, 2.0);
                row.precision
                    .push(if n == 0 { 0.0 } else { ok as f64 / n as f64 });
                let mut srng = ChaCha8Rng::seed_from_u64(7);
                let threshold_px = config.pnp_threshold_cells * ENCODER_STRIDE as f64;
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
            done += 1;
            progress("queries", done, total);
        }
    }

    // Fit vs generalisation: matching from the true pose on training and test views.
    let truth_maps = |views: &[TrainingView]| -> Result<Vec<RenderedPoints>, PipelineError> {
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
    let mut from_true_pose = Vec::with_capacity(acc.len());
    for (k, r) in acc.iter().enumerate() {
        progress("from the true pose", k, acc.len());
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
            cells.push((mean(&prec), med(&inl)));
        }
        from_true_pose.push(FromTruePoseRow {
            name: r.name.clone(),
            train_precision_mean: cells[0].0,
            train_inliers_median: cells[0].1,
            test_precision_mean: cells[1].0,
            test_inliers_median: cells[1].1,
        });
    }
    progress("from the true pose", acc.len(), acc.len());

    let rows = acc
        .into_iter()
        .map(|r| FieldTable3Row {
            match_ms_median: med(&r.match_ms),
            matches_median: med(&r.matches),
            precision_mean: mean(&r.precision),
            t_err_median_m: med(&r.t_err),
            r_err_median_deg: med(&r.r_err),
            refined_t_err_median_m: med(&r.t_ref),
            refined_r_err_median_deg: med(&r.r_ref),
            failures: r.failures,
            queries: r.t_err.len(),
            name: r.name,
            dims: r.dims,
        })
        .collect();
    let table = FieldTable3 {
        config: config.clone(),
        scene,
        encoder: encoder_summary,
        gt: gt_summary,
        selections,
        start_t_median_m: med(&start_t),
        start_r_median_deg: med(&start_r),
        rows,
        from_true_pose,
    };
    Ok((table, encoder))
}

fn subcell_name(side: SubcellSide) -> &'static str {
    match side {
        SubcellSide::Map => "map",
        SubcellSide::Query => "query",
        SubcellSide::Off => "off",
    }
}

/// The report as text: the scene, encoder, GT-pair and selection lines, the conditions of the
/// queries, the table from the perturbed starts and the from-true-pose table (markdown).
pub fn markdown(t: &FieldTable3) -> String {
    let c = &t.config;
    let sc = &t.scene;
    let mut s = format!(
        "scene: preset {} seed {}, {} train views, {} test views, {} feature dims\n",
        c.preset, c.seed, sc.train_views, sc.test_views, sc.dims
    );
    if let Some(e) = &t.encoder {
        s.push_str(&format!(
            "encoder: {} + {} head steps (w_reg {}, w_nce {}) in {:.0} s, final loss {:.3} (mse {:.3}, nce {:.3})\n",
            e.steps, e.head_steps, e.w_reg, e.w_nce, e.seconds, e.loss, e.mse, e.nce
        ));
    }
    s.push_str(&format!(
        "GT pairs: {} from {} perturbed renders ({:.1} s)\n",
        t.gt.pairs, t.gt.renders, t.gt.seconds
    ));
    for sel in &t.selections {
        s.push_str(&format!(
            "{}: dims {:?} ({:.1} s, objective {:.4})\n",
            sel.name, sel.dims, sel.seconds, sel.objective
        ));
    }
    s.push_str(&format!(
        "queries: {} test views x {} starts; query {}x{} px, grid {}x{}; sub-cell refinement {}, window {}; start perturbation uniform ball {} m / {} deg (median start error {:.2} m / {:.2} deg)\n",
        sc.test_views,
        c.starts,
        sc.image_width,
        sc.image_height,
        sc.grid_cols,
        sc.grid_rows,
        subcell_name(c.subcell),
        c.window_px
            .map_or("whole image".to_string(), |w| format!("{w} px")),
        c.start.translation_m,
        c.start.rotation_deg,
        t.start_t_median_m,
        t.start_r_median_deg
    ));
    s.push_str(&format!(
        "PnP inlier threshold {} cells; refined = feature-metric refinement of the PnP pose on all {} dims\n",
        c.pnp_threshold_cells, sc.dims
    ));
    s.push_str(
        "| feature set | dims | matching time (ms, median) | matches | precision (<= 2 px) | median t err (m) | median R err (deg) | refined: median t / R | PnP failures |\n|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in &t.rows {
        s.push_str(&format!(
            "| {} | {} | {:.2} | {:.0} | {:.3} | {:.3} | {:.3} | {:.3} / {:.3} | {}/{} |\n",
            r.name,
            r.dims.len(),
            r.match_ms_median,
            r.matches_median,
            r.precision_mean,
            r.t_err_median_m,
            r.r_err_median_deg,
            r.refined_t_err_median_m,
            r.refined_r_err_median_deg,
            r.failures,
            r.queries
        ));
    }
    s.push_str(
        "from the true pose (fit vs generalisation): | feature set | train precision | train inliers | test precision | test inliers |\n|---|---|---|---|---|\n",
    );
    for r in &t.from_true_pose {
        s.push_str(&format!(
            "| {} | {:.3} | {:.0} | {:.3} | {:.0} |\n",
            r.name,
            r.train_precision_mean,
            r.train_inliers_median,
            r.test_precision_mean,
            r.test_inliers_median
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn oracle_table_on_tiny() {
        let config = FieldTable3Config {
            preset: "tiny".into(),
            train_views: 4,
            query_source: QuerySource::Oracle,
            starts: 1,
            ..FieldTable3Config::default()
        };
        let mut calls = 0;
        let (t, encoder) = evaluate(&config, &mut |_, _, _| calls += 1).unwrap();
        assert!(encoder.is_none() && t.encoder.is_none());
        assert!(calls > 0);
        assert_eq!(t.scene.train_views, 4);
        let names: Vec<&str> = t.rows.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "all-47",
                "pos-32",
                "mlp-15",
                "greedy N_s=10",
                "greedy N_s=5",
                "paper-BIP N_s=10",
                "random-5"
            ]
        );
        assert_eq!(t.rows[0].dims.len(), 47);
        assert_eq!(t.rows[1].dims.len(), 32);
        assert_eq!(t.rows[2].dims.len(), 15);
        assert_eq!(t.selections.len(), 4);
        assert_eq!(t.from_true_pose.len(), t.rows.len());
        assert!(t.start_t_median_m.is_finite() && t.start_r_median_deg.is_finite());
        for r in &t.rows {
            assert_eq!(r.queries, t.scene.test_views * config.starts);
            assert!((0.0..=1.0).contains(&r.precision_mean), "{r:?}");
            for m in [
                r.match_ms_median,
                r.matches_median,
                r.t_err_median_m,
                r.r_err_median_deg,
                r.refined_t_err_median_m,
                r.refined_r_err_median_deg,
            ] {
                assert!(m.is_finite(), "{r:?}");
            }
        }
        for r in &t.from_true_pose {
            assert!((0.0..=1.0).contains(&r.train_precision_mean), "{r:?}");
            assert!((0.0..=1.0).contains(&r.test_precision_mean), "{r:?}");
        }
        let all = &t.rows[0];
        assert!(
            all.t_err_median_m < t.start_t_median_m,
            "all-47 {} m, start {} m",
            all.t_err_median_m,
            t.start_t_median_m
        );
        let back: FieldTable3 = serde_json::from_str(&serde_json::to_string(&t).unwrap()).unwrap();
        assert_eq!(back, t);
        let md = markdown(&t);
        assert!(md.contains("| all-47 | 47 |"), "{md}");
    }
}
