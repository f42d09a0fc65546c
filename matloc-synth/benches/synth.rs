//! Rendering throughput of the synthetic world at 320×240 (target: ≥ 20 images/s on 2 cores).
//!
//! `cargo bench -p matloc-synth --bench synth`; the "elements" throughput is images per second.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use matloc_synth::{SynthConfig, generate};

fn render_throughput(c: &mut Criterion) {
    let mut group = c.benchmark_group("synth_render_320x240");
    for preset in ["small", "rubble", "building"] {
        let cfg = SynthConfig::preset(preset).expect("preset exists");
        let (world, plan) = generate(&cfg).expect("preset generates");
        // A fixed spread of views across the survey, rendered in turn.
        let views: Vec<_> = plan
            .frames
            .iter()
            .step_by(plan.frames.len() / 16)
            .take(16)
            .collect();
        group.throughput(Throughput::Elements(views.len() as u64));
        group.sample_size(10);
        group.bench_function(preset, |b| {
            b.iter(|| {
                for f in &views {
                    std::hint::black_box(world.render(&f.camera, &f.cam_from_world, &cfg.render));
                }
            })
        });
    }
    group.finish();
}

fn world_generation(c: &mut Criterion) {
    let cfg = SynthConfig::preset("rubble").expect("preset exists");
    c.bench_function("synth_generate_rubble", |b| {
        b.iter(|| generate(&cfg).expect("generates"))
    });
}

criterion_group!(benches, render_throughput, world_generation);
criterion_main!(benches);
