//! `matloc synth`: render a synthetic aerial dataset.

use std::path::Path;
use std::time::Instant;

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use matloc_data::dataset::Split;
use matloc_synth::{Progress, SecondFlight, SynthConfig, SynthOutput, synthesize_with};

use crate::progress;

/// `matloc synth` arguments.
#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Preset: tiny, small, rubble or building.
    #[arg(long, default_value = "small")]
    pub preset: String,
    /// Output directory (created; an existing dataset there is replaced).
    #[arg(long)]
    pub out: PathBuf,
    /// World and capture seed (default: the preset's).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Image width in pixels (height by the preset's aspect, same field of view): renders
    /// the preset's survey at another resolution.
    #[arg(long)]
    pub width: Option<u32>,
    /// Write no depth maps (as real data comes).
    #[arg(long)]
    pub no_depth: bool,
    /// Also write the sparse point cloud real data would have: a COLMAP model with
    /// points3D and tracks in OUT/sparse/0 and nerfstudio's OUT/sparse_pc.ply.
    #[arg(long)]
    pub points: bool,
    /// Also re-shoot the test views as a later flight into OUT/second_flight (sun turned 55°
    /// and lowered to 22°, +0.4 EV, warmer white balance, a k1 = -0.05 lens, 0.5 px blur,
    /// sensor noise): transforms.json with ground truth and `camera_model` OPENCV, and an hloc
    /// list queries_with_intrinsics.txt for `localize --queries`.
    #[arg(long)]
    pub second_flight: bool,
    /// JSON file overriding second-flight fields (`sun_azimuth_shift_deg`,
    /// `sun_elevation_deg`, `exposure_ev`, `white_balance`, `k1`, `k2`, `blur_sigma_px`,
    /// `read_noise`, `shot_noise`, `seed`); implies --second-flight.
    #[arg(long, value_name = "FILE")]
    pub second_flight_config: Option<PathBuf>,
}

/// Runs `matloc synth`.
pub fn run(args: &SynthArgs, quiet: bool) -> Result<()> {
    let output = SynthOutput {
        depth: !args.no_depth,
        points: args.points,
    };
    let flight = match &args.second_flight_config {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let f: SecondFlight = serde_json::from_str(&text)
                .with_context(|| format!("parsing second-flight config {}", path.display()))?;
            f.validate()
                .with_context(|| format!("second-flight config {}", path.display()))?;
            Some(f)
        }
        None => args.second_flight.then(SecondFlight::default),
    };
    render(
        &args.preset,
        &args.out,
        args.seed,
        args.width,
        &output,
        flight.as_ref(),
        quiet,
    )
}

/// Synthesises the preset into `out` (and its second flight into `out/second_flight`) and
/// prints where it went.
pub fn render(
    preset: &str,
    out: &Path,
    seed: Option<u64>,
    width: Option<u32>,
    output: &SynthOutput,
    second_flight: Option<&SecondFlight>,
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
    if let Some(flight) = second_flight {
        let dir = out.join("second_flight");
        let bar = progress::bar(0, "second flight", quiet);
        let start = Instant::now();
        let flown =
            matloc_synth::synthesize_second_flight(&config, flight, &dir, &|p: Progress| {
                bar.set_length(p.total as u64);
                bar.set_position(p.done as u64);
            })
            .with_context(|| format!("rendering the second flight into {}", dir.display()))?;
        bar.finish_and_clear();
        outln!(
            "wrote the second flight ({} query images, query list {}) to {} in {:.1} s",
            flown.frames.len(),
            dir.join(matloc_synth::flight::QUERY_LIST).display(),
            dir.join("transforms.json").display(),
            start.elapsed().as_secs_f64(),
        )?;
    }
    Ok(())
}
