//! `matloc place train|eval`: pose groups and the place predictor (paper Table 4).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand, ValueEnum};
use matloc_core::{Camera, Image, Pose};
use matloc_data::{Dataset, Split};
use matloc_pipeline::eval::table4::{self, PlaceQueries};
use matloc_place::{
    GroupConfig, PlaceMethod, PlaceModel, PoseGroups, TrainConfig, view_point_from_depth,
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

/// Images, depth maps, cameras and poses of the frames `indices` of `dataset`, loaded in
/// parallel.
fn load_frames(
    dataset: &Dataset,
    indices: &[usize],
    label: &str,
    quiet: bool,
) -> Result<PlaceQueries> {
    // Depth files, or the surface a map build would use (points, triangulation).
    let train = dataset.split_indices(matloc_data::Split::Train);
    let surfaces = matloc_surface::FrameSurfaces::prepare(
        dataset,
        &train,
        &matloc_surface::SurfaceConfig::default(),
        &|_, _, _| {},
    )?;
    let bar = progress::bar(indices.len() as u64, label, quiet);
    let loaded: Vec<(Image<f32>, Image<f32>, Camera, Pose)> = indices
        .par_iter()
        .map(|&i| {
            let f = &dataset.frames[i];
            let (img, cam) = matloc_data::images::load_frame_image(dataset, f, 1)
                .with_context(|| format!("image of frame {i}"))?;
            let depth = surfaces
                .depth(dataset, i)
                .with_context(|| format!("surface of frame {i}"))?;
            bar.inc(1);
            Ok((img, depth, cam, f.cam_from_world))
        })
        .collect::<Result<_>>()?;
    bar.finish_and_clear();
    let mut out = PlaceQueries::default();
    for (&frame, (image, depth, camera, pose)) in indices.iter().zip(loaded) {
        out.push(frame, image, depth, camera, pose);
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
    outln!(
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
    )?;
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
            if r.epoch % 10 == 0 || r.epoch + 1 == cfg.epochs {
                tracing::info!(epoch = r.epoch, loss = r.loss, "place classifier training");
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
    outln!(
        "trained {:?} in {train_secs:.1} s (final loss {last:.4}; total {:.1} s); wrote {}",
        model.method(),
        t0.elapsed().as_secs_f64(),
        out.display()
    )?;
    Ok(())
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
    outln!("{}", table4::table_header())?;
    let mut oracle = None;
    for (k, dir) in args.model.iter().enumerate() {
        let mut model =
            PlaceModel::load(dir).with_context(|| format!("loading {}", dir.display()))?;
        if k == 0 {
            oracle = table4::retrieval_oracle(&model, &test.poses);
        }
        let variants = table4::variants(
            model.method(),
            args.refine,
            &args.member_weight,
            &args.member_blend,
        );
        for variant in variants {
            let row = table4::evaluate(&mut model, variant, &test, &train_camera, args.min_overlap)
                .with_context(|| format!("evaluating {}", dir.display()))?;
            outln!("{}", table4::table_line(&short(dir), &row))?;
        }
    }
    outln!("{}", table4::table_footer(test.len(), args.min_overlap))?;
    if let Some(o) = oracle {
        outln!("{}", table4::oracle_line(o))?;
    }
    Ok(())
}

fn short(p: &Path) -> String {
    p.file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}
