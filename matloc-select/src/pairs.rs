//! Ground-truth pair sets: the input of every selector.

use crate::error::SelectError;
use serde::{Deserialize, Serialize};

/// Feature vectors of ground-truth 2D–3D correspondences: row `p` of `f2d` (query/encoder
/// feature of a pixel) corresponds to row `p` of `f3d` (rendered feature of its 3D point).
/// Optional distractors are features known to match none of the pairs (other rendered points on
/// the map side, other pixels on the query side); matching-driven selectors match against them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairSet {
    dims: usize,
    f2d: Vec<f32>,
    f3d: Vec<f32>,
    distractors_2d: Vec<f32>,
    distractors_3d: Vec<f32>,
    /// Optional group per pair (e.g. the render it comes from): matching-driven selectors then
    /// match each group only against itself, as localization matches one query against one
    /// render.
    groups: Option<Vec<u32>>,
}

fn check_block(name: &str, data: &[f32], dims: usize) -> Result<usize, SelectError> {
    if dims == 0 {
        return Err(SelectError::Shape("feature dims must be positive".into()));
    }
    if !data.len().is_multiple_of(dims) {
        return Err(SelectError::DimensionMismatch {
            what: name.to_string(),
            len: data.len(),
            dims,
        });
    }
    if let Some(i) = data.iter().position(|v| !v.is_finite()) {
        return Err(SelectError::NonFinite {
            what: name.to_string(),
            index: i / dims,
        });
    }
    Ok(data.len() / dims)
}

impl PairSet {
    /// Pairs without distractors. `f2d` and `f3d` are row-major `P × dims`.
    pub fn new(dims: usize, f2d: Vec<f32>, f3d: Vec<f32>) -> Result<Self, SelectError> {
        Self::with_distractors(dims, f2d, f3d, Vec::new(), Vec::new())
    }

    /// Pairs plus query-side and map-side distractor features (row-major, `dims` wide).
    pub fn with_distractors(
        dims: usize,
        f2d: Vec<f32>,
        f3d: Vec<f32>,
        distractors_2d: Vec<f32>,
        distractors_3d: Vec<f32>,
    ) -> Result<Self, SelectError> {
        let p2 = check_block("f2d", &f2d, dims)?;
        let p3 = check_block("f3d", &f3d, dims)?;
        check_block("distractors_2d", &distractors_2d, dims)?;
        check_block("distractors_3d", &distractors_3d, dims)?;
        if p2 != p3 {
            return Err(SelectError::Shape(format!(
                "{p2} 2D features but {p3} 3D features"
            )));
        }
        if p2 == 0 {
            return Err(SelectError::EmptyPairs);
        }
        Ok(PairSet {
            dims,
            f2d,
            f3d,
            distractors_2d,
            distractors_3d,
            groups: None,
        })
    }

    /// Assigns a group to every pair (see [`PairSet::groups`]).
    pub fn with_groups(mut self, groups: Vec<u32>) -> Result<Self, SelectError> {
        if groups.len() != self.len() {
            return Err(SelectError::Shape(format!(
                "{} group ids for {} pairs",
                groups.len(),
                self.len()
            )));
        }
        self.groups = Some(groups);
        Ok(self)
    }

    /// Group of every pair, if assigned.
    pub fn groups(&self) -> Option<&[u32]> {
        self.groups.as_deref()
    }

    /// Feature dims `D`.
    pub fn dims(&self) -> usize {
        self.dims
    }

    /// Number of pairs `P`.
    pub fn len(&self) -> usize {
        self.f2d.len() / self.dims
    }

    /// Always false: construction rejects empty sets.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// 2D features, `P × D`.
    pub fn f2d(&self) -> &[f32] {
        &self.f2d
    }

    /// 3D features, `P × D`.
    pub fn f3d(&self) -> &[f32] {
        &self.f3d
    }

    /// Query-side distractors.
    pub fn distractors_2d(&self) -> &[f32] {
        &self.distractors_2d
    }

    /// Map-side distractors.
    pub fn distractors_3d(&self) -> &[f32] {
        &self.distractors_3d
    }

    /// Query side for matching: pairs first, then distractors.
    pub fn query_side(&self) -> Vec<f32> {
        let mut v = self.f2d.clone();
        v.extend_from_slice(&self.distractors_2d);
        v
    }

    /// Map side for matching: pairs first, then distractors.
    pub fn map_side(&self) -> Vec<f32> {
        let mut v = self.f3d.clone();
        v.extend_from_slice(&self.distractors_3d);
        v
    }

    /// Per-dim cost of the paper's BIP: `c_d = Σ_p |F2d[p, d] − F3d[p, d]|`.
    pub fn abs_diff_costs(&self) -> Vec<f64> {
        let d = self.dims;
        let mut c = vec![0.0f64; d];
        for (a, b) in self.f2d.chunks_exact(d).zip(self.f3d.chunks_exact(d)) {
            for k in 0..d {
                c[k] += (a[k] as f64 - b[k] as f64).abs();
            }
        }
        c
    }
}
