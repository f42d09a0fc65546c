use matloc_nerf_field::{FeatureField, SceneBox, contract_to_unit};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::error::RenderError;

/// Occupancy-grid settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct OccupancyConfig {
    /// Cells per axis over the contracted cube `[0,1]³` (the scene box covers the middle half
    /// of each axis).
    pub resolution: usize,
    /// Multiplier applied to every cell's estimate at each update before taking the max with
    /// the new value (instant-ngp: 0.95 with partial updates over 35k steps; 0.5 with full
    /// updates lets a cleared cell drop out after a few updates in short CPU runs).
    pub decay: f32,
    /// Occupancy threshold in *normalised* density units (multiples of
    /// `SceneBox::density_scale`, i.e. of the initial density): a cell is occupied if its
    /// estimate exceeds `min(density_threshold · scale, mean estimate)`. Scale-free, so the
    /// same value suits a 10 m and a 1 km scene. Default 0.1: at 0.01 (instant-ngp's value)
    /// the residual fog of short CPU runs (~3–10 % of the initial density) kept every cell
    /// occupied on the synthetic plane test.
    pub density_threshold: f32,
    /// Fraction of cells re-evaluated per update after the first (full) one; cells are drawn
    /// at random. 1.0 = every cell every update.
    pub update_fraction: f32,
    /// Cap the threshold at the mean estimate (instant-ngp's rule, which keeps the denser
    /// half of a still-uniform field occupied early on). With a scene box that holds most of
    /// the grid's cells in its contracted shell, the mean sits near the initial density and
    /// nothing in the box is ever pruned; `false` applies `density_threshold` as is.
    pub cap_at_mean: bool,
}

impl Default for OccupancyConfig {
    fn default() -> Self {
        Self {
            resolution: 64,
            decay: 0.5,
            density_threshold: 0.1,
            update_fraction: 1.0,
            cap_at_mean: true,
        }
    }
}

/// Bytes per cell: the density estimate (f32), the occupancy bit, and the estimate of one
/// update (f32).
pub const OCCUPANCY_CELL_BYTES: u64 = 9;

/// The memory an occupancy grid of `cells` cells takes.
fn grid_request(cells: u64) -> matloc_core::limits::MemoryRequest {
    matloc_core::limits::MemoryRequest {
        what: "the NeRF occupancy grid",
        count: cells,
        unit: "cells",
        bytes_each: OCCUPANCY_CELL_BYTES,
        remedy: "lower `train.occupancy.resolution` (in a map config: `nerf.model_overrides`)",
    }
}

/// A density grid over the contracted cube with an occupancy bitfield, for empty-space
/// skipping (instant-ngp style).
///
/// Each cell keeps `max(decay · old, new)` of the field's density at a random point in the
/// cell. Because cells are in contracted space, far cells cover large world volumes, which is
/// where most rays spend their steps in unbounded scenes.
#[derive(Clone, Debug)]
pub struct OccupancyGrid {
    config: OccupancyConfig,
    scene_box: SceneBox,
    density: Vec<f32>,
    bits: Vec<u64>,
    updates: u64,
}

impl OccupancyGrid {
    /// A grid with every cell occupied (nothing is known yet).
    pub fn new(config: OccupancyConfig, scene_box: SceneBox) -> Result<Self, RenderError> {
        if !(2..=1024).contains(&config.resolution) {
            return Err(RenderError::InvalidConfig {
                field: "occupancy.resolution",
                reason: format!("{} not in 2..=1024", config.resolution),
            });
        }
        let n = config.resolution.pow(3);
        matloc_core::limits::check_memory(&grid_request(n as u64))?;
        Ok(Self {
            config,
            scene_box,
            density: vec![f32::MAX; n],
            bits: vec![u64::MAX; n.div_ceil(64)],
            updates: 0,
        })
    }

    /// Settings.
    pub fn config(&self) -> &OccupancyConfig {
        &self.config
    }

    /// Number of cells.
    pub fn num_cells(&self) -> usize {
        self.density.len()
    }

    /// Fraction of occupied cells.
    pub fn occupied_fraction(&self) -> f32 {
        let n = self.num_cells();
        (0..n).filter(|&i| self.bit(i)).count() as f32 / n as f32
    }

    #[inline]
    fn bit(&self, i: usize) -> bool {
        (self.bits[i >> 6] >> (i & 63)) & 1 == 1
    }

    #[inline]
    fn cell_of_unit(&self, u: [f32; 3]) -> usize {
        let r = self.config.resolution;
        let c = |x: f32| ((x * r as f32) as usize).min(r - 1);
        c(u[0]) + r * (c(u[1]) + r * c(u[2]))
    }

    /// Whether the cell containing world point `p` is occupied.
    #[inline]
    pub fn is_occupied_world(&self, p: [f32; 3]) -> bool {
        self.bit(self.cell_of_unit(contract_to_unit(&self.scene_box, p)))
    }

    /// World point of unit-cube point `u` (inverse of the contraction; points on the outer
    /// boundary map to a very distant point).
    pub fn unit_to_world(&self, u: [f32; 3]) -> [f32; 3] {
        let c: [f32; 3] = [4.0 * u[0] - 2.0, 4.0 * u[1] - 2.0, 4.0 * u[2] - 2.0];
        let n = c[0].abs().max(c[1].abs()).max(c[2].abs());
        let x = if n <= 1.0 {
            c
        } else {
            let m = 1.0 / (2.0 - n.min(2.0 - 1e-6));
            [c[0] * m / n, c[1] * m / n, c[2] * m / n]
        };
        let sb = &self.scene_box;
        [0, 1, 2].map(|a| (x[a] + 1.0) * 0.5 * (sb.max[a] - sb.min[a]) + sb.min[a])
    }

    /// One update from the field: decays every estimate, evaluates the density at a random
    /// point in a set of cells (all cells on the first update, then a random
    /// `update_fraction`), and rebuilds the bitfield.
    pub fn update<R: Rng>(
        &mut self,
        field: &dyn FeatureField,
        rng: &mut R,
    ) -> Result<(), RenderError> {
        let n = self.num_cells();
        let r = self.config.resolution;
        let cells: Vec<usize> = if self.updates == 0 || self.config.update_fraction >= 1.0 {
            (0..n).collect()
        } else {
            let m = ((n as f32 * self.config.update_fraction) as usize).clamp(1, n);
            (0..m).map(|_| rng.random_range(0..n)).collect()
        };
        let pts: Vec<[f32; 3]> = cells
            .iter()
            .map(|&i| {
                let (x, y, z) = (i % r, (i / r) % r, i / (r * r));
                let j = |c: usize, rng: &mut R| (c as f32 + rng.random::<f32>()) / r as f32;
                self.unit_to_world([j(x, rng), j(y, rng), j(z, rng)])
            })
            .collect();
        let mut dens = vec![0f32; pts.len()];
        field.density(&pts, &mut dens)?;
        if self.updates == 0 {
            self.density.fill(0.0);
        } else {
            for d in &mut self.density {
                *d *= self.config.decay;
            }
        }
        for (&i, &d) in cells.iter().zip(&dens) {
            let d = if d.is_finite() { d } else { f32::MAX };
            self.density[i] = self.density[i].max(d);
        }
        self.updates += 1;
        self.rebuild_bits();
        Ok(())
    }

    fn rebuild_bits(&mut self) {
        let mut thr = (self.config.density_threshold * self.scene_box.density_scale()) as f64;
        if self.config.cap_at_mean {
            let mean =
                self.density.iter().map(|&d| d as f64).sum::<f64>() / self.num_cells() as f64;
            thr = thr.min(mean);
        }
        let thr = thr as f32;
        self.bits.fill(0);
        for (i, &d) in self.density.iter().enumerate() {
            if d > thr {
                self.bits[i >> 6] |= 1 << (i & 63);
            }
        }
    }

    /// A copy whose occupied cells are further restricted to estimates above
    /// `min_density` normalised units (multiples of `SceneBox::density_scale`): the
    /// render-time grid of a trained model, where thin fog that the training threshold keeps
    /// is not worth evaluating. `min_density <= 0` returns the grid unchanged.
    pub fn pruned(&self, min_density: f32) -> Self {
        let mut g = self.clone();
        if min_density > 0.0 {
            let thr = min_density * self.scene_box.density_scale();
            for (i, &d) in self.density.iter().enumerate() {
                if d <= thr {
                    g.bits[i >> 6] &= !(1u64 << (i & 63));
                }
            }
        }
        g
    }

    /// Fraction of the cells inside the scene box that are occupied (the part of the grid
    /// that box-clipped rays see).
    pub fn occupied_fraction_in_box(&self) -> f32 {
        let r = self.config.resolution;
        let (lo, hi) = (r / 4, r - r / 4);
        let mut n = 0usize;
        let mut occ = 0usize;
        for z in lo..hi {
            for y in lo..hi {
                for x in lo..hi {
                    n += 1;
                    occ += usize::from(self.bit(x + r * (y + r * z)));
                }
            }
        }
        occ as f32 / n.max(1) as f32
    }

    /// Per-cell density estimates (1/m), x fastest, for saving with a model.
    pub fn density(&self) -> &[f32] {
        &self.density
    }

    /// Scene box the grid covers (through the contraction).
    pub fn scene_box(&self) -> &SceneBox {
        &self.scene_box
    }

    /// Restores a grid from saved per-cell estimates ([`OccupancyGrid::density`]).
    pub fn from_density(
        config: OccupancyConfig,
        scene_box: SceneBox,
        density: Vec<f32>,
    ) -> Result<Self, RenderError> {
        let mut g = Self::new(config, scene_box)?;
        if density.len() != g.num_cells() {
            return Err(RenderError::LengthMismatch {
                what: "occupancy density",
                expected: g.num_cells(),
                actual: density.len(),
            });
        }
        g.density = density;
        g.updates = 1;
        g.rebuild_bits();
        Ok(g)
    }

    /// A grid built from the field by one full update (e.g. after loading a model).
    pub fn from_field<R: Rng>(
        config: OccupancyConfig,
        scene_box: SceneBox,
        field: &dyn FeatureField,
        rng: &mut R,
    ) -> Result<Self, RenderError> {
        let mut g = Self::new(config, scene_box)?;
        g.update(field, rng)?;
        Ok(g)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::limits::{BudgetSource, MemoryBudget, check_against};

    #[test]
    fn a_training_batch_beyond_the_memory_budget_is_refused() {
        let budget = Some(MemoryBudget {
            bytes: 1 << 30,
            source: BudgetSource::Explicit,
        });
        assert!(check_against(&crate::train::batch_request(4096, 48), budget).is_ok());
        let e = check_against(&crate::train::batch_request(1 << 20, 64), budget)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("67108864 samples") && e.contains("train.batch_rays"),
            "{e}"
        );
    }

    #[test]
    fn a_grid_beyond_the_memory_budget_is_refused() {
        let budget = Some(MemoryBudget {
            bytes: 1 << 30,
            source: BudgetSource::Explicit,
        });
        assert!(check_against(&grid_request(64u64.pow(3)), budget).is_ok());
        let e = check_against(&grid_request(1024u64.pow(3)), budget)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("occupancy grid")
                && e.contains("1073741824 cells")
                && e.contains("train.occupancy.resolution"),
            "{e}"
        );
    }
}
