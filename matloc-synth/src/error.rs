//! Errors of the synthetic-world generator.

use std::path::PathBuf;

use thiserror::Error;

/// Errors of the synthetic-world generator.
#[derive(Debug, Error)]
pub enum SynthError {
    /// The preset name is not one of [`crate::PRESET_NAMES`].
    #[error("unknown synthetic preset {name:?}; valid presets: {valid}")]
    UnknownPreset {
        /// The name asked for.
        name: String,
        /// Comma-separated valid names.
        valid: String,
    },
    /// A configuration value is out of range.
    #[error("invalid synthetic config field `{field}`: {reason}")]
    InvalidConfig {
        /// Dotted field path, e.g. `survey.pitch_deg`.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// The survey plan placed a camera inside or under scene geometry.
    #[error(
        "survey camera {index} at {position:?} is inside or below scene geometry; raise survey.altitude_m"
    )]
    CameraInsideScene {
        /// Index of the planned view.
        index: usize,
        /// Its world position.
        position: [f64; 3],
    },
    /// Writing an output file failed.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// Writing an image or depth file failed.
    #[error(transparent)]
    Image(Box<matloc_data::images::ImageLoadError>),
    /// Writing `transforms.json` failed.
    #[error(transparent)]
    Dataset(Box<matloc_data::nerfstudio::NerfstudioError>),
    /// Writing `sparse_pc.ply` failed.
    #[error(transparent)]
    Ply(Box<matloc_data::ply::PlyError>),
    /// Writing the COLMAP model failed.
    #[error(transparent)]
    Colmap(Box<matloc_data::colmap::ColmapError>),
}
