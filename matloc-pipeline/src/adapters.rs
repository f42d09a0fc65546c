//! Adapters from the stage crates' concrete types to the interfaces the localizer composes.
//! (A trained sub-NeRF is a `ViewRenderer` through `matloc_match::nerf_view::NerfViewRenderer`.)

use matloc_core::{FeatureMap, Image};
use matloc_encoder::{ENCODER_STRIDE, QueryEncoder};

use crate::error::PipelineError;
use crate::localizer::QueryFeatureEncoder;

impl QueryFeatureEncoder for QueryEncoder {
    fn dims(&self) -> &[usize] {
        QueryEncoder::dims(self)
    }

    fn stride(&self) -> u32 {
        ENCODER_STRIDE
    }

    fn stats(&self) -> Option<&matloc_match::FeatureStats> {
        Some(QueryEncoder::stats(self))
    }

    fn encode(&self, image: &Image<f32>) -> Result<FeatureMap, PipelineError> {
        Ok(QueryEncoder::encode(self, image)?)
    }
}
