//! Where a localizer-sized feature render spends its time.
//!
//! `cargo run --release -p matloc-research --example render_profile -- DATA MODEL_DIR [STRIDE]`

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use matloc_data::{Split, read_dataset};
use matloc_nerf_field::{FEATURE_DIM, FeatureField, FieldError};
use matloc_render::{
    NerfModel, PixelSet, RenderOptions, camera_rays, pixel_positions, render_rays,
};

struct Counting<'a> {
    inner: &'a dyn FeatureField,
    points: AtomicUsize,
    calls: AtomicUsize,
    nanos: AtomicUsize,
}

impl FeatureField for Counting<'_> {
    fn density_and_features(
        &self,
        points: &[[f32; 3]],
        dims: &[usize],
        density: &mut [f32],
        features: &mut [f32],
    ) -> Result<(), FieldError> {
        let t = Instant::now();
        self.points.fetch_add(points.len(), Ordering::Relaxed);
        self.calls.fetch_add(1, Ordering::Relaxed);
        let r = self
            .inner
            .density_and_features(points, dims, density, features);
        self.nanos
            .fetch_add(t.elapsed().as_nanos() as usize, Ordering::Relaxed);
        r
    }
    fn colour(
        &self,
        f: &[f32],
        d: &[[f32; 3]],
        a: Option<u32>,
        rgb: &mut [f32],
    ) -> Result<(), FieldError> {
        self.inner.colour(f, d, a, rgb)
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let data = Path::new(&args[1]);
    let model = NerfModel::load(Path::new(&args[2]))?;
    let stride: usize = args.get(3).map(|s| s.parse()).transpose()?.unwrap_or(4);
    let spr: usize = args.get(4).map(|s| s.parse()).transpose()?.unwrap_or(0);
    let mint: f32 = args.get(5).map(|s| s.parse()).transpose()?.unwrap_or(-1.0);
    let dataset = read_dataset(data)?;
    let cfg = model.config().clone();
    let counting = Counting {
        inner: model.field(),
        points: AtomicUsize::new(0),
        calls: AtomicUsize::new(0),
        nanos: AtomicUsize::new(0),
    };
    let mut opts = RenderOptions {
        march: cfg.render.march,
        dims: (0..FEATURE_DIM).collect(),
        rgb: false,
        appearance: None,
        background: model.background(),
        min_transmittance: cfg.render.min_transmittance,
        samples_per_round: cfg.render.samples_per_round,
        tile_rays: cfg.render.tile_rays,
        min_density: cfg.render.min_density * model.field().density_scale(),
    };
    if spr > 0 {
        opts.samples_per_round = spr;
    }
    if let Some(st) = args.get(6) {
        opts.march.steps = st.parse()?;
    }
    if mint >= 0.0 {
        opts.min_transmittance = mint;
    }
    let (mut total, mut rays_n) = (Duration::ZERO, 0usize);
    for frame in dataset.split(Split::Test).take(10) {
        let (px, _, _) = pixel_positions(
            &frame.camera,
            &PixelSet::Grid {
                stride: stride as u32,
            },
        )?;
        let (mut rays, _, _) = camera_rays(
            &frame.camera,
            &frame.cam_from_world,
            &px,
            cfg.near_m,
            cfg.far_m,
        )?;
        if let Some((lo, hi)) = cfg.clip_box() {
            rays.clip_to_box(lo, hi);
        }
        let t = Instant::now();
        render_rays(&counting, &rays, Some(model.render_grid()), &opts)?;
        total += t.elapsed();
        rays_n += rays.len();
    }
    let pts = counting.points.load(Ordering::Relaxed);
    println!(
        "rays/view {} samples/ray {:.1} calls/view {:.1} render {:.1} ms/view field {:.1} ms/view (CPU-summed)",
        rays_n / 10,
        pts as f64 / rays_n as f64,
        counting.calls.load(Ordering::Relaxed) as f64 / 10.0,
        total.as_secs_f64() * 100.0,
        counting.nanos.load(Ordering::Relaxed) as f64 / 1e6 / 10.0
    );
    Ok(())
}
