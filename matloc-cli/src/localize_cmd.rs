//! `matloc localize`: localize query images against a map, one JSON line per query.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::{Camera, Distortion, Image, Pose};
use matloc_data::{Dataset, Split};
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::{Method, MethodOptions, localize_with};
use serde::Deserialize;

use crate::split_args::{self, SplitArgs};

/// Arguments of `matloc localize`.
#[derive(Args)]
pub struct LocalizeArgs {
    /// Map directory (from `matloc map build`).
    #[arg(long)]
    map: PathBuf,
    /// Query images (PNG/JPEG).
    #[arg(long, num_args = 1.., required = true)]
    images: Vec<PathBuf>,
    /// Intrinsics of the queries: a JSON file with nerfstudio keys (`w`, `h`, `fl_x`, `fl_y`,
    /// `cx`, `cy`, optional `k1 k2 p1 p2 k3`) or a matloc camera (`width`, `height`, `fx`, ...).
    #[arg(long, conflicts_with = "data")]
    intrinsics: Option<PathBuf>,
    /// Dataset the queries belong to: gives each image its own intrinsics and, when it has
    /// poses, the errors against them.
    #[arg(long)]
    data: Option<PathBuf>,
    /// Method.
    #[arg(long, default_value = "matloc")]
    method: Method,
    /// Test split of the --data dataset when it has none; by default the map's.
    #[command(flatten)]
    split: SplitArgs,
}

/// One query ready to localize.
pub struct Query {
    /// Name (the image path as given).
    pub name: String,
    /// RGB image at the map's resolution.
    pub image: Image<f32>,
    /// Its camera.
    pub camera: Camera,
    /// Ground truth, when known.
    pub cam_from_world: Option<Pose>,
}

#[derive(Deserialize)]
struct NerfstudioIntrinsics {
    w: u32,
    h: u32,
    fl_x: f64,
    fl_y: f64,
    cx: f64,
    cy: f64,
    #[serde(default)]
    k1: f64,
    #[serde(default)]
    k2: f64,
    #[serde(default)]
    p1: f64,
    #[serde(default)]
    p2: f64,
    #[serde(default)]
    k3: f64,
}

/// Reads an intrinsics file (nerfstudio keys or a matloc camera).
pub fn read_intrinsics(path: &Path) -> Result<Camera> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let camera = if let Ok(n) = serde_json::from_str::<NerfstudioIntrinsics>(&text) {
        Camera {
            width: n.w,
            height: n.h,
            fx: n.fl_x,
            fy: n.fl_y,
            cx: n.cx,
            cy: n.cy,
            distortion: Distortion {
                k1: n.k1,
                k2: n.k2,
                p1: n.p1,
                p2: n.p2,
                k3: n.k3,
            },
        }
    } else {
        serde_json::from_str::<Camera>(&text).with_context(|| {
            format!(
                "{}: expected nerfstudio intrinsics (w, h, fl_x, fl_y, cx, cy) or a matloc camera (width, height, fx, fy, cx, cy)",
                path.display()
            )
        })?
    };
    camera
        .validate()
        .with_context(|| format!("{}: invalid intrinsics", path.display()))?;
    Ok(camera)
}

/// Brings a query to the map's image size when it differs (same aspect ratio; the pose does
/// not depend on resolution, and the encoder was trained at the map's size).
pub fn to_map_resolution(
    image: Image<f32>,
    camera: Camera,
    map_camera: Option<&Camera>,
    name: &str,
) -> Result<(Image<f32>, Camera)> {
    let (w, h, c) = image.shape();
    if c != 3 {
        bail!("{name}: expected an RGB image, got {c} channels");
    }
    let camera = if (w as u32, h as u32) != (camera.width, camera.height) {
        camera.rescaled(w as u32, h as u32).with_context(|| {
            format!(
                "{name}: the image is {w}×{h} but the intrinsics are for {}×{}",
                camera.width, camera.height
            )
        })?
    } else {
        camera
    };
    let Some(target) = map_camera else {
        return Ok((image, camera));
    };
    if (target.width, target.height) == (camera.width, camera.height) {
        return Ok((image, camera));
    }
    let rescaled = camera
        .rescaled(target.width, target.height)
        .with_context(|| {
            format!(
                "{name}: a {w}×{h} query cannot be brought to the map's {}×{} images (aspect ratio differs)",
                target.width, target.height
            )
        })?;
    let resized = matloc_place::resize_area(&image, target.width as usize, target.height as usize);
    Ok((resized, rescaled))
}

fn frame_of<'a>(dataset: &'a Dataset, path: &Path) -> Option<&'a matloc_data::dataset::Frame> {
    let canon = |p: &Path| std::fs::canonicalize(p).ok();
    let want = canon(path);
    dataset.frames.iter().find(|f| {
        let p = dataset.image_path(f);
        (want.is_some() && canon(&p) == want) || p.ends_with(path)
    })
}

/// Loads the queries named on the command line.
fn load_queries(args: &LocalizeArgs, map: &LoadedMap) -> Result<Vec<Query>> {
    let dataset = match &args.data {
        Some(d) => {
            let mut ds = matloc_data::read_dataset(d)
                .with_context(|| format!("reading dataset {}", d.display()))?;
            let split = args.split.for_map(map.dir.manifest().split.as_ref())?;
            split_args::apply(split.as_ref(), &mut ds)
                .with_context(|| format!("splitting dataset {}", d.display()))?;
            Some(ds)
        }
        None => {
            if args.split.spec()?.is_some() {
                bail!("--test-every / --test-list need --data");
            }
            None
        }
    };
    let fixed = match &args.intrinsics {
        Some(p) => Some(read_intrinsics(p)?),
        None => None,
    };
    let target = map.camera();
    let mut out = Vec::new();
    for path in &args.images {
        let name = path.display().to_string();
        let image = matloc_data::images::load_rgb(path)
            .with_context(|| format!("reading query image {name}"))?;
        let (camera, gt) = if let Some(ds) = &dataset {
            let f = frame_of(ds, path).with_context(|| {
                format!("{name} is not an image of dataset {}", ds.root.display())
            })?;
            if f.split == Split::Train {
                tracing::warn!(query = %name, "the query is a training frame of the dataset");
            }
            (f.camera, Some(f.cam_from_world))
        } else if let Some(c) = fixed {
            (c, None)
        } else if let Some(c) = target {
            (c, None)
        } else {
            bail!("{name}: no intrinsics (pass --intrinsics FILE or --data DIR)");
        };
        let (image, camera) = to_map_resolution(image, camera, target.as_ref(), &name)?;
        out.push(Query {
            name,
            image,
            camera,
            cam_from_world: gt,
        });
    }
    Ok(out)
}

/// The test queries of a dataset.
pub fn dataset_queries(dataset: &Dataset, map: &LoadedMap, limit: usize) -> Result<Vec<Query>> {
    let target = map.camera();
    let mut out = Vec::new();
    for f in dataset
        .split(Split::Test)
        .take(if limit == 0 { usize::MAX } else { limit })
    {
        let path = dataset.image_path(f);
        let name = f.image_path.display().to_string();
        let image = matloc_data::images::load_rgb(&path)
            .with_context(|| format!("reading query image {}", path.display()))?;
        let (image, camera) = to_map_resolution(image, f.camera, target.as_ref(), &name)?;
        out.push(Query {
            name,
            image,
            camera,
            cam_from_world: Some(f.cam_from_world),
        });
    }
    Ok(out)
}

/// Runs `matloc localize`.
pub fn run(args: &LocalizeArgs) -> Result<()> {
    let map = LoadedMap::open(&args.map)
        .with_context(|| format!("opening map {}", args.map.display()))?;
    let queries = load_queries(args, &map)?;
    let options = MethodOptions::default();
    for q in &queries {
        let r = localize_with(&map, args.method, &q.name, &q.image, &q.camera, &options)
            .with_context(|| format!("localizing {}", q.name))?;
        let mut line = serde_json::to_value(&r)?;
        if let (Some(gt), Some(est)) = (q.cam_from_world, r.cam_from_world) {
            line["error_translation_m"] = translation_error_m(&est, &gt).into();
            line["error_rotation_deg"] = rotation_error_deg(&est, &gt).into();
        }
        outln!("{}", serde_json::to_string(&line)?)?;
    }
    Ok(())
}
