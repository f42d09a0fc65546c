//! Selection of NeRF feature dimensions for matching (paper Section 3.1.2).
//!
//! Every selector implements [`FeatureSelector`]: given ground-truth 2D–3D feature pairs
//! ([`PairSet`]) and a budget `N_s`, it returns sorted dim indices and a report.
//!
//! - [`PaperBipSelector`]: the paper's binary integer program, solved exactly by
//!   [`branch_and_bound`]. As printed its objective is a mean, so it always selects one dim
//!   (proof in [`bip`]).
//! - [`MatchingSelector`]: greedy forward selection with one-swap refinement maximising the
//!   quality of mutual-nearest-neighbour matching of the GT pairs among distractors.
//! - [`FisherSelector`]: between-pair vs within-pair variance per dim with a redundancy penalty.
//! - [`RandomSelector`]: seeded baseline.
//!
//! [`RegionSelections`] holds one selection per scene region (sub-NeRF), as stored in the map.

pub mod bip;
pub mod error;
pub mod greedy;
pub mod pairs;
pub mod region;

pub use bip::{
    Aggregate, PaperBipSelector, SeparableObjective, SubsetObjective, SubsetSolution,
    branch_and_bound, brute_force,
};
pub use error::SelectError;
pub use greedy::{
    FisherConfig, FisherSelector, GreedyResult, GreedySearch, MatchScore, MatchingSelector,
    MatchingSelectorConfig,
};
pub use pairs::PairSet;
pub use region::{RegionId, RegionSelections, select_per_region};

use rand::RngCore;
use rand::seq::index::sample;
use serde::{Deserialize, Serialize};

/// What a selector reports besides the dims.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SelectionReport {
    /// Selector name.
    pub selector: String,
    /// What `objective` measures and whether it is minimised or maximised.
    pub objective_name: String,
    /// The selector's criterion at the returned selection.
    pub objective: f64,
    /// Cost of each dim on its own under the selector's criterion (lower is better; scores
    /// that are maximised are negated), `D` entries.
    pub per_dim_cost: Vec<f64>,
    /// Candidate subsets (or dims) evaluated.
    pub evaluations: usize,
}

/// A selection: sorted, distinct dim indices and its report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Selection {
    /// Selected dims, ascending.
    pub dims: Vec<usize>,
    /// Diagnostics.
    pub report: SelectionReport,
}

/// Chooses at most `n_s` feature dims from ground-truth pairs. Object-safe; randomness comes
/// only from the injected RNG, so a seeded RNG makes every selector deterministic.
pub trait FeatureSelector: Send + Sync {
    /// Short name for tables and reports.
    fn name(&self) -> &str;
    /// Selects `1..=n_s` dims.
    fn select(
        &self,
        pairs: &PairSet,
        n_s: usize,
        rng: &mut dyn RngCore,
    ) -> Result<Selection, SelectError>;
}

/// Rejects budgets outside `1..=D`.
pub fn check_budget(pairs: &PairSet, n_s: usize) -> Result<(), SelectError> {
    if n_s == 0 || n_s > pairs.dims() {
        return Err(SelectError::InvalidBudget {
            n_s,
            dims: pairs.dims(),
        });
    }
    if pairs.is_empty() {
        return Err(SelectError::EmptyPairs);
    }
    Ok(())
}

/// Uniformly random `N_s` dims (baseline).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RandomSelector {}

impl FeatureSelector for RandomSelector {
    fn name(&self) -> &str {
        "random"
    }

    fn select(
        &self,
        pairs: &PairSet,
        n_s: usize,
        rng: &mut dyn RngCore,
    ) -> Result<Selection, SelectError> {
        check_budget(pairs, n_s)?;
        let mut dims = sample(rng, pairs.dims(), n_s).into_vec();
        dims.sort_unstable();
        Ok(Selection {
            dims,
            report: SelectionReport {
                selector: self.name().to_string(),
                objective_name: "none".into(),
                objective: 0.0,
                per_dim_cost: vec![0.0; pairs.dims()],
                evaluations: 0,
            },
        })
    }
}
