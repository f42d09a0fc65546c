//! Errors of the pipeline library. Every stage crate's typed error is a source here, so a
//! caller can match on it or walk `source()` down to the file and field that failed.

use std::path::PathBuf;

use matloc_core::CameraError;

/// Errors from map building, map loading, localization and evaluation.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// Map directory problem.
    #[error(transparent)]
    Map(#[from] crate::map::manifest::MapError),
    /// Rendering a NeRF failed (bad pose, model problem).
    #[error(transparent)]
    Render(#[from] matloc_render::RenderError),
    /// A renderer behind the `ViewRenderer` seam failed.
    #[error("rendering the map: {0}")]
    ViewRender(#[source] matloc_match::RenderFailure),
    /// Pose solving failed in a way that is not simply "no consensus".
    #[error(transparent)]
    Pnp(#[from] matloc_pnp::PnpError),
    /// Camera model problem (e.g. a resolution the intrinsics cannot be rescaled to).
    #[error("camera: {0}")]
    Camera(#[from] CameraError),
    /// The query's intrinsics are well formed but no real camera has them (a principal point
    /// outside the image, tangential distortion far beyond a lens's, a field of view no lens
    /// gives): rejected before localizing, naming the field and the bound.
    #[error("implausible query camera: {0}")]
    ImplausibleCamera(#[from] matloc_core::ImplausibleCamera),
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
    /// Matching failed (e.g. encoder and map dims disagree).
    #[error(transparent)]
    Match(#[from] matloc_match::MatchError),
    /// The query encoder failed (training, loading, encoding).
    #[error("query encoder: {0}")]
    Encoder(#[from] matloc_encoder::EncoderError),
    /// The place predictor failed.
    #[error("place prediction: {0}")]
    Place(#[from] matloc_place::PlaceError),
    /// Finding the scene surface of the training views failed.
    #[error("surface: {0}")]
    Surface(#[from] matloc_surface::SurfaceError),
    /// Structure store or structure localizer.
    #[error(transparent)]
    Structure(#[from] matloc_structure::StructureError),
    /// The partition failed.
    #[error("partition: {0}")]
    Partition(#[from] matloc_partition::PartitionError),
    /// Ground-truth pair generation, storage or loading failed.
    #[error("ground-truth pairs: {0}")]
    Pairs(#[from] crate::gt::GtError),
    /// Feature selection failed.
    #[error("feature selection: {0}")]
    Select(#[from] matloc_select::SelectError),
    /// The synthetic world could not be generated.
    #[error("synthetic world: {0}")]
    Synth(#[from] matloc_synth::SynthError),
    /// A dataset image or depth map could not be loaded.
    #[error(transparent)]
    Image(#[from] matloc_data::images::ImageLoadError),
    /// The confidence model could not be fitted.
    #[error("confidence calibration: {0}")]
    Calibration(#[from] crate::localizer::confidence::CalibrationError),
    /// A stage of one block failed.
    #[error("block {block}: {source}")]
    Block {
        /// The block.
        block: usize,
        /// What failed.
        source: Box<PipelineError>,
    },
    /// The place predictor returned no hypothesis.
    #[error("the place predictor returned no hypothesis")]
    NoPlaceHypothesis,
    /// A training view sees no surface (nothing to anchor its pose group on).
    #[error("training frame {frame} sees no surface in its depth")]
    ViewSeesNoSurface {
        /// Frame index in the dataset.
        frame: usize,
    },
    /// A block selects a feature dim the query encoder does not produce.
    #[error("feature dim {dim} is selected by the map but not produced by the query encoder")]
    DimsNotEncoded {
        /// The field dim.
        dim: usize,
    },
    /// The job list or its scripts.
    #[error(transparent)]
    Jobs(#[from] crate::build::jobs::JobError),
    /// An I/O error outside the map's own files.
    #[error("{path}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// The configuration stored in a map's manifest does not parse as a map config.
    #[error("manifest config: {source}")]
    ManifestConfig {
        /// The parse error.
        source: serde_json::Error,
    },
    /// A configuration could not be turned into JSON or back (e.g. `nerf.model_overrides`
    /// that do not fit the model config).
    #[error("map config field `{field}`: {source}")]
    ConfigJson {
        /// The field.
        field: &'static str,
        /// The serde error.
        source: serde_json::Error,
    },
    /// The build configuration or the data cannot make this stage work (the message says
    /// which setting or input and why).
    #[error("map config: {0}")]
    Config(String),
    /// The map's build did not finish this stage (resume it with `matloc map build`).
    #[error(
        "map {root} is incomplete: stage {stage} has not finished (run the build again to resume)"
    )]
    Incomplete {
        /// Map root.
        root: PathBuf,
        /// First unfinished stage.
        stage: String,
    },
    /// A broken internal invariant (a bug, reported instead of panicking).
    #[error("internal error: {0}")]
    Internal(&'static str),
}

impl From<matloc_match::localize::LocalizeError> for PipelineError {
    fn from(e: matloc_match::localize::LocalizeError) -> Self {
        match e {
            matloc_match::localize::LocalizeError::Render(r) => PipelineError::ViewRender(r),
            matloc_match::localize::LocalizeError::Match(m) => PipelineError::Match(m),
        }
    }
}

impl PipelineError {
    /// `source` as the failure of block `block`.
    pub fn in_block(block: usize, source: impl Into<PipelineError>) -> Self {
        PipelineError::Block {
            block,
            source: Box::new(source.into()),
        }
    }
}
