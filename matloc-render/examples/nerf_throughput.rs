//! Training throughput on a dataset, for the PyTorch comparison in `bench/nerf/`.
//!
//! `cargo run --release -p matloc-render --example nerf_throughput -- DATA STEPS [SAMPLER]`
//! trains `STEPS` steps of 4096 random rays and prints one JSON line with rays/s (wall) and
//! rays per CPU-second. `SAMPLER` is `uniform48` (48 stratified samples per ray, what the
//! PyTorch reference does; default) or `occupancy` (the trainer's default sampler).

use std::time::Instant;

use matloc_data::read_dataset;
use matloc_nerf_field::NerfactoField;
use matloc_render::{MarchConfig, SamplerKind, TrainImages, Trainer, config_for_dataset};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// User + system CPU seconds of this process (Linux `/proc/self/stat`, 100 ticks/s).
fn cpu_seconds() -> f64 {
    let Ok(s) = std::fs::read_to_string("/proc/self/stat") else {
        return f64::NAN;
    };
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = s.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| {
        f.get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    (tick(11) + tick(12)) / 100.0
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let data = args
        .get(1)
        .ok_or("usage: nerf_throughput DATA STEPS [uniform48|occupancy]")?;
    let steps: u64 = args.get(2).map_or(Ok(50), |s| s.parse())?;
    let sampler = args.get(3).map_or("uniform48", String::as_str);
    let dataset = read_dataset(std::path::Path::new(data))?;
    let mut cfg = config_for_dataset(&dataset, 10_000);
    match sampler {
        "uniform48" => {
            cfg.train.sampler = SamplerKind::Uniform;
            cfg.train.march = MarchConfig {
                steps: 48,
                max_samples: 48,
                ..cfg.train.march
            };
        }
        "occupancy" => {}
        other => return Err(format!("unknown sampler {other}").into()),
    }
    let images = TrainImages::load(&dataset, matloc_data::Split::Train, 1, &cfg)?;
    let mut trainer = Trainer::new(NerfactoField::new(cfg.field.clone())?, cfg.train.clone())?;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batch = cfg.train.batch_rays;
    // Warm-up (page faults of the table, first occupancy update).
    for _ in 0..3 {
        let (rays, rgb) = images.sample(batch, &mut rng);
        trainer.train_step(&rays, &rgb)?;
    }
    let (t0, c0) = (Instant::now(), cpu_seconds());
    let mut samples = 0usize;
    let mut last = None;
    for _ in 0..steps {
        let (rays, rgb) = images.sample(batch, &mut rng);
        let s = trainer.train_step(&rays, &rgb)?;
        samples += s.samples;
        last = Some(s);
    }
    let wall = t0.elapsed().as_secs_f64();
    let cpu = cpu_seconds() - c0;
    let rays = (steps as usize * batch) as f64;
    println!(
        "{{\"impl\": \"rust\", \"sampler\": \"{sampler}\", \"steps\": {steps}, \"batch\": {batch}, \
         \"threads\": {}, \"wall_s\": {wall:.3}, \"cpu_s\": {cpu:.3}, \"rays_per_s\": {:.1}, \
         \"rays_per_cpu_s\": {:.1}, \"samples_per_ray\": {:.1}, \"final_loss\": {:.5}, \
         \"near_m\": {}, \"far_m\": {}, \"linear_range_m\": {}, \"log2_table_size\": {}}}",
        rayon::current_num_threads(),
        rays / wall,
        rays / cpu,
        samples as f64 / rays,
        last.map_or(f32::NAN, |s| s.loss),
        cfg.near_m,
        cfg.far_m,
        cfg.train.march.spacing.linear_range_m,
        cfg.field.log2_table_size,
    );
    Ok(())
}
