//! Query-encoder study on a real NeRF map: trains an encoder on a dataset's training views with
//! the block's rendered features as targets, then measures what matching needs, on training
//! views (fit) and on test views (generalisation), next to a perfect encoder (the NeRF's own
//! features rendered at the true pose):
//!
//! * from the true pose: MNN matches, precision (≤ 2 px) and PnP inliers;
//! * from perturbed starts (3 m / 5°, the pipeline's coarse-pose regime): success within
//!   1 m / 5° after one render–match–PnP step;
//! * per-dim Pearson correlation of encoder vs rendered features.
//!
//! Dims: greedy forward selection (N_s = 5) maximising correct matches from the true pose on the
//! training views (the pipeline's selector optimises the same thing on GT pairs), and all 47.
//!
//!     cargo run --release -p matloc-research --example encoder_study -- MAP DATA [CONFIG_JSON]
//!
//! `MAP` is a map directory (its `blocks/0` NeRF is used), `DATA` the dataset it was built from,
//! `CONFIG_JSON` an [`EncoderTrainConfig`] (missing fields take the defaults), e.g.
//! `'{"steps":600,"net":{"width":64}}'`. `ENC_VIEWS` caps the training views (default 48).

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::{Camera, FeatureMap, Image, Pose};
use matloc_data::{Split, read_dataset};
use matloc_encoder::{
    ENCODER_STRIDE, EncoderSample, EncoderTrainConfig, QueryEncoder, train_encoder,
};
use matloc_match::ViewRenderer;
use matloc_match::localize::{correct_matches, render_map_points, solve_pose, timed_match};
use matloc_match::nerf_view::NerfViewRenderer;
use matloc_match::{FeatureStats, MnnConfig, MnnMatcher, QueryFeatures, RenderedPoints};
use matloc_pipeline::gt::{PerturbKind, Perturbation};
use matloc_pnp::LoRansacPnp;
use matloc_render::NerfModel;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

struct View {
    image: Image<f32>,
    camera: Camera,
    pose: Pose,
    /// Map side rendered at the true pose (all dims).
    truth: RenderedPoints,
    /// Features rendered at the true pose on the query grid (the perfect encoder).
    oracle: FeatureMap,
    /// Map sides rendered at perturbed starts.
    starts: Vec<(Pose, RenderedPoints)>,
}

#[derive(Default, Clone, Copy)]
struct Score {
    matches: f64,
    correct: f64,
    correct8: f64,
    inliers: f64,
    localized: usize,
    tries: usize,
}

fn score(
    views: &[View],
    queries: &[FeatureMap],
    dims: &[usize],
    matcher: &MnnMatcher,
    starts: bool,
) -> Score {
    let mut options = matloc_pnp::PnpOptions::default();
    if let Some(px) = std::env::var("ENC_PNP_PX")
        .ok()
        .and_then(|v| v.parse().ok())
    {
        options.ransac.max_error_px = px;
    }
    let solver = LoRansacPnp::new(options);
    let mut s = Score::default();
    for (v, q) in views.iter().zip(queries) {
        let query = QueryFeatures::new(q.clone(), ENCODER_STRIDE as f64);
        let tm = timed_match(matcher, &query, &v.truth, Some(dims)).expect("match");
        s.matches += tm.matches.len() as f64;
        s.correct += correct_matches(&tm.matches, &v.camera, &v.pose, 2.0) as f64;
        s.correct8 += correct_matches(&tm.matches, &v.camera, &v.pose, 8.0) as f64;
        if !starts {
            continue;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        if let Ok(r) = solve_pose(&tm.matches, &v.camera, &solver, &mut rng) {
            s.inliers += r.inliers.iter().filter(|&&b| b).count() as f64;
        }
        {
            for (_, map) in &v.starts {
                let tm = timed_match(matcher, &query, map, Some(dims)).expect("match");
                s.tries += 1;
                let mut rng = ChaCha8Rng::seed_from_u64(7);
                if let Ok(r) = solve_pose(&tm.matches, &v.camera, &solver, &mut rng) {
                    let ni = r.inliers.iter().filter(|&&b| b).count();
                    if ni >= 12
                        && translation_error_m(&r.cam_from_world, &v.pose) <= 1.0
                        && rotation_error_deg(&r.cam_from_world, &v.pose) <= 5.0
                    {
                        s.localized += 1;
                    }
                }
            }
        }
    }
    let n = views.len().max(1) as f64;
    s.matches /= n;
    s.correct /= n;
    s.correct8 /= n;
    s.inliers /= n;
    s
}

fn greedy(views: &[View], queries: &[FeatureMap], matcher: &MnnMatcher, n_s: usize) -> Vec<usize> {
    let mut sel: Vec<usize> = Vec::new();
    for _ in 0..n_s {
        let mut best = (f64::MIN, 0);
        for d in 0..47 {
            if sel.contains(&d) {
                continue;
            }
            let mut trial = sel.clone();
            trial.push(d);
            let c = score(views, queries, &trial, matcher, false).correct;
            if c > best.0 {
                best = (c, d);
            }
        }
        sel.push(best.1);
    }
    sel
}

fn correlations(views: &[View], queries: &[FeatureMap], dims: &[usize]) -> Vec<f64> {
    dims.iter()
        .map(|&d| {
            let (mut xs, mut ys) = (Vec::new(), Vec::new());
            for (v, q) in views.iter().zip(queries) {
                let (o, w) = (&v.oracle, v.oracle.width());
                for i in 0..w * o.height() {
                    let t = o.pixel(i % w, i / w)[d];
                    if t.is_finite() && v.truth_valid(i) {
                        xs.push(t as f64);
                        ys.push(q.pixel(i % w, i / w)[d] as f64);
                    }
                }
            }
            matloc_core::metrics::pearson(&xs, &ys).unwrap_or(0.0)
        })
        .collect()
}

impl View {
    fn truth_valid(&self, i: usize) -> bool {
        self.truth.valid()[i]
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: encoder_study MAP DATA [CONFIG_JSON]");
        std::process::exit(2);
    }
    let cfg: EncoderTrainConfig = args
        .get(3)
        .map(|s| serde_json::from_str(s).expect("config JSON"))
        .unwrap_or_default();
    let max_views: usize = std::env::var("ENC_VIEWS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(48);
    let model =
        NerfModel::load(&std::path::Path::new(&args[1]).join("blocks/0")).expect("block 0 NeRF");
    let renderer = NerfViewRenderer::new(model, "blocks/0");
    let dataset = read_dataset(std::path::Path::new(&args[2])).expect("dataset");
    let all: Vec<usize> = (0..47).collect();
    let perturb = Perturbation {
        kind: PerturbKind::UniformBall,
        translation_m: 3.0,
        rotation_deg: 5.0,
    };
    let t0 = Instant::now();
    let load = |split: Split, cap: usize, starts: usize| -> Vec<View> {
        let frames: Vec<_> = dataset.split(split).collect();
        let n = cap.min(frames.len());
        let step = frames.len() as f64 / n.max(1) as f64;
        (0..n)
            .map(|k| {
                let f = frames[((k as f64 + 0.5) * step) as usize];
                let (image, camera) =
                    matloc_data::images::load_frame_image(&dataset, f, 1).expect("image");
                let truth = render_map_points(
                    &renderer,
                    &camera,
                    &f.cam_from_world,
                    ENCODER_STRIDE,
                    &all,
                    0.5,
                )
                .expect("render");
                let r = renderer
                    .render_view(&camera, &f.cam_from_world, ENCODER_STRIDE, &all)
                    .expect("render");
                let oracle = FeatureMap::from_vec(r.cols, r.rows, 47, r.features).expect("map");
                let mut prng = ChaCha8Rng::seed_from_u64(1000 + k as u64);
                let starts = (0..starts)
                    .map(|_| {
                        let p = perturb.apply(&f.cam_from_world, &mut prng);
                        let m =
                            render_map_points(&renderer, &camera, &p, ENCODER_STRIDE, &all, 0.5)
                                .expect("render");
                        (p, m)
                    })
                    .collect();
                View {
                    image,
                    camera,
                    pose: f.cam_from_world,
                    truth,
                    oracle,
                    starts,
                }
            })
            .collect()
    };
    let train = load(Split::Train, max_views, 0);
    let test = load(Split::Test, usize::MAX, 3);
    // Fit is measured on 10 evenly spaced training views (with perturbed starts).
    let n_fit = 10.min(train.len());
    let fit: Vec<View> = (0..n_fit)
        .map(|k| {
            let v = &train[k * train.len() / n_fit];
            let mut prng = ChaCha8Rng::seed_from_u64(2000 + k as u64);
            let starts = (0..3)
                .map(|_| {
                    let p = perturb.apply(&v.pose, &mut prng);
                    let m = render_map_points(&renderer, &v.camera, &p, ENCODER_STRIDE, &all, 0.5)
                        .expect("render");
                    (p, m)
                })
                .collect();
            View {
                image: v.image.clone(),
                camera: v.camera,
                pose: v.pose,
                truth: v.truth.clone(),
                oracle: v.oracle.clone(),
                starts,
            }
        })
        .collect();
    println!(
        "{} train views, {} test views, {}x{} px; rendered in {:.1} s",
        train.len(),
        test.len(),
        train[0].image.width(),
        train[0].image.height(),
        t0.elapsed().as_secs_f64()
    );
    // Statistics and samples.
    let mut rows = Vec::new();
    let samples: Vec<EncoderSample> = train
        .iter()
        .map(|v| {
            let r = renderer
                .render_view(&v.camera, &v.pose, ENCODER_STRIDE, &all)
                .expect("render");
            for i in 0..r.cols * r.rows {
                if r.has_surface(i, cfg.min_accumulation) {
                    rows.extend_from_slice(&r.features[i * 47..(i + 1) * 47]);
                }
            }
            EncoderSample {
                image: v.image.clone(),
                target: r,
                view: None,
            }
        })
        .collect();
    let stats = FeatureStats::from_features(&rows, 47);
    let matcher = MnnMatcher::new(MnnConfig {
        stats: Some(stats.clone()),
        ..Default::default()
    });
    let t1 = Instant::now();
    let mut last = None;
    let loaded = std::env::var("ENC_LOAD")
        .ok()
        .map(|p| QueryEncoder::load(std::path::Path::new(&p)).expect("encoder file"));
    let enc = if let Some(e) = loaded {
        e
    } else {
        train_encoder(&samples, all.clone(), stats, &cfg, &mut |p| {
            if p.step % 100 == 0 || p.step == p.steps {
                eprintln!(
                    "  step {}/{} loss {:.3} (mse {:.3}, nce {:.3}) {:.0} s",
                    p.step,
                    p.steps,
                    p.loss,
                    p.mse,
                    p.nce,
                    t1.elapsed().as_secs_f64()
                );
            }
            last = Some(*p);
        })
        .expect("train")
    };
    if let Ok(p) = std::env::var("ENC_SAVE") {
        enc.save(std::path::Path::new(&p)).expect("save encoder");
    }
    let train_s = t1.elapsed().as_secs_f64();
    let encode = |views: &[View], e: &QueryEncoder| -> Vec<FeatureMap> {
        views
            .iter()
            .map(|v| e.encode(&v.image).expect("encode"))
            .collect()
    };
    let q_fit = encode(&fit, &enc);
    let q_test = encode(&test, &enc);
    let o_fit: Vec<FeatureMap> = fit.iter().map(|v| v.oracle.clone()).collect();
    // Noise-weighted matching: standardise each dim by the encoder's residual RMS on the fit
    // views instead of the feature spread (a per-dim Mahalanobis weight under Gaussian noise).
    let matcher_w = {
        let mut sq = vec![0.0f64; 47];
        let mut n = 0usize;
        for (v, q) in fit.iter().zip(&q_fit) {
            let w = v.oracle.width();
            for i in 0..w * v.oracle.height() {
                if !v.truth_valid(i) {
                    continue;
                }
                let (o, e) = (v.oracle.pixel(i % w, i / w), q.pixel(i % w, i / w));
                for d in 0..47 {
                    let r = (e[d] - o[d]) as f64;
                    sq[d] += r * r;
                }
                n += 1;
            }
        }
        let full = enc.stats().clone();
        let std: Vec<f32> = sq
            .iter()
            .map(|s| ((s / n.max(1) as f64).sqrt() as f32).max(1e-6))
            .collect();
        eprintln!(
            "residual RMS / feature std per dim: {:?}",
            std.iter()
                .zip(&full.std)
                .map(|(r, f)| format!("{:.2}", r / f))
                .collect::<Vec<_>>()
        );
        MnnMatcher::new(MnnConfig {
            stats: Some(FeatureStats {
                mean: full.mean.clone(),
                std,
            }),
            ..Default::default()
        })
    };
    let o_test: Vec<FeatureMap> = test.iter().map(|v| v.oracle.clone()).collect();
    if std::env::var("ENC_ERRORS").is_ok() {
        let rerender = |cam: &matloc_core::Camera, p: &Pose| {
            render_map_points(&renderer, cam, p, ENCODER_STRIDE, &all, 0.5).expect("render")
        };
        error_structure(&test, &q_test, &all, &matcher, &rerender);
        error_structure(&test, &o_test, &all, &matcher, &rerender);
        return;
    }
    let n_s: usize = std::env::var("ENC_NS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5);
    let sel = greedy(&fit, &q_fit, &matcher, n_s);
    let sel_oracle = if std::env::var("ENC_SKIP_ORACLE").is_ok() {
        vec![8, 17, 0, 1, 2]
    } else {
        greedy(&fit, &o_fit, &matcher, 5)
    };
    let p = last.unwrap_or(matloc_encoder::EncoderProgress {
        step: 0,
        steps: 0,
        loss: f32::NAN,
        mse: f32::NAN,
        nce: f32::NAN,
    });
    println!(
        "config {}",
        serde_json::to_string(&cfg).expect("config JSON")
    );
    println!(
        "training: {} steps in {train_s:.0} s, final loss {:.3} (mse {:.3}, nce {:.3}); greedy dims {sel:?} (perfect encoder: {sel_oracle:?})",
        p.steps, p.loss, p.mse, p.nce
    );
    println!(
        "| query | dims | views | matches (true pose) | correct <= 2 px | precision | <= 8 px | PnP inliers | localized <= 1 m / 5 deg from 3 m / 5 deg starts | corr (min / median) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for (name, dims_name, dims, m) in [
        ("encoder", "greedy-5", &sel, &matcher),
        ("encoder", "all-47", &all, &matcher),
        ("encoder", "all-47 noise-weighted", &all, &matcher_w),
        ("perfect", "greedy-5", &sel_oracle, &matcher),
        ("perfect", "encoder's greedy-5", &sel, &matcher),
    ] {
        for (vname, views, q) in [
            (
                "train",
                &fit,
                if name == "encoder" { &q_fit } else { &o_fit },
            ),
            (
                "test",
                &test,
                if name == "encoder" { &q_test } else { &o_test },
            ),
        ] {
            let s = score(views, q, dims, m, true);
            let mut c = correlations(views, q, dims);
            c.sort_by(f64::total_cmp);
            println!(
                "| {name} | {dims_name} | {vname} | {:.0} | {:.0} | {:.3} | {:.3} | {:.1} | {}/{} | {:.2} / {:.2} |",
                s.matches,
                s.correct,
                s.correct / s.matches.max(1.0),
                s.correct8 / s.matches.max(1.0),
                s.inliers,
                s.localized,
                s.tries,
                c[0],
                c[c.len() / 2]
            );
        }
    }
}

/// Per view: how coherent the match errors from the true pose are (share of their variance an
/// affine function of the pixel explains), and the pose PnP makes of them.
fn error_structure(
    views: &[View],
    queries: &[FeatureMap],
    dims: &[usize],
    matcher: &MnnMatcher,
    rerender: &dyn Fn(&matloc_core::Camera, &Pose) -> RenderedPoints,
) {
    let rounds: usize = std::env::var("FM_ROUNDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let px: f64 = std::env::var("ENC_PNP_PX")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(12.0);
    let mut options = matloc_pnp::PnpOptions::default();
    options.ransac.max_error_px = px;
    let solver = LoRansacPnp::new(options);
    println!(
        "| view | matches | median err px | mean err vec px | affine-explained var | PnP t err m | r err deg | inliers | t err horiz / vert m | depth m | FM t / r | starts: PnP t err | starts: FM t err |"
    );
    let mut fm_cfg = matloc_match::featuremetric::FeatureMetricConfig::default();
    if let Ok(l) = std::env::var("FM_LEVELS") {
        fm_cfg.levels = l
            .split(',')
            .map(|v| v.parse().expect("FM_LEVELS"))
            .collect();
    }
    fm_cfg.robust_scale = std::env::var("FM_SCALE")
        .ok()
        .map(|v| v.parse().expect("FM_SCALE"));
    let fm_dims: Vec<usize> = match std::env::var("FM_DIMS") {
        Ok(v) if v == "coarse" => (0..18).chain(32..47).collect(),
        _ => dims.to_vec(),
    };
    let dims_fm = &fm_dims[..];
    let stats = matcher.config.stats.as_ref();
    let fm = |q: &QueryFeatures,
              map: &RenderedPoints,
              cam: &matloc_core::Camera,
              p: &matloc_core::Pose| {
        let t = Instant::now();
        let out = matloc_match::featuremetric::refine_pose(
            q,
            map,
            cam,
            p,
            Some(dims_fm),
            stats,
            true,
            &fm_cfg,
        );
        if std::env::var("FM_TIME").is_ok() {
            eprintln!(
                "fm {:.1} ms, {:?} steps",
                t.elapsed().as_secs_f64() * 1e3,
                out.as_ref().map(|o| o.steps)
            );
        }
        out.map(|o| o.cam_from_world).unwrap_or(*p)
    };
    let (mut pnp_all, mut fm_all) = (Vec::new(), Vec::new());
    for (k, (v, q)) in views.iter().zip(queries).enumerate() {
        let query = QueryFeatures::new(q.clone(), ENCODER_STRIDE as f64);
        let tm = timed_match(matcher, &query, &v.truth, Some(dims)).expect("match");
        let mut rows = Vec::new();
        let mut depths = Vec::new();
        for m in &tm.matches {
            let x = nalgebra::Point3::from(m.point_world);
            if let Some(u) = v.camera.project_world(&v.pose, &x) {
                let e = [u.x - m.query_px[0], u.y - m.query_px[1]];
                if e[0].hypot(e[1]) < 40.0 {
                    rows.push((m.query_px, e));
                }
                depths.push((v.pose.transform_point(&x)).z);
            }
        }
        let n = rows.len().max(1) as f64;
        let mean = [
            rows.iter().map(|r| r.1[0]).sum::<f64>() / n,
            rows.iter().map(|r| r.1[1]).sum::<f64>() / n,
        ];
        let mut mags: Vec<f64> = rows.iter().map(|r| r.1[0].hypot(r.1[1])).collect();
        mags.sort_by(f64::total_cmp);
        // Least squares e = A [u v 1] per component.
        let mut explained = 0.0;
        let mut total = 0.0;
        for c in 0..2 {
            let a = nalgebra::DMatrix::from_fn(rows.len(), 3, |i, j| match j {
                0 => rows[i].0[0],
                1 => rows[i].0[1],
                _ => 1.0,
            });
            let b = nalgebra::DVector::from_fn(rows.len(), |i, _| rows[i].1[c]);
            if let Ok(sol) = a.clone().svd(true, true).solve(&b, 1e-9) {
                let r = &b - &a * sol;
                total += b.iter().map(|x| x * x).sum::<f64>();
                explained +=
                    b.iter().map(|x| x * x).sum::<f64>() - r.iter().map(|x| x * x).sum::<f64>();
            }
        }
        depths.sort_by(f64::total_cmp);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let pose = solve_pose(&tm.matches, &v.camera, &solver, &mut rng);
        match pose {
            Ok(r) => {
                let c_est = r.cam_from_world.inverse().translation.vector;
                let c_true = v.pose.inverse().translation.vector;
                let d = c_est - c_true;
                let refined = fm(&query, &v.truth, &v.camera, &r.cam_from_world);
                let mut st = (String::new(), String::new());
                for (_, map) in &v.starts {
                    let tm = timed_match(matcher, &query, map, Some(dims)).expect("match");
                    let mut rng = ChaCha8Rng::seed_from_u64(7);
                    if let Ok(r) = solve_pose(&tm.matches, &v.camera, &solver, &mut rng) {
                        let e0 = translation_error_m(&r.cam_from_world, &v.pose);
                        let mut p1 = fm(&query, map, &v.camera, &r.cam_from_world);
                        for _ in 1..rounds {
                            let m2 = rerender(&v.camera, &p1);
                            if std::env::var("FM_PNP2").is_ok() {
                                let tm =
                                    timed_match(matcher, &query, &m2, Some(dims)).expect("match");
                                let mut rng = ChaCha8Rng::seed_from_u64(7);
                                if let Ok(r) = solve_pose(&tm.matches, &v.camera, &solver, &mut rng)
                                {
                                    p1 = r.cam_from_world;
                                }
                            }
                            p1 = fm(&query, &m2, &v.camera, &p1);
                        }
                        let e1 = translation_error_m(&p1, &v.pose);
                        st.0 += &format!("{e0:.2} ");
                        st.1 += &format!("{e1:.2} ");
                        pnp_all.push(e0);
                        fm_all.push(e1);
                    }
                }
                println!(
                    "| {k} | {} | {:.1} | ({:.1}, {:.1}) | {:.2} | {:.2} | {:.2} | {} | {:.2} / {:.2} | {:.0} | {:.2} / {:.2} | {} | {} |",
                    rows.len(),
                    mags[mags.len() / 2],
                    mean[0],
                    mean[1],
                    explained / total.max(1e-12),
                    translation_error_m(&r.cam_from_world, &v.pose),
                    rotation_error_deg(&r.cam_from_world, &v.pose),
                    r.inliers.iter().filter(|&&b| b).count(),
                    d.x.hypot(d.y),
                    d.z.abs(),
                    depths[depths.len() / 2],
                    translation_error_m(&refined, &v.pose),
                    rotation_error_deg(&refined, &v.pose),
                    st.0,
                    st.1,
                );
            }
            Err(e) => println!("| {k} | {} | PnP failed: {e} |", rows.len()),
        }
    }
    pnp_all.sort_by(f64::total_cmp);
    fm_all.sort_by(f64::total_cmp);
    let med = |v: &[f64]| v.get(v.len() / 2).copied().unwrap_or(f64::NAN);
    let within = |v: &[f64]| v.iter().filter(|&&e| e <= 1.0).count();
    println!(
        "starts: PnP median {:.2} m ({} of {} within 1 m), + feature-metric median {:.2} m ({} within 1 m)",
        med(&pnp_all),
        within(&pnp_all),
        pnp_all.len(),
        med(&fm_all),
        within(&fm_all)
    );
}
