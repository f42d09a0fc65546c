//! Inputs and outputs of 2D–3D matching.

use crate::error::{MatchError, Side};
use matloc_core::FeatureMap;
use serde::{Deserialize, Serialize};

/// One 2D–3D correspondence.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Match2d3d {
    /// Continuous pixel coordinates `(x, y)` of the query feature cell centre in the query image
    /// (pixel centres at `+0.5`, as in `matloc-core`).
    pub query_px: [f64; 2],
    /// World point of the matched rendered feature.
    pub point_world: [f64; 3],
    /// Similarity (dot product of the normalised features, in `[-1, 1]`).
    pub similarity: f32,
    /// Row-major cell index in the query feature map (`row * width + col`).
    pub query_index: usize,
    /// Index of the point in [`RenderedPoints`].
    pub map_index: usize,
}

/// How query feature cells map to image pixels: cell `(col, row)` covers
/// `[offset + stride·col, offset + stride·(col + 1))`, so its centre is at
/// `offset + stride·(col + 0.5)`. A full-resolution map has `stride = 1, offset = 0`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct QueryGrid {
    /// Image pixels per feature cell.
    pub stride: f64,
    /// Pixel offset `(x, y)` of the grid's top-left corner.
    pub offset: [f64; 2],
}

impl Default for QueryGrid {
    fn default() -> Self {
        QueryGrid {
            stride: 1.0,
            offset: [0.0, 0.0],
        }
    }
}

impl QueryGrid {
    /// A grid with the given stride and no offset.
    pub fn with_stride(stride: f64) -> Self {
        QueryGrid {
            stride,
            offset: [0.0, 0.0],
        }
    }

    /// Pixel coordinates of the centre of cell `(col, row)`.
    pub fn cell_centre(&self, col: usize, row: usize) -> [f64; 2] {
        [
            self.offset[0] + self.stride * (col as f64 + 0.5),
            self.offset[1] + self.stride * (row as f64 + 0.5),
        ]
    }
}

/// The query side: a dense feature map (`H × W × C`) and its pixel grid.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QueryFeatures {
    /// Encoder output, channels = feature dims.
    pub map: FeatureMap,
    /// Cell-to-pixel mapping.
    pub grid: QueryGrid,
}

impl QueryFeatures {
    /// Wraps a feature map computed at `stride` pixels per cell.
    pub fn new(map: FeatureMap, stride: f64) -> Self {
        QueryFeatures {
            map,
            grid: QueryGrid::with_stride(stride),
        }
    }

    /// Number of feature cells.
    pub fn len(&self) -> usize {
        self.map.width() * self.map.height()
    }

    /// Whether the map has no cells.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Pixel centre of cell `index` (row-major).
    pub fn cell_px(&self, index: usize) -> [f64; 2] {
        let w = self.map.width().max(1);
        self.grid.cell_centre(index % w, index / w)
    }
}

/// The map side: `N` rendered features of `D` dims with their world points and validity
/// (e.g. rendered accumulation above a threshold; invalid points are never matched).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderedPoints {
    dims: usize,
    features: Vec<f32>,
    points: Vec<[f64; 3]>,
    valid: Vec<bool>,
    /// Row-major grid layout `(cols, rows)` of the points, when they come from a rendered grid
    /// (sub-cell refinement on the map side needs the neighbours of a cell).
    #[serde(default)]
    grid: Option<(usize, usize)>,
    /// Cell → pixel mapping of that grid, when known (windowed matching needs it).
    #[serde(default)]
    pixel_grid: Option<QueryGrid>,
}

impl RenderedPoints {
    /// Builds from row-major `N × dims` features, `N` world points and `N` validity flags.
    pub fn new(
        dims: usize,
        features: Vec<f32>,
        points: Vec<[f64; 3]>,
        valid: Vec<bool>,
    ) -> Result<Self, MatchError> {
        let n = points.len();
        if features.len() != n * dims || valid.len() != n {
            return Err(MatchError::Shape(format!(
                "{} points need {} feature values and {} flags, got {} and {}",
                n,
                n * dims,
                n,
                features.len(),
                valid.len()
            )));
        }
        Ok(RenderedPoints {
            dims,
            features,
            points,
            valid,
            grid: None,
            pixel_grid: None,
        })
    }

    /// Declares the points a row-major `cols × rows` grid (point `row·cols + col`).
    pub fn with_grid(mut self, cols: usize, rows: usize) -> Result<Self, MatchError> {
        if cols.checked_mul(rows) != Some(self.len()) {
            return Err(MatchError::Shape(format!(
                "a {cols}x{rows} grid does not hold {} points",
                self.len()
            )));
        }
        self.grid = Some((cols, rows));
        Ok(self)
    }

    /// Grid layout `(cols, rows)`, if the points form one.
    pub fn grid(&self) -> Option<(usize, usize)> {
        self.grid
    }

    /// Declares where the grid's cells lie in the image the map was rendered for (cell centres
    /// as in [`QueryGrid::cell_centre`]). Needs a grid layout ([`Self::with_grid`]).
    pub fn with_pixel_grid(mut self, grid: QueryGrid) -> Result<Self, MatchError> {
        if self.grid.is_none() {
            return Err(MatchError::Shape(
                "a pixel grid needs the points' grid layout".into(),
            ));
        }
        if !(grid.stride > 0.0 && grid.stride.is_finite())
            || grid.offset.iter().any(|v| !v.is_finite())
        {
            return Err(MatchError::Shape(format!("invalid pixel grid {grid:?}")));
        }
        self.pixel_grid = Some(grid);
        Ok(self)
    }

    /// Cell → pixel mapping, if known ([`crate::localize::render_map_points`] sets it).
    pub fn pixel_grid(&self) -> Option<QueryGrid> {
        self.pixel_grid
    }

    /// All points valid.
    pub fn all_valid(
        dims: usize,
        features: Vec<f32>,
        points: Vec<[f64; 3]>,
    ) -> Result<Self, MatchError> {
        let valid = vec![true; points.len()];
        Self::new(dims, features, points, valid)
    }

    /// From a rendered feature map, per-pixel world points (row-major, `W·H` of them) and
    /// accumulated opacity: pixels with `accumulation >= min_accumulation` and finite points
    /// are valid.
    pub fn from_rendered(
        features: &FeatureMap,
        points: Vec<[f64; 3]>,
        accumulation: &[f32],
        min_accumulation: f32,
    ) -> Result<Self, MatchError> {
        let n = features.width() * features.height();
        if accumulation.len() != n {
            return Err(MatchError::Shape(format!(
                "{n} pixels need {n} accumulation values, got {}",
                accumulation.len()
            )));
        }
        let valid = accumulation
            .iter()
            .zip(&points)
            .map(|(&acc, p)| acc >= min_accumulation && p.iter().all(|v| v.is_finite()))
            .collect();
        Self::new(features.channels(), features.data().to_vec(), points, valid)?
            .with_grid(features.width(), features.height())
    }

    /// Feature dims.
    pub fn dims(&self) -> usize {
        self.dims
    }

    /// Number of points (valid or not).
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Row-major features.
    pub fn features(&self) -> &[f32] {
        &self.features
    }

    /// Feature vector of point `i`.
    pub fn feature(&self, i: usize) -> &[f32] {
        &self.features[i * self.dims..(i + 1) * self.dims]
    }

    /// World points.
    pub fn points(&self) -> &[[f64; 3]] {
        &self.points
    }

    /// Validity flags.
    pub fn valid(&self) -> &[bool] {
        &self.valid
    }

    /// Indices of the valid points.
    pub fn valid_indices(&self) -> Vec<usize> {
        (0..self.len()).filter(|&i| self.valid[i]).collect()
    }

    /// Checks this side is usable: at least one valid point.
    pub(crate) fn check_nonempty(&self) -> Result<(), MatchError> {
        if self.valid.iter().any(|&v| v) {
            Ok(())
        } else {
            Err(MatchError::Empty { side: Side::Map })
        }
    }
}
