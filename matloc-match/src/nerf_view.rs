//! [`ViewRenderer`] over a trained NeRF (`matloc-render`'s [`NerfModel`] and [`render_view`]):
//! what pair generation and localization use on real maps.

use crate::view::{RenderFailure, RenderedView, ViewRenderer};
use matloc_core::{Camera, Pose};
use matloc_render::{NerfModel, PixelSet, RenderRequest, render_view};

/// A NeRF map rendered on the stride grid (features are `Σ w_k f_k`, not normalised by
/// accumulation, as in the paper).
#[derive(Clone, Debug)]
pub struct NerfViewRenderer {
    model: NerfModel,
    label: String,
}

impl NerfViewRenderer {
    /// Wraps a model; `label` (e.g. its directory) goes into pair provenance.
    pub fn new(model: NerfModel, label: impl Into<String>) -> Self {
        NerfViewRenderer {
            model,
            label: label.into(),
        }
    }

    /// The model.
    pub fn model(&self) -> &NerfModel {
        &self.model
    }
}

impl ViewRenderer for NerfViewRenderer {
    fn num_features(&self) -> usize {
        matloc_nerf_field::FEATURE_DIM
    }

    fn describe(&self) -> String {
        format!("NeRF {} at step {}", self.label, self.model.step())
    }

    fn render_view(
        &self,
        camera: &Camera,
        cam_from_world: &Pose,
        stride: u32,
        dims: &[usize],
    ) -> Result<RenderedView, RenderFailure> {
        let request = RenderRequest {
            rgb: false,
            dims: dims.to_vec(),
            appearance: None,
        };
        let v = render_view(
            &self.model,
            camera,
            cam_from_world,
            &PixelSet::Grid { stride },
            &request,
        )?;
        Ok(RenderedView {
            cols: v.width,
            rows: v.height,
            dims: dims.len(),
            features: v.features,
            depth_z: v.z_depth,
            accumulation: v.accumulation,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_render::ModelConfig;

    #[test]
    fn adapter_renders_the_stride_grid_in_request_order() {
        let cfg = ModelConfig::for_scene([-10.0, -10.0, -2.0], [10.0, 10.0, 8.0], 20.0, 1);
        let r = NerfViewRenderer::new(NerfModel::new(cfg).unwrap(), "untrained");
        assert_eq!(r.num_features(), 47);
        let camera = Camera::from_hfov(32, 24, 60.0).unwrap();
        let pose = matloc_core::pose::look_at(
            &nalgebra::Point3::new(0.0, -20.0, 20.0),
            &nalgebra::Point3::origin(),
            &nalgebra::Vector3::z(),
        )
        .unwrap();
        let v = r.render_view(&camera, &pose, 4, &[40, 3]).unwrap();
        assert_eq!((v.cols, v.rows, v.dims), (8, 6, 2));
        assert_eq!(v.features.len(), 8 * 6 * 2);
        assert_eq!(v.depth_z.len(), 48);
        assert!(
            v.accumulation
                .iter()
                .all(|a| (0.0..=1.0 + 1e-5).contains(a))
        );
        assert!(r.describe().contains("untrained"));
    }
}
