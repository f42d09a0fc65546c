//! How well the sun's direction is found from a dataset's images (`estimate_sun`), against
//! the `sun_direction` its metadata holds: for the surface from depth files (when there are
//! any) and from triangulated points, the angle off, the search's time, its edge contrast,
//! pairs and rival, and how much of the true sun's shadow the estimate's masks cover (IoU over
//! the views searched).
//!
//!     cargo run --release -p matloc-research --example sun_study -- DATA [DATA ...]

use matloc_core::Image;
use matloc_data::images::{downscale_depth, load_frame_image};
use matloc_data::{Split, read_dataset};
use matloc_surface::sunlight::{
    DepthView, estimate_sun, nearest_views, shadow_mask, sun_edges, sun_views,
};
use matloc_surface::{FrameSurfaces, SurfaceChoice, SurfaceConfig};

/// The pipeline's settings: eight views, six neighbours, a 192-cell grid (depth kept to 640).
const VIEWS: usize = 8;
const SIDE: usize = 192;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.is_empty() {
        eprintln!("usage: sun_study DATA [DATA ...]");
        std::process::exit(2);
    }
    println!(
        "| data | surface | off | seconds | contrast | pairs | rival | IoU | true sun: contrast, pairs |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for data in &args {
        let dataset = read_dataset(std::path::Path::new(data)).expect("dataset");
        let truth = dataset.metadata.sun_direction.map(nalgebra::Vector3::from);
        let train = dataset.split_indices(Split::Train);
        let frames: Vec<_> = train.iter().map(|&i| &dataset.frames[i]).collect();
        let centres: Vec<_> = frames.iter().map(|f| f.center()).collect();
        let neighbours = nearest_views(&centres, 6);
        let picked = matloc_core::subset::evenly_spaced(frames.len(), VIEWS);
        let images: Vec<Image<f32>> = picked
            .iter()
            .map(|&v| load_frame_image(&dataset, frames[v], 1).expect("image").0)
            .collect();
        let has_depth = frames.iter().all(|f| f.depth_path.is_some());
        let mut sources = vec![("triangulated", SurfaceChoice::Triangulate)];
        if has_depth {
            sources.insert(0, ("depth files", SurfaceChoice::Depth));
        }
        for (name, choice) in sources {
            let cfg = SurfaceConfig {
                source: choice,
                ..SurfaceConfig::default()
            };
            let s = FrameSurfaces::prepare(&dataset, &train, &cfg, &|_, _, _| {}).expect("surface");
            let depths: Vec<Image<f32>> = train
                .iter()
                .map(|&i| {
                    let d = s.depth(&dataset, i).expect("depth");
                    let k = (d.width().max(d.height()) / 640) as u32;
                    if k >= 2 { downscale_depth(&d, k) } else { d }
                })
                .collect();
            let views: Vec<DepthView> = frames
                .iter()
                .zip(&depths)
                .map(|(f, d)| DepthView::of(f, d))
                .collect();
            let search = sun_views(&views, &neighbours, &picked, &images);
            let t = std::time::Instant::now();
            let Some(est) = estimate_sun(&search, SIDE) else {
                println!("| {data} | {name} | none | | | | | |");
                continue;
            };
            let secs = t.elapsed().as_secs_f64();
            let true_edges = match truth {
                Some(sun) => match sun_edges(&search, &sun, SIDE).contrast() {
                    Some((c, n)) => format!("{c:.3}, {n}"),
                    None => "no edges".into(),
                },
                None => "?".into(),
            };
            let (off, iou) = match truth {
                Some(sun) => {
                    let (mut both, mut either) = (0usize, 0usize);
                    for v in &search {
                        let a = shadow_mask(&v.view, &v.others, &sun, SIDE);
                        let b = shadow_mask(&v.view, &v.others, &est.direction, SIDE);
                        for (x, y) in a.data().iter().zip(b.data()) {
                            both += usize::from(*x > 0.5 && *y > 0.5);
                            either += usize::from(*x > 0.5 || *y > 0.5);
                        }
                    }
                    (
                        format!("{:.2}°", est.direction.angle(&sun).to_degrees()),
                        format!("{:.3}", both as f64 / either.max(1) as f64),
                    )
                }
                None => ("?".into(), "?".into()),
            };
            println!(
                "| {data} | {name} | {off} | {secs:.1} | {:.3} | {} | {:.3} | {iou} | {true_edges} |",
                est.contrast, est.pairs, est.rival
            );
        }
    }
}
