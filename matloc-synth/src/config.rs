//! What defines a synthetic dataset ([`SynthConfig`]) and the named presets. Each preset fixes
//! the scene and the capture so its image count and resolution suit its purpose (CI speed,
//! demo, paper-like scenes).

use serde::{Deserialize, Serialize};

use super::error::SynthError;
use super::render::RenderOptions;
use super::survey::SurveyConfig;
use super::world::WorldConfig;

/// Everything that defines a synthetic dataset: scene, capture and rendering.
///
/// `Default` is the `small` preset with seed 0. Deserialising a partial file fills the missing
/// fields from `Default`, so a preset tweak is a few lines of JSON/TOML.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SynthConfig {
    /// Preset name recorded in the dataset metadata.
    pub preset: String,
    /// Seed of the world and of the survey jitter.
    pub seed: u64,
    /// Scene content.
    pub world: WorldConfig,
    /// Drone capture plan.
    pub survey: SurveyConfig,
    /// Renderer settings.
    pub render: RenderOptions,
}

impl Default for SynthConfig {
    fn default() -> Self {
        small()
    }
}

impl SynthConfig {
    /// The configuration of a named preset (`tiny`, `small`, `rubble`, `building`), seed 0.
    pub fn preset(name: &str) -> Result<SynthConfig, SynthError> {
        by_name(name).ok_or_else(|| SynthError::UnknownPreset {
            name: name.to_string(),
            valid: PRESET_NAMES.join(", "),
        })
    }

    /// The same configuration with another seed.
    pub fn with_seed(mut self, seed: u64) -> Self {
        self.seed = seed;
        self
    }

    /// Checks every field; generation calls this first.
    pub fn validate(&self) -> Result<(), SynthError> {
        self.world.validate()?;
        self.survey.validate()?;
        if self.render.edge_samples > 8 {
            return Err(SynthError::InvalidConfig {
                field: "render.edge_samples",
                reason: format!("must be at most 8, got {}", self.render.edge_samples),
            });
        }
        for (field, v) in [
            ("render.sun_strength", self.render.sun_strength),
            ("render.exposure", self.render.exposure),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(SynthError::InvalidConfig {
                    field,
                    reason: format!("must be a non-negative number, got {v}"),
                });
            }
        }
        if !self
            .render
            .white_balance
            .iter()
            .all(|g| g.is_finite() && *g > 0.0)
        {
            return Err(SynthError::InvalidConfig {
                field: "render.white_balance",
                reason: format!(
                    "gains must be positive numbers, got {:?}",
                    self.render.white_balance
                ),
            });
        }
        Ok(())
    }
}

/// Valid preset names.
pub const PRESET_NAMES: [&str; 4] = ["tiny", "small", "rubble", "building"];

pub(crate) fn by_name(name: &str) -> Option<SynthConfig> {
    match name {
        "tiny" => Some(tiny()),
        "small" => Some(small()),
        "rubble" => Some(rubble()),
        "building" => Some(building()),
        _ => None,
    }
}

/// ~80 m square, a handful of buildings, 160×120 images, ~48 train + 10 test views.
pub(crate) fn tiny() -> SynthConfig {
    SynthConfig {
        preset: "tiny".into(),
        seed: 0,
        world: WorldConfig {
            extent_m: 80.0,
            margin_m: 50.0,
            terrain_relief_m: 2.0,
            terrain_cell_m: 0.5,
            roads: 1,
            buildings: 6,
            building_size_m: [8.0, 18.0],
            building_height_m: [5.0, 12.0],
            rubble_fields: 1,
            rubble_radius_m: [6.0, 9.0],
            rocks_per_field: 150,
            trees: 12,
            ..WorldConfig::default()
        },
        survey: SurveyConfig {
            width: 160,
            height: 120,
            altitude_m: 30.0,
            cross_pass: true,
            test_views: 10,
            ..SurveyConfig::default()
        },
        render: RenderOptions::default(),
    }
}

/// ~200 m square town with a rubble patch, 320×240 images, ~220 train + 30 test views.
pub(crate) fn small() -> SynthConfig {
    SynthConfig {
        preset: "small".into(),
        seed: 0,
        world: WorldConfig::default(),
        survey: SurveyConfig::default(),
        render: RenderOptions::default(),
    }
}

/// ~300 m site dominated by dense rubble (Mill-19 "Rubble"-like), a few buildings.
pub(crate) fn rubble() -> SynthConfig {
    SynthConfig {
        preset: "rubble".into(),
        seed: 0,
        world: WorldConfig {
            extent_m: 300.0,
            margin_m: 90.0,
            roads: 2,
            buildings: 12,
            building_size_m: [8.0, 30.0],
            building_height_m: [5.0, 15.0],
            rubble_fields: 10,
            rubble_radius_m: [15.0, 35.0],
            rocks_per_field: 2500,
            trees: 40,
            ..WorldConfig::default()
        },
        survey: SurveyConfig {
            forward_overlap: 0.7,
            test_views: 40,
            ..SurveyConfig::default()
        },
        render: RenderOptions::default(),
    }
}

/// ~300 m dense town of taller buildings (Mill-19 "Building"-like).
pub(crate) fn building() -> SynthConfig {
    SynthConfig {
        preset: "building".into(),
        seed: 0,
        world: WorldConfig {
            extent_m: 300.0,
            margin_m: 90.0,
            roads: 4,
            buildings: 200,
            building_size_m: [10.0, 40.0],
            building_height_m: [8.0, 30.0],
            rubble_fields: 1,
            rocks_per_field: 300,
            trees: 50,
            ..WorldConfig::default()
        },
        survey: SurveyConfig {
            altitude_m: 40.0,
            forward_overlap: 0.7,
            test_views: 40,
            ..SurveyConfig::default()
        },
        render: RenderOptions::default(),
    }
}
