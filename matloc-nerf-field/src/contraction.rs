use serde::{Deserialize, Serialize};

/// Axis-aligned box (metres, world frame) that holds the "foreground" of a scene.
///
/// The box is mapped affinely onto `[-1, 1]³`; everything outside is squashed by the
/// ∞-norm contraction ([`contract`]) into the shell `[-2, 2]³ \ [-1, 1]³`, so unbounded aerial
/// scenes (sky, far terrain) still get a finite, resolution-limited representation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneBox {
    /// Minimum corner (metres).
    pub min: [f32; 3],
    /// Maximum corner (metres).
    pub max: [f32; 3],
}

impl Default for SceneBox {
    fn default() -> Self {
        Self {
            min: [-1.0; 3],
            max: [1.0; 3],
        }
    }
}

impl SceneBox {
    /// Maps a world point to the box's normalised frame, where the box is `[-1, 1]³`.
    #[inline]
    pub fn normalize(&self, p: [f32; 3]) -> [f32; 3] {
        let mut q = [0.0; 3];
        for a in 0..3 {
            q[a] = (p[a] - self.min[a]) / (self.max[a] - self.min[a]) * 2.0 - 1.0;
        }
        q
    }

    /// Density (1/m) of one unit of normalised density: `2 / mean extent`, the length of the
    /// box's `[-1,1]` frame per metre. See `NerfactoField::density_scale`.
    pub fn density_scale(&self) -> f32 {
        let e: f32 = (0..3).map(|a| self.max[a] - self.min[a]).sum::<f32>() / 3.0;
        2.0 / e
    }

    /// Whether every extent is positive and finite.
    pub fn is_valid(&self) -> bool {
        (0..3).all(|a| {
            self.min[a].is_finite() && self.max[a].is_finite() && self.max[a] > self.min[a]
        })
    }
}

/// nerfstudio's ∞-norm scene contraction: `x` if `‖x‖∞ ≤ 1`, else `(2 − 1/‖x‖∞)·x/‖x‖∞`.
///
/// The result lies in `[-2, 2]³`; it is the identity inside the unit cube and strictly
/// increasing along every ray from the origin.
#[inline]
pub fn contract(x: [f32; 3]) -> [f32; 3] {
    let n = x[0].abs().max(x[1].abs()).max(x[2].abs());
    if n <= 1.0 {
        x
    } else {
        let s = (2.0 - 1.0 / n) / n;
        [x[0] * s, x[1] * s, x[2] * s]
    }
}

/// World point → hash-grid input in `[0, 1]³`: box-normalise, contract, then `(c + 2) / 4`.
#[inline]
pub fn contract_to_unit(scene_box: &SceneBox, p_world: [f32; 3]) -> [f32; 3] {
    let c = contract(scene_box.normalize(p_world));
    [
        ((c[0] + 2.0) * 0.25).clamp(0.0, 1.0),
        ((c[1] + 2.0) * 0.25).clamp(0.0, 1.0),
        ((c[2] + 2.0) * 0.25).clamp(0.0, 1.0),
    ]
}
