//! `matloc dataset info`: validate and summarise a dataset.

use std::path::Path;

use anyhow::{Context, Result, bail};
use matloc_data::summary::{self, detect_format};

/// Reads the dataset, checks every referenced file and prints the summary. Fails (non-zero
/// exit) when the dataset cannot be read or any file problem is found.
pub fn info(path: &Path, json: bool) -> Result<()> {
    let format = detect_format(path)?;
    let dataset = summary::read_dataset(path)
        .with_context(|| format!("reading dataset at {}", path.display()))?;
    let summary = summary::summarize(&dataset);
    let problems = summary::validate(&dataset);
    if json {
        let value = serde_json::json!({
            "format": format!("{format:?}"),
            "summary": summary,
            "problems": problems.iter().map(|p| p.to_string()).collect::<Vec<_>>(),
        });
        println!("{}", serde_json::to_string_pretty(&value)?);
    } else {
        println!("format: {format:?}");
        print!("{summary}");
        if problems.is_empty() {
            println!("files: all referenced images and depth maps present and consistent");
        } else {
            println!("problems ({}):", problems.len());
            for p in problems.iter().take(50) {
                println!("  - {p}");
            }
            if problems.len() > 50 {
                println!("  ... and {} more", problems.len() - 50);
            }
        }
    }
    if !problems.is_empty() {
        bail!("{} problem(s) found in {}", problems.len(), path.display());
    }
    Ok(())
}
