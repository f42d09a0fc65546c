//! A nerfacto-like radiance field that trains and renders on the CPU.
//!
//! The field maps a world point to a density and a 47-d intermediate feature vector
//! (`f_pos`: 16 hash-grid levels × 2 features, then `f_mlp`: the 15-d geometry feature), and
//! maps `f_mlp` plus a view direction (and a per-image appearance embedding) to RGB. Every
//! backward pass is hand-written and checked against finite differences in the tests.
//!
//! Pipeline for one point (see [`NerfactoField`]):
//!
//! ```text
//! x_world ─► SceneBox → [-1,1]³ ─► ∞-norm contraction → [-2,2]³ ─► [0,1]³
//!         ─► hash grid (16 × 2) = f_pos (32) ─► 32→64 ReLU→16 ─► [0]: σ = trunc_exp, [1..16]: f_mlp
//! [SH₄(d) (16), f_mlp (15), appearance (A)] ─► 64 ReLU ─► 64 ReLU ─► 3 sigmoid = RGB
//! ```
//!
//! Rendering, sampling and the training loop live in `matloc-render`; this crate owns the
//! network, its gradients, the optimiser and (de)serialisation.

mod activation;
mod adam;
mod config;
mod contraction;
mod error;
mod feature;
mod field;
mod hashgrid;
mod io;
mod mlp;
mod sh;

pub use activation::{sigmoid, trunc_exp, trunc_exp_grad};
pub use adam::{Adam, AdamConfig, ExponentialDecay};
pub use config::{AppearanceFallback, FieldConfig};
pub use contraction::{SceneBox, contract, contract_to_unit};
pub use error::FieldError;
pub use feature::{F_MLP_DIM, F_MLP_DIMS, F_POS_DIM, F_POS_DIMS, FEATURE_DIM, FeatureField};
pub use field::{FieldGrads, NerfactoField, TrainCache};
pub use hashgrid::{HashGrid, LevelInfo, N_FEATURES_PER_LEVEL, N_LEVELS, hash_coords};
pub use mlp::{Linear, LinearGrad};
pub use sh::{SH_DIM, sh_encode};
