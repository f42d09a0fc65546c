//! Diagnostic stand-ins for learned stages, to measure what the rest of the pipeline can do
//! without them.

use matloc_core::{Camera, FeatureMap, Image, Pose};
use matloc_match::gt::ViewRenderer;

use crate::error::PipelineError;
use crate::localizer::QueryFeatureEncoder;

/// A perfect query encoder: ignores the image and returns the map's own features rendered at
/// the query's true pose. Localizing with it bounds what matching + PnP + refinement reach
/// with the map's NeRF features and depth, independent of the CNN encoder.
pub struct RenderedQueryEncoder<'a> {
    /// The block's renderer.
    pub renderer: &'a dyn ViewRenderer,
    /// Query camera.
    pub camera: Camera,
    /// True `cam_from_world` of the query.
    pub cam_from_world: Pose,
    /// Field dims rendered (the channel order of the output).
    pub dims: Vec<usize>,
    /// Grid stride.
    pub stride: u32,
}

impl QueryFeatureEncoder for RenderedQueryEncoder<'_> {
    fn dims(&self) -> &[usize] {
        &self.dims
    }

    fn stride(&self) -> u32 {
        self.stride
    }

    fn encode(&self, _image: &Image<f32>) -> Result<FeatureMap, PipelineError> {
        let r = self
            .renderer
            .render_view(&self.camera, &self.cam_from_world, self.stride, &self.dims)
            .map_err(|e| PipelineError::RenderFailure(e.to_string()))?;
        FeatureMap::from_vec(r.cols, r.rows, self.dims.len(), r.features)
            .map_err(|_| PipelineError::Internal("rendered feature map has the wrong size"))
    }
}
