//! A [`ViewRenderer`] backed by the synthetic world's exact ray caster and an analytic feature
//! field, so pair generation, matching and localization can be tested against exact geometry
//! without training a NeRF.
//!
//! The feature field imitates the NeRF's layout (32 positional + 15 MLP dims):
//! - dims `0..n_pos`: `sin(w_k · x + φ_k)` of the world point with random directions and
//!   wavelengths log-spaced from `min_wavelength_m` to `max_wavelength_m`, like the levels of a
//!   multi-resolution hash grid (the longest ones are nearly constant over a scene, so useless
//!   for matching, as coarse hash levels are);
//! - the remaining dims: a per-material embedding plus a medium-frequency positional term, like
//!   the geometry MLP's semantic output.

use crate::{Material, World};
use matloc_core::{Camera, Pose};
use matloc_match::QueryGrid;
use matloc_match::{RenderFailure, RenderedView, ViewRenderer, grid_size};
use nalgebra::{Point2, Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Settings of the analytic feature field.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SynthFieldConfig {
    /// Positional dims.
    pub n_pos: usize,
    /// Material ("MLP") dims.
    pub n_mlp: usize,
    /// Shortest positional wavelength, metres.
    pub min_wavelength_m: f64,
    /// Longest positional wavelength, metres.
    pub max_wavelength_m: f64,
    /// Seed of directions, phases and material embeddings.
    pub seed: u64,
}

impl Default for SynthFieldConfig {
    fn default() -> Self {
        SynthFieldConfig {
            n_pos: 32,
            n_mlp: 15,
            min_wavelength_m: 1.5,
            max_wavelength_m: 400.0,
            seed: 7,
        }
    }
}

const MATERIALS: usize = 7;

fn material_id(m: Material) -> usize {
    match m {
        Material::Ground => 0,
        Material::Road => 1,
        Material::Facade => 2,
        Material::Roof => 3,
        Material::Rubble => 4,
        Material::Vegetation => 5,
        Material::Vehicle => 6,
    }
}

/// The analytic feature field.
#[derive(Clone, Debug, PartialEq)]
pub struct SynthFeatureField {
    config: SynthFieldConfig,
    /// Wave vectors (rad/m) of all dims.
    waves: Vec<Vector3<f64>>,
    phases: Vec<f64>,
    /// `MATERIALS × n_mlp` embedding.
    embedding: Vec<f32>,
}

impl SynthFeatureField {
    /// Builds the field from its settings.
    pub fn new(config: SynthFieldConfig) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        let d = config.n_pos + config.n_mlp;
        let mut waves = Vec::with_capacity(d);
        let mut phases = Vec::with_capacity(d);
        let (lo, hi) = (
            config.min_wavelength_m.max(1e-3).ln(),
            config.max_wavelength_m.max(1e-3).ln(),
        );
        for k in 0..d {
            let wl = if k < config.n_pos {
                let t = if config.n_pos > 1 {
                    k as f64 / (config.n_pos - 1) as f64
                } else {
                    0.0
                };
                (lo + t * (hi - lo)).exp()
            } else {
                rng.random_range(6.0..30.0)
            };
            let dir = loop {
                let v = Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                );
                let n: f64 = v.norm();
                if n > 0.1 && n <= 1.0 {
                    break v / n;
                }
            };
            waves.push(dir * (std::f64::consts::TAU / wl));
            phases.push(rng.random_range(0.0..std::f64::consts::TAU));
        }
        let embedding = (0..MATERIALS * config.n_mlp)
            .map(|_| rng.random_range(-1.0f32..1.0))
            .collect();
        SynthFeatureField {
            config,
            waves,
            phases,
            embedding,
        }
    }

    /// Total dims.
    pub fn dims(&self) -> usize {
        self.config.n_pos + self.config.n_mlp
    }

    /// Settings.
    pub fn config(&self) -> &SynthFieldConfig {
        &self.config
    }

    /// Feature `dim` of a surface point of `material`.
    pub fn feature(&self, p: &Point3<f64>, material: Material, dim: usize) -> f32 {
        let s = (self.waves[dim].dot(&p.coords) + self.phases[dim]).sin() as f32;
        if dim < self.config.n_pos {
            s
        } else {
            let k = dim - self.config.n_pos;
            self.embedding[material_id(material) * self.config.n_mlp + k] + 0.5 * s
        }
    }
}

/// The synthetic world seen through [`SynthFeatureField`]: exact z-depth from the ray caster,
/// accumulation 1 on a hit and 0 for sky.
#[derive(Clone, Debug)]
pub struct SynthFeatureRenderer {
    world: World,
    field: SynthFeatureField,
}

impl SynthFeatureRenderer {
    /// Wraps a generated world.
    pub fn new(world: World, field: SynthFeatureField) -> Self {
        SynthFeatureRenderer { world, field }
    }

    /// The world (for RGB rendering of the same views).
    pub fn world(&self) -> &World {
        &self.world
    }

    /// The feature field.
    pub fn field(&self) -> &SynthFeatureField {
        &self.field
    }
}

impl ViewRenderer for SynthFeatureRenderer {
    fn num_features(&self) -> usize {
        self.field.dims()
    }

    fn describe(&self) -> String {
        format!(
            "synthetic world (seed {}) with analytic features {:?}",
            self.world.seed(),
            self.field.config()
        )
    }

    fn render_view(
        &self,
        camera: &Camera,
        cam_from_world: &Pose,
        stride: u32,
        dims: &[usize],
    ) -> Result<RenderedView, RenderFailure> {
        if let Some(&d) = dims.iter().find(|&&d| d >= self.field.dims()) {
            return Err(format!("dim {d} out of range for {} dims", self.field.dims()).into());
        }
        camera.validate()?;
        let (cols, rows) = grid_size(camera, stride);
        let grid = QueryGrid::with_stride(stride.max(1) as f64);
        let nd = dims.len();
        let world_from_cam = cam_from_world.inverse();
        let origin = Point3::from(world_from_cam.translation.vector);
        let cells: Vec<(f32, f32, Vec<f32>)> = (0..cols * rows)
            .into_par_iter()
            .map(|i| {
                let c = grid.cell_centre(i % cols, i / cols);
                let miss = (0.0, 0.0, vec![0.0; nd]);
                let Some(bearing) = camera.unproject(Point2::new(c[0], c[1])) else {
                    return miss;
                };
                let dir = world_from_cam.rotation * bearing;
                let Some(hit) = self.world.raycast(&origin, &dir) else {
                    return miss;
                };
                let f = dims
                    .iter()
                    .map(|&d| self.field.feature(&hit.point, hit.material, d))
                    .collect();
                ((hit.t * bearing.z) as f32, 1.0, f)
            })
            .collect();
        let mut view = RenderedView {
            cols,
            rows,
            dims: nd,
            features: Vec::with_capacity(cols * rows * nd),
            depth_z: Vec::with_capacity(cols * rows),
            accumulation: Vec::with_capacity(cols * rows),
        };
        for (z, a, f) in cells {
            view.depth_z.push(z);
            view.accumulation.push(a);
            view.features.extend(f);
        }
        Ok(view)
    }
}
