//! Training on an analytic scene: a textured ground plane seen from hand-made cameras.

use matloc_nerf_field::ExponentialDecay;
use matloc_nerf_field::{FEATURE_DIM, FieldConfig, NerfactoField, SceneBox};
use matloc_render::{
    Background, MarchConfig, OccupancyConfig, RayBatch, RenderOptions, SamplerKind, Spacing,
    TrainConfig, Trainer, render_rays, render_rays_single_pass,
};

fn texture(x: f32, y: f32) -> [f32; 3] {
    // Several frequencies: the fine ones give parallax cues that pin the surface's depth.
    [
        0.5 + 0.25 * (1.3 * x).sin() + 0.2 * (5.0 * x + 1.0).sin() * (4.0 * y).cos(),
        0.5 + 0.25 * (1.1 * y).cos() + 0.2 * (6.0 * y).sin(),
        0.5 + 0.2 * (0.7 * (x + y)).sin() + 0.25 * (4.5 * (x - y)).cos(),
    ]
}

/// Rays of a `w × h` pinhole camera at `centre`, looking down (−z) with a tilt about x.
fn camera_rays(centre: [f32; 3], tilt: f32, w: usize, h: usize) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let f = 0.8 * w as f32; // ~64° horizontal field of view
    let (s, c) = tilt.sin_cos();
    let mut o = Vec::new();
    let mut d = Vec::new();
    for v in 0..h {
        for u in 0..w {
            let x = (u as f32 + 0.5 - w as f32 / 2.0) / f;
            let y = (v as f32 + 0.5 - h as f32 / 2.0) / f;
            // Camera axes (OpenCV): x right, y down, z forward. z_cam → world −z, tilted.
            let cam = [x, y, 1.0];
            let world = [cam[0], -cam[1] * c - cam[2] * s, -cam[2] * c + cam[1] * s];
            let n = (world[0] * world[0] + world[1] * world[1] + world[2] * world[2]).sqrt();
            o.push(centre);
            d.push([world[0] / n, world[1] / n, world[2] / n]);
        }
    }
    (o, d)
}

fn ground_truth(o: [f32; 3], d: [f32; 3]) -> ([f32; 3], f32) {
    let t = -o[2] / d[2];
    (texture(o[0] + t * d[0], o[1] + t * d[1]), t)
}

fn scene_box() -> SceneBox {
    SceneBox {
        min: [-4.0, -4.0, -1.0],
        max: [4.0, 4.0, 3.0],
    }
}

fn dataset(cams: &[([f32; 3], f32)], w: usize, h: usize) -> (RayBatch, Vec<f32>, Vec<f32>) {
    let mut origins = Vec::new();
    let mut dirs = Vec::new();
    for &(c, tilt) in cams {
        let (o, d) = camera_rays(c, tilt, w, h);
        origins.extend(o);
        dirs.extend(d);
    }
    let mut rgb = Vec::new();
    let mut depth = Vec::new();
    for (o, d) in origins.iter().zip(&dirs) {
        let (c, t) = ground_truth(*o, *d);
        rgb.extend(c);
        depth.push(t);
    }
    let rays = RayBatch::new(origins, dirs, 1.5, 12.0).unwrap();
    (rays, rgb, depth)
}

#[test]
fn training_lowers_loss_and_recovers_depth() {
    // A 4 × 4 grid of cameras at varying heights and tilts.
    let train_cams: Vec<([f32; 3], f32)> = (0..16)
        .map(|i| {
            let (gx, gy) = ((i % 4) as f32 - 1.5, (i / 4) as f32 - 1.5);
            let h = 2.6 + 0.3 * ((i * 7 % 5) as f32 - 2.0) / 2.0;
            let tilt = 0.25 * ((i * 3 % 5) as f32 - 2.0) / 2.0;
            ([1.2 * gx, 1.2 * gy, h], tilt)
        })
        .collect();
    let (rays, rgb, _) = dataset(&train_cams, 32, 24);
    let field = NerfactoField::new(FieldConfig {
        // Small capacity on purpose: with few views, a fine grid can memorise each pixel as
        // fog in front of its own camera instead of finding the shared surface.
        log2_table_size: 14,
        base_resolution: 4,
        max_resolution: 64,
        scene_box: scene_box(),
        num_images: 0,
        appearance_dim: 0,
        seed: 1,
        ..FieldConfig::default()
    })
    .unwrap();
    let steps = 400;
    let config = TrainConfig {
        batch_rays: 512,
        schedule: ExponentialDecay {
            lr_init: 1e-2,
            lr_final: 1e-3,
            max_steps: steps,
        },
        sampler: SamplerKind::Occupancy,
        march: MarchConfig {
            spacing: Spacing {
                linear_range_m: 8.0,
            },
            steps: 128,
            max_samples: 32,
        },
        occupancy: OccupancyConfig {
            resolution: 32,
            ..OccupancyConfig::default()
        },
        occupancy_update_every: 16,
        background: Background::Fixed([0.0; 3]),
        distortion_weight: 0.002,
        seed: 2,
        ..TrainConfig::default()
    };
    let mut trainer = Trainer::new(field, config).unwrap();
    let mut losses = Vec::new();
    trainer
        .fit(&rays, &rgb, steps, |p| losses.push(p.stats.loss))
        .unwrap();
    let first: f32 = losses[..10].iter().sum::<f32>() / 10.0;
    let last: f32 = losses[losses.len() - 20..].iter().sum::<f32>() / 20.0;
    eprintln!(
        "loss {first:.5} -> {last:.5}; occupied {:.3}",
        trainer.grid.as_ref().unwrap().occupied_fraction()
    );
    assert!(last < 0.25 * first, "loss {first} -> {last}");
    assert!(last < 0.01, "final loss {last}");

    // Held-out view: depth from the rendered weights against the analytic plane.
    let (test_rays, test_rgb, test_depth) = dataset(&[([0.5, -0.5, 3.2], 0.15)], 24, 18);
    let opts = RenderOptions {
        march: trainer.config.march,
        rgb: true,
        ..RenderOptions::default()
    };
    let out = render_rays(&trainer.field, &test_rays, trainer.grid.as_ref(), &opts).unwrap();
    let mut rel: Vec<f32> = (0..test_rays.len())
        .map(|i| {
            let d = out.normalized_depth(i).unwrap_or(0.0);
            (d - test_depth[i]).abs() / test_depth[i]
        })
        .collect();
    rel.sort_by(f32::total_cmp);
    let median = rel[rel.len() / 2];
    let mse: f32 = out
        .rgb
        .iter()
        .zip(&test_rgb)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f32>()
        / test_rgb.len() as f32;
    eprintln!("held-out: median depth error {median:.4}, rgb mse {mse:.5}");
    // Features: a subset equals the slice of all 47, and the round-based renderer agrees
    // with the single-pass one (early termination only drops negligible weight).
    let all: Vec<usize> = (0..FEATURE_DIM).collect();
    let sub = vec![45usize, 2, 33, 17];
    let render = |dims: &[usize], tile_rays: usize| {
        render_rays(
            &trainer.field,
            &test_rays,
            trainer.grid.as_ref(),
            &RenderOptions {
                march: trainer.config.march,
                dims: dims.to_vec(),
                tile_rays,
                ..RenderOptions::default()
            },
        )
        .unwrap()
    };
    let default_tile = RenderOptions::default().tile_rays;
    let full = render(&all, default_tile);
    let part = render(&sub, default_tile);
    for i in 0..test_rays.len() {
        for (j, &d) in sub.iter().enumerate() {
            assert_eq!(
                part.features[i * sub.len() + j],
                full.features[i * FEATURE_DIM + d]
            );
        }
        assert_eq!(part.depth[i], full.depth[i]);
    }
    // Rays are independent: one thread and small tiles give the same render bit for bit.
    let serial = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| render(&all, 40));
    assert_eq!(serial, full);
    let single = render_rays_single_pass(
        &trainer.field,
        &test_rays,
        trainer.grid.as_ref(),
        // The round-based renderer has no per-ray budget; match it.
        &MarchConfig {
            max_samples: 1 << 20,
            ..trainer.config.march
        },
        &all,
    )
    .unwrap();
    for i in 0..test_rays.len() {
        assert!((single.depth[i] - full.depth[i]).abs() < 1e-2 * single.depth[i].max(1.0));
        for d in 0..FEATURE_DIM {
            let (a, b) = (
                single.features[i * FEATURE_DIM + d],
                full.features[i * FEATURE_DIM + d],
            );
            assert!(
                (a - b).abs() < 1e-3 + 1e-2 * a.abs(),
                "ray {i} dim {d}: {a} vs {b}"
            );
        }
    }

    // Save / load renders identically.
    let dir = std::env::temp_dir().join(format!("matloc-render-test-{}", std::process::id()));
    trainer.field.save_dir(&dir).unwrap();
    let loaded = NerfactoField::load_dir(&dir).unwrap();
    let again = render_rays(&loaded, &test_rays, trainer.grid.as_ref(), &opts).unwrap();
    assert_eq!(again, out);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn non_finite_targets_are_a_typed_error_and_leave_weights() {
    let field = NerfactoField::new(FieldConfig {
        log2_table_size: 10,
        base_resolution: 4,
        max_resolution: 32,
        scene_box: scene_box(),
        seed: 3,
        ..FieldConfig::default()
    })
    .unwrap();
    let (rays, mut rgb, _) = dataset(&[([0.0, 0.0, 3.0], 0.0)], 8, 8);
    rgb[5] = f32::NAN;
    let mut trainer = Trainer::new(field.clone(), TrainConfig::default()).unwrap();
    let err = trainer.train_step(&rays, &rgb).unwrap_err();
    assert!(matches!(
        err,
        matloc_render::RenderError::NonFiniteLoss { step: 0, .. }
    ));
    assert_eq!(trainer.field.grid.table, field.grid.table);
    assert_eq!(trainer.field.col[0].w, field.col[0].w);
    assert_eq!(trainer.step(), 0);
}
