//! Rendering a camera view: pixels → rays through the lens model → volume rendering.

use matloc_core::{Camera, FeatureMap, Image};
use matloc_nerf_field::FEATURE_DIM;
use nalgebra::{Isometry3, Point2};

use crate::error::RenderError;
use crate::model::{DepthKind, NerfModel};
use crate::rays::RayBatch;
use crate::render::{RenderOptions, render_rays};

/// Which pixels of a camera to render.
///
/// Pixel coordinates are continuous, with the centre of pixel `(col, row)` at
/// `(col + 0.5, row + 0.5)` (the workspace convention).
#[derive(Clone, Debug, PartialEq)]
pub enum PixelSet {
    /// Every pixel centre, `width × height` results in row-major order.
    Full,
    /// A regular grid of `stride × stride` blocks: sample `(i, j)` is the centre of block
    /// `(i, j)`, at `((i + 0.5)·stride, (j + 0.5)·stride)`, for `i < width / stride`,
    /// `j < height / stride` (integer division). `stride = 1` is [`PixelSet::Full`]; `stride = 4`
    /// at 320×240 gives the 80×60 grid of a stride-4 CNN feature map.
    Grid {
        /// Block size in pixels (≥ 1).
        stride: u32,
    },
    /// Arbitrary continuous pixel positions; results in list order (`width = len`, `height = 1`).
    List(Vec<Point2<f64>>),
}

/// What to render besides depth and accumulation (always rendered).
#[derive(Clone, Debug, PartialEq)]
pub struct RenderRequest {
    /// Render RGB (runs the colour MLP; costs roughly as much again as depth alone).
    pub rgb: bool,
    /// Feature dims to render, any subset of `0..47` in any order (`0..32` = f_pos, the 16
    /// hash levels × 2, coarse to fine; `32..47` = f_mlp). Empty = none.
    pub dims: Vec<usize>,
    /// Appearance embedding (training image index) for RGB; `None` = the field's fallback
    /// (mean of the trained embeddings), the right choice for unseen views.
    pub appearance: Option<u32>,
}

impl Default for RenderRequest {
    fn default() -> Self {
        Self {
            rgb: false,
            dims: (0..FEATURE_DIM).collect(),
            appearance: None,
        }
    }
}

/// The result of [`render_view`]: one entry per requested pixel, in row-major order of
/// `width × height` (for [`PixelSet::List`], `height = 1`).
#[derive(Clone, Debug, PartialEq)]
pub struct RenderedView {
    /// Columns of the result grid.
    pub width: usize,
    /// Rows of the result grid.
    pub height: usize,
    /// The continuous pixel position of every entry.
    pub pixels: Vec<Point2<f64>>,
    /// `false` where the lens model could not undistort the pixel; such entries are all zero.
    pub valid: Vec<bool>,
    /// RGB in `[0, 1]`, 3 per entry (background-composited); empty unless requested.
    pub rgb: Vec<f32>,
    /// Expected distance along the ray (metres), `Σ w_k t_k / Σ w_k`; 0 where nothing was hit
    /// (accumulation < 1e-4).
    pub distance: Vec<f32>,
    /// Expected z-depth (along the optical axis, metres): `distance · cos(angle to the axis)`,
    /// comparable with `matloc synth` depth maps.
    pub z_depth: Vec<f32>,
    /// Accumulated opacity `Σ w_k ∈ [0, 1]`.
    pub accumulation: Vec<f32>,
    /// The rendered feature dims, in request order.
    pub dims: Vec<usize>,
    /// Features `F(r) = Σ w_k f_k` (not normalised by accumulation, as in the paper),
    /// `dims.len()` per entry.
    pub features: Vec<f32>,
}

impl RenderedView {
    /// Number of entries.
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    /// Whether there are no entries.
    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    /// RGB as a `width × height × 3` image, if rendered.
    pub fn rgb_image(&self) -> Option<Image<f32>> {
        (!self.rgb.is_empty()).then(|| {
            Image::from_vec(self.width, self.height, 3, self.rgb.clone()).expect("3 per entry")
        })
    }

    /// Z-depth as a single-channel image (metres, 0 = no surface).
    pub fn z_depth_image(&self) -> Image<f32> {
        Image::from_vec(self.width, self.height, 1, self.z_depth.clone()).expect("1 per entry")
    }

    /// Features as a `width × height × dims.len()` map.
    pub fn feature_map(&self) -> FeatureMap {
        Image::from_vec(
            self.width,
            self.height,
            self.dims.len(),
            self.features.clone(),
        )
        .expect("dims per entry")
    }
}

/// Bytes per ray of a rendered view besides its features: pixel position, ray, validity,
/// near/far, and the rendered RGB, depth, accumulation, median and z-depth.
pub const VIEW_BYTES_PER_RAY: u64 = 16 + 24 + 4 + 1 + 8 + 12 + 4 * 5;

/// Rays a [`PixelSet`] of `camera` casts (no allocation).
pub fn ray_count(camera: &Camera, pixels: &PixelSet) -> u64 {
    match pixels {
        PixelSet::Full => u64::from(camera.width) * u64::from(camera.height),
        PixelSet::Grid { stride } => {
            let s = u64::from((*stride).max(1));
            (u64::from(camera.width) / s) * (u64::from(camera.height) / s)
        }
        PixelSet::List(list) => list.len() as u64,
    }
}

/// The memory rendering `rays` rays with `dims` features takes (features twice: the
/// renderer's output and the view's copy).
pub fn view_request(rays: u64, dims: usize) -> matloc_core::limits::MemoryRequest {
    matloc_core::limits::MemoryRequest {
        what: "rendering a view",
        count: rays,
        unit: "rays",
        bytes_each: VIEW_BYTES_PER_RAY + 8 * dims as u64,
        remedy: "render at a coarser stride or a smaller camera (`images.max_side`, `localize.max_side`)",
    }
}

/// The pixel positions and result-grid size of a [`PixelSet`] for `camera`.
pub fn pixel_positions(
    camera: &Camera,
    pixels: &PixelSet,
) -> Result<(Vec<Point2<f64>>, usize, usize), RenderError> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let grid = |s: usize| {
        let (gw, gh) = (w / s, h / s);
        let mut v = Vec::with_capacity(gw * gh);
        for j in 0..gh {
            for i in 0..gw {
                v.push(Point2::new(
                    (i as f64 + 0.5) * s as f64,
                    (j as f64 + 0.5) * s as f64,
                ));
            }
        }
        (v, gw, gh)
    };
    Ok(match pixels {
        PixelSet::Full => grid(1),
        PixelSet::Grid { stride } => {
            if *stride == 0 {
                return Err(RenderError::InvalidConfig {
                    field: "PixelSet::Grid.stride",
                    reason: "must be >= 1".into(),
                });
            }
            grid(*stride as usize)
        }
        PixelSet::List(list) => {
            if let Some(i) = list
                .iter()
                .position(|p| !(p.x.is_finite() && p.y.is_finite()))
            {
                return Err(RenderError::InvalidPixel { index: i });
            }
            (list.clone(), list.len(), 1)
        }
    })
}

/// World-frame rays (unit directions, f32) through `pixels` of a camera at `cam_from_world`,
/// with their camera-frame bearings' z (cosine to the optical axis) and a validity flag
/// (`false` where undistortion failed: such a ray gets the optical axis as a placeholder).
pub fn camera_rays(
    camera: &Camera,
    cam_from_world: &Isometry3<f64>,
    pixels: &[Point2<f64>],
    near_m: f32,
    far_m: f32,
) -> Result<(RayBatch, Vec<f32>, Vec<bool>), RenderError> {
    camera
        .validate()
        .map_err(|e| RenderError::InvalidCamera(e.to_string()))?;
    let world_from_cam = cam_from_world.inverse();
    let c = world_from_cam.translation.vector;
    let origin = [c.x as f32, c.y as f32, c.z as f32];
    let n = pixels.len();
    let mut origins = Vec::with_capacity(n);
    let mut directions = Vec::with_capacity(n);
    let mut cos_axis = Vec::with_capacity(n);
    let mut valid = Vec::with_capacity(n);
    for px in pixels {
        let (b, ok) = match camera.unproject(*px) {
            Some(b) if b.iter().all(|v| v.is_finite()) => (b, true),
            _ => (nalgebra::Vector3::z(), false),
        };
        let d = world_from_cam.rotation * b;
        let d = d / d.norm();
        origins.push(origin);
        directions.push([d.x as f32, d.y as f32, d.z as f32]);
        cos_axis.push(b.z as f32);
        valid.push(ok);
    }
    let rays = RayBatch::new(origins, directions, near_m, far_m)?;
    Ok((rays, cos_axis, valid))
}

/// Renders depth, accumulation, the requested feature dims and optionally RGB of a camera
/// view from a trained [`NerfModel`].
///
/// Rays come from `camera` (lens distortion removed per pixel with `Camera::unproject`) at
/// pose `cam_from_world` (OpenCV axes), and are sampled with the model's occupancy grid and
/// early ray termination. Pure: the model is not changed and the result is deterministic.
pub fn render_view(
    model: &NerfModel,
    camera: &Camera,
    cam_from_world: &Isometry3<f64>,
    pixels: &PixelSet,
    request: &RenderRequest,
) -> Result<RenderedView, RenderError> {
    if !(cam_from_world
        .translation
        .vector
        .iter()
        .all(|v| v.is_finite())
        && cam_from_world.rotation.coords.iter().all(|v| v.is_finite()))
    {
        return Err(RenderError::InvalidPose);
    }
    matloc_core::limits::check_memory(&view_request(
        ray_count(camera, pixels),
        request.dims.len(),
    ))?;
    let (pixels, width, height) = pixel_positions(camera, pixels)?;
    let cfg = model.config();
    let (mut rays, cos_axis, valid) =
        camera_rays(camera, cam_from_world, &pixels, cfg.near_m, cfg.far_m)?;
    if let Some((lo, hi)) = cfg.clip_box() {
        rays.clip_to_box(lo, hi);
    }
    let opts = RenderOptions {
        march: cfg.render.march,
        dims: request.dims.clone(),
        rgb: request.rgb,
        appearance: request.appearance,
        background: model.background(),
        min_transmittance: cfg.render.min_transmittance,
        samples_per_round: cfg.render.samples_per_round,
        tile_rays: cfg.render.tile_rays,
        min_density: cfg.render.min_density * model.field().density_scale(),
    };
    let out = render_rays(model.field(), &rays, Some(model.render_grid()), &opts)?;
    let n = pixels.len();
    let nd = request.dims.len();
    let mut distance = vec![0f32; n];
    let mut z_depth = vec![0f32; n];
    let mut accumulation = out.accumulation;
    let mut features = out.features;
    let mut rgb = out.rgb;
    for i in 0..n {
        if !valid[i] {
            accumulation[i] = 0.0;
            features[i * nd..(i + 1) * nd].fill(0.0);
            if !rgb.is_empty() {
                rgb[3 * i..3 * i + 3].fill(0.0);
            }
            continue;
        }
        let a = accumulation[i];
        if a > 1e-4 {
            distance[i] = match cfg.render.depth {
                DepthKind::Median if out.median[i] > 0.0 => out.median[i],
                _ => out.depth[i] / a,
            };
            z_depth[i] = distance[i] * cos_axis[i];
        }
    }
    Ok(RenderedView {
        width,
        height,
        pixels,
        valid,
        rgb,
        distance,
        z_depth,
        accumulation,
        dims: request.dims.clone(),
        features,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::limits::{BudgetSource, MemoryBudget, check_against};

    #[test]
    fn a_view_beyond_the_memory_budget_is_refused() {
        let budget = Some(MemoryBudget {
            bytes: 1 << 30,
            source: BudgetSource::Explicit,
        });
        let small = Camera::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0).unwrap();
        let rays = ray_count(&small, &PixelSet::Grid { stride: 4 });
        assert_eq!(rays, 160 * 120);
        assert!(check_against(&view_request(rays, 47), budget).is_ok());
        let huge = Camera::pinhole(100_000, 100_000, 5e4, 5e4, 5e4, 5e4).unwrap();
        let rays = ray_count(&huge, &PixelSet::Full);
        let e = check_against(&view_request(rays, 3), budget)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("rendering a view") && e.contains("10000000000 rays"),
            "{e}"
        );
    }
}
