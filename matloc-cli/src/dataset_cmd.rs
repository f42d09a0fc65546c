//! `matloc dataset info`: validate and summarise a dataset.

use std::path::Path;

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
