use serde::{Deserialize, Serialize};

use crate::contraction::SceneBox;
use crate::error::FieldError;

/// Which appearance embedding [`crate::FeatureField::colour`] uses for an image it was not
/// trained on (`appearance = None`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum AppearanceFallback {
    /// The mean of all trained embeddings (nerfacto's `use_average_appearance_embedding`).
    #[default]
    Mean,
    /// The zero vector.
    Zero,
}

/// Everything that determines the field's tensor shapes plus its initialisation seed.
///
/// Level count (16), features per level (2) and hidden widths (64) are fixed because the
/// 47-d feature interface (`FeatureField`) depends on them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FieldConfig {
    /// log2 of the per-level hash table size T (nerfacto: 19).
    pub log2_table_size: u32,
    /// Coarsest grid resolution N_min.
    pub base_resolution: u32,
    /// Finest grid resolution N_max.
    pub max_resolution: u32,
    /// Foreground box in world metres (mapped to `[-1,1]³` before contraction).
    pub scene_box: SceneBox,
    /// Number of training images, i.e. appearance embeddings (may be 0).
    pub num_images: usize,
    /// Width of each appearance embedding (nerfacto: 32; default here 8).
    pub appearance_dim: usize,
    /// Embedding used for images without one.
    pub appearance_fallback: AppearanceFallback,
    /// Seed of the weight initialisation.
    pub seed: u64,
}

impl Default for FieldConfig {
    fn default() -> Self {
        Self {
            log2_table_size: 19,
            base_resolution: 16,
            max_resolution: 2048,
            scene_box: SceneBox::default(),
            num_images: 0,
            appearance_dim: 8,
            appearance_fallback: AppearanceFallback::Mean,
            seed: 0,
        }
    }
}

impl FieldConfig {
    /// Checks every value's range.
    pub fn validate(&self) -> Result<(), FieldError> {
        if !(4..=26).contains(&self.log2_table_size) {
            return Err(FieldError::InvalidConfig {
                field: "log2_table_size",
                reason: format!("{} not in 4..=26", self.log2_table_size),
            });
        }
        if self.base_resolution < 1 {
            return Err(FieldError::InvalidConfig {
                field: "base_resolution",
                reason: "must be >= 1".into(),
            });
        }
        if self.max_resolution < self.base_resolution || self.max_resolution > 1 << 20 {
            return Err(FieldError::InvalidConfig {
                field: "max_resolution",
                reason: format!(
                    "{} must be in [base_resolution = {}, 2^20]",
                    self.max_resolution, self.base_resolution
                ),
            });
        }
        if !self.scene_box.is_valid() {
            return Err(FieldError::InvalidConfig {
                field: "scene_box",
                reason: format!("{:?} must be finite with max > min", self.scene_box),
            });
        }
        if self.appearance_dim > 256 {
            return Err(FieldError::InvalidConfig {
                field: "appearance_dim",
                reason: format!("{} > 256", self.appearance_dim),
            });
        }
        Ok(())
    }

    /// Width of the colour MLP input: SH (16) + f_mlp (15) + appearance.
    pub fn colour_input_dim(&self) -> usize {
        crate::sh::SH_DIM + crate::feature::F_MLP_DIM + self.appearance_dim
    }
}
