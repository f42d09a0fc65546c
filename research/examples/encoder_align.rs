//! Where on the image does the query encoder's cell look? For test views, correlates the
//! encoder's output with the block's features rendered at the true pose on grids shifted by
//! `(dx, dy)` pixels (principal point moved by `−(dx, dy)`), mean over the 47 dims. A peak away
//! from `(0, 0)` is a systematic misalignment between the encoder grid and the rendering grid.
//!
//!     cargo run --release -p matloc-research --example encoder_align -- MAP DATA [VIEWS]

use matloc_data::{Split, read_dataset};
use matloc_pipeline::LoadedMap;
use matloc_pipeline::eval::diagnostics::encoder_correlation;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: encoder_align MAP DATA [VIEWS]");
        std::process::exit(2);
    }
    let map = LoadedMap::open(std::path::Path::new(&args[1])).expect("map");
    let dataset = read_dataset(std::path::Path::new(&args[2])).expect("dataset");
    let views: usize = args.get(3).map_or(10, |v| v.parse().expect("views"));
    let shifts = [-2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0];
    let all: Vec<usize> = (0..47).collect();
    let mut sum_x = vec![0.0; shifts.len()];
    let mut sum_y = vec![0.0; shifts.len()];
    let mut n = 0usize;
    for f in dataset.split(Split::Test).take(views) {
        let (image, camera) = matloc_data::images::load_frame_image(&dataset, f, 1).expect("image");
        let h = map.place.predict(&image, &camera, 1).expect("place");
        let blk = &map.blocks.0[h[0].block.unwrap_or(0)];
        let enc = blk.encoder.encode(&image).expect("encode");
        let corr_at = |dx: f64, dy: f64| {
            let mut cam = camera;
            cam.cx -= dx;
            cam.cy -= dy;
            let t = blk
                .renderer
                .render_view(&cam, &f.cam_from_world, 4, &all)
                .expect("render");
            let corr = encoder_correlation(&t, &enc, &all);
            corr.iter().map(|c| c.unwrap_or(0.0)).sum::<f64>() / corr.len() as f64
        };
        let cx: Vec<f64> = shifts.iter().map(|&s| corr_at(s, 0.0)).collect();
        let cy: Vec<f64> = shifts.iter().map(|&s| corr_at(0.0, s)).collect();
        println!(
            "{}: x {:?}\n    y {:?}",
            f.image_path.display(),
            cx.iter().map(|c| format!("{c:.3}")).collect::<Vec<_>>(),
            cy.iter().map(|c| format!("{c:.3}")).collect::<Vec<_>>()
        );
        for k in 0..shifts.len() {
            sum_x[k] += cx[k];
            sum_y[k] += cy[k];
        }
        n += 1;
    }
    println!("shift (px)   {shifts:?}");
    let fmt = |v: &[f64]| {
        v.iter()
            .map(|c| format!("{:.4}", c / n as f64))
            .collect::<Vec<_>>()
    };
    println!("mean corr x  {:?}", fmt(&sum_x));
    println!("mean corr y  {:?}", fmt(&sum_y));
}
