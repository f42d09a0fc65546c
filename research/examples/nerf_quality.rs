//! Trains on a dataset and evaluates the test views: the quality/speed measurement behind
//! `docs/BENCHMARKS.md`.
//!
//! `cargo run --release -p matloc-research --example nerf_quality -- DATA OUT STEPS [JSON]`
//! where `DATA` is a dataset directory (synthesised first if it is missing and its name is a
//! synth preset, e.g. `data/tiny`), `OUT` the model directory (resumed if it has a
//! checkpoint), and `JSON` optional config overrides such as `{"train":{"batch_rays":2048}}`.

use std::path::Path;
use std::time::Instant;

use matloc_data::{Split, read_dataset};
use matloc_render::{
    FitOptions, ModelConfig, NerfModel, PixelSet, RenderRequest, config_for_dataset, evaluate,
    has_checkpoint, render_view, train_on_dataset,
};
use matloc_synth as synth;

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
        // An enum variant (one capitalised key) replaces rather than merges.
        (serde_json::Value::Object(b), serde_json::Value::Object(o))
            if !(o.len() == 1 && o.keys().all(|k| k.starts_with(char::is_uppercase))) =>
        {
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
    let cpu0 = cpu_seconds();
    let mut next_print = 0.0;
    // A finished model in OUT is evaluated as is, with JSON's `render` settings applied.
    let existing = if has_checkpoint(out) {
        let m = NerfModel::load(out)?;
        (m.step() >= steps).then_some(m)
    } else {
        None
    };
    let trained = existing.is_none();
    let model = if let Some(m) = existing {
        eprintln!("evaluating the existing {}-step model", m.step());
        m.with_view_config(cfg.render)?
    } else {
        train_on_dataset(
            &dataset,
            &cfg,
            out,
            &FitOptions {
                steps,
                checkpoint_every: std::env::var("NQ_CKPT")
                    .ok()
                    .and_then(|v| v.parse().ok())
                    .unwrap_or(1000),
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
        )?
    };
    let train_s = t0.elapsed().as_secs_f64();
    let train_cpu = cpu_seconds() - cpu0;
    eprintln!(
        "trained ({trained}) in {train_s:.1} s ({train_cpu:.1} CPU-s); occupied {:.3}, in box {:.3}, render grid in box {:.3}",
        model.grid().occupied_fraction(),
        model.grid().occupied_fraction_in_box(),
        model.render_grid().occupied_fraction_in_box()
    );
    {
        // In-box occupancy-grid densities in normalised units.
        let g = model.grid();
        let r = g.config().resolution;
        let scale = model.field().density_scale();
        let mut d: Vec<f32> = Vec::new();
        for z in r / 4..r - r / 4 {
            for y in r / 4..r - r / 4 {
                for x in r / 4..r - r / 4 {
                    d.push(g.density()[x + r * (y + r * z)] / scale);
                }
            }
        }
        d.sort_by(f32::total_cmp);
        let q = |f: f64| d[((d.len() - 1) as f64 * f) as usize];
        eprintln!(
            "in-box grid density (units): p50 {:.2} p80 {:.2} p90 {:.2} p95 {:.2} p99 {:.2} max {:.1}",
            q(0.5),
            q(0.8),
            q(0.9),
            q(0.95),
            q(0.99),
            q(1.0)
        );
    }
    {
        // Field density (normalised units) at GT surface points and in the air in front of
        // them (fractions of the GT depth), over a pixel grid of a few test views.
        let scale = model.field().density_scale();
        let mut pts: Vec<Vec<[f32; 3]>> = vec![Vec::new(); 4];
        let fracs = [1.0f64, 0.97, 0.9, 0.5];
        for frame in dataset.split(Split::Test).take(4) {
            let Ok(Some(gt)) = matloc_data::images::load_frame_depth(&dataset, frame, 1) else {
                continue;
            };
            let wfc = frame.cam_from_world.inverse();
            for y in (4..gt.height()).step_by(16) {
                for x in (4..gt.width()).step_by(16) {
                    let z = gt.data()[y * gt.width() + x] as f64;
                    if !(z > 0.0 && z.is_finite()) {
                        continue;
                    }
                    let Some(b) = frame
                        .camera
                        .unproject(nalgebra::Point2::new(x as f64 + 0.5, y as f64 + 0.5))
                    else {
                        continue;
                    };
                    for (fi, f) in fracs.iter().enumerate() {
                        let pc = nalgebra::Point3::from(b * (z * f / b.z));
                        let pw = wfc * pc;
                        pts[fi].push([pw.x as f32, pw.y as f32, pw.z as f32]);
                    }
                }
            }
        }
        for (fi, p) in pts.iter().enumerate() {
            let mut d = vec![0f32; p.len()];
            matloc_nerf_field::FeatureField::density(model.field(), p, &mut d)?;
            let mut d: Vec<f32> = d.iter().map(|v| v / scale).collect();
            d.sort_by(f32::total_cmp);
            if d.is_empty() {
                continue;
            }
            let q = |f: f64| d[((d.len() - 1) as f64 * f) as usize];
            eprintln!(
                "field density at {:.2} x GT depth (units): p10 {:.2} p50 {:.2} p90 {:.2}",
                fracs[fi],
                q(0.1),
                q(0.5),
                q(0.9)
            );
        }
    }
    // NQ_EVAL_VIEWS=n evaluates n evenly spaced test views (quicker experiments).
    let mut eval_set = dataset.clone();
    if let Some(n) = std::env::var("NQ_EVAL_VIEWS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
    {
        let idx = eval_set.split_indices(Split::Test);
        let keep: Vec<usize> = (0..n.min(idx.len()))
            .map(|i| idx[i * idx.len() / n.min(idx.len()).max(1)])
            .collect();
        for i in idx {
            if !keep.contains(&i) {
                eval_set.frames[i].split = Split::Val;
            }
        }
    }
    let timing_only = args.get(5).is_some_and(|a| a == "timing");
    let report = if timing_only {
        None
    } else {
        let t_eval = Instant::now();
        let c_eval = cpu_seconds();
        let mut signed = Vec::new();
        let test_frames: Vec<_> = eval_set.split(Split::Test).cloned().collect();
        let dump = std::env::var("NQ_DUMP").ok();
        let r = evaluate(&model, &eval_set, Split::Test, 1, &[], |i, v| {
            if let Some(d) = &dump {
                // Rendered z-depth and accumulation as raw little-endian f32 (H×W).
                let bytes: Vec<u8> = v
                    .rendered
                    .z_depth
                    .iter()
                    .chain(&v.rendered.accumulation)
                    .flat_map(|x| x.to_le_bytes())
                    .collect();
                let _ = std::fs::write(format!("{d}/view{i}.f32"), bytes);
            }
            if let Ok(Some(gt)) =
                matloc_data::images::load_frame_depth(&eval_set, &test_frames[i], 1)
            {
                for (g, r) in gt.data().iter().zip(&v.rendered.z_depth) {
                    if *g > 0.0 && g.is_finite() {
                        signed.push(((r - g) / g) as f64);
                    }
                }
            }
            Ok(())
        })?;
        signed.sort_by(f64::total_cmp);
        let q = |f: f64| signed[((signed.len() - 1) as f64 * f) as usize];
        let within =
            signed.iter().filter(|e| e.abs() <= 0.02).count() as f64 / signed.len().max(1) as f64;
        eprintln!(
            "eval {} views in {:.1} s ({:.1} CPU-s); signed rel depth error p10 {:.4} p50 {:.4} p90 {:.4}; within 2 %: {:.3}",
            r.views.len(),
            t_eval.elapsed().as_secs_f64(),
            cpu_seconds() - c_eval,
            q(0.1),
            q(0.5),
            q(0.9),
            within
        );
        Some(r)
    };
    if let Some(report) = report {
        let render_s: Vec<f64> = report.views.iter().map(|v| v.render_s).collect();
        println!(
            "{{\"steps\": {}, \"train_s\": {train_s:.1}, \"train_cpu_s\": {train_cpu:.1}, \"test_psnr\": {:.3}, \"test_ssim\": {:.4}, \
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
