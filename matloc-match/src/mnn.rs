//! Feature normalisation and the mutual-nearest-neighbour matcher.

use crate::error::{MatchError, Side};
#[cfg(feature = "faer")]
use crate::kernel::nn_tables_faer;
use crate::kernel::{NnTables, nn_tables_reference, nn_tables_tiled};
use crate::subcell::{PreparedGrid, SubcellConfig, SubcellSide, interpolate_point, peak_offset};
use crate::types::{Match2d3d, QueryFeatures, RenderedPoints};
use crate::window::{Side as WindowSide, nn_tables_windowed};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Per-dimension standardisation statistics over all `D` feature dims; the map stores them and
/// both sides are standardised with the same values.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureStats {
    /// Mean per dim.
    pub mean: Vec<f32>,
    /// Standard deviation per dim.
    pub std: Vec<f32>,
}

impl FeatureStats {
    /// Mean and standard deviation of row-major `rows × dims` features.
    pub fn from_features(data: &[f32], dims: usize) -> Self {
        let rows = data.len().checked_div(dims).unwrap_or(0);
        let mut mean = vec![0.0f64; dims];
        let mut sq = vec![0.0f64; dims];
        for row in data.chunks_exact(dims.max(1)).take(rows) {
            for (k, &v) in row.iter().enumerate() {
                mean[k] += v as f64;
                sq[k] += (v as f64) * (v as f64);
            }
        }
        let nr = rows.max(1) as f64;
        let mean_f: Vec<f32> = mean.iter().map(|m| (m / nr) as f32).collect();
        let std = mean
            .iter()
            .zip(&sq)
            .map(|(m, s)| ((s / nr - (m / nr).powi(2)).max(0.0)).sqrt() as f32)
            .collect();
        FeatureStats { mean: mean_f, std }
    }
}

/// Which kernel computes the nearest-neighbour tables.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum MnnKernel {
    /// Tiled kernel, similarity matrix never stored (default).
    #[default]
    Tiled,
    /// Materialised matrix with plain loops (bit-identical to `Tiled`; tests).
    Reference,
    /// Materialised matrix by faer GEMM (benchmark baseline; `faer` feature).
    #[cfg(feature = "faer")]
    FaerGemm,
}

/// Mutual-nearest-neighbour matcher settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MnnConfig {
    /// Keep only matches with similarity `>=` this.
    pub min_similarity: Option<f32>,
    /// Lowe-style ratio test in feature-distance space, applied on both sides: keep a match only
    /// if `dist(best) <= ratio · dist(second best)` for the query row and the map column, with
    /// `dist = sqrt(max(0, 2 − 2·similarity))` (the Euclidean distance of unit vectors). A side
    /// with a single candidate passes.
    pub ratio: Option<f32>,
    /// Standardise each dim with these statistics before L2 normalisation.
    pub stats: Option<FeatureStats>,
    /// L2-normalise each (selected, standardised) vector; zero vectors stay zero.
    pub l2_normalise: bool,
    /// Kernel used for the tables.
    pub kernel: MnnKernel,
    /// Sub-cell refinement of the matches ([`crate::subcell`]); only [`Matcher::match_features`]
    /// applies it (the raw [`mnn_prepared`] pairs are cell indices).
    pub subcell: SubcellConfig,
    /// Image-space window (beyond the paper): match a query cell only with rendered cells whose
    /// centres lie within this many pixels of its own, and vice versa ([`crate::window`]).
    /// Needs [`RenderedPoints::pixel_grid`] (set by `render_map_points`); without it the full
    /// MNN runs. `None` (default): the whole image, as in the paper.
    pub window_px: Option<f64>,
}

impl Default for MnnConfig {
    fn default() -> Self {
        MnnConfig {
            min_similarity: None,
            ratio: None,
            stats: None,
            l2_normalise: true,
            kernel: MnnKernel::Tiled,
            subcell: SubcellConfig::default(),
            window_px: None,
        }
    }
}

impl MnnConfig {
    fn validate(&self, dims: usize) -> Result<(), MatchError> {
        if let Some(r) = self.ratio
            && !(r > 0.0 && r.is_finite())
        {
            return Err(MatchError::InvalidConfig(format!(
                "ratio must be positive and finite, got {r}"
            )));
        }
        if let Some(t) = self.min_similarity
            && t.is_nan()
        {
            return Err(MatchError::InvalidConfig("min_similarity is NaN".into()));
        }
        if let Some(w) = self.window_px
            && !(w > 0.0 && w.is_finite())
        {
            return Err(MatchError::InvalidConfig(format!(
                "window_px must be positive and finite, got {w}"
            )));
        }
        let sc = &self.subcell;
        if !(sc.max_shift >= 0.0 && sc.max_shift.is_finite()) || sc.max_spacing_ratio.is_nan() {
            return Err(MatchError::InvalidConfig(format!(
                "sub-cell max_shift must be finite and >= 0 (got {}), max_spacing_ratio not NaN",
                sc.max_shift
            )));
        }
        if let Some(s) = &self.stats {
            if s.mean.len() != dims || s.std.len() != dims {
                return Err(MatchError::InvalidConfig(format!(
                    "stats have {} means and {} stds for {dims}-d features",
                    s.mean.len(),
                    s.std.len()
                )));
            }
            if s.mean.iter().chain(&s.std).any(|v| !v.is_finite()) {
                return Err(MatchError::InvalidConfig("non-finite stats".into()));
            }
        }
        Ok(())
    }
}

/// A match between row `query` of the prepared query matrix and row `map` of the prepared map
/// matrix.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RawMatch {
    /// Query row.
    pub query: usize,
    /// Map row.
    pub map: usize,
    /// Similarity.
    pub similarity: f32,
}

/// Checks a selection of dims: non-empty, in range, no repeats.
pub fn check_selection(sel: &[usize], dims: usize) -> Result<(), MatchError> {
    if sel.is_empty() {
        return Err(MatchError::InvalidSelection("no dims selected".into()));
    }
    let mut seen = vec![false; dims];
    for &d in sel {
        if d >= dims {
            return Err(MatchError::DimOutOfRange { dim: d, dims });
        }
        if seen[d] {
            return Err(MatchError::InvalidSelection(format!("dim {d} repeated")));
        }
        seen[d] = true;
    }
    Ok(())
}

/// Checks that query and map are non-empty and have the same dims; returns the dims.
pub(crate) fn check_inputs(
    query: &QueryFeatures,
    map: &RenderedPoints,
) -> Result<usize, MatchError> {
    let qd = query.map.channels();
    if qd != map.dims() {
        return Err(MatchError::DimensionMismatch {
            query: qd,
            map: map.dims(),
        });
    }
    if query.is_empty() {
        return Err(MatchError::Empty { side: Side::Query });
    }
    map.check_nonempty()?;
    Ok(qd)
}

/// The dims to use: a checked `selection`, or all `dims` of the features when `None`.
pub(crate) fn resolve_selection(
    selection: Option<&[usize]>,
    dims: usize,
) -> Result<std::borrow::Cow<'_, [usize]>, MatchError> {
    let sel = match selection {
        Some(s) => {
            check_selection(s, dims)?;
            std::borrow::Cow::Borrowed(s)
        }
        None => std::borrow::Cow::Owned((0..dims).collect()),
    };
    if sel.is_empty() {
        return Err(MatchError::InvalidSelection("zero feature dims".into()));
    }
    Ok(sel)
}

/// Gathers the rows `rows` of a row-major `? × dims` buffer into a dense matrix of the
/// selected dims, standardised and L2-normalised as configured. `rows[k]` is reported as the
/// index in errors.
pub fn prepare_rows(
    data: &[f32],
    dims: usize,
    rows: &[usize],
    selection: &[usize],
    stats: Option<&FeatureStats>,
    l2_normalise: bool,
    side: Side,
) -> Result<Vec<f32>, MatchError> {
    let ds = selection.len();
    // Rows are independent: fixed blocks in parallel, in order (the first bad row is reported).
    let blocks: Vec<Result<Vec<f32>, MatchError>> = rows
        .par_chunks(PREPARE_BLOCK)
        .map(|block| {
            let mut out = Vec::with_capacity(block.len() * ds);
            for &i in block {
                prepare_row(
                    data,
                    dims,
                    i,
                    selection,
                    stats,
                    l2_normalise,
                    side,
                    &mut out,
                )?;
            }
            Ok(out)
        })
        .collect();
    let mut out = Vec::with_capacity(rows.len() * ds);
    for b in blocks {
        out.extend_from_slice(&b?);
    }
    Ok(out)
}

/// Rows per parallel block of [`prepare_rows`].
const PREPARE_BLOCK: usize = 512;

/// Appends row `i` of `data`, prepared, to `out`.
fn prepare_row(
    data: &[f32],
    dims: usize,
    i: usize,
    selection: &[usize],
    stats: Option<&FeatureStats>,
    l2_normalise: bool,
    side: Side,
    out: &mut Vec<f32>,
) -> Result<(), MatchError> {
    let row = data
        .get(i * dims..(i + 1) * dims)
        .ok_or_else(|| MatchError::Shape(format!("row {i} out of range for {side} features")))?;
    if let Some(dim) = row.iter().position(|v| !v.is_finite()) {
        return Err(MatchError::NonFinite {
            side,
            index: i,
            dim,
        });
    }
    let start = out.len();
    for &d in selection {
        let mut v = row[d];
        if let Some(s) = stats {
            // A constant dim carries no information: map it to 0 instead of dividing by 0.
            v = if s.std[d] > 1e-12 {
                (v - s.mean[d]) / s.std[d]
            } else {
                0.0
            };
        }
        out.push(v);
    }
    if l2_normalise {
        let v = &mut out[start..];
        let norm = v
            .iter()
            .map(|x| (*x as f64) * (*x as f64))
            .sum::<f64>()
            .sqrt();
        if norm > 0.0 {
            let inv = (1.0 / norm) as f32;
            v.iter_mut().for_each(|x| *x *= inv);
        }
    }
    Ok(())
}

/// Nearest-neighbour tables of prepared (already normalised) matrices with the chosen kernel.
pub fn tables(
    kernel: MnnKernel,
    query: &[f32],
    n: usize,
    map: &[f32],
    m: usize,
    d: usize,
    track_second: bool,
) -> NnTables {
    match kernel {
        MnnKernel::Tiled => nn_tables_tiled(query, n, map, m, d, track_second),
        MnnKernel::Reference => nn_tables_reference(query, n, map, m, d),
        #[cfg(feature = "faer")]
        MnnKernel::FaerGemm => nn_tables_faer(query, n, map, m, d),
    }
}

fn ratio_ok(best: f32, second: f32, ratio: f32) -> bool {
    if second == f32::NEG_INFINITY {
        return true;
    }
    let d1 = (2.0 - 2.0 * best).max(0.0).sqrt();
    let d2 = (2.0 - 2.0 * second).max(0.0).sqrt();
    d1 <= ratio * d2
}

/// Mutual nearest neighbours of two prepared `n × d` and `m × d` matrices (rows finite,
/// normally unit length), filtered by the threshold and ratio test of `config`. Sorted by query
/// row.
pub fn mnn_prepared(
    query: &[f32],
    map: &[f32],
    d: usize,
    config: &MnnConfig,
) -> Result<Vec<RawMatch>, MatchError> {
    if d == 0 {
        return Err(MatchError::InvalidSelection("zero feature dims".into()));
    }
    if !query.len().is_multiple_of(d) || !map.len().is_multiple_of(d) {
        return Err(MatchError::Shape(format!(
            "buffers of {} and {} values are not multiples of {d} dims",
            query.len(),
            map.len()
        )));
    }
    let (n, m) = (query.len() / d, map.len() / d);
    if n == 0 {
        return Err(MatchError::Empty { side: Side::Query });
    }
    if m == 0 {
        return Err(MatchError::Empty { side: Side::Map });
    }
    let t = tables(config.kernel, query, n, map, m, d, config.ratio.is_some());
    Ok(mutual_from_tables(&t, config))
}

/// Extracts mutual pairs from nearest-neighbour tables and applies the filters.
pub fn mutual_from_tables(t: &NnTables, config: &MnnConfig) -> Vec<RawMatch> {
    let mut out = Vec::new();
    for (i, &j) in t.rows.arg.iter().enumerate() {
        let j = j as usize;
        if j >= t.cols.len() || t.cols.arg[j] as usize != i {
            continue;
        }
        let s = t.rows.best[i];
        if let Some(th) = config.min_similarity
            && s < th
        {
            continue;
        }
        if let Some(r) = config.ratio
            && !(ratio_ok(s, t.rows.second[i], r) && ratio_ok(s, t.cols.second[j], r))
        {
            continue;
        }
        out.push(RawMatch {
            query: i,
            map: j,
            similarity: s,
        });
    }
    out
}

/// Matches a query feature map against rendered 3D points.
///
/// Object-safe so pipelines can hold a `Box<dyn Matcher>`.
pub trait Matcher: Send + Sync {
    /// Matches on the dims in `selection` (all dims when `None`). Returns matches sorted by
    /// query cell index.
    fn match_features(
        &self,
        query: &QueryFeatures,
        map: &RenderedPoints,
        selection: Option<&[usize]>,
    ) -> Result<Vec<Match2d3d>, MatchError>;

    /// The space the matcher compares features in: per-dim statistics the features are
    /// standardised with (indexed like the features it is given) and whether they are then
    /// L2-normalised. Refinement stages that work on the same features (e.g.
    /// [`crate::featuremetric`]) use it so that both agree on what "similar" means. Default:
    /// raw features, L2-normalised.
    fn feature_space(&self) -> (Option<&FeatureStats>, bool) {
        (None, true)
    }

    /// Radius in pixels of the image-space window matches are restricted to (`None`: the
    /// whole image). A pose solver's test of "could these inliers be chance" needs it: inside
    /// a window a wrong match lands near its rendered pixel, not anywhere in the image.
    fn window_px(&self) -> Option<f64> {
        None
    }
}

/// Mutual-nearest-neighbour matcher on normalised features (see [`MnnConfig`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MnnMatcher {
    /// Settings.
    pub config: MnnConfig,
}

impl MnnMatcher {
    /// A matcher with the given settings.
    pub fn new(config: MnnConfig) -> Self {
        MnnMatcher { config }
    }
}

impl Matcher for MnnMatcher {
    fn feature_space(&self) -> (Option<&FeatureStats>, bool) {
        (self.config.stats.as_ref(), self.config.l2_normalise)
    }

    fn window_px(&self) -> Option<f64> {
        self.config.window_px
    }

    fn match_features(
        &self,
        query: &QueryFeatures,
        map: &RenderedPoints,
        selection: Option<&[usize]>,
    ) -> Result<Vec<Match2d3d>, MatchError> {
        let qd = check_inputs(query, map)?;
        self.config.validate(qd)?;
        let sel = resolve_selection(selection, qd)?;
        let sel = &sel[..];
        let stats = self.config.stats.as_ref();
        let norm = self.config.l2_normalise;
        let qrows: Vec<usize> = (0..query.len()).collect();
        let q = prepare_rows(query.map.data(), qd, &qrows, sel, stats, norm, Side::Query)?;
        let mrows = map.valid_indices();
        let mp = prepare_rows(map.features(), qd, &mrows, sel, stats, norm, Side::Map)?;
        let d = sel.len();
        let (qw, qh) = (query.map.width(), query.map.height());
        let raw = match (self.config.window_px, map.grid(), map.pixel_grid()) {
            (Some(radius), Some((cols, rows)), Some(pgrid)) => {
                let mut row_of = vec![u32::MAX; map.len()];
                for (k, &i) in mrows.iter().enumerate() {
                    row_of[i] = k as u32;
                }
                let qside = WindowSide {
                    data: &q,
                    cols: qw,
                    rows: qh,
                    grid: query.grid,
                    row_of: None,
                    cell_of: None,
                };
                let mside = WindowSide {
                    data: &mp,
                    cols,
                    rows,
                    grid: pgrid,
                    row_of: Some(&row_of),
                    cell_of: Some(&mrows),
                };
                let t = nn_tables_windowed(&qside, &mside, d, radius);
                mutual_from_tables(&t, &self.config)
            }
            _ => mnn_prepared(&q, &mp, d, &self.config)?,
        };
        let sc = &self.config.subcell;
        let qgrid = PreparedGrid {
            data: &q,
            d,
            cols: qw,
            rows: qh,
            row_of: None,
        };
        // Map cell -> prepared map row, for map-side refinement on a gridded map.
        let map_rows: Option<Vec<u32>> = match (sc.side, map.grid()) {
            (SubcellSide::Map, Some(_)) => {
                let mut r = vec![u32::MAX; map.len()];
                for (k, &i) in mrows.iter().enumerate() {
                    r[i] = k as u32;
                }
                Some(r)
            }
            _ => None,
        };
        // Refinement is a few dot products per match: parallel over matches, order kept.
        Ok(raw
            .into_par_iter()
            .map(|r| {
                let mi = mrows[r.map];
                let mut query_px = query.cell_px(r.query);
                let mut point_world = map.points()[mi];
                match (sc.side, map.grid(), &map_rows) {
                    (SubcellSide::Query, _, _) => {
                        let target = &mp[r.map * d..(r.map + 1) * d];
                        let off = peak_offset(target, &qgrid, r.query, sc);
                        for (k, o) in off.iter().enumerate() {
                            query_px[k] += query.grid.stride * o.unwrap_or(0.0);
                        }
                    }
                    (SubcellSide::Map, Some((cols, rows)), Some(row_of)) => {
                        let target = &q[r.query * d..(r.query + 1) * d];
                        let mgrid = PreparedGrid {
                            data: &mp,
                            d,
                            cols,
                            rows,
                            row_of: Some(row_of),
                        };
                        let off = peak_offset(target, &mgrid, mi, sc);
                        point_world =
                            interpolate_point(map, cols, rows, mi, off, sc.max_spacing_ratio);
                    }
                    _ => {}
                }
                Match2d3d {
                    query_px,
                    point_world,
                    similarity: r.similarity,
                    query_index: r.query,
                    map_index: mi,
                }
            })
            .collect())
    }
}
