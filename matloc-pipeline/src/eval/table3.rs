//! The paper's Table 3 on a built map: for each set of NeRF feature dims (all 47, the 32
//! positional, the 15 MLP, learned selections, the paper's BIP, random), how long matching
//! takes, how precise the matches are, and how far the final pose is from the truth when the
//! map's own query encoder, NeRFs and localizer start from perturbed true poses.
//!
//! Unlike `matloc match eval` on the analytic field, this measures the product: the features
//! are rendered by the trained sub-NeRFs and the query side is the learned encoder. Every
//! selector scores dims on the block's GT pairs with that encoder's features as the query
//! side, so the selection sees the encoder's errors. Each query is served by the block of its
//! nearest training camera, as the place classifier's groups would.

use crate::gt::{PerturbKind, Perturbation};
use matloc_core::metrics::{
    median, paired_median_difference, rotation_error_deg, translation_error_m,
};
use matloc_core::{Camera, Image, Pose};
use matloc_data::{Dataset, Split};
use matloc_encoder::QueryEncoder;
use matloc_match::localize::{correct_matches, render_map_points, timed_match};
use matloc_match::{MatchError, QueryFeatures};
use matloc_place::PlaceHypothesis;
use matloc_select::{
    FeatureSelector, MatchingSelector, PaperBipSelector, RandomSelector, Selection,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::build::common::load_image;
use crate::build::encoder::{encoder_views, train_block_encoder};
use crate::build::select::{block_pair_set, select_on_renders, selection_views};
use crate::config::{RenderScore, RenderSelectConfig};
use crate::error::PipelineError;
use crate::localizer::confidence::ConfidenceModel;
use crate::localizer::options::LocalizeOptions;
use crate::localizer::{FixedPlace, Localizer, LocalizerBlock, QueryFeatureEncoder, positions_of};
use crate::map::load::{LoadedMap, MapBlock, block_matcher};

/// Settings of the evaluation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Table3Config {
    /// Start poses: the true pose perturbed by this (the paper's coarse-pose error regime).
    pub start: Perturbation,
    /// Perturbed starts per test query.
    pub starts_per_query: usize,
    /// At most this many test queries (evenly spaced; 0 = all).
    pub max_queries: usize,
    /// A match is correct when its 3D point projects within this many pixels of its query
    /// pixel under the true pose.
    pub precision_px: f64,
    /// Seed of the starts and of the random selection.
    pub seed: u64,
    /// Feature sets (by name, e.g. `"greedy N_s=5"`) that also get a row with encoders of
    /// their own: one per block trained on only those dims, the map's encoder recipe and
    /// views (the paper's encoder projects into the selected features). Minutes per block.
    pub own_encoder_sets: Vec<String>,
    /// Lowe ratio test of the matcher for every set (`None`: the map's matcher, none).
    pub ratio: Option<f32>,
    /// Extra N_s = 5 rows selected on held-out renders by these criteria
    /// ([`crate::build::select`]), e.g. windowed-match F1 or one PnP pass.
    pub render_scores: Vec<RenderScore>,
}

impl Default for Table3Config {
    fn default() -> Self {
        Self {
            start: Perturbation {
                kind: PerturbKind::UniformBall,
                translation_m: 3.0,
                rotation_deg: 5.0,
            },
            starts_per_query: 1,
            max_queries: 0,
            precision_px: 2.0,
            seed: 0,
            own_encoder_sets: Vec::new(),
            ratio: None,
            render_scores: Vec::new(),
        }
    }
}

/// One row: a feature set and what matching and localization on it give.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Table3Row {
    /// Feature set name.
    pub name: String,
    /// Dims per block.
    pub dims: Vec<Vec<usize>>,
    /// Median wall time of one match at the start pose, milliseconds.
    pub match_ms: f64,
    /// Median matches at the start pose.
    pub matches: f64,
    /// Mean fraction of matches at the start pose within `precision_px` of their true
    /// projection.
    pub precision: f64,
    /// The same within two query cells.
    pub precision_2_cells: f64,
    /// Median translation / rotation error after the paper's single pass (render at the
    /// start, match, PnP); a pass without a pose keeps the start.
    pub single_pass_t_m: f64,
    /// See [`Self::single_pass_t_m`].
    pub single_pass_r_deg: f64,
    /// Median errors after the map's localizer (passes, feature-metric refinement, the map's
    /// options; every pose is kept, refused or not), rendering and refining on the set's dims.
    pub localized: Localized,
    /// The same matching on the set's dims but rendering and refining on all encoded dims
    /// ([`crate::LocalizeOptions::refine_on_all_dims`]); `None` for a set with its own
    /// encoder, which encodes no other dims.
    pub localized_refine_all: Option<Localized>,
}

/// Accuracy of the localizer from the starts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Localized {
    /// Median translation error, metres (a start without a pose counts with its own error).
    pub t_m: f64,
    /// Median rotation error, degrees.
    pub r_deg: f64,
    /// Starts brought within 1 m / 5°.
    pub within_1m: usize,
    /// Starts without a pose.
    pub failures: usize,
    /// Translation error of every start, metres, in start order (the starts of one query
    /// are consecutive), for paired comparisons between feature sets.
    #[serde(default)]
    pub per_start_t_m: Vec<f64>,
    /// Rotation error of every start, degrees.
    #[serde(default)]
    pub per_start_r_deg: Vec<f64>,
}

/// The table and the conditions it was measured under.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Table3 {
    /// Rows, in the paper's order plus the baselines.
    pub rows: Vec<Table3Row>,
    /// Test queries used.
    pub queries: usize,
    /// Starts in all.
    pub starts: usize,
    /// Median start error, metres.
    pub start_t_m: f64,
    /// Median start error, degrees.
    pub start_r_deg: f64,
    /// The settings.
    pub config: Table3Config,
}

/// A named feature set: the dims matched in each block.
pub type FeatureSet = (String, Vec<Vec<usize>>);

/// Feature sets per block: fixed groups and the selectors' choices on each block's pairs.
pub fn feature_sets(
    map: &LoadedMap,
    dataset: &Dataset,
    seed: u64,
) -> Result<Vec<FeatureSet>, PipelineError> {
    let nb = map.blocks.0.len();
    let nd = map
        .blocks
        .0
        .first()
        .map(|b| b.encoder.dims().len())
        .ok_or(PipelineError::Config("map without blocks".into()))?;
    let every = |dims: Vec<usize>| vec![dims; nb];
    let mut sets = vec![
        ("all-47".to_string(), every((0..nd).collect())),
        ("pos-32".to_string(), every((0..32.min(nd)).collect())),
        ("mlp-15".to_string(), every((32.min(nd)..nd).collect())),
    ];
    let greedy = MatchingSelector::default();
    let bip = PaperBipSelector::default();
    let random = RandomSelector::default();
    let selectors: [(&str, &dyn FeatureSelector, usize); 4] = [
        ("greedy N_s=10", &greedy, 10),
        ("greedy N_s=5", &greedy, 5),
        ("paper-BIP N_s=10", &bip, 10),
        ("random-5", &random, 5),
    ];
    let mut chosen: Vec<Vec<Vec<usize>>> = vec![Vec::new(); selectors.len()];
    for b in 0..nb {
        let pairs = block_pair_set(&map.dir, dataset, b)?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ (b as u64) << 8);
        for (k, (name, sel, n_s)) in selectors.iter().enumerate() {
            let s: Selection = sel
                .select(&pairs, *n_s, &mut rng)
                .map_err(|e| PipelineError::Config(format!("{name}, block {b}: {e}")))?;
            chosen[k].push(s.dims);
        }
    }
    for ((name, _, _), dims) in selectors.iter().zip(chosen) {
        sets.push((name.to_string(), dims));
    }
    Ok(sets)
}

/// Camera centre of a pose.
/// Block serving a pose: the block of the nearest training camera.
fn serving_block(map: &LoadedMap, dataset: &Dataset, pose: &Pose) -> usize {
    let c = matloc_core::pose::camera_center(pose);
    dataset
        .split_indices(Split::Train)
        .iter()
        .enumerate()
        .map(|(k, &i)| {
            (
                k,
                (matloc_core::pose::camera_center(&dataset.frames[i].cam_from_world) - c).norm(),
            )
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .and_then(|(k, _)| map.partition.block_of_member(k))
        .unwrap_or(0)
}

/// One test query's inputs.
struct Query {
    image: Image<f32>,
    camera: Camera,
    truth: Pose,
    block: usize,
}

/// Runs the evaluation; `progress(stage, done, total)` during encoder training (stage
/// `"encoder SET / block B"`, in steps) and after every start (stage `"starts"`).
pub fn evaluate(
    map: &LoadedMap,
    dataset: &Dataset,
    config: &Table3Config,
    progress: &mut dyn FnMut(&str, usize, usize),
) -> Result<Table3, PipelineError> {
    // A set, its dims per block and, for an own-encoder row, its encoders per block.
    type EvalSet = (String, Vec<Vec<usize>>, Option<Vec<QueryEncoder>>);
    let mut sets: Vec<EvalSet> = feature_sets(map, dataset, config.seed)?
        .into_iter()
        .map(|(n, d)| (n, d, None))
        .collect();
    for score in &config.render_scores {
        let name = match score {
            RenderScore::MatchF1 { tol_px } => format!("render-F1 {tol_px} px N_s=5"),
            RenderScore::SinglePass => "render-PnP N_s=5".to_string(),
        };
        let cfg = RenderSelectConfig {
            score: *score,
            seed: config.seed,
            ..RenderSelectConfig::default()
        };
        let mut dims = Vec::new();
        for (b, block) in map.blocks.0.iter().enumerate() {
            progress(&format!("select {name} / block {b}"), 0, 1);
            let views = selection_views(block, dataset, &map.partition, &map.config, b, &cfg)?;
            let sel = select_on_renders(
                block,
                &views,
                5,
                map.options().first_pass_threshold_cells,
                &cfg,
                map.solver.as_ref(),
            )?;
            progress(&format!("select {name} / block {b}"), 1, 1);
            dims.push(sel.dims);
        }
        sets.push((name, dims, None));
    }
    for name in &config.own_encoder_sets {
        let dims = sets
            .iter()
            .find(|s| &s.0 == name)
            .map(|s| s.1.clone())
            .ok_or_else(|| PipelineError::Config(format!("no feature set named {name:?}")))?;
        let mut encoders = Vec::with_capacity(dims.len());
        for (b, d) in dims.iter().enumerate() {
            let views = encoder_views(dataset, &map.partition, &map.config, b);
            let stage = format!("encoder {name} / block {b}");
            let total = map.config.encoder.train.total_steps();
            encoders.push(train_block_encoder(
                &map.dir,
                dataset,
                &map.config,
                b,
                &views,
                d,
                &mut |p| progress(&stage, p.step, total),
            )?);
        }
        sets.push((format!("{name}, own encoder"), dims, Some(encoders)));
    }
    let mut test: Vec<usize> = dataset.split_indices(Split::Test);
    if test.is_empty() {
        return Err(PipelineError::Config(
            "the dataset has no test views".into(),
        ));
    }
    if config.max_queries > 0 && test.len() > config.max_queries {
        let step = test.len() as f64 / config.max_queries as f64;
        test = (0..config.max_queries)
            .map(|k| test[((k as f64 + 0.5) * step) as usize])
            .collect();
    }
    let mut queries = Vec::with_capacity(test.len());
    for &i in &test {
        let f = &dataset.frames[i];
        let (image, camera) = load_image(dataset, i)?;
        queries.push(Query {
            image,
            camera,
            truth: f.cam_from_world,
            block: serving_block(map, dataset, &f.cam_from_world),
        });
    }

    let solver = map.solver.as_ref();
    let base = map.options();
    // Every pose is kept: the table measures accuracy, not refusal.
    let keep_all = LocalizeOptions {
        top_k: 1,
        confidence: ConfidenceModel {
            accept_threshold: 0.0,
            ..base.confidence.clone()
        },
        ..base
    };
    let single_pass = LocalizeOptions {
        max_passes: 1,
        featuremetric: None,
        ..keep_all.clone()
    };
    let window: Vec<Option<f64>> = map.blocks.0.iter().map(|b| b.matcher.window_px()).collect();

    // Per-start translation / rotation errors, starts within 1 m / 5°, starts without a pose.
    type Run = (Vec<f64>, Vec<f64>, usize, usize);
    struct Acc {
        ms: Vec<f64>,
        matches: Vec<f64>,
        prec: Vec<f64>,
        prec2: Vec<f64>,
        // Single pass, localizer on the set's dims, localizer refining on all dims.
        runs: [Run; 3],
    }
    let mut acc: Vec<Acc> = sets
        .iter()
        .map(|_| Acc {
            ms: vec![],
            matches: vec![],
            prec: vec![],
            prec2: vec![],
            runs: Default::default(),
        })
        .collect();
    // Each block's matcher over all its encoded dims (the refine-on-all-dims variant).
    let full_matchers = map
        .blocks
        .0
        .iter()
        .zip(&window)
        .map(|(b, w)| {
            let mut m = block_matcher(b.encoder.as_ref(), b.encoder.dims(), *w)?;
            m.config.ratio = config.ratio;
            Ok(m)
        })
        .collect::<Result<Vec<_>, PipelineError>>()?;
    let (mut start_t, mut start_r) = (Vec::new(), Vec::new());
    let total = queries.len() * config.starts_per_query.max(1);
    let mut done = 0;
    for (qi, q) in queries.iter().enumerate() {
        let blk = &map.blocks.0[q.block];
        let encode = |e: &dyn QueryFeatureEncoder| e.encode(&q.image);
        let encoded = encode(blk.encoder.as_ref())?;
        let own_encoded = sets
            .iter()
            .map(|s| s.2.as_ref().map(|e| encode(&e[q.block])).transpose())
            .collect::<Result<Vec<_>, _>>()?;
        let stride = blk.encoder.stride();
        for s in 0..config.starts_per_query.max(1) {
            let mut rng = ChaCha8Rng::seed_from_u64(config.seed.wrapping_add(1000));
            rng.set_stream((qi * 64 + s) as u64);
            let start = config.start.apply(&q.truth, &mut rng);
            start_t.push(translation_error_m(&start, &q.truth));
            start_r.push(rotation_error_deg(&start, &q.truth));
            for (((_, dims, own), a), own_map) in sets.iter().zip(acc.iter_mut()).zip(&own_encoded)
            {
                let dims = &dims[q.block];
                let enc: &dyn QueryFeatureEncoder = match own {
                    Some(e) => &e[q.block],
                    None => blk.encoder.as_ref(),
                };
                let encoded = own_map.as_ref().unwrap_or(&encoded);
                let mut matcher = block_matcher(enc, dims, window[q.block])?;
                matcher.config.ratio = config.ratio;
                let channels = positions_of(dims, enc.dims())?;
                // Matching at the start pose: time and precision.
                let points = render_map_points(
                    blk.renderer.as_ref(),
                    &q.camera,
                    &start,
                    stride,
                    dims,
                    keep_all.min_accumulation,
                )?;
                let query = QueryFeatures::new(encoded.select_channels(&channels), stride as f64);
                let (n, ok, ok2) = match timed_match(&matcher, &query, &points, None) {
                    Ok(tm) => {
                        a.ms.push(tm.elapsed.as_secs_f64() * 1e3);
                        (
                            tm.matches.len(),
                            correct_matches(&tm.matches, &q.camera, &q.truth, config.precision_px),
                            correct_matches(&tm.matches, &q.camera, &q.truth, 2.0 * stride as f64),
                        )
                    }
                    Err(MatchError::Empty { .. }) => (0, 0, 0),
                    Err(e) => return Err(PipelineError::Match(e)),
                };
                a.matches.push(n as f64);
                let frac = |k: usize| if n == 0 { 0.0 } else { k as f64 / n as f64 };
                a.prec.push(frac(ok));
                a.prec2.push(frac(ok2));

                // Localization from the start on these dims.
                let fixed = FixedPlace(vec![PlaceHypothesis {
                    group: 0,
                    score: 1.0,
                    cam_from_world: start,
                    block: Some(q.block),
                }]);
                let mut variants = vec![
                    (&single_pass, &matcher, dims.clone(), None),
                    (&keep_all, &matcher, dims.clone(), None),
                ];
                // An encoder of the set's own dims has nothing else to refine on.
                if own.is_none() {
                    variants.push((
                        &keep_all,
                        &full_matchers[q.block],
                        blk.encoder.dims().to_vec(),
                        Some(dims.clone()),
                    ));
                }
                for ((options, m, render_dims, match_dims), out) in
                    variants.into_iter().zip(a.runs.iter_mut())
                {
                    let mut bl: Vec<LocalizerBlock<'_>> =
                        map.blocks.0.iter().map(MapBlock::localizer_block).collect();
                    bl[q.block] = LocalizerBlock {
                        renderer: blk.renderer.as_ref(),
                        encoder: enc,
                        matcher: m,
                        dims: render_dims,
                        match_dims,
                    };
                    let localizer = Localizer {
                        place: &fixed,
                        blocks: bl,
                        solver,
                        options: options.clone(),
                    };
                    let r = localizer.localize(&q.image, &q.camera)?;
                    let pose = r.cam_from_world.unwrap_or(start);
                    let (te, re) = (
                        translation_error_m(&pose, &q.truth),
                        rotation_error_deg(&pose, &q.truth),
                    );
                    out.0.push(te);
                    out.1.push(re);
                    if r.cam_from_world.is_none() {
                        out.3 += 1;
                    } else if te <= 1.0 && re <= 5.0 {
                        out.2 += 1;
                    }
                }
            }
            done += 1;
            progress("starts", done, total);
        }
    }
    let med = |v: &[f64]| median(v).unwrap_or(f64::NAN);
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let localized = |(t, r, within_1m, failures): Run| Localized {
        t_m: med(&t),
        r_deg: med(&r),
        within_1m,
        failures,
        per_start_t_m: t,
        per_start_r_deg: r,
    };
    let rows = sets
        .into_iter()
        .zip(acc)
        .map(|((name, dims, _), a)| {
            let [single, own, all] = a.runs;
            Table3Row {
                name,
                dims,
                match_ms: med(&a.ms),
                matches: med(&a.matches),
                precision: mean(&a.prec),
                precision_2_cells: mean(&a.prec2),
                single_pass_t_m: med(&single.0),
                single_pass_r_deg: med(&single.1),
                localized: localized(own),
                localized_refine_all: (!all.0.is_empty()).then(|| localized(all)),
            }
        })
        .collect();
    Ok(Table3 {
        rows,
        queries: queries.len(),
        starts: total,
        start_t_m: med(&start_t),
        start_r_deg: med(&start_r),
        config: config.clone(),
    })
}

/// The table in markdown, in the paper's layout plus precision, the single pass and the
/// localizer refining on the set's dims or on all dims.
pub fn markdown(t: &Table3) -> String {
    let mut s = String::from(
        "| feature set | dims | matching time (ms, median) | matches | precision (≤ 2 px) | ≤ 2 cells | single pass: median t / R | localized: median t / R, within 1 m | localized, refined on all dims: median t / R, within 1 m |\n|---|---|---|---|---|---|---|---|---|\n",
    );
    let loc = |l: &Localized| {
        format!(
            "{:.3} m / {:.3}°, {}/{}{}",
            l.t_m,
            l.r_deg,
            l.within_1m,
            t.starts,
            if l.failures > 0 {
                format!(" ({} without a pose)", l.failures)
            } else {
                String::new()
            }
        )
    };
    for r in &t.rows {
        let dims = r.dims.first().map_or(0, Vec::len);
        s.push_str(&format!(
            "| {} | {} | {:.2} | {:.0} | {:.3} | {:.3} | {:.3} m / {:.3}° | {} | {} |\n",
            r.name,
            dims,
            r.match_ms,
            r.matches,
            r.precision,
            r.precision_2_cells,
            r.single_pass_t_m,
            r.single_pass_r_deg,
            loc(&r.localized),
            r.localized_refine_all
                .as_ref()
                .map_or("n/a".to_string(), loc),
        ));
    }
    s
}

/// Each set against the first (all 47 dims): the improvement of the median translation error
/// over the start's, and the difference of its median errors from the first set's on the same
/// starts, with a 95 % bootstrap interval that resamples queries (their starts together).
/// A set is "no worse" than all 47 dims only where the interval's upper end is at or below 0;
/// an interval across 0 means the starts cannot tell them apart.
pub fn paired_markdown(t: &Table3) -> String {
    let mut s = String::from(
        "| feature set | improvement over the start (median t) | Δ median t vs first [95 % CI] | Δ median R vs first [95 % CI] | refined on all dims: improvement, Δ median t [95 % CI] |\n|---|---|---|---|---|\n",
    );
    let Some(first) = t.rows.first() else {
        return s;
    };
    let cluster = t.config.starts_per_query.max(1);
    let delta = |a: &[f64], b: &[f64], unit: &str| {
        paired_median_difference(a, b, cluster, 2000, 0.95, t.config.seed).map_or_else(
            || "n/a".to_string(),
            |d| format!("{:+.3}{unit} [{:+.3}, {:+.3}]", d.difference, d.low, d.high),
        )
    };
    let gain = |l: &Localized| format!("{:.1}×", t.start_t_m / l.t_m);
    let r0 = &first.localized;
    for r in &t.rows {
        let l = &r.localized;
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} |\n",
            r.name,
            gain(l),
            delta(&l.per_start_t_m, &r0.per_start_t_m, " m"),
            delta(&l.per_start_r_deg, &r0.per_start_r_deg, "°"),
            r.localized_refine_all
                .as_ref()
                .map_or("n/a".to_string(), |f| format!(
                    "{}, {}",
                    gain(f),
                    delta(&f.per_start_t_m, &r0.per_start_t_m, " m")
                )),
        ));
    }
    s
}
