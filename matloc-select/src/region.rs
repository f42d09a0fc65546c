//! One selection per scene region (sub-NeRF), as stored in the map: regions added later (new
//! blocks, other domains) get their own dims without touching the others.

use crate::error::SelectError;
use crate::pairs::PairSet;
use crate::{FeatureSelector, SelectionReport};
use rand::RngCore;
use serde::{Deserialize, Serialize};

/// Identifier of a scene region / sub-NeRF.
pub type RegionId = u32;

/// Selected dims per region.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RegionSelections {
    /// `(region id, sorted dims)`, one entry per region.
    pub per_region: Vec<(RegionId, Vec<usize>)>,
}

impl RegionSelections {
    /// Dims of `region`, if selected.
    pub fn get(&self, region: RegionId) -> Option<&[usize]> {
        self.per_region
            .iter()
            .find(|(r, _)| *r == region)
            .map(|(_, d)| d.as_slice())
    }

    /// Sets the dims of `region`, replacing an earlier entry.
    pub fn insert(&mut self, region: RegionId, dims: Vec<usize>) {
        match self.per_region.iter_mut().find(|(r, _)| *r == region) {
            Some(entry) => entry.1 = dims,
            None => self.per_region.push((region, dims)),
        }
    }
}

/// Runs `selector` on each region's pairs (in the given order, one RNG stream).
pub fn select_per_region(
    selector: &dyn FeatureSelector,
    regions: &[(RegionId, &PairSet)],
    n_s: usize,
    rng: &mut dyn RngCore,
) -> Result<(RegionSelections, Vec<SelectionReport>), SelectError> {
    let mut out = RegionSelections::default();
    let mut reports = Vec::with_capacity(regions.len());
    for (id, pairs) in regions {
        let sel = selector.select(pairs, n_s, rng)?;
        out.insert(*id, sel.dims);
        reports.push(sel.report);
    }
    Ok((out, reports))
}
