//! `matloc synth`: render a synthetic aerial dataset.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use matloc_data::dataset::Split;
use matloc_synth::{Progress, SynthConfig, SynthOutput, synthesize_with};

use crate::progress;

/// Synthesises the preset into `out` and prints where it went.
pub fn run(
    preset: &str,
    out: &Path,
    seed: Option<u64>,
    width: Option<u32>,
    output: &SynthOutput,
    quiet: bool,
) -> Result<()> {
    let mut config = SynthConfig::preset(preset)?;
    if let Some(seed) = seed {
        config = config.with_seed(seed);
    }
    if let Some(w) = width {
        let s = &mut config.survey;
        if !(16..=16384).contains(&w) {
            anyhow::bail!("--width must be in 16..=16384, got {w}");
        }
        s.height =
            ((f64::from(w) * f64::from(s.height) / f64::from(s.width)).round() as u32).max(1);
        s.width = w;
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let bar = progress::bar(0, "rendering", quiet);
    let start = Instant::now();
    let dataset = synthesize_with(&config, out, output, &|p: Progress| {
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
