//! `matloc eval`: localize a dataset's test queries with each method on one map and write a
//! report (markdown in the paper's Table 1/2 layouts, JSON, and PNG plots).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use matloc_core::Pose;
use matloc_pipeline::methods::{Method, MethodOptions, QueryResult, localize_with};
use matloc_pipeline::stages::LoadedMap;
use matloc_pipeline::{MethodSummary, QueryOutcome, accuracy_table, summarize, timing_table};

use crate::localize_cmd::{Query, dataset_queries};
use crate::plot::{self, Canvas};
use crate::progress;

/// Arguments of `matloc eval`.
#[derive(Args, Clone)]
pub struct EvalArgs {
    /// Map directory.
    #[arg(long)]
    pub map: PathBuf,
    /// Dataset whose test split are the queries.
    #[arg(long)]
    pub data: PathBuf,
    /// Methods, comma-separated (matloc, rgb-keypoints, curriculum-inerf, inerf).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "matloc,rgb-keypoints,curriculum-inerf,inerf"
    )]
    pub methods: Vec<Method>,
    /// Use at most this many test queries (0 = all).
    #[arg(long, default_value_t = 0)]
    pub queries: usize,
    /// Use at most this many queries for the iNeRF baselines (0 = as many as the others): they
    /// take tens of seconds per query on the CPU.
    #[arg(long, default_value_t = 0)]
    pub inerf_queries: usize,
    /// Report directory (created).
    #[arg(long)]
    pub out: PathBuf,
}

/// One method's results.
struct MethodRun {
    method: Method,
    results: Vec<QueryResult>,
    outcomes: Vec<QueryOutcome>,
    summary: MethodSummary,
}

/// Runs `matloc eval`; returns the path of the markdown report.
pub fn run(args: &EvalArgs, quiet: bool) -> Result<PathBuf> {
    if args.methods.is_empty() {
        bail!("no methods given");
    }
    let map = LoadedMap::open(&args.map)
        .with_context(|| format!("opening map {}", args.map.display()))?;
    let dataset = matloc_data::read_dataset(&args.data)
        .with_context(|| format!("reading dataset {}", args.data.display()))?;
    let queries = dataset_queries(&dataset, &map, args.queries)?;
    if queries.is_empty() {
        bail!("{} has no test views to localize", args.data.display());
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let options = MethodOptions::default();
    let mut runs = Vec::new();
    for &method in &args.methods {
        let n = match method {
            Method::Inerf | Method::CurriculumInerf if args.inerf_queries > 0 => {
                args.inerf_queries.min(queries.len())
            }
            _ => queries.len(),
        };
        let subset = spaced(&queries, n);
        let bar = progress::bar(subset.len() as u64, method.name(), quiet);
        let t = Instant::now();
        let mut results = Vec::new();
        let mut outcomes = Vec::new();
        for q in subset {
            let r = localize_with(&map, method, &q.name, &q.image, &q.camera, &options)
                .with_context(|| format!("{method} on {}", q.name))?;
            if let Some(gt) = q.cam_from_world {
                outcomes.push(r.outcome(gt));
            }
            bar.inc(1);
            results.push(r);
        }
        bar.finish_and_clear();
        let summary = summarize(method.name(), &outcomes);
        println!(
            "{:<17} {} queries in {:>6.1} s: median {:.3} m / {:.3}°, refused {:.0} %, {:.3} s/query",
            method.name(),
            results.len(),
            t.elapsed().as_secs_f64(),
            summary.median_translation_m,
            summary.median_rotation_deg,
            100.0 * summary.refusal_rate,
            summary.mean_seconds
        );
        runs.push(MethodRun {
            method,
            results,
            outcomes,
            summary,
        });
    }

    // Files.
    let mut lines = String::new();
    for r in &runs {
        for (res, out) in r.results.iter().zip(&r.outcomes) {
            let mut v = serde_json::to_value(res)?;
            if let Some((t, rot)) = out.errors() {
                v["error_translation_m"] = t.into();
                v["error_rotation_deg"] = rot.into();
            }
            v["cam_from_world_gt"] = serde_json::to_value(out.cam_from_world_gt)?;
            lines.push_str(&serde_json::to_string(&v)?);
            lines.push('\n');
        }
    }
    write(&args.out.join("results.jsonl"), lines.as_bytes())?;
    let summaries: Vec<&MethodSummary> = runs.iter().map(|r| &r.summary).collect();
    write(
        &args.out.join("summary.json"),
        serde_json::to_string_pretty(&summaries)?.as_bytes(),
    )?;
    plot_cdf(&runs, &args.out.join("error_cdf.png"))?;
    plot_topdown(&runs, &dataset, &map, &args.out.join("topdown.png"))?;
    plot_stage_times(&runs, &args.out.join("stage_times.png"))?;
    let report = report(&runs, &map, &dataset, args)?;
    let path = args.out.join("report.md");
    write(&path, report.as_bytes())?;
    Ok(path)
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    matloc_data::fsutil::write_atomic(path, bytes)
        .with_context(|| format!("writing {}", path.display()))
}

fn spaced(v: &[Query], n: usize) -> Vec<&Query> {
    if n >= v.len() {
        return v.iter().collect();
    }
    let step = v.len() as f64 / n as f64;
    (0..n)
        .map(|k| &v[((k as f64 + 0.5) * step) as usize])
        .collect()
}

fn center(p: &Pose) -> [f64; 3] {
    let c = p.inverse().translation.vector;
    [c.x, c.y, c.z]
}

/// Cumulative distribution of translation error (log axis, 1 cm – 100 m) per method.
fn plot_cdf(runs: &[MethodRun], path: &Path) -> Result<()> {
    let (w, h) = (900u32, 560u32);
    let mut c = Canvas::new(w, h, plot::WHITE);
    c.text_px(
        20.0,
        12.0,
        "translation error CDF (refused = never)",
        plot::BLACK,
        2,
    );
    let area = [70.0, 50.0, w as f64 - 100.0, h as f64 - 120.0];
    let (lo, hi) = (-2.0f64, 2.0f64);
    c.set_view(area, [lo, 0.0], [hi, 1.0], false);
    for k in [-2, -1, 0, 1, 2] {
        let x = k as f64;
        c.line([x, 0.0], [x, 1.0], [225, 225, 225], 1.0);
        let (px, py) = c.to_px(x, 0.0);
        let label = match k {
            -2 => "1 CM".to_string(),
            -1 => "10 CM".to_string(),
            0 => "1 M".to_string(),
            1 => "10 M".to_string(),
            _ => "100 M".to_string(),
        };
        c.text_px(px - 12.0, py + 6.0, &label, plot::BLACK, 1);
    }
    for f in [0.25, 0.5, 0.75, 1.0] {
        c.line([lo, f], [hi, f], [225, 225, 225], 1.0);
        let (px, py) = c.to_px(lo, f);
        c.text_px(
            px - 40.0,
            py - 3.0,
            &format!("{:.0} %", 100.0 * f),
            plot::BLACK,
            1,
        );
    }
    for (i, r) in runs.iter().enumerate() {
        let mut e: Vec<f64> = r
            .outcomes
            .iter()
            .filter_map(|o| o.errors().map(|e| e.0))
            .collect();
        e.sort_by(f64::total_cmp);
        let n = r.outcomes.len().max(1) as f64;
        let col = plot::palette(i);
        let mut prev = [lo, 0.0];
        for (k, v) in e.iter().enumerate() {
            let x = v.max(1e-2).log10().min(hi);
            let y = (k + 1) as f64 / n;
            c.line(prev, [x, prev[1]], col, 2.0);
            c.line([x, prev[1]], [x, y], col, 2.0);
            prev = [x, y];
        }
        c.line(prev, [hi, prev[1]], col, 2.0);
        let ly = 60.0 + 16.0 * i as f64;
        c.fill_rect_px(area[0] + 10.0, ly, 12.0, 8.0, col, 1.0);
        c.text_px(area[0] + 28.0, ly, r.method.name(), plot::BLACK, 1);
    }
    c.frame(plot::BLACK, "log10 m");
    c.save_png(path)
}

/// Top-down map: training cameras, ground-truth query positions and each method's estimates.
fn plot_topdown(
    runs: &[MethodRun],
    dataset: &matloc_data::Dataset,
    map: &LoadedMap,
    path: &Path,
) -> Result<()> {
    let (w, h) = (900u32, 900u32);
    let mut c = Canvas::new(w, h, plot::WHITE);
    c.text_px(
        20.0,
        12.0,
        "top-down: truth (black) and estimates",
        plot::BLACK,
        2,
    );
    let mut min = [f64::INFINITY; 2];
    let mut max = [f64::NEG_INFINITY; 2];
    for f in &dataset.frames {
        let p = f.center();
        for k in 0..2 {
            min[k] = min[k].min(p[k]);
            max[k] = max[k].max(p[k]);
        }
    }
    for b in &map.partition.blocks {
        for k in 0..2 {
            min[k] = min[k].min(b.bounds.min[k]);
            max[k] = max[k].max(b.bounds.max[k]);
        }
    }
    c.set_view(
        [40.0, 50.0, w as f64 - 80.0, h as f64 - 110.0],
        min,
        max,
        true,
    );
    for b in &map.partition.blocks {
        c.rect(
            [b.bounds.min[0], b.bounds.min[1]],
            [b.bounds.max[0], b.bounds.max[1]],
            plot::palette(b.id + 6),
            1.0,
        );
    }
    for f in dataset.split(matloc_data::Split::Train) {
        let p = f.center();
        c.point(p[0], p[1], 2.0, plot::GREY, 0.6);
    }
    for (i, r) in runs.iter().enumerate() {
        let col = plot::palette(i);
        for o in &r.outcomes {
            let g = center(&o.cam_from_world_gt);
            if let Some(est) = &o.cam_from_world_est {
                let e = center(est);
                c.line([g[0], g[1]], [e[0], e[1]], col, 1.0);
                c.point(e[0], e[1], 3.0, col, 0.9);
            }
        }
        let ly = 60.0 + 16.0 * i as f64;
        c.fill_rect_px(w as f64 - 200.0, ly, 12.0, 8.0, col, 1.0);
        c.text_px(w as f64 - 182.0, ly, r.method.name(), plot::BLACK, 1);
    }
    if let Some(r) = runs.first() {
        for o in &r.outcomes {
            let g = center(&o.cam_from_world_gt);
            c.point(g[0], g[1], 4.0, plot::BLACK, 1.0);
        }
    }
    c.frame(plot::BLACK, "m");
    c.save_png(path)
}

/// Mean seconds per query and stage, one stacked bar per method.
fn plot_stage_times(runs: &[MethodRun], path: &Path) -> Result<()> {
    let (w, h) = (900u32, 120 + 60 * runs.len() as u32);
    let mut c = Canvas::new(w, h, plot::WHITE);
    c.text_px(
        20.0,
        12.0,
        "mean time per query by stage (s)",
        plot::BLACK,
        2,
    );
    let max_t = runs
        .iter()
        .map(|r| {
            r.summary
                .stage_mean_seconds
                .iter()
                .map(|s| s.1)
                .sum::<f64>()
        })
        .fold(1e-3, f64::max);
    let mut stage_names: Vec<String> = Vec::new();
    for r in runs {
        for (s, _) in &r.summary.stage_mean_seconds {
            if !stage_names.contains(s) {
                stage_names.push(s.clone());
            }
        }
    }
    let left = 160.0;
    let width = w as f64 - left - 40.0;
    for (i, r) in runs.iter().enumerate() {
        let y = 50.0 + 60.0 * i as f64;
        c.text_px(10.0, y + 10.0, r.method.name(), plot::BLACK, 1);
        let mut x = left;
        for (s, t) in &r.summary.stage_mean_seconds {
            let k = stage_names.iter().position(|n| n == s).unwrap_or(0);
            let bw = width * t / max_t;
            c.fill_rect_px(x, y, bw, 30.0, plot::palette(k), 1.0);
            x += bw;
        }
        let total: f64 = r.summary.stage_mean_seconds.iter().map(|s| s.1).sum();
        c.text_px(x + 6.0, y + 10.0, &format!("{total:.3} S"), plot::BLACK, 1);
    }
    let mut x = 20.0;
    let y = h as f64 - 30.0;
    for (k, s) in stage_names.iter().enumerate() {
        c.fill_rect_px(x, y, 12.0, 8.0, plot::palette(k), 1.0);
        x += 16.0 + c.text_px(x + 16.0, y, s, plot::BLACK, 1) + 14.0;
    }
    c.save_png(path)
}

fn report(
    runs: &[MethodRun],
    map: &LoadedMap,
    dataset: &matloc_data::Dataset,
    args: &EvalArgs,
) -> Result<String> {
    let mut s = String::new();
    writeln!(s, "# matloc evaluation report\n")?;
    writeln!(
        s,
        "Map `{}`, queries: test split of `{}`.\n",
        args.map.display(),
        args.data.display()
    )?;
    // Scene facts.
    let (mut min, mut max) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for f in &dataset.frames {
        let p = f.center();
        for k in 0..3 {
            min[k] = min[k].min(p[k]);
            max[k] = max[k].max(p[k]);
        }
    }
    if let Some(f) = dataset.split(matloc_data::Split::Train).next() {
        let ground = dataset.metadata.bounds_min.map_or(0.0, |b| b[2]);
        let altitude = f.center()[2] - ground;
        writeln!(
            s,
            "Scene: cameras span {:.0} × {:.0} m at {:.0}–{:.0} m height; {}×{} px images, focal {:.0} px; ground sampling distance ≈ {:.2} m/px at nadir from {:.0} m.\n",
            max[0] - min[0],
            max[1] - min[1],
            min[2],
            max[2],
            f.camera.width,
            f.camera.height,
            f.camera.fx,
            altitude / f.camera.fx,
            altitude
        )?;
    }
    let m = map.dir.manifest();
    writeln!(s, "## Map\n")?;
    writeln!(s, "| block | poses | selected dims |\n|---|---|---|")?;
    for (b, e) in m.blocks.iter().enumerate() {
        writeln!(s, "| {b} | {} | {:?} |", e.num_poses, e.selected_dims)?;
    }
    writeln!(s, "\nBuild stages (s): {}\n", {
        let v: Vec<String> = m
            .stages
            .iter()
            .map(|st| format!("{} {:.0}", st.name, st.seconds))
            .collect();
        v.join(", ")
    })?;
    writeln!(s, "## Table 1 — accuracy\n")?;
    let summaries: Vec<MethodSummary> = runs.iter().map(|r| r.summary.clone()).collect();
    writeln!(s, "{}", accuracy_table(&summaries))?;
    writeln!(
        s,
        "Medians over all queries count a refused query as ∞; \"accepted\" medians are over returned poses only. A false accept is a returned pose outside 5 m / 10°.\n"
    )?;
    writeln!(s, "## Table 2 — iterations and time\n")?;
    writeln!(s, "{}", timing_table(&summaries))?;
    if let Some(base) = summaries.iter().find(|x| x.method == "matloc") {
        for o in summaries.iter().filter(|x| x.method != "matloc") {
            writeln!(
                s,
                "- matloc is {:.1}× faster than {} per query.",
                o.mean_seconds / base.mean_seconds.max(1e-9),
                o.method
            )?;
        }
        writeln!(s)?;
    }
    writeln!(s, "## Plots\n")?;
    writeln!(s, "- `error_cdf.png`: translation error CDF per method")?;
    writeln!(
        s,
        "- `topdown.png`: truth and estimated camera positions, block bounds"
    )?;
    writeln!(s, "- `stage_times.png`: mean time per query and stage\n")?;
    writeln!(
        s,
        "Per-query results: `results.jsonl`; summaries: `summary.json`."
    )?;
    Ok(s)
}
