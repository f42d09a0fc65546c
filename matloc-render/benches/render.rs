//! Rendering depth + 47-d features at 320×240, and full training steps of 4096 rays.
//!
//! Setup trains a small field on an analytic textured plane (as in the synthetic test) so the
//! occupancy grid and early termination see a realistic density. The machine is shared and
//! has 2 cores: wall-clock numbers are noisy.

use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use matloc_nerf_field::{ExponentialDecay, FEATURE_DIM, FieldConfig, NerfactoField, SceneBox};
use matloc_render::{
    MarchConfig, OccupancyConfig, OccupancyGrid, RayBatch, RenderOptions, SamplerKind, Spacing,
    TrainConfig, Trainer, render_rays,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn texture(x: f32, y: f32) -> [f32; 3] {
    [
        0.5 + 0.25 * (1.3 * x).sin() + 0.2 * (5.0 * x + 1.0).sin() * (4.0 * y).cos(),
        0.5 + 0.25 * (1.1 * y).cos() + 0.2 * (6.0 * y).sin(),
        0.5 + 0.2 * (0.7 * (x + y)).sin() + 0.25 * (4.5 * (x - y)).cos(),
    ]
}

fn camera(centre: [f32; 3], tilt: f32, w: usize, h: usize) -> RayBatch {
    let f = 0.8 * w as f32;
    let (s, c) = tilt.sin_cos();
    let mut o = Vec::new();
    let mut d = Vec::new();
    for v in 0..h {
        for u in 0..w {
            let x = (u as f32 + 0.5 - w as f32 / 2.0) / f;
            let y = (v as f32 + 0.5 - h as f32 / 2.0) / f;
            let wv = [x, -y * c - s, -c + y * s];
            let n = (wv[0] * wv[0] + wv[1] * wv[1] + wv[2] * wv[2]).sqrt();
            o.push(centre);
            d.push([wv[0] / n, wv[1] / n, wv[2] / n]);
        }
    }
    RayBatch::new(o, d, 1.5, 12.0).expect("rays")
}

fn scene_box() -> SceneBox {
    SceneBox {
        min: [-4.0, -4.0, -1.0],
        max: [4.0, 4.0, 3.0],
    }
}

fn training_set() -> (RayBatch, Vec<f32>) {
    let mut all = RayBatch::default();
    let mut rgb = Vec::new();
    for i in 0..16 {
        let (gx, gy) = ((i % 4) as f32 - 1.5, (i / 4) as f32 - 1.5);
        let r = camera(
            [1.2 * gx, 1.2 * gy, 2.6],
            0.1 * ((i % 3) as f32 - 1.0),
            64,
            48,
        );
        for k in 0..r.len() {
            let (o, d) = (r.origins[k], r.directions[k]);
            let t = -o[2] / d[2];
            rgb.extend(texture(o[0] + t * d[0], o[1] + t * d[1]));
        }
        all.origins.extend(r.origins);
        all.directions.extend(r.directions);
        all.near.extend(r.near);
        all.far.extend(r.far);
    }
    (all, rgb)
}

fn march() -> MarchConfig {
    MarchConfig {
        spacing: Spacing {
            linear_range_m: 8.0,
        },
        steps: 128,
        max_samples: 48,
    }
}

fn train_config(batch: usize, steps: u64) -> TrainConfig {
    TrainConfig {
        batch_rays: batch,
        schedule: ExponentialDecay {
            lr_init: 1e-2,
            lr_final: 1e-3,
            max_steps: steps,
        },
        sampler: SamplerKind::Occupancy,
        march: march(),
        ..TrainConfig::default()
    }
}

fn bench(c: &mut Criterion) {
    let (rays, rgb) = training_set();
    // A trained field for rendering (small table: quick to train in the bench setup).
    let small = NerfactoField::new(FieldConfig {
        log2_table_size: 16,
        base_resolution: 4,
        max_resolution: 128,
        scene_box: scene_box(),
        appearance_dim: 0,
        ..FieldConfig::default()
    })
    .expect("field");
    let mut trainer = Trainer::new(small, train_config(1024, 300)).expect("trainer");
    trainer.fit(&rays, &rgb, 300, |_| {}).expect("train");
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let grid = OccupancyGrid::from_field(
        OccupancyConfig {
            resolution: 128,
            ..OccupancyConfig::default()
        },
        scene_box(),
        &trainer.field,
        &mut rng,
    )
    .expect("grid");
    eprintln!("occupied fraction (128^3): {:.3}", grid.occupied_fraction());
    let view = camera([0.3, -0.2, 2.8], 0.1, 320, 240);
    let all: Vec<usize> = (0..FEATURE_DIM).collect();

    let mut g = c.benchmark_group("render");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(6))
        .warm_up_time(Duration::from_secs(1))
        .throughput(Throughput::Elements(view.len() as u64));
    let depth_feat = RenderOptions {
        march: march(),
        dims: all.clone(),
        ..RenderOptions::default()
    };
    g.bench_function("depth_features47_320x240_occupancy", |b| {
        b.iter(|| {
            render_rays(&trainer.field, black_box(&view), Some(&grid), &depth_feat).expect("render")
        })
    });
    let rgb_opts = RenderOptions {
        march: march(),
        dims: Vec::new(),
        rgb: true,
        ..RenderOptions::default()
    };
    g.bench_function("rgb_depth_320x240_occupancy", |b| {
        b.iter(|| {
            render_rays(&trainer.field, black_box(&view), Some(&grid), &rgb_opts).expect("render")
        })
    });
    let five = RenderOptions {
        march: march(),
        dims: vec![3, 10, 33, 40, 46],
        ..RenderOptions::default()
    };
    g.bench_function("depth_features5_320x240_occupancy", |b| {
        b.iter(|| {
            render_rays(&trainer.field, black_box(&view), Some(&grid), &five).expect("render")
        })
    });
    g.bench_function("depth_features47_320x240_no_grid", |b| {
        b.iter(|| render_rays(&trainer.field, black_box(&view), None, &depth_feat).expect("render"))
    });

    // A full training step at the paper's batch size with the default (nerfacto-sized) field.
    let big = NerfactoField::new(FieldConfig {
        scene_box: scene_box(),
        ..FieldConfig::default()
    })
    .expect("field");
    let mut t2 = Trainer::new(big, train_config(4096, 1000)).expect("trainer");
    t2.fit(&rays, &rgb, 20, |_| {}).expect("warm-up");
    g.throughput(Throughput::Elements(4096));
    let idx: Vec<usize> = (0..4096).map(|i| (i * 7919) % rays.len()).collect();
    let batch = rays.gather(&idx);
    let target: Vec<f32> = idx
        .iter()
        .flat_map(|&i| rgb[3 * i..3 * i + 3].to_vec())
        .collect();
    g.bench_function("train_step_4096_rays", |b| {
        b.iter(|| t2.train_step(black_box(&batch), &target).expect("step"))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
