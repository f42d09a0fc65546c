//! 2D–3D matching between a query image's dense feature map and features rendered from a NeRF
//! map (paper Section 3.1).
//!
//! - [`Matcher`] is the object-safe interface; [`MnnMatcher`] finds mutual nearest neighbours
//!   of L2-normalised (optionally standardised) features under the dot-product similarity, with
//!   an optional similarity threshold and ratio test.
//! - The similarity matrix is never materialised: [`kernel::nn_tables_tiled`] keeps running
//!   row and column maxima in registers and a per-thread column state, so the cost is the
//!   `2·N·M·D` FLOP of the products. [`kernel::nn_tables_reference`] (plain loops, bit-identical)
//!   and [`kernel::nn_tables_faer`] (faer GEMM) materialise it for tests and benchmarks.
//! - The lower-level [`prepare_rows`] and [`mnn_prepared`] work on plain row-major buffers; the
//!   feature selector uses them.
//! - [`subcell`] refines each match below the grid cell (on by default: query side, parabola
//!   fit), so the 2D–3D correspondences are continuous and PnP is not limited by the grid.
//! - [`gt`] generates ground-truth 2D–3D pairs from perturbed training poses (paper 3.1.2)
//!   through any [`gt::ViewRenderer`]; [`synth_view`] is one backed by the synthetic world's
//!   exact geometry and an analytic feature field, [`nerf_view`] one over a trained NeRF.
//! - [`encoder`] (feature `encoder`, on by default) is the burn CNN mapping RGB to the NeRF
//!   feature domain at stride 4.
//! - [`localize`] renders the map at a coarse pose, lifts it to 3D, matches and solves PnP.
//! - [`featuremetric`] refines a pose against the dense query feature map (every rendered
//!   point, not only the matches): what makes learned-encoder poses sub-metre.

#[cfg(feature = "encoder")]
pub mod encoder;
pub mod error;
pub mod featuremetric;
pub mod gt;
pub mod kernel;
pub mod localize;
pub mod mnn;
pub mod nerf_view;
pub mod subcell;
pub mod synth_view;
pub mod types;
pub mod window;

pub use error::{MatchError, Side};
pub use kernel::{NnTable, NnTables};
pub use mnn::{
    FeatureStats, Matcher, MnnConfig, MnnKernel, MnnMatcher, RawMatch, check_selection,
    mnn_prepared, mutual_from_tables, prepare_rows, tables,
};
pub use subcell::{SubcellConfig, SubcellFit, SubcellSide};
pub use types::{Match2d3d, QueryFeatures, QueryGrid, RenderedPoints};
