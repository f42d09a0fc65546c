//! Errors of the pipeline library.

use matloc_core::CameraError;

/// Errors from localization and map handling.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// Map directory problem.
    #[error(transparent)]
    Map(#[from] crate::manifest::MapError),
    /// Rendering failed (bad pose, model problem).
    #[error(transparent)]
    Render(#[from] matloc_render::RenderError),
    /// Pose solving failed in a way that is not simply "no consensus".
    #[error(transparent)]
    Pnp(#[from] matloc_pnp::PnpError),
    /// Camera model problem (e.g. a resolution the intrinsics cannot be rescaled to).
    #[error("camera: {0}")]
    Camera(CameraError),
    /// The query image does not have the camera's size or is not RGB.
    #[error(
        "query image is {}×{} with {} channels, the camera is {}×{} (RGB expected)",
        image.0, image.1, image.2, camera.0, camera.1
    )]
    QueryShape {
        /// Image width, height, channels.
        image: (usize, usize, usize),
        /// Camera width, height.
        camera: (u32, u32),
    },
    /// Rendering a block for matching failed.
    #[error("rendering the map: {0}")]
    RenderFailure(String),
    /// Matching failed (e.g. encoder and map dims disagree).
    #[error(transparent)]
    Match(#[from] matloc_match::MatchError),
    /// The query encoder failed.
    #[error("query encoder: {0}")]
    Encoder(String),
    /// The place predictor failed.
    #[error("place prediction: {0}")]
    Place(String),
    /// A block selects a feature dim the query encoder does not produce.
    #[error("feature dim {dim} is selected by the map but not produced by the query encoder")]
    DimsNotEncoded {
        /// The field dim.
        dim: usize,
    },
    /// An I/O error outside the map's own files.
    #[error("{path}: {source}")]
    Io {
        /// The path.
        path: std::path::PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// The build configuration is invalid or cannot be serialised.
    #[error("map config: {0}")]
    Config(String),
    /// The partition stage failed.
    #[error("partition: {0}")]
    Partition(String),
    /// The map's build did not finish this stage (resume it with `matloc map build`).
    #[error(
        "map {root} is incomplete: stage {stage} has not finished (run the build again to resume)"
    )]
    Incomplete {
        /// Map root.
        root: std::path::PathBuf,
        /// First unfinished stage.
        stage: String,
    },
    /// A broken internal invariant (a bug, reported instead of panicking).
    #[error("internal error: {0}")]
    Internal(&'static str),
}
