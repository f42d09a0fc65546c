//! Trains on a dataset and evaluates the test views: the quality/speed measurement behind
//! `docs/BENCHMARKS.md`.
//!
//! `cargo run --release -p matloc-render --example nerf_quality -- DATA OUT STEPS [JSON]`
//! where `DATA` is a dataset directory (synthesised first if it is missing and its name is a
//! synth preset, e.g. `data/tiny`), `OUT` the model directory (resumed if it has a
//! checkpoint), and `JSON` optional config overrides such as `{"train":{"batch_rays":2048}}`.

use std::path::Path;
use std::time::Instant;

use matloc_data::{Split, read_dataset, synth};
use matloc_render::{
    FitOptions, ModelConfig, PixelSet, RenderRequest, config_for_dataset, evaluate, render_view,
    train_on_dataset,
};

/// User + system CPU seconds of this process (Linux `/proc/self/stat`, 100 ticks/s).
fn cpu_seconds() -> f64 {
    let Ok(s) = std::fs::read_to_string("/proc/self/stat") else {
        return f64::NAN;
    };
    let rest = s.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| {
        f.get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    (tick(11) + tick(12)) / 100.0
}

fn merge(base: &mut serde_json::Value, over: &serde_json::Value) {
    match (base, over) {
        (serde_json::Value::Object(b), serde_json::Value::Object(o)) => {
            for (k, v) in o {
                merge(b.entry(k.clone()).or_insert(serde_json::Value::Null), v);
            }
        }
        (b, o) => *b = o.clone(),
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let usage = "usage: nerf_quality DATA OUT STEPS [JSON]";
    let data = Path::new(args.get(1).ok_or(usage)?);
    let out = Path::new(args.get(2).ok_or(usage)?);
    let steps: u64 = args.get(3).ok_or(usage)?.parse()?;
    if !data.join("transforms.json").exists() {
        let preset = data.file_name().and_then(|s| s.to_str()).unwrap_or("");
        let cfg = synth::SynthConfig::preset(preset)?;
        eprintln!("synthesising {preset} into {}", data.display());
        synth::synthesize(&cfg, data, &|_| {})?;
    }
    let dataset = read_dataset(data)?;
    let mut cfg = config_for_dataset(&dataset, steps);
    if let Some(j) = args.get(4) {
        let mut v = serde_json::to_value(&cfg)?;
        merge(&mut v, &serde_json::from_str(j)?);
        cfg = serde_json::from_value::<ModelConfig>(v)?;
    }
    eprintln!(
        "box {:?}..{:?} near {} far {} linear {}",
        cfg.field.scene_box.min,
        cfg.field.scene_box.max,
        cfg.near_m,
        cfg.far_m,
        cfg.train.march.spacing.linear_range_m
    );
    let t0 = Instant::now();
    let mut next_print = 0.0;
    let model = train_on_dataset(
        &dataset,
        &cfg,
        out,
        &FitOptions {
            steps,
            checkpoint_every: 1000,
            downscale: 1,
        },
        |p| {
            if p.elapsed_s >= next_print || p.stats.step + 1 == p.total_steps {
                next_print = p.elapsed_s + 10.0;
                eprintln!(
                    "step {:5} loss {:.5} psnr {:5.2} lr {:.2e} samples/ray {:5.1} {:7.0} rays/s eta {:4.0}s",
                    p.stats.step + 1,
                    p.stats.loss,
                    p.stats.psnr,
                    p.stats.lr,
                    p.stats.samples as f64 / cfg.train.batch_rays as f64,
                    p.rays_per_s,
                    p.eta_s
                );
            }
        },
    )?;
    let train_s = t0.elapsed().as_secs_f64();
    eprintln!(
        "trained in {train_s:.1} s; occupied {:.3}",
        model.grid().occupied_fraction()
    );
    let timing_only = args.get(5).is_some_and(|a| a == "timing");
    let report = if timing_only {
        None
    } else {
        Some(evaluate(&model, &dataset, Split::Test, 1, &[], |_, _| {
            Ok(())
        })?)
    };
    if let Some(report) = report {
        let render_s: Vec<f64> = report.views.iter().map(|v| v.render_s).collect();
        println!(
            "{{\"steps\": {}, \"train_s\": {train_s:.1}, \"test_psnr\": {:.3}, \"test_ssim\": {:.4}, \
         \"median_depth_rel_error\": {:.5}, \"rgb_depth_render_s_mean\": {:.3}}}",
            model.step(),
            report.mean_psnr,
            report.mean_ssim,
            report.median_depth_rel_error.unwrap_or(f64::NAN),
            render_s.iter().sum::<f64>() / render_s.len().max(1) as f64
        );
    }
    // Feature rendering times at one test view (best of 3).
    let frame = dataset.split(Split::Test).next().ok_or("no test view")?;
    for (name, pixels, rgb, dims) in [
        (
            "depth+47 full",
            PixelSet::Full,
            false,
            (0..47).collect::<Vec<_>>(),
        ),
        (
            "depth+47 stride4",
            PixelSet::Grid { stride: 4 },
            false,
            (0..47).collect(),
        ),
        (
            "depth+5 stride4",
            PixelSet::Grid { stride: 4 },
            false,
            vec![3, 10, 33, 40, 46],
        ),
        ("rgb+depth full", PixelSet::Full, true, Vec::new()),
    ] {
        let mut best = f64::INFINITY;
        let mut best_cpu = f64::INFINITY;
        for _ in 0..3 {
            let t = Instant::now();
            let c = cpu_seconds();
            let v = render_view(
                &model,
                &frame.camera,
                &frame.cam_from_world,
                &pixels,
                &RenderRequest {
                    rgb,
                    dims: dims.clone(),
                    appearance: None,
                },
            )?;
            std::hint::black_box(&v);
            best = best.min(t.elapsed().as_secs_f64());
            best_cpu = best_cpu.min(cpu_seconds() - c);
        }
        println!("render {name}: {best:.3} s wall, {best_cpu:.3} CPU-s");
    }
    Ok(())
}
