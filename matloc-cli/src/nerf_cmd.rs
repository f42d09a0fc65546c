//! `matloc nerf train` and `matloc nerf render`: train a NeRF on a dataset, render test views.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use matloc_core::Image;
use matloc_data::images::write_png_rgb;
use matloc_data::{Split, read_dataset};
use matloc_render::{
    FitOptions, ModelConfig, NerfModel, config_for_dataset, evaluate, has_checkpoint,
    train_on_dataset,
};
use nalgebra::{DMatrix, SymmetricEigen};

use crate::progress;

/// `matloc nerf …`.
#[derive(Args)]
pub struct NerfArgs {
    #[command(subcommand)]
    command: NerfCommand,
}

#[derive(Subcommand)]
enum NerfCommand {
    /// Train a model on the training views of a dataset (resumes from MODEL's checkpoint).
    Train {
        /// Dataset directory (transforms.json or COLMAP).
        #[arg(long)]
        data: PathBuf,
        /// Model directory (written: model.safetensors, model.json, optimizer.safetensors).
        #[arg(long)]
        out: PathBuf,
        /// Total training steps (the learning rate decays 1e-2 → 1e-4 over them).
        #[arg(long, default_value_t = 5000)]
        steps: u64,
        /// JSON overrides merged into the dataset-derived config, e.g.
        /// `{"train": {"batch_rays": 2048}, "field": {"log2_table_size": 18}}`.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Steps between checkpoints.
        #[arg(long, default_value_t = 500)]
        checkpoint_every: u64,
        /// Integer image downscale factor.
        #[arg(long, default_value_t = 1)]
        downscale: u32,
    },
    /// Render the test views of a dataset (RGB, depth, feature PCA) and print metrics.
    Render {
        /// Model directory.
        #[arg(long)]
        model: PathBuf,
        /// Dataset directory.
        #[arg(long)]
        data: PathBuf,
        /// Output directory for PNGs and metrics.json.
        #[arg(long)]
        out: PathBuf,
        /// Render at most this many test views.
        #[arg(long)]
        limit: Option<usize>,
        /// Integer image downscale factor.
        #[arg(long, default_value_t = 1)]
        downscale: u32,
    },
}

/// Runs a `nerf` subcommand.
pub fn run(args: &NerfArgs, quiet: bool) -> Result<()> {
    match &args.command {
        NerfCommand::Train {
            data,
            out,
            steps,
            config,
            checkpoint_every,
            downscale,
        } => train(
            data,
            out,
            *steps,
            config.as_deref(),
            *checkpoint_every,
            *downscale,
            quiet,
        ),
        NerfCommand::Render {
            model,
            data,
            out,
            limit,
            downscale,
        } => render(model, data, out, *limit, *downscale, quiet),
    }
}

fn train(
    data: &Path,
    out: &Path,
    steps: u64,
    overrides: Option<&Path>,
    checkpoint_every: u64,
    downscale: u32,
    quiet: bool,
) -> Result<()> {
    let dataset = read_dataset(data).with_context(|| format!("reading {}", data.display()))?;
    let mut config = config_for_dataset(&dataset, steps);
    if let Some(path) = overrides {
        let text = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let over: serde_json::Value =
            serde_json::from_slice(&text).with_context(|| format!("parsing {}", path.display()))?;
        let mut base = serde_json::to_value(&config)?;
        matloc_pipeline::config::overlay_json(&mut base, over.clone());
        config = serde_json::from_value::<ModelConfig>(base)
            .with_context(|| format!("config overrides in {}", path.display()))?;
        let read = serde_json::to_value(&config)?;
        if let Some(key) = matloc_pipeline::config::unknown_overlay_keys(&over, &read).first() {
            bail!(
                "config overrides in {}: unknown field `{key}` (not a field of the NeRF model config)",
                path.display()
            );
        }
    }
    if has_checkpoint(out) {
        let step = NerfModel::load(out)
            .with_context(|| format!("reading the checkpoint in {}", out.display()))?
            .step();
        tracing::info!(
            "resuming from step {step} (checkpoint in {})",
            out.display()
        );
    }
    let pb = progress::bar(steps, "training", quiet);
    let model = train_on_dataset(
        &dataset,
        &config,
        out,
        &FitOptions {
            steps,
            checkpoint_every,
            downscale,
        },
        |p| {
            if pb.position() == 0 {
                pb.set_position(p.start_step);
                pb.reset_eta();
            }
            pb.set_position(p.stats.step + 1);
            pb.set_message(format!(
                "loss {:.4} PSNR {:.2} | {:.0} rays/s",
                p.stats.loss, p.stats.psnr, p.rays_per_s
            ));
        },
    )
    .with_context(|| format!("training into {}", out.display()))?;
    pb.finish_and_clear();
    outln!(
        "trained {} steps ({} training images) → {}",
        model.step(),
        model.config().field.num_images,
        out.display()
    )?;
    Ok(())
}

fn render(
    model_dir: &Path,
    data: &Path,
    out: &Path,
    limit: Option<usize>,
    downscale: u32,
    quiet: bool,
) -> Result<()> {
    let model = NerfModel::load(model_dir)
        .with_context(|| format!("loading model {}", model_dir.display()))?;
    let mut dataset = read_dataset(data).with_context(|| format!("reading {}", data.display()))?;
    let mut kept = 0;
    dataset.frames.retain(|f| {
        let keep = f.split != Split::Test || limit.is_none_or(|l| kept < l);
        if f.split == Split::Test {
            kept += 1;
        }
        keep
    });
    let n_test = dataset.split(Split::Test).count();
    if n_test == 0 {
        bail!("{} has no test views", data.display());
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let pb = progress::bar(n_test as u64, "rendering", quiet);
    let all: Vec<usize> = (0..47).collect();
    let report = evaluate(&model, &dataset, Split::Test, downscale, &all, |i, v| {
        let stem = format!("test_{i:03}");
        let io = |e: anyhow::Error| matloc_render::RenderError::Data(format!("{e:#}"));
        let r = &v.rendered;
        if let Some(rgb) = r.rgb_image() {
            write_png_rgb(&rgb, &out.join(format!("{stem}_rgb.png"))).map_err(|e| io(e.into()))?;
        }
        write_png_rgb(
            &depth_colour(&r.z_depth, r.width, r.height),
            &out.join(format!("{stem}_depth.png")),
        )
        .map_err(|e| io(e.into()))?;
        write_png_rgb(
            &feature_pca(&r.features, r.dims.len(), r.width, r.height),
            &out.join(format!("{stem}_features.png")),
        )
        .map_err(|e| io(e.into()))?;
        pb.inc(1);
        Ok(())
    })?;
    pb.finish_and_clear();
    for (i, v) in report.views.iter().enumerate() {
        outln!(
            "test_{i:03}  PSNR {:6.2} dB  SSIM {:.4}  depth err {}  ({:.2} s)  {}",
            v.psnr,
            v.ssim,
            v.median_depth_rel_error
                .map_or("-".into(), |d| format!("{:.2} %", 100.0 * d)),
            v.render_s,
            v.image.display()
        )?;
    }
    outln!(
        "mean PSNR {:.2} dB, mean SSIM {:.4}, median depth error {}",
        report.mean_psnr,
        report.mean_ssim,
        report
            .median_depth_rel_error
            .map_or("-".into(), |d| format!("{:.2} %", 100.0 * d))
    )?;
    let json = serde_json::json!({
        "model": model_dir,
        "step": model.step(),
        "mean_psnr": report.mean_psnr,
        "mean_ssim": report.mean_ssim,
        "median_depth_rel_error": report.median_depth_rel_error,
        "views": report.views.iter().map(|v| serde_json::json!({
            "image": v.image, "psnr": v.psnr, "ssim": v.ssim,
            "median_depth_rel_error": v.median_depth_rel_error, "render_s": v.render_s,
        })).collect::<Vec<_>>(),
    });
    matloc_core::fsutil::write_atomic(
        &out.join("metrics.json"),
        &serde_json::to_vec_pretty(&json)?,
    )?;
    Ok(())
}

/// The `q`-quantile of the finite positive values (0 if none).
fn quantile(values: &[f32], q: f64) -> f32 {
    let mut v: Vec<f32> = values
        .iter()
        .copied()
        .filter(|x| x.is_finite() && *x > 0.0)
        .collect();
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f32::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// A blue → cyan → green → yellow → red ramp over `t ∈ [0, 1]`.
fn ramp(t: f32) -> [f32; 3] {
    let t = t.clamp(0.0, 1.0) * 4.0;
    let f = t.fract();
    match t as u32 {
        0 => [0.0, f, 1.0],
        1 => [0.0, 1.0, 1.0 - f],
        2 => [f, 1.0, 0.0],
        3 => [1.0, 1.0 - f, 0.0],
        _ => [1.0, 0.0, 0.0],
    }
}

/// Near = blue, far = red over the 2–98 % depth range; no surface = black.
fn depth_colour(depth: &[f32], w: usize, h: usize) -> Image<f32> {
    let (lo, hi) = (quantile(depth, 0.02), quantile(depth, 0.98));
    let data = depth
        .iter()
        .flat_map(|&d| {
            if d > 0.0 && d.is_finite() {
                ramp((d - lo) / (hi - lo).max(1e-6))
            } else {
                [0.0; 3]
            }
        })
        .collect();
    Image::from_vec(w, h, 3, data).expect("3 per pixel")
}

/// The first three principal components of the per-pixel features as RGB (each stretched
/// over its 1–99 % range).
fn feature_pca(features: &[f32], dims: usize, w: usize, h: usize) -> Image<f32> {
    let n = w * h;
    if dims == 0 || n == 0 {
        return Image::new(w, h, 3);
    }
    let mut mean = vec![0f64; dims];
    for row in features.chunks_exact(dims) {
        for (m, &v) in mean.iter_mut().zip(row) {
            *m += v as f64;
        }
    }
    mean.iter_mut().for_each(|m| *m /= n as f64);
    let mut cov = DMatrix::<f64>::zeros(dims, dims);
    for row in features.chunks_exact(dims) {
        let c: Vec<f64> = row.iter().zip(&mean).map(|(&v, m)| v as f64 - m).collect();
        for i in 0..dims {
            for j in i..dims {
                cov[(i, j)] += c[i] * c[j];
            }
        }
    }
    for i in 0..dims {
        for j in 0..i {
            cov[(i, j)] = cov[(j, i)];
        }
    }
    let eig = SymmetricEigen::new(cov);
    let mut order: Vec<usize> = (0..dims).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let mut comps = vec![vec![0f32; n]; 3];
    for (k, comp) in comps.iter_mut().enumerate() {
        let Some(&e) = order.get(k) else { break };
        let v = eig.eigenvectors.column(e);
        for (p, row) in features.chunks_exact(dims).enumerate() {
            comp[p] = row
                .iter()
                .zip(&mean)
                .enumerate()
                .map(|(i, (&x, m))| (x as f64 - m) * v[i])
                .sum::<f64>() as f32;
        }
    }
    let mut data = vec![0f32; 3 * n];
    for (k, comp) in comps.iter().enumerate() {
        let mut s = comp.clone();
        s.sort_by(f32::total_cmp);
        let (lo, hi) = (s[n / 100], s[(n - 1) * 99 / 100]);
        for p in 0..n {
            data[3 * p + k] = ((comp[p] - lo) / (hi - lo).max(1e-9)).clamp(0.0, 1.0);
        }
    }
    Image::from_vec(w, h, 3, data).expect("3 per pixel")
}
