//! Ground-truth 2D–3D pairs (paper Section 3.1.2), generic over the renderer.
//!
//! For a training view with its true pose `T`, the pose is perturbed to `T'` (a coarse-pose
//! error as the place predictor would make), features and depth are rendered at `T'` on a pixel
//! grid, every rendered cell is lifted to its world point with the depth, and the point is
//! projected into the training view with `T`. A pair *(query cell `i` of the training view, map
//! point `j` rendered at `T'`)* is kept when
//!
//! - the projection lands within `reprojection_px` of the centre of cell `i` (the matcher works
//!   on cell centres, so this is the error a perfect match would make), and
//! - the point is visible at `T`: its z in the true camera agrees with the depth rendered at `T`
//!   at the projection (within `depth_abs_tol_m + depth_rel_tol · z`; inverse depth interpolated
//!   bilinearly from the cells around it, exact on planes), which rejects points hidden behind a
//!   facade from the training viewpoint and points on a depth edge, where the grid cannot tell.
//!
//! Each query cell keeps its closest candidate, so pairs are one-to-one. The query-side features
//! of a pair are the features rendered at the *true* pose in cell `i` (the targets the query
//! encoder is trained on); the map-side features are those rendered at `T'` — together the input
//! of feature selection.
//!
//! [`GtPairSet::save`] stores pair sets as safetensors (columns per pair) with their provenance
//! (configuration, seed, renderer, per-view cameras and poses) as JSON metadata.

use matloc_core::{Camera, Pose};
use matloc_match::{QueryGrid, RenderFailure, RenderedView, ViewRenderer, grid_size};
use nalgebra::{Point2, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use safetensors::{Dtype, SafeTensors, tensor::TensorView};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why ground-truth pairs could not be generated, stored or loaded.
#[derive(Debug, Error)]
pub enum GtError {
    /// The renderer failed.
    #[error("rendering view {view} failed: {source}")]
    Render {
        /// Index of the view.
        view: usize,
        /// The renderer's error.
        source: RenderFailure,
    },
    /// A rendered view has buffers of the wrong size.
    #[error("rendered view {view}: {reason}")]
    BadRender {
        /// Index of the view.
        view: usize,
        /// What is wrong.
        reason: String,
    },
    /// Configuration out of range.
    #[error("invalid pair-generation config field `{field}`: {reason}")]
    InvalidConfig {
        /// Field name.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// A requested feature dim does not exist in the renderer.
    #[error("feature dim {dim} out of range for a {dims}-d renderer")]
    DimOutOfRange {
        /// The dim asked for.
        dim: usize,
        /// Dims of the renderer.
        dims: usize,
    },
    /// No views to generate pairs from.
    #[error("no training views given")]
    NoViews,
    /// File I/O.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file is not a valid pair set.
    #[error("{path}: not a valid ground-truth pair file: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// Shape of the pose perturbation distribution.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum PerturbKind {
    /// Translation uniform in a ball of radius `translation_m`; rotation vector uniform in a
    /// ball of radius `rotation_deg` (so errors are bounded).
    #[default]
    UniformBall,
    /// Each translation component `N(0, translation_m²)`, each rotation-vector component
    /// `N(0, rotation_deg²)` (heavier tails, like a place predictor's misses).
    Gaussian,
}

/// Coarse-pose error model: the camera centre moves by `δt` (world frame) and the camera rotates
/// by `δR` about its own centre (`R' = δR · R` in `cam_from_world`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Perturbation {
    /// Distribution shape.
    pub kind: PerturbKind,
    /// Translation scale, metres.
    pub translation_m: f64,
    /// Rotation scale, degrees.
    pub rotation_deg: f64,
}

impl Default for Perturbation {
    fn default() -> Self {
        Perturbation {
            kind: PerturbKind::UniformBall,
            translation_m: 2.0,
            rotation_deg: 3.0,
        }
    }
}

/// Standard normal sample (Box–Muller; one of the pair is discarded for simplicity).
fn normal(rng: &mut dyn RngCore) -> f64 {
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn random_unit(rng: &mut dyn RngCore) -> Vector3<f64> {
    loop {
        let v = Vector3::new(normal(rng), normal(rng), normal(rng));
        if let Some(u) = v.try_normalize(1e-9) {
            return u;
        }
    }
}

impl Perturbation {
    fn validate(&self) -> Result<(), GtError> {
        for (field, v) in [
            ("perturbation.translation_m", self.translation_m),
            ("perturbation.rotation_deg", self.rotation_deg),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(GtError::InvalidConfig {
                    field,
                    reason: format!("must be finite and >= 0, got {v}"),
                });
            }
        }
        Ok(())
    }

    fn draw(&self, scale: f64, rng: &mut dyn RngCore) -> Vector3<f64> {
        match self.kind {
            PerturbKind::UniformBall => {
                let r = scale * rng.random::<f64>().cbrt();
                random_unit(rng) * r
            }
            PerturbKind::Gaussian => Vector3::new(normal(rng), normal(rng), normal(rng)) * scale,
        }
    }

    /// A perturbed copy of `cam_from_world`.
    pub fn apply(&self, cam_from_world: &Pose, rng: &mut dyn RngCore) -> Pose {
        let dt = self.draw(self.translation_m, rng);
        let dr = self.draw(self.rotation_deg.to_radians(), rng);
        let centre = cam_from_world.inverse_transform_point(&Point3::origin());
        let rot = UnitQuaternion::from_scaled_axis(dr) * cam_from_world.rotation;
        let c2 = centre.coords + dt;
        Pose::from_parts(Translation3::from(-(rot * c2)), rot)
    }
}

/// Settings of ground-truth pair generation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GtConfig {
    /// Image pixels per grid cell (the query encoder's output stride).
    pub stride: u32,
    /// Coarse-pose error model.
    pub perturbation: Perturbation,
    /// Perturbed renders per training view.
    pub perturbations_per_view: usize,
    /// Largest distance (pixels) between a point's projection and its query cell centre.
    pub reprojection_px: f64,
    /// Visibility: relative depth tolerance.
    pub depth_rel_tol: f64,
    /// Visibility: absolute depth tolerance, metres.
    pub depth_abs_tol_m: f64,
    /// Cells with less accumulated opacity (sky, holes) are never paired.
    pub min_accumulation: f32,
    /// Feature dims to render and store; `None` = all of the renderer's.
    pub dims: Option<Vec<usize>>,
}

impl Default for GtConfig {
    fn default() -> Self {
        GtConfig {
            stride: 4,
            perturbation: Perturbation::default(),
            perturbations_per_view: 1,
            reprojection_px: 2.0,
            depth_rel_tol: 0.02,
            depth_abs_tol_m: 0.05,
            min_accumulation: 0.5,
            dims: None,
        }
    }
}

impl GtConfig {
    fn validate(&self, renderer_dims: usize) -> Result<Vec<usize>, GtError> {
        self.perturbation.validate()?;
        if self.stride == 0 {
            return Err(GtError::InvalidConfig {
                field: "stride",
                reason: "must be positive".into(),
            });
        }
        for (field, v) in [
            ("reprojection_px", self.reprojection_px),
            ("depth_rel_tol", self.depth_rel_tol),
            ("depth_abs_tol_m", self.depth_abs_tol_m),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(GtError::InvalidConfig {
                    field,
                    reason: format!("must be finite and >= 0, got {v}"),
                });
            }
        }
        if !self.min_accumulation.is_finite() {
            return Err(GtError::InvalidConfig {
                field: "min_accumulation",
                reason: "must be finite".into(),
            });
        }
        if self.perturbations_per_view == 0 {
            return Err(GtError::InvalidConfig {
                field: "perturbations_per_view",
                reason: "must be at least 1".into(),
            });
        }
        let dims = match &self.dims {
            Some(d) => d.clone(),
            None => (0..renderer_dims).collect(),
        };
        if dims.is_empty() {
            return Err(GtError::InvalidConfig {
                field: "dims",
                reason: "no dims selected".into(),
            });
        }
        if let Some(&dim) = dims.iter().find(|&&d| d >= renderer_dims) {
            return Err(GtError::DimOutOfRange {
                dim,
                dims: renderer_dims,
            });
        }
        Ok(dims)
    }
}

/// One training view to generate pairs from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainingView {
    /// Caller's index of the view (e.g. frame index in the dataset).
    pub index: usize,
    /// Intrinsics.
    pub camera: Camera,
    /// True pose.
    pub cam_from_world: Pose,
}

/// Provenance of one perturbed render.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderProvenance {
    /// The training view.
    pub view: TrainingView,
    /// The perturbed pose the map side was rendered at.
    pub perturbed_cam_from_world: Pose,
    /// Grid columns and rows.
    pub grid: [usize; 2],
    /// Why candidate cells were dropped.
    pub counts: PairCounts,
}

/// Bookkeeping of one perturbed render: how many rendered cells ended where.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PairCounts {
    /// Cells with a surface at the perturbed pose.
    pub surface: usize,
    /// Projected outside the training image (or behind it).
    pub out_of_view: usize,
    /// Too far from the nearest cell centre.
    pub reprojection: usize,
    /// Hidden at the true pose (depth disagrees) or no surface there.
    pub occluded: usize,
    /// Lost to a closer candidate for the same query cell.
    pub duplicate: usize,
    /// Kept.
    pub kept: usize,
}

/// How a pair set was made.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// Generator and version.
    pub generator: String,
    /// The renderer's self-description.
    pub renderer: String,
    /// Settings.
    pub config: GtConfig,
    /// Seed of the perturbations (render `k` uses stream `k`).
    pub seed: u64,
    /// Stored feature dims (renderer dim indices, column order of the feature tensors).
    pub dims: Vec<usize>,
    /// One entry per perturbed render; pair column `render` indexes it.
    pub renders: Vec<RenderProvenance>,
}

/// Ground-truth pairs as columns, one row per pair.
#[derive(Clone, Debug, PartialEq)]
pub struct GtPairSet {
    /// Provenance; `render[p]` indexes `provenance.renders`.
    pub provenance: Provenance,
    /// Perturbed render each pair comes from.
    pub render: Vec<u32>,
    /// Query cell (row-major, in the training view's grid).
    pub query_index: Vec<u32>,
    /// Map cell (row-major, in the perturbed render's grid).
    pub map_index: Vec<u32>,
    /// Exact projection of the world point into the training view, pixels.
    pub query_px: Vec<[f64; 2]>,
    /// World point (lifted at the perturbed pose).
    pub point_world: Vec<[f64; 3]>,
    /// Distance of `query_px` to the query cell centre, pixels.
    pub reprojection_px: Vec<f32>,
    /// `P × dims` features rendered at the true pose in the query cell.
    pub query_features: Vec<f32>,
    /// `P × dims` features rendered at the perturbed pose in the map cell.
    pub map_features: Vec<f32>,
}

struct Candidate {
    err: f64,
    map: usize,
    px: [f64; 2],
    world: [f64; 3],
}

fn render_checked(
    renderer: &dyn ViewRenderer,
    view: &TrainingView,
    pose: &Pose,
    stride: u32,
    dims: &[usize],
) -> Result<RenderedView, GtError> {
    let r = renderer
        .render_view(&view.camera, pose, stride, dims)
        .map_err(|source| GtError::Render {
            view: view.index,
            source,
        })?;
    let (cols, rows) = grid_size(&view.camera, stride);
    r.check_shape(cols, rows, dims.len())
        .map_err(|reason| GtError::BadRender {
            view: view.index,
            reason,
        })?;
    Ok(r)
}

/// Pairs of one training view against one render at `perturbed` (both rendered by the caller).
/// Returns `(query cell, map cell, projection, world point, reprojection error)` rows sorted
/// by query cell, and the counts.
fn pair_view(
    camera: &Camera,
    true_pose: &Pose,
    at_true: &RenderedView,
    perturbed: &Pose,
    at_perturbed: &RenderedView,
    cfg: &GtConfig,
) -> (Vec<(usize, Candidate)>, PairCounts) {
    let grid = QueryGrid::with_stride(cfg.stride as f64);
    let s = cfg.stride as f64;
    let (cols, rows) = (at_true.cols, at_true.rows);
    let mut best: Vec<Option<Candidate>> = (0..cols * rows).map(|_| None).collect();
    let mut counts = PairCounts::default();
    let world_from_perturbed = perturbed.inverse();
    for j in 0..at_perturbed.cols * at_perturbed.rows {
        if !at_perturbed.has_surface(j, cfg.min_accumulation) {
            continue;
        }
        counts.surface += 1;
        let c = grid.cell_centre(j % at_perturbed.cols, j / at_perturbed.cols);
        let Some(bearing) = camera.unproject(Point2::new(c[0], c[1])) else {
            counts.out_of_view += 1;
            continue;
        };
        let z = at_perturbed.depth_z[j] as f64;
        let p_cam = Point3::from(bearing * (z / bearing.z));
        let x_world = world_from_perturbed * p_cam;
        let x_true = true_pose * x_world;
        let Some(u) = camera.project(&x_true.coords) else {
            counts.out_of_view += 1;
            continue;
        };
        if !camera.contains(u) {
            counts.out_of_view += 1;
            continue;
        }
        let (col, row) = ((u.x / s).floor() as usize, (u.y / s).floor() as usize);
        if col >= cols || row >= rows {
            counts.out_of_view += 1;
            continue;
        }
        let i = row * cols + col;
        let centre = grid.cell_centre(col, row);
        let err = (u.x - centre[0]).hypot(u.y - centre[1]);
        if err > cfg.reprojection_px {
            counts.reprojection += 1;
            continue;
        }
        // Visibility: inverse depth interpolated bilinearly at the projection from the (up to 4)
        // cells around it must agree with the point's. Inverse depth is affine in pixels on a
        // plane, so this is exact on planar patches, while across a depth edge the blend of
        // foreground and background disagrees and the point is dropped rather than mispaired.
        let zx = x_true.z;
        let tol = cfg.depth_abs_tol_m + cfg.depth_rel_tol * zx;
        let gx = (u.x / s - 0.5).clamp(0.0, (cols - 1) as f64);
        let gy = (u.y / s - 0.5).clamp(0.0, (rows - 1) as f64);
        let (c0, r0) = (gx.floor() as usize, gy.floor() as usize);
        let (fx, fy) = (gx - c0 as f64, gy - r0 as f64);
        let mut inv = 0.0;
        let mut visible = true;
        for (c, r, w) in [
            (c0, r0, (1.0 - fx) * (1.0 - fy)),
            (c0 + 1, r0, fx * (1.0 - fy)),
            (c0, r0 + 1, (1.0 - fx) * fy),
            (c0 + 1, r0 + 1, fx * fy),
        ] {
            if w <= 0.0 {
                continue;
            }
            let k = r * cols + c;
            if c >= cols || r >= rows || !at_true.has_surface(k, cfg.min_accumulation) {
                visible = false;
                break;
            }
            inv += w / at_true.depth_z[k] as f64;
        }
        visible = visible && inv > 0.0 && (1.0 / inv - zx).abs() <= tol;
        if !visible {
            counts.occluded += 1;
            continue;
        }
        let cand = Candidate {
            err,
            map: j,
            px: [u.x, u.y],
            world: [x_world.x, x_world.y, x_world.z],
        };
        match &best[i] {
            Some(b) if b.err <= err => counts.duplicate += 1,
            Some(_) => {
                counts.duplicate += 1;
                best[i] = Some(cand);
            }
            None => best[i] = Some(cand),
        }
    }
    let out: Vec<(usize, Candidate)> = best
        .into_iter()
        .enumerate()
        .filter_map(|(i, c)| c.map(|c| (i, c)))
        .collect();
    counts.kept = out.len();
    (out, counts)
}

/// Generates ground-truth pairs for `views` (in parallel over views), perturbation `k` of view
/// `v` drawn from stream `v · perturbations_per_view + k` of a ChaCha8 RNG seeded with `seed`,
/// so the result does not depend on thread count or order.
pub fn generate_pairs(
    renderer: &dyn ViewRenderer,
    views: &[TrainingView],
    config: &GtConfig,
    seed: u64,
) -> Result<GtPairSet, GtError> {
    if views.is_empty() {
        return Err(GtError::NoViews);
    }
    let dims = config.validate(renderer.num_features())?;
    let nd = dims.len();
    let per = config.perturbations_per_view;
    type ViewOut = Vec<(
        RenderProvenance,
        Vec<(usize, Candidate)>,
        RenderedView,
        RenderedView,
    )>;
    let results: Vec<Result<ViewOut, GtError>> = views
        .par_iter()
        .enumerate()
        .map(|(v, view)| {
            for (field, ok) in [
                ("views.camera", view.camera.validate().is_ok()),
                (
                    "views.cam_from_world",
                    view.cam_from_world
                        .to_homogeneous()
                        .iter()
                        .all(|x| x.is_finite()),
                ),
            ] {
                if !ok {
                    return Err(GtError::InvalidConfig {
                        field,
                        reason: format!("view {} is invalid", view.index),
                    });
                }
            }
            let at_true =
                render_checked(renderer, view, &view.cam_from_world, config.stride, &dims)?;
            let mut out = Vec::with_capacity(per);
            for k in 0..per {
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                rng.set_stream((v * per + k) as u64);
                let perturbed = config.perturbation.apply(&view.cam_from_world, &mut rng);
                let at_p = render_checked(renderer, view, &perturbed, config.stride, &dims)?;
                let (pairs, counts) = pair_view(
                    &view.camera,
                    &view.cam_from_world,
                    &at_true,
                    &perturbed,
                    &at_p,
                    config,
                );
                let prov = RenderProvenance {
                    view: view.clone(),
                    perturbed_cam_from_world: perturbed,
                    grid: [at_true.cols, at_true.rows],
                    counts,
                };
                out.push((prov, pairs, at_true.clone(), at_p));
            }
            Ok(out)
        })
        .collect();
    let mut set = GtPairSet {
        provenance: Provenance {
            generator: format!("matloc-match {}", env!("CARGO_PKG_VERSION")),
            renderer: renderer.describe(),
            config: config.clone(),
            seed,
            dims,
            renders: Vec::new(),
        },
        render: Vec::new(),
        query_index: Vec::new(),
        map_index: Vec::new(),
        query_px: Vec::new(),
        point_world: Vec::new(),
        reprojection_px: Vec::new(),
        query_features: Vec::new(),
        map_features: Vec::new(),
    };
    for r in results {
        for (prov, pairs, at_true, at_p) in r? {
            let render_id = set.provenance.renders.len() as u32;
            set.provenance.renders.push(prov);
            for (i, c) in pairs {
                set.render.push(render_id);
                set.query_index.push(i as u32);
                set.map_index.push(c.map as u32);
                set.query_px.push(c.px);
                set.point_world.push(c.world);
                set.reprojection_px.push(c.err as f32);
                set.query_features
                    .extend_from_slice(&at_true.features[i * nd..(i + 1) * nd]);
                set.map_features
                    .extend_from_slice(&at_p.features[c.map * nd..(c.map + 1) * nd]);
            }
        }
    }
    Ok(set)
}

fn bytes_of<T: Copy, const N: usize>(v: &[T], to: impl Fn(T) -> [u8; N]) -> Vec<u8> {
    v.iter().flat_map(|&x| to(x)).collect()
}

fn read_column<T, const N: usize>(
    st: &SafeTensors,
    name: &str,
    dtype: Dtype,
    width: usize,
    rows: Option<usize>,
    from: impl Fn([u8; N]) -> T,
    path: &Path,
) -> Result<Vec<T>, GtError> {
    let bad = |reason: String| GtError::Format {
        path: path.to_path_buf(),
        reason,
    };
    let t = st
        .tensor(name)
        .map_err(|e| bad(format!("tensor `{name}`: {e}")))?;
    if t.dtype() != dtype {
        return Err(bad(format!("tensor `{name}` has dtype {:?}", t.dtype())));
    }
    let shape = t.shape();
    let ok = match (shape, width) {
        ([n], 1) => rows.is_none_or(|r| r == *n),
        ([n, w], _) => *w == width && rows.is_none_or(|r| r == *n),
        _ => false,
    };
    if !ok {
        return Err(bad(format!(
            "tensor `{name}` has shape {shape:?}, expected [{}, {width}]",
            rows.map_or("P".to_string(), |r| r.to_string())
        )));
    }
    Ok(t.data()
        .chunks_exact(N)
        .map(|c| from(c.try_into().expect("chunk of N bytes")))
        .collect())
}

impl GtPairSet {
    /// The pairs as feature-selection input: query-side features (rendered at the true pose,
    /// i.e. the encoder's targets) against map-side features (rendered at the perturbed pose),
    /// grouped by render. `query_features` replaces the query side, e.g. with the encoder's
    /// output at the pairs' query cells (`P × dims`).
    pub fn to_pair_set(
        &self,
        query_features: Option<Vec<f32>>,
    ) -> Result<matloc_select::PairSet, matloc_select::SelectError> {
        let f2d = query_features.unwrap_or_else(|| self.query_features.clone());
        matloc_select::PairSet::new(self.dims(), f2d, self.map_features.clone())?
            .with_groups(self.render.clone())
    }

    /// Number of pairs.
    pub fn len(&self) -> usize {
        self.render.len()
    }

    /// Whether there are no pairs.
    pub fn is_empty(&self) -> bool {
        self.render.is_empty()
    }

    /// Stored feature dims.
    pub fn dims(&self) -> usize {
        self.provenance.dims.len()
    }

    /// Query-side features of pair `p`.
    pub fn query_feature(&self, p: usize) -> &[f32] {
        let d = self.dims();
        &self.query_features[p * d..(p + 1) * d]
    }

    /// Map-side features of pair `p`.
    pub fn map_feature(&self, p: usize) -> &[f32] {
        let d = self.dims();
        &self.map_features[p * d..(p + 1) * d]
    }

    /// Serialises to safetensors bytes (columns as tensors, provenance as JSON metadata).
    pub fn to_bytes(&self) -> Result<Vec<u8>, GtError> {
        let p = self.len();
        let d = self.dims();
        let cols: Vec<(&str, Dtype, Vec<usize>, Vec<u8>)> = vec![
            (
                "render",
                Dtype::U32,
                vec![p],
                bytes_of(&self.render, u32::to_le_bytes),
            ),
            (
                "query_index",
                Dtype::U32,
                vec![p],
                bytes_of(&self.query_index, u32::to_le_bytes),
            ),
            (
                "map_index",
                Dtype::U32,
                vec![p],
                bytes_of(&self.map_index, u32::to_le_bytes),
            ),
            (
                "query_px",
                Dtype::F64,
                vec![p, 2],
                bytes_of(self.query_px.as_flattened(), f64::to_le_bytes),
            ),
            (
                "point_world",
                Dtype::F64,
                vec![p, 3],
                bytes_of(self.point_world.as_flattened(), f64::to_le_bytes),
            ),
            (
                "reprojection_px",
                Dtype::F32,
                vec![p],
                bytes_of(&self.reprojection_px, f32::to_le_bytes),
            ),
            (
                "query_features",
                Dtype::F32,
                vec![p, d],
                bytes_of(&self.query_features, f32::to_le_bytes),
            ),
            (
                "map_features",
                Dtype::F32,
                vec![p, d],
                bytes_of(&self.map_features, f32::to_le_bytes),
            ),
        ];
        let fmt = |reason: String| GtError::Format {
            path: PathBuf::new(),
            reason,
        };
        let mut views = Vec::with_capacity(cols.len());
        for (name, dtype, shape, bytes) in &cols {
            views.push((
                name.to_string(),
                TensorView::new(*dtype, shape.clone(), bytes).map_err(|e| fmt(e.to_string()))?,
            ));
        }
        let meta = HashMap::from([
            ("format".to_string(), "matloc-gt-pairs/1".to_string()),
            (
                "provenance".to_string(),
                serde_json::to_string(&self.provenance).map_err(|e| fmt(e.to_string()))?,
            ),
        ]);
        safetensors::serialize(views, Some(meta)).map_err(|e| fmt(e.to_string()))
    }

    /// Parses [`GtPairSet::to_bytes`] output; `path` only labels errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self, GtError> {
        let bad = |reason: String| GtError::Format {
            path: path.to_path_buf(),
            reason,
        };
        let (_, meta) = SafeTensors::read_metadata(bytes).map_err(|e| bad(e.to_string()))?;
        let info = meta
            .metadata()
            .as_ref()
            .ok_or_else(|| bad("no metadata".into()))?;
        if info.get("format").map(String::as_str) != Some("matloc-gt-pairs/1") {
            return Err(bad("missing format tag matloc-gt-pairs/1".into()));
        }
        let provenance: Provenance = serde_json::from_str(
            info.get("provenance")
                .ok_or_else(|| bad("no provenance".into()))?,
        )
        .map_err(|e| bad(format!("provenance: {e}")))?;
        let st = SafeTensors::deserialize(bytes).map_err(|e| bad(e.to_string()))?;
        let d = provenance.dims.len();
        let render = read_column(&st, "render", Dtype::U32, 1, None, u32::from_le_bytes, path)?;
        let p = Some(render.len());
        let u32c = |name| read_column(&st, name, Dtype::U32, 1, p, u32::from_le_bytes, path);
        let query_index = u32c("query_index")?;
        let map_index = u32c("map_index")?;
        let f64c = |name, w| read_column(&st, name, Dtype::F64, w, p, f64::from_le_bytes, path);
        let qpx = f64c("query_px", 2)?;
        let pw = f64c("point_world", 3)?;
        let f32c = |name, w| read_column(&st, name, Dtype::F32, w, p, f32::from_le_bytes, path);
        let reprojection_px = f32c("reprojection_px", 1)?;
        let query_features = f32c("query_features", d)?;
        let map_features = f32c("map_features", d)?;
        if let Some(&r) = render
            .iter()
            .find(|&&r| r as usize >= provenance.renders.len())
        {
            return Err(bad(format!(
                "render index {r} but {} renders",
                provenance.renders.len()
            )));
        }
        Ok(GtPairSet {
            provenance,
            render,
            query_index,
            map_index,
            query_px: qpx.chunks_exact(2).map(|c| [c[0], c[1]]).collect(),
            point_world: pw.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
            reprojection_px,
            query_features,
            map_features,
        })
    }

    /// Writes the pair set atomically (temporary file + rename).
    pub fn save(&self, path: &Path) -> Result<(), GtError> {
        let bytes = self.to_bytes().map_err(|e| match e {
            GtError::Format { reason, .. } => GtError::Format {
                path: path.to_path_buf(),
                reason,
            },
            other => other,
        })?;
        matloc_core::fsutil::write_atomic(path, &bytes).map_err(|source| GtError::Io {
            path: path.to_path_buf(),
            source,
        })
    }

    /// Reads a pair set written by [`GtPairSet::save`].
    pub fn load(path: &Path) -> Result<Self, GtError> {
        let bytes = std::fs::read(path).map_err(|source| GtError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_bytes(&bytes, path)
    }
}
