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
    /// A broken internal invariant (a bug, reported instead of panicking).
    #[error("internal error: {0}")]
    Internal(&'static str),
}
