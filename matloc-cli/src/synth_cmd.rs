//! `matloc synth`: render a synthetic aerial dataset.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use matloc_data::dataset::Split;
use matloc_synth::{Progress, SynthConfig, synthesize};

use crate::progress;

/// Synthesises the preset into `out` and prints where it went.
pub fn run(preset: &str, out: &Path, seed: Option<u64>, quiet: bool) -> Result<()> {
    let mut config = SynthConfig::preset(preset)?;
    if let Some(seed) = seed {
        config = config.with_seed(seed);
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let bar = progress::bar(0, "rendering", quiet);
    let start = Instant::now();
    let dataset = synthesize(&config, out, &|p: Progress| {
        bar.set_length(p.total as u64);
        bar.set_position(p.done as u64);
    })
    .with_context(|| format!("synthesising preset `{preset}` into {}", out.display()))?;
    bar.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    let n = dataset.frames.len();
    outln!(
        "wrote {} ({} train, {} test images, seed {}) to {} in {:.1} s ({:.1} images/s)",
        preset,
        dataset.split(Split::Train).count(),
        dataset.split(Split::Test).count(),
        config.seed,
        out.join("transforms.json").display(),
        secs,
        n as f64 / secs.max(1e-9),
    )?;
    Ok(())
}
