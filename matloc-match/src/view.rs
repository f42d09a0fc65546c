//! The view seam: anything that renders features and depth of a scene at a pose on a pixel
//! grid (a trained NeRF, or the synthetic world's exact geometry in tests and studies).

use matloc_core::{Camera, Pose};

/// Error type a renderer reports; kept opaque so any renderer can implement [`ViewRenderer`].
pub type RenderFailure = Box<dyn std::error::Error + Send + Sync>;

/// Features, depth and accumulated opacity of one view rendered on a pixel grid of stride `s`:
/// cell `(col, row)` is the ray through pixel `(s·(col + 0.5), s·(row + 0.5))`, with
/// `cols = width / s` and `rows = height / s` (see [`grid_size`]). Row-major cells.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderedView {
    /// Grid columns.
    pub cols: usize,
    /// Grid rows.
    pub rows: usize,
    /// Number of feature dims per cell (the dims requested, in request order).
    pub dims: usize,
    /// `cols · rows · dims` features.
    pub features: Vec<f32>,
    /// Z-depth in metres along the optical axis; `0` or non-finite where nothing was hit.
    pub depth_z: Vec<f32>,
    /// Accumulated opacity in `[0, 1]` (1 for an opaque hit).
    pub accumulation: Vec<f32>,
}

impl RenderedView {
    /// Checks the grid size and buffer lengths against what was asked for; the error says what
    /// differs.
    pub fn check_shape(&self, cols: usize, rows: usize, dims: usize) -> Result<(), String> {
        let n = cols * rows;
        if self.cols != cols || self.rows != rows || self.dims != dims {
            return Err(format!(
                "grid {}x{}x{} instead of {cols}x{rows}x{dims}",
                self.cols, self.rows, self.dims
            ));
        }
        if self.features.len() != n * dims
            || self.depth_z.len() != n
            || self.accumulation.len() != n
        {
            return Err(format!(
                "buffers of {}, {}, {} values for {n} cells of {dims} dims",
                self.features.len(),
                self.depth_z.len(),
                self.accumulation.len()
            ));
        }
        Ok(())
    }

    /// Whether cell `i` saw a surface: finite positive depth and enough opacity.
    pub fn has_surface(&self, i: usize, min_accumulation: f32) -> bool {
        let z = self.depth_z[i];
        z.is_finite() && z > 0.0 && self.accumulation[i] >= min_accumulation
    }
}

/// Grid size `(cols, rows)` of a camera's image at `stride` pixels per cell.
pub fn grid_size(camera: &Camera, stride: u32) -> (usize, usize) {
    let s = stride.max(1);
    ((camera.width / s) as usize, (camera.height / s) as usize)
}

/// Something that renders features and depth of a scene at any pose: the NeRF map, or (in
/// tests) the synthetic world's exact geometry.
pub trait ViewRenderer: Send + Sync {
    /// Feature dims available (47 for the nerfacto-like field).
    fn num_features(&self) -> usize;
    /// One line describing the renderer and its model, stored as provenance.
    fn describe(&self) -> String;
    /// Renders the requested feature `dims` (in that order), z-depth and accumulation on the
    /// grid of `stride` (see [`RenderedView`]).
    fn render_view(
        &self,
        camera: &Camera,
        cam_from_world: &Pose,
        stride: u32,
        dims: &[usize],
    ) -> Result<RenderedView, RenderFailure>;
}
