//! `matloc place train|eval`: pose groups and the place predictor (paper Table 4).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand, ValueEnum};
use matloc_core::metrics::translation_error_m;
use matloc_core::{Camera, Image, Pose};
use matloc_data::{Dataset, Split};
use matloc_place::{
    GroupConfig, PlaceMethod, PlaceModel, PlacePredictor, PoseGroups, TrainConfig, view_overlap,
    view_point_from_depth,
};
use rayon::prelude::*;

use crate::progress;

/// Place-predictor network on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum MethodArg {
    /// CNN embedding + ArcFace classifier over pose groups.
    Arcface,
    /// PoseNet-style translation + quaternion regression on the same backbone.
    Regression,
}

impl From<MethodArg> for PlaceMethod {
    fn from(m: MethodArg) -> Self {
        match m {
            MethodArg::Arcface => PlaceMethod::ArcFace,
            MethodArg::Regression => PlaceMethod::Regression,
        }
    }
}

/// `matloc place` subcommands.
#[derive(Subcommand, Debug)]
pub enum PlaceCommand {
    /// Group the training poses and train a place predictor.
    Train(TrainArgs),
    /// Evaluate place predictors on the test views (Table 4).
    Eval(EvalArgs),
}

/// Arguments of `matloc place train`.
#[derive(Args, Debug)]
pub struct TrainArgs {
    /// Dataset directory (images and depth maps, e.g. from `matloc synth`).
    #[arg(long)]
    data: PathBuf,
    /// Network.
    #[arg(long, value_enum, default_value = "arcface")]
    method: MethodArg,
    /// Output model directory (default: DATA/place-METHOD).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Partition JSON whose blocks serve the groups (from `matloc partition`).
    #[arg(long)]
    partition: Option<PathBuf>,
    /// Training epochs.
    #[arg(long, default_value_t = 40)]
    epochs: usize,
    /// Seed of grouping, weights and augmentation.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Largest angle between a member's and its group's viewing direction, degrees.
    #[arg(long, default_value_t = 30.0)]
    max_angle_deg: f64,
    /// Spatial group radius as a multiple of the median viewing distance.
    #[arg(long, default_value_t = 0.3)]
    radius_factor: f64,
}

/// Arguments of `matloc place eval`.
#[derive(Args, Debug)]
pub struct EvalArgs {
    /// Dataset directory.
    #[arg(long)]
    data: PathBuf,
    /// Model directories (one table row each).
    #[arg(long, required = true)]
    model: Vec<PathBuf>,
    /// Overlap with the true view that counts as co-visible.
    #[arg(long, default_value_t = 0.5)]
    min_overlap: f64,
    /// Also evaluate each classifier with the coarse pose refined to the group member nearest
    /// in embedding space (instead of the group medoid).
    #[arg(long)]
    refine: bool,
    /// Also evaluate each classifier scoring groups with these weights of the best member
    /// similarity (`PlaceModel::set_member_weight`), comma-separated.
    #[arg(long, value_delimiter = ',')]
    member_weight: Vec<f32>,
    /// Also evaluate each classifier (with `--refine`) blending the nearest member's pose with
    /// its best neighbour's at these temperatures (`PlaceModel::set_member_blend`).
    #[arg(long, value_delimiter = ',')]
    member_blend: Vec<f32>,
}

/// Runs a `matloc place` subcommand.
pub fn run(cmd: &PlaceCommand, quiet: bool) -> Result<()> {
    match cmd {
        PlaceCommand::Train(a) => train(a, quiet),
        PlaceCommand::Eval(a) => eval(a, quiet),
    }
}

struct Frames {
    images: Vec<Image<f32>>,
    depths: Vec<Image<f32>>,
    cameras: Vec<Camera>,
    poses: Vec<Pose>,
}

fn load_frames(dataset: &Dataset, indices: &[usize], label: &str, quiet: bool) -> Result<Frames> {
    let bar = progress::bar(indices.len() as u64, label, quiet);
    let loaded: Vec<(Image<f32>, Image<f32>, Camera, Pose)> = indices
        .par_iter()
        .map(|&i| {
            let f = &dataset.frames[i];
            let (img, cam) = matloc_data::images::load_frame_image(dataset, f, 1)
                .with_context(|| format!("image of frame {i}"))?;
            let depth = matloc_data::images::load_frame_depth(dataset, f, 1)
                .with_context(|| format!("depth of frame {i}"))?
                .with_context(|| format!("frame {i} has no depth map"))?;
            bar.inc(1);
            Ok((img, depth, cam, f.cam_from_world))
        })
        .collect::<Result<_>>()?;
    bar.finish_and_clear();
    let mut out = Frames {
        images: Vec::new(),
        depths: Vec::new(),
        cameras: Vec::new(),
        poses: Vec::new(),
    };
    for (i, d, c, p) in loaded {
        out.images.push(i);
        out.depths.push(d);
        out.cameras.push(c);
        out.poses.push(p);
    }
    Ok(out)
}

fn train(args: &TrainArgs, quiet: bool) -> Result<()> {
    let dataset = matloc_data::read_dataset(&args.data)
        .with_context(|| format!("reading dataset {}", args.data.display()))?;
    let train_idx = dataset.split_indices(Split::Train);
    if train_idx.is_empty() {
        bail!("{} has no training frames", args.data.display());
    }
    let t0 = Instant::now();
    let frames = load_frames(&dataset, &train_idx, "loading", quiet)?;
    let view_points: Vec<_> = (0..frames.poses.len())
        .map(|i| {
            view_point_from_depth(&frames.cameras[i], &frames.poses[i], &frames.depths[i], 4)
                .with_context(|| format!("frame {} sees no surface", train_idx[i]))
        })
        .collect::<Result<_>>()?;
    let group_cfg = GroupConfig {
        seed: args.seed,
        max_angle_deg: args.max_angle_deg,
        radius_factor: args.radius_factor,
        ..GroupConfig::default()
    };
    let mut groups = PoseGroups::build(&frames.poses, &view_points, &group_cfg)?;
    if let Some(p) = &args.partition {
        let part = matloc_partition::read_partition(p)?;
        groups.attach_blocks(|i| part.block_of_member(train_idx[i]));
    }
    println!(
        "{} training poses → {} spatial clusters (radius {:.1} m), {} pose groups (sizes {:?})",
        frames.poses.len(),
        groups.num_spatial,
        groups.spatial_radius_m,
        groups.len(),
        groups
            .groups
            .iter()
            .map(|g| g.members.len())
            .collect::<Vec<_>>()
    );
    let cfg = TrainConfig {
        epochs: args.epochs,
        seed: args.seed,
        ..TrainConfig::default()
    };
    let bar = progress::bar(cfg.epochs as u64, "training", quiet);
    let t1 = Instant::now();
    let mut last = f32::NAN;
    let model = PlaceModel::train(
        args.method.into(),
        &frames.images,
        &frames.poses,
        &groups,
        &cfg,
        &mut |r| {
            last = r.loss;
            bar.set_message(format!("loss {:.3}", r.loss));
            bar.inc(1);
            if quiet && (r.epoch % 10 == 0 || r.epoch + 1 == cfg.epochs) {
                println!("epoch {:>3} loss {:.4}", r.epoch, r.loss);
            }
        },
    )?;
    bar.finish_and_clear();
    let train_secs = t1.elapsed().as_secs_f64();
    let out = args.out.clone().unwrap_or_else(|| {
        dataset.root.join(match args.method {
            MethodArg::Arcface => "place-arcface",
            MethodArg::Regression => "place-regression",
        })
    });
    model.save(&out)?;
    println!(
        "trained {:?} in {train_secs:.1} s (final loss {last:.4}; total {:.1} s); wrote {}",
        model.method(),
        t0.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(())
}

/// Median of a non-empty list.
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn eval(args: &EvalArgs, quiet: bool) -> Result<()> {
    let dataset = matloc_data::read_dataset(&args.data)
        .with_context(|| format!("reading dataset {}", args.data.display()))?;
    let test_idx = dataset.split_indices(Split::Test);
    let train_idx = dataset.split_indices(Split::Train);
    if test_idx.is_empty() {
        bail!("{} has no test frames", args.data.display());
    }
    let test = load_frames(&dataset, &test_idx, "loading", quiet)?;
    let train_camera = dataset.frames[train_idx.first().copied().unwrap_or(0)].camera;
    println!(
        "{:<40} {:>10} {:>10} {:>8} {:>8} {:>12} {:>14}",
        "model", "ms/query", "(median)", "top-1", "top-3", "co-visible", "coarse t (m)"
    );
    for dir in &args.model {
        let mut model =
            PlaceModel::load(dir).with_context(|| format!("loading {}", dir.display()))?;
        // (refine within group, member weight, blend temperature)
        let mut variants = vec![(false, 0.0, 0.0)];
        if model.method() == PlaceMethod::ArcFace {
            if args.refine {
                variants.push((true, 0.0, 0.0));
                for &t in &args.member_blend {
                    variants.push((true, 0.0, t));
                }
            }
            for &w in &args.member_weight {
                variants.push((args.refine, w, 0.0));
            }
        }
        for (refine, w, blend) in variants {
            model.set_refine_within_group(refine);
            model.set_member_weight(w);
            model.set_member_blend(blend);
            let row = evaluate(&model, &test, &train_camera, args.min_overlap)?;
            let name = format!(
                "{:?}{}{}{} ({})",
                model.method(),
                if refine { "+member" } else { "" },
                if w > 0.0 {
                    format!(" w={w}")
                } else {
                    String::new()
                },
                if blend > 0.0 {
                    format!(" blend={blend}")
                } else {
                    String::new()
                },
                short(dir)
            );
            println!(
                "{:<40} {:>10.2} {:>10.2} {:>7.1}% {:>7.1}% {:>11.1}% {:>14.2}",
                name,
                row.mean_ms,
                row.median_ms,
                100.0 * row.top1,
                100.0 * row.top3,
                100.0 * row.covisible,
                row.median_coarse_m
            );
        }
    }
    println!(
        "{} test views; co-visible = coarse pose sees >= {:.0} % of the ground the true view sees",
        test.poses.len(),
        100.0 * args.min_overlap
    );
    if let Some(dir) = args.model.first() {
        let model = PlaceModel::load(dir)?;
        if let Some(o) = retrieval_oracle(&model, &test.poses) {
            println!(
                "top-1 of perfect retrieval (the group of the training pose nearest each query, \
                 centre distance + 20 m per radian of rotation): {:.1}%",
                100.0 * o
            );
        }
    }
    Ok(())
}

/// Fraction of `queries` whose group is the group of their nearest training pose: an upper
/// bound for place recognition by image retrieval against the training views.
fn retrieval_oracle(model: &PlaceModel, queries: &[Pose]) -> Option<f64> {
    use matloc_core::metrics::rotation_error_deg;
    let groups = model.groups();
    let train = model.training_poses();
    if queries.is_empty() || train.len() != groups.labels.len() {
        return None;
    }
    let mut hits = 0usize;
    for q in queries {
        let truth = groups.assign(q)?;
        let nearest = (0..train.len()).min_by(|&a, &b| {
            let cost = |j: usize| {
                translation_error_m(&train[j], q)
                    + 20.0 * rotation_error_deg(&train[j], q).to_radians()
            };
            cost(a).total_cmp(&cost(b))
        })?;
        hits += usize::from(groups.labels[nearest] == truth);
    }
    Some(hits as f64 / queries.len() as f64)
}

fn short(p: &Path) -> String {
    p.file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}

struct Row {
    mean_ms: f64,
    median_ms: f64,
    top1: f64,
    top3: f64,
    covisible: f64,
    /// Median distance of the top-1 coarse camera centre to the truth.
    median_coarse_m: f64,
}

fn evaluate(
    model: &PlaceModel,
    test: &Frames,
    coarse_camera: &Camera,
    min_overlap: f64,
) -> Result<Row> {
    let groups = model.groups();
    let (mut top1, mut top3, mut covis) = (0usize, 0usize, 0usize);
    let mut times = Vec::new();
    let mut coarse_m = Vec::new();
    // One warm-up query so the first timing does not include lazy initialisation.
    model.predict(&test.images[0], &test.cameras[0], 3)?;
    for i in 0..test.poses.len() {
        let t = Instant::now();
        let h = model.predict(&test.images[i], &test.cameras[i], 3)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
        let truth = groups
            .assign(&test.poses[i])
            .context("test pose cannot be assigned to a group")?;
        top1 += usize::from(h.first().is_some_and(|x| x.group == truth));
        top3 += usize::from(h.iter().any(|x| x.group == truth));
        if let Some(best) = h.first() {
            coarse_m.push(translation_error_m(&best.cam_from_world, &test.poses[i]));
            let o = view_overlap(
                &test.cameras[i],
                &test.poses[i],
                &test.depths[i],
                coarse_camera,
                &best.cam_from_world,
                4,
            );
            covis += usize::from(o >= min_overlap);
        }
    }
    let n = test.poses.len() as f64;
    let mean_ms = times.iter().sum::<f64>() / n;
    Ok(Row {
        mean_ms,
        median_ms: median(&mut times),
        top1: top1 as f64 / n,
        top3: top3 as f64 / n,
        covisible: covis as f64 / n,
        median_coarse_m: if coarse_m.is_empty() {
            f64::NAN
        } else {
            median(&mut coarse_m)
        },
    })
}
