//! 2D–3D matching between a query image's dense feature map and features rendered from a NeRF
//! map (paper Section 3.1).
//!
//! - [`Matcher`] is the object-safe interface; [`MnnMatcher`] finds mutual nearest neighbours
//!   of L2-normalised (optionally standardised) features under the dot-product similarity, with
//!   an optional similarity threshold and ratio test.
//! - The similarity matrix is never materialised: [`kernel::nn_tables_tiled`] keeps running
//!   row and column maxima in registers and a per-thread column state, so the cost is the
//!   `2·N·M·D` FLOP of the products. [`kernel::nn_tables_reference`] (plain loops, bit-identical)
//!   materialises it for tests; with the `faer` feature, `kernel::nn_tables_faer` (faer GEMM)
//!   is the materialised baseline of the benchmarks.
//! - The lower-level [`prepare_rows`] and [`mnn_prepared`] work on plain row-major buffers; the
//!   feature selector uses them.
//! - [`subcell`] refines each match below the grid cell (on by default: map side, quadratic
//!   fit), so the 2D–3D correspondences are continuous and PnP is not limited by the grid.
//! - [`view::ViewRenderer`] is the seam to whatever renders features and depth at a pose;
//!   [`nerf_view`] implements it over a trained NeRF.
//! - [`localize`] renders the map at a coarse pose, lifts it to 3D, matches and solves PnP.
//! - [`featuremetric`] refines a pose against the dense query feature map (every rendered
//!   point, not only the matches): what makes learned-encoder poses sub-metre.

pub mod error;
pub mod featuremetric;
pub mod kernel;
pub mod localize;
pub mod mnn;
pub mod nerf_view;
pub mod subcell;
pub mod types;
pub mod view;
pub mod window;

pub use error::{MatchError, Side};
pub use kernel::{NnTable, NnTables};
pub use mnn::{
    FeatureStats, Matcher, MnnConfig, MnnKernel, MnnMatcher, RawMatch, check_selection,
    mnn_prepared, mutual_from_tables, prepare_rows, tables,
};
pub use subcell::{SubcellConfig, SubcellFit, SubcellSide};
pub use types::{Match2d3d, QueryFeatures, QueryGrid, RenderedPoints};
pub use view::{RenderFailure, RenderedView, ViewRenderer, grid_size};
