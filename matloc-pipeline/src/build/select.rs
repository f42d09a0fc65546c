//! The feature-selection stage: per block, which of the field's dims to match on — all of them
//! by default; otherwise greedy MNN-F1 on the block's GT pairs, or scored on held-out renders
//! the way the localizer matches.
//!
//! Selection on renders (beyond the paper): [`matloc_select::MatchingSelector`] scores a
//! subset by how many GT pairs find their exact partner among the other pairs of a render. The
//! localizer instead matches the encoder's whole grid against the whole render inside an image
//! window, and what it needs is matches close enough to their true projection for PnP. So
//! [`select_on_renders`] scores subsets on exactly that: a block's held-out views (kept out of
//! its encoder, so their encoder features are as weak as a query's), each rendered once on all
//! dims at a perturbed pose, matched with the block's own windowed matcher restricted to the
//! candidate dims, and either counted against the true projection or solved with PnP. The
//! greedy search is [`matloc_select::GreedySearch`].

use matloc_core::metrics::translation_error_m;
use matloc_core::{FeatureMap, Pose};
use matloc_data::Dataset;
use matloc_match::localize::{correct_matches, render_map_points, solve_pose_within};
use matloc_match::{MatchError, Matcher, QueryFeatures, RenderedPoints};
use matloc_partition::Partition;
use matloc_pnp::{LoRansacPnp, PoseSolver};
use matloc_select::{FeatureSelector, MatchingSelector, PairSet, Selection, SelectionReport};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::build::common::{BuildEvent, load_image, spaced, stage, views_of_block};
use crate::config::{MapConfig, RenderScore, RenderSelectConfig, SelectorKind};
use crate::error::PipelineError;
use crate::gt::GtPairSet;
use crate::map::layout::{SelectionRecord, pairs_file, selection_file};
use crate::map::load::{MapBlock, NerfMapComponents, block_matcher, load_encoder};
use crate::map::manifest::MapDir;

/// Selects block `b`'s dims and records them in the manifest (a block job: in its record).
pub fn run(
    dataset: &Dataset,
    partition: &Partition,
    b: usize,
    map: &mut MapDir,
    config: &MapConfig,
    progress: &mut dyn FnMut(&BuildEvent),
) -> Result<(), PipelineError> {
    let all_dims: Vec<usize> = (0..matloc_nerf_field::FEATURE_DIM).collect();
    stage(map, &format!("select/{b}"), 0, progress, &mut |map, _| {
        let record = if config.select.dims >= all_dims.len() {
            SelectionRecord {
                dims: all_dims.clone(),
                selector: "all dims".into(),
                objective: 0.0,
                pairs: 0,
            }
        } else {
            match config.select.selector {
                SelectorKind::GtPairs => greedy_selection(map, dataset, b, config.select.dims)?,
                SelectorKind::Renders => {
                    render_selection(map, dataset, partition, config, b, &all_dims)?
                }
            }
        };
        map.write_json(&selection_file(b), &record)?;
        map.set_selected_dims(b, record.dims);
        map.save()?;
        Ok(())
    })
}

/// Block `b`'s GT pairs with its encoder's features at their query cells: what selectors
/// score dims on (the query side is what the encoder sees, not the NeRF at the true pose).
pub fn block_pair_set(map: &MapDir, dataset: &Dataset, b: usize) -> Result<PairSet, PipelineError> {
    let gt = GtPairSet::from_bytes(
        &map.read_file(&pairs_file(b))?,
        &map.path_of(&pairs_file(b))?,
    )
    .map_err(|e| PipelineError::in_block(b, e))?;
    let enc = load_encoder(map, b)?;
    let mut maps = Vec::new();
    for r in &gt.provenance.renders {
        if maps.iter().any(|(i, _)| *i == r.view.index) {
            continue;
        }
        let (image, _) = load_image(dataset, r.view.index)?;
        let m = enc.encode(&image)?;
        maps.push((r.view.index, m));
    }
    let qf = pair_query_features(&gt, &maps)?;
    gt.to_pair_set(Some(qf))
        .map_err(|e| PipelineError::in_block(b, e))
}

/// Encoder feature map value of each pair's query cell.
fn pair_query_features(
    gt: &GtPairSet,
    maps: &[(usize, FeatureMap)],
) -> Result<Vec<f32>, PipelineError> {
    let nd = gt.dims();
    let mut qf = Vec::with_capacity(gt.len() * nd);
    for p in 0..gt.len() {
        let r = &gt.provenance.renders[gt.render[p] as usize];
        let m = &maps
            .iter()
            .find(|(i, _)| *i == r.view.index)
            .ok_or(PipelineError::Internal(
                "pair of a view that was not encoded",
            ))?
            .1;
        let q = gt.query_index[p] as usize;
        let (x, y) = (q % m.width(), q / m.width());
        if y >= m.height() {
            return Err(PipelineError::Internal(
                "pair cell outside the encoder grid",
            ));
        }
        qf.extend_from_slice(m.pixel(x, y));
    }
    Ok(qf)
}

/// Greedy MNN-F1 selection of `n_s` dims for block `b`, on its GT pairs with the block's
/// encoder features as the query side.
fn greedy_selection(
    map: &MapDir,
    dataset: &Dataset,
    b: usize,
    n_s: usize,
) -> Result<SelectionRecord, PipelineError> {
    let pairs = block_pair_set(map, dataset, b)?;
    let mut rng = ChaCha8Rng::seed_from_u64(b as u64);
    let sel = MatchingSelector::default()
        .select(&pairs, n_s, &mut rng)
        .map_err(|e| PipelineError::in_block(b, e))?;
    Ok(SelectionRecord {
        dims: sel.dims,
        selector: "greedy MNN-F1".into(),
        objective: sel.report.objective,
        pairs: pairs.len(),
    })
}

/// Selection of `config.select.dims` dims for block `b` on its held-out renders, scored as
/// the map's localizer will match (its window, its first-pass PnP threshold).
fn render_selection(
    map: &MapDir,
    dataset: &Dataset,
    partition: &Partition,
    config: &MapConfig,
    b: usize,
    all_dims: &[usize],
) -> Result<SelectionRecord, PipelineError> {
    let block = MapBlock::load(map, b, &config.localize, &NerfMapComponents, |_| {
        (all_dims.to_vec(), None)
    })?;
    let cfg = &config.select.renders;
    let views = selection_views(&block, dataset, partition, config, b, cfg)?;
    let sel = select_on_renders(
        &block,
        &views,
        config.select.dims,
        config.localize.first_pass_threshold_cells,
        cfg,
        &LoRansacPnp::new(config.localize.pnp.clone()),
    )?;
    Ok(SelectionRecord {
        dims: sel.dims,
        selector: sel.report.objective_name,
        objective: sel.report.objective,
        pairs: views.len(),
    })
}

/// One held-out view as the selection scores it: the encoder's map of its image on every
/// encoded dim and the block's render at a perturbed pose on the same dims.
pub struct SelectionView {
    /// Frame index in the dataset.
    pub index: usize,
    /// Intrinsics.
    pub camera: matloc_core::Camera,
    /// True pose.
    pub truth: Pose,
    /// The perturbed pose rendered at.
    pub start: Pose,
    /// Encoder features on every encoded dim.
    pub query: QueryFeatures,
    /// Rendered points with features on every encoded dim.
    pub points: RenderedPoints,
}

/// Block `b`'s selection views: its held-out views (every `holdout_every`-th, as calibration
/// uses), encoded by `block`'s encoder and rendered by its NeRF at perturbed poses.
pub fn selection_views(
    block: &MapBlock,
    dataset: &Dataset,
    partition: &Partition,
    map_config: &MapConfig,
    b: usize,
    config: &RenderSelectConfig,
) -> Result<Vec<SelectionView>, PipelineError> {
    if b >= partition.blocks.len() {
        return Err(PipelineError::Config(format!(
            "no block {b} (the partition has {})",
            partition.blocks.len()
        )));
    }
    let holdout = map_config.calibration.holdout_every;
    let (_, held) = views_of_block(dataset, partition, b, holdout);
    if held.is_empty() {
        return Err(PipelineError::Config(format!(
            "block {b} has no held-out views to select on (calibration.holdout_every = {holdout})"
        )));
    }
    let held = spaced(&held, config.max_views);
    let stride = block.encoder.stride();
    let dims = block.encoder.dims().to_vec();
    let min_acc = map_config.localize.min_accumulation;
    let mut out = Vec::with_capacity(held.len());
    for v in held {
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        rng.set_stream(((b as u64) << 32) | v.index as u64);
        let start = config.perturbation.apply(&v.cam_from_world, &mut rng);
        let (image, camera) = load_image(dataset, v.index)?;
        let encoded = block.encoder.encode(&image)?;
        let points = render_map_points(
            block.renderer.as_ref(),
            &camera,
            &start,
            stride,
            &dims,
            min_acc,
        )?;
        out.push(SelectionView {
            index: v.index,
            camera,
            truth: v.cam_from_world,
            start,
            query: QueryFeatures::new(encoded, stride as f64),
            points,
        });
    }
    Ok(out)
}

/// Selects `n_s` of the block's encoded dims by the greedy search over `config.score` on
/// `views` (from [`selection_views`] of the same block); `threshold_cells` is the PnP inlier
/// threshold of [`RenderScore::SinglePass`] (the map's first-pass one).
pub fn select_on_renders(
    block: &MapBlock,
    views: &[SelectionView],
    n_s: usize,
    threshold_cells: f64,
    config: &RenderSelectConfig,
    solver: &dyn PoseSolver,
) -> Result<Selection, PipelineError> {
    let encoded = block.encoder.dims().to_vec();
    if n_s == 0 || n_s > encoded.len() {
        return Err(PipelineError::Config(format!(
            "N_s = {n_s} must be in 1..={}",
            encoded.len()
        )));
    }
    if views.is_empty() {
        return Err(PipelineError::Config("no selection views".into()));
    }
    let window = block.matcher.window_px();
    let matcher = block_matcher(block.encoder.as_ref(), &encoded, window)?;
    let threshold_px = threshold_cells * block.encoder.stride() as f64;
    let mut score = |positions: &[usize]| -> Result<f64, PipelineError> {
        let (mut correct, mut matched, mut valid) = (0usize, 0usize, 0usize);
        let mut rel_err = 0.0;
        for (k, v) in views.iter().enumerate() {
            let matches = match matcher.match_features(&v.query, &v.points, Some(positions)) {
                Ok(m) => m,
                Err(MatchError::Empty { .. }) => Vec::new(),
                Err(e) => return Err(PipelineError::Match(e)),
            };
            let start_err = translation_error_m(&v.start, &v.truth).max(1e-6);
            match config.score {
                RenderScore::MatchF1 { tol_px } => {
                    valid += v.points.valid().iter().filter(|&&x| x).count();
                    matched += matches.len();
                    correct += correct_matches(&matches, &v.camera, &v.truth, tol_px);
                }
                RenderScore::SinglePass => {
                    let mut rng = ChaCha8Rng::seed_from_u64(config.seed ^ 0x5e1ec7);
                    rng.set_stream(k as u64);
                    let err = solve_pose_within(
                        &matches,
                        &v.camera,
                        solver,
                        Some(threshold_px),
                        &mut rng,
                    )
                    .map_or(start_err, |r| {
                        translation_error_m(&r.cam_from_world, &v.truth)
                    });
                    rel_err += err.min(start_err) / start_err;
                }
            }
        }
        Ok(match config.score {
            RenderScore::MatchF1 { .. } => {
                if correct == 0 {
                    0.0
                } else {
                    let p = correct as f64 / matched as f64;
                    let r = correct as f64 / valid.max(1) as f64;
                    2.0 * p * r / (p + r)
                }
            }
            RenderScore::SinglePass => -rel_err / views.len() as f64,
        })
    };
    let found = config.search.run(encoded.len(), n_s, &mut score)?;
    let mut dims: Vec<usize> = found.dims.iter().map(|&p| encoded[p]).collect();
    dims.sort_unstable();
    Ok(Selection {
        dims,
        report: SelectionReport {
            selector: "greedy on renders".into(),
            objective_name: match config.score {
                RenderScore::MatchF1 { tol_px } => {
                    format!("F1 of windowed MNN within {tol_px} px on held-out renders (maximised)")
                }
                RenderScore::SinglePass => {
                    "minus mean relative translation error of one PnP pass (maximised)".into()
                }
            },
            objective: found.score,
            per_dim_cost: found.single.iter().map(|s| -s).collect(),
            evaluations: found.evaluations,
        },
    })
}
