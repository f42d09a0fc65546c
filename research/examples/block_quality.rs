//! The paper's Table 6 for built maps: per map, its blocks' sampling space (the sub-NeRF box
//! volume) against the rendering quality of the test views each block serves (PSNR / SSIM of
//! RGB rendered at the true pose by the serving sub-NeRF). Localization errors of the same
//! maps come from `matloc eval`.
//!
//!     cargo run --release -p matloc-research --example block_quality -- DATA MAP...

use matloc_core::metrics::{psnr, ssim};
use matloc_data::{Split, read_dataset};
use matloc_partition::{assign_pose, samples_from_dataset};
use matloc_pipeline::LoadedMap;
use matloc_render::{PixelSet, RenderRequest, render_view};

fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: block_quality DATA MAP...");
        std::process::exit(2);
    }
    let dataset = read_dataset(std::path::Path::new(&args[1])).expect("dataset");
    let test_idx = dataset.split_indices(Split::Test);
    println!(
        "| map | blocks | poses per block | sampling space per block (10³ m³, mean) | test PSNR (dB) | test SSIM | NeRF training (s, all blocks) |"
    );
    println!("|---|---|---|---|---|---|---|");
    for root in &args[2..] {
        let map = LoadedMap::open(std::path::Path::new(root)).expect("map");
        let mut samples = samples_from_dataset(&dataset, &test_idx, &map.config.samples, &|| {})
            .expect("samples");
        // Test poses are not partition members: make sure no id collides with one.
        for s in &mut samples {
            s.id = usize::MAX;
        }
        let (mut p, mut s) = (Vec::new(), Vec::new());
        for (k, &i) in test_idx.iter().enumerate() {
            let f = &dataset.frames[i];
            let b = assign_pose(&map.partition, &samples[k]).unwrap_or(0);
            let (image, camera) =
                matloc_data::images::load_frame_image(&dataset, f, 1).expect("image");
            let nerf = map.nerf(b).expect("block NeRF");
            let view = render_view(
                nerf,
                &camera,
                &f.cam_from_world,
                &PixelSet::Full,
                &RenderRequest {
                    rgb: true,
                    dims: Vec::new(),
                    appearance: None,
                },
            )
            .expect("render");
            let rgb = view.rgb_image().expect("rgb");
            p.push(psnr(&rgb, &image).expect("psnr"));
            s.push(ssim(&rgb, &image).expect("ssim"));
        }
        let blocks = &map.partition.blocks;
        let sizes: Vec<usize> = blocks.iter().map(|b| b.pose_ids.len()).collect();
        let vol: Vec<f64> = blocks.iter().map(|b| b.sampling_volume_m3 / 1e3).collect();
        let nerf_s: f64 = map
            .dir
            .manifest()
            .stages
            .iter()
            .filter(|st| st.name.starts_with("nerf/"))
            .map(|st| st.seconds)
            .sum();
        println!(
            "| {root} | {} | {sizes:?} | {:.0} | {:.2} | {:.3} | {nerf_s:.0} |",
            blocks.len(),
            mean(&vol),
            mean(&p),
            mean(&s),
        );
    }
}
