//! Diagnostic stand-ins for learned stages, to measure what the rest of the pipeline can do
//! without them.

use matloc_core::{Camera, FeatureMap, Image, Pose};
use matloc_match::ViewRenderer;

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

    fn stats(&self) -> Option<&matloc_match::FeatureStats> {
        None
    }

    fn encode(&self, _image: &Image<f32>) -> Result<FeatureMap, PipelineError> {
        let r = self
            .renderer
            .render_view(&self.camera, &self.cam_from_world, self.stride, &self.dims)
            .map_err(PipelineError::ViewRender)?;
        FeatureMap::from_vec(r.cols, r.rows, self.dims.len(), r.features)
            .map_err(|_| PipelineError::Internal("rendered feature map has the wrong size"))
    }
}

/// Per-dim Pearson correlation between an encoder's output and features rendered on the same
/// grid, over the cells the render hit (accumulation > 0.5): how well the encoder predicts
/// each field dim. `target` holds `target.dims` channels and `encoded` at least as many, in the
/// same order; `None` for a dim whose correlation is undefined (constant, or fewer than two
/// cells) and for every dim when the grids differ in size.
pub fn encoder_correlation(
    target: &matloc_match::RenderedView,
    encoded: &FeatureMap,
    dims: &[usize],
) -> Vec<Option<f64>> {
    let same_grid = encoded.width() == target.cols && encoded.height() == target.rows;
    // The hit cells are the same for every dim: find them once.
    let hits: Vec<usize> = (0..target.cols * target.rows)
        .filter(|&i| target.accumulation[i] > 0.5)
        .collect();
    dims.iter()
        .map(|&d| {
            if !same_grid || d >= target.dims || d >= encoded.channels() {
                return None;
            }
            let xs: Vec<f64> = hits
                .iter()
                .map(|&i| f64::from(target.features[i * target.dims + d]))
                .collect();
            let ys: Vec<f64> = hits
                .iter()
                .map(|&i| f64::from(encoded.pixel(i % target.cols, i / target.cols)[d]))
                .collect();
            matloc_core::metrics::pearson(&xs, &ys)
        })
        .collect()
}
