use std::ops::Range;

use crate::error::FieldError;

/// Width of `f_pos` (hash-grid features, level-major: level l feature f at index 2l+f).
pub const F_POS_DIM: usize = 32;
/// Width of `f_mlp` (geometry MLP outputs 1..16).
pub const F_MLP_DIM: usize = 15;
/// Width of the full intermediate feature vector `[f_pos, f_mlp]`.
pub const FEATURE_DIM: usize = F_POS_DIM + F_MLP_DIM;
/// Indices of `f_pos` inside the 47-d vector.
pub const F_POS_DIMS: Range<usize> = 0..F_POS_DIM;
/// Indices of `f_mlp` inside the 47-d vector.
pub const F_MLP_DIMS: Range<usize> = F_POS_DIM..FEATURE_DIM;

/// A radiance field that exposes density, intermediate features and colour for batches.
///
/// This is the stable interface the renderer, matcher and selector use. Buffers are
/// point-major (`features[i * dims.len() + j]` is dim `dims[j]` of point `i`). The trait is
/// object-safe so pipelines can hold `&dyn FeatureField`.
pub trait FeatureField: Send + Sync {
    /// Number of intermediate feature dims (47 for the nerfacto-like field).
    fn feature_dim(&self) -> usize {
        FEATURE_DIM
    }

    /// Density (1/m) and the chosen feature dims for world points.
    ///
    /// `density.len()` must equal `points.len()` and `features.len()` must equal
    /// `points.len() * dims.len()`. `dims` may be empty (density only). Work a subset does not
    /// need is skipped where the architecture allows it.
    fn density_and_features(
        &self,
        points: &[[f32; 3]],
        dims: &[usize],
        density: &mut [f32],
        features: &mut [f32],
    ) -> Result<(), FieldError>;

    /// Density only (convenience over [`Self::density_and_features`]).
    fn density(&self, points: &[[f32; 3]], density: &mut [f32]) -> Result<(), FieldError> {
        self.density_and_features(points, &[], density, &mut [])
    }

    /// RGB in `[0,1]` from `f_mlp` (15 per point, point-major) and unit view directions.
    ///
    /// `appearance = None` uses the field's fallback embedding (for unseen images).
    fn colour(
        &self,
        f_mlp: &[f32],
        directions: &[[f32; 3]],
        appearance: Option<u32>,
        rgb: &mut [f32],
    ) -> Result<(), FieldError>;
}
