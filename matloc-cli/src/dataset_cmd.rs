//! `matloc dataset info`: validate and summarise a dataset; `matloc dataset refine-poses`:
//! bundle-adjust a survey's GPS/IMU poses.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use matloc_data::Split;
use matloc_data::summary::{self, detect_format};
use matloc_surface::SurfaceChoice;

use crate::progress;

/// Reads the dataset, checks every referenced file (decoded in full, in parallel; headers only
/// with `quick`) and the plausibility of intrinsics and poses, and prints the summary. Fails
/// (non-zero exit) when the dataset cannot be read or any problem is found; the problems go to
/// stderr (and to stdout with the summary).
pub fn info(path: &Path, json: bool, quick: bool, quiet: bool) -> Result<()> {
    let format = detect_format(path)?;
    let dataset = summary::read_dataset(path)
        .with_context(|| format!("reading dataset at {}", path.display()))?;
    let summary = summary::summarize(&dataset);
    let problems = if quick {
        summary::validate(&dataset)
    } else {
        let bar = progress::bar(
            summary::decoded_file_count(&dataset) as u64,
            "decoding",
            quiet,
        );
        let problems = summary::validate_deep(&dataset, &|| bar.inc(1));
        bar.finish_and_clear();
        problems
    };
    // What a map build (default surface settings) would partition on.
    let train = dataset.split_indices(Split::Train);
    let surface = matloc_surface::plan(&dataset, &train, SurfaceChoice::Auto)?;
    if json {
        let value = serde_json::json!({
            "format": format!("{format:?}"),
            "surface": surface,
            "summary": summary,
            "problems": problems.iter().map(|p| p.to_string()).collect::<Vec<_>>(),
        });
        outln!("{}", serde_json::to_string_pretty(&value)?)?;
    } else {
        outln!("format: {format:?}")?;
        out!("{summary}")?;
        outln!(
            "surface for map build: {} — {} ({} of {} training frames have depth files)",
            surface.kind,
            surface.detail,
            surface.frames_with_depth,
            surface.frames
        )?;
        if problems.is_empty() {
            if quick {
                outln!(
                    "files: all referenced images and depth maps present, headers consistent \
                     (not decoded: --quick)"
                )?;
            } else {
                outln!("files: all referenced images and depth maps decode and are consistent")?;
            }
        } else {
            outln!("problems ({}):", problems.len())?;
            for p in problems.iter().take(50) {
                outln!("  - {p}")?;
            }
            if problems.len() > 50 {
                outln!("  ... and {} more", problems.len() - 50)?;
            }
        }
    }
    if !problems.is_empty() {
        // Also on stderr, one line each, for whoever reads only the errors.
        for p in problems.iter().take(50) {
            errln!("problem: {p}");
        }
        if problems.len() > 50 {
            errln!("problem: ... and {} more", problems.len() - 50);
        }
        bail!("{} problem(s) found in {}", problems.len(), path.display());
    }
    Ok(())
}

/// Arguments of `matloc dataset refine-poses`.
#[derive(clap::Args)]
pub struct RefinePosesArgs {
    /// Dataset directory, transforms.json file, or COLMAP model directory.
    pub path: PathBuf,
    /// Where to write the refined transforms.json (a directory, or a file ending in .json).
    #[arg(long)]
    pub out: PathBuf,
    /// Largest reprojection error of a triangulated observation under the given poses,
    /// pixels at the detection size (about 5 px per degree of attitude error at 320 px wide).
    #[arg(long, default_value_t = 8.0)]
    pub gate_px: f64,
    /// Standard deviation of the given camera positions, metres (per axis).
    #[arg(long, default_value_t = 0.3)]
    pub prior_position_m: f64,
    /// Standard deviation of the given attitudes, degrees (per axis).
    #[arg(long, default_value_t = 1.0)]
    pub prior_rotation_deg: f64,
}

/// Refines the poses of every frame of the dataset at `args.path` and writes them.
pub fn refine_poses(args: &RefinePosesArgs, quiet: bool) -> Result<()> {
    let dataset = summary::read_dataset(&args.path)
        .with_context(|| format!("reading dataset at {}", args.path.display()))?;
    let frames: Vec<usize> = (0..dataset.frames.len()).collect();
    let triangulate = matloc_surface::TriangulateConfig {
        max_reprojection_px: args.gate_px,
        ..matloc_surface::TriangulateConfig::default()
    };
    let config = matloc_surface::bundle::BundleConfig {
        prior_position_m: args.prior_position_m,
        prior_rotation_deg: args.prior_rotation_deg,
        ..matloc_surface::bundle::BundleConfig::default()
    };
    let bar = progress::bar(frames.len() as u64, "triangulating", quiet);
    let refined = matloc_surface::bundle::refine_poses(
        &dataset,
        &frames,
        &triangulate,
        &config,
        &|phase, done, total| {
            bar.set_message(format!("triangulating ({phase})"));
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        },
    )
    .with_context(|| format!("refining the poses of {}", args.path.display()))?;
    bar.finish_and_clear();
    let mut out = dataset.clone();
    for (&f, pose) in refined.frames.iter().zip(&refined.poses) {
        out.frames[f].cam_from_world = *pose;
    }
    matloc_data::nerfstudio::write_nerfstudio(&out, &args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    outln!(
        "refined {} poses over {} points ({} observations, {} iterations): reprojection error \
         median {:.2} → {:.2} px; cameras moved {:.3} m (median, largest {:.3} m) and turned \
         {:.3}° (largest {:.3}°); written to {}",
        refined.poses.len(),
        refined.points,
        refined.observations,
        refined.iterations,
        refined.median_px.0,
        refined.median_px.1,
        refined.moved_m.0,
        refined.moved_m.1,
        refined.turned_deg.0,
        refined.turned_deg.1,
        args.out.display()
    )?;
    Ok(())
}
