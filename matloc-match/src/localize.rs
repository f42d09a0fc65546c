//! One localization step from a coarse pose: render the map at the coarse pose, lift the
//! rendered cells to 3D, match the query feature map against them on the selected dims, and
//! solve PnP. Also the scoring used by the paper's Table 3 (match precision against the true
//! pose, pose errors).

use crate::error::MatchError;
use crate::mnn::Matcher;
use crate::types::{Match2d3d, QueryFeatures, QueryGrid, RenderedPoints};
use crate::view::{ViewRenderer, grid_size};
use matloc_core::{Camera, FeatureMap, Pose};
use matloc_pnp::{PnpError, PnpInput, PnpResult, PoseSolver};
use nalgebra::{Point2, Point3};
use rand::RngCore;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Why a localization step failed before PnP.
#[derive(Debug, Error)]
pub enum LocalizeError {
    /// Rendering the map failed.
    #[error("rendering the map failed: {0}")]
    Render(crate::view::RenderFailure),
    /// Matching failed (dimension mismatch, empty sides, ...).
    #[error(transparent)]
    Match(#[from] MatchError),
}

/// Renders `dims` of the map at `cam_from_world` on the stride grid and lifts every cell with a
/// surface to its world point. Features are stored in `dims` order.
pub fn render_map_points(
    renderer: &dyn ViewRenderer,
    camera: &Camera,
    cam_from_world: &Pose,
    stride: u32,
    dims: &[usize],
    min_accumulation: f32,
) -> Result<RenderedPoints, LocalizeError> {
    let view = renderer
        .render_view(camera, cam_from_world, stride, dims)
        .map_err(LocalizeError::Render)?;
    let (cols, rows) = grid_size(camera, stride);
    if view.cols != cols || view.rows != rows || view.features.len() != cols * rows * dims.len() {
        return Err(MatchError::Shape(format!(
            "renderer returned a {}x{} grid for {cols}x{rows}",
            view.cols, view.rows
        ))
        .into());
    }
    let grid = QueryGrid::with_stride(stride as f64);
    let world_from_cam = cam_from_world.inverse();
    let mut points = Vec::with_capacity(cols * rows);
    for i in 0..cols * rows {
        let c = grid.cell_centre(i % cols, i / cols);
        let z = view.depth_z[i] as f64;
        let p = match camera.unproject(Point2::new(c[0], c[1])) {
            Some(b) if view.has_surface(i, min_accumulation) => {
                let w = world_from_cam * Point3::from(b * (z / b.z));
                [w.x, w.y, w.z]
            }
            _ => [f64::NAN; 3],
        };
        points.push(p);
    }
    let fmap = FeatureMap::from_vec(cols, rows, dims.len(), view.features)
        .map_err(|e| MatchError::Shape(e.to_string()))?;
    Ok(
        RenderedPoints::from_rendered(&fmap, points, &view.accumulation, min_accumulation)?
            .with_pixel_grid(grid)?,
    )
}

/// Matches and the time matching took.
#[derive(Clone, Debug)]
pub struct TimedMatches {
    /// The matches.
    pub matches: Vec<Match2d3d>,
    /// Wall time of `match_features` (normalisation + tiled MNN).
    pub elapsed: Duration,
}

/// Runs the matcher and times it.
pub fn timed_match(
    matcher: &dyn Matcher,
    query: &QueryFeatures,
    map: &RenderedPoints,
    selection: Option<&[usize]>,
) -> Result<TimedMatches, MatchError> {
    let t0 = Instant::now();
    let matches = matcher.match_features(query, map, selection)?;
    Ok(TimedMatches {
        matches,
        elapsed: t0.elapsed(),
    })
}

/// Matches whose 3D point projects, at the true pose, within `max_px` of the query pixel.
pub fn correct_matches(
    matches: &[Match2d3d],
    camera: &Camera,
    true_cam_from_world: &Pose,
    max_px: f64,
) -> usize {
    matches
        .iter()
        .filter(|m| {
            camera
                .project_world(true_cam_from_world, &Point3::from(m.point_world))
                .is_some_and(|u| (u.x - m.query_px[0]).hypot(u.y - m.query_px[1]) <= max_px)
        })
        .count()
}

/// PnP on matches (similarities as PROSAC scores).
pub fn solve_pose(
    matches: &[Match2d3d],
    camera: &Camera,
    solver: &dyn PoseSolver,
    rng: &mut dyn RngCore,
) -> Result<PnpResult, PnpError> {
    solve_pose_within(matches, camera, solver, None, rng)
}

/// [`solve_pose`] with an inlier threshold (pixels) for these matches instead of the
/// solver's own (see [`matloc_pnp::PnpInput::max_error_px`]).
pub fn solve_pose_within(
    matches: &[Match2d3d],
    camera: &Camera,
    solver: &dyn PoseSolver,
    max_error_px: Option<f64>,
    rng: &mut dyn RngCore,
) -> Result<PnpResult, PnpError> {
    let pixels: Vec<Point2<f64>> = matches
        .iter()
        .map(|m| Point2::new(m.query_px[0], m.query_px[1]))
        .collect();
    let points: Vec<Point3<f64>> = matches
        .iter()
        .map(|m| Point3::from(m.point_world))
        .collect();
    let scores: Vec<f64> = matches.iter().map(|m| m.similarity as f64).collect();
    let mut input = PnpInput::new(camera, &pixels, &points).with_scores(&scores);
    input.max_error_px = max_error_px;
    solver.solve(&input, rng)
}

/// Settings of [`localize`].
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct LocalizeConfig {
    /// Stride of the map's rendering grid. The query map's stride is its own; a finer map grid
    /// (e.g. 1 against a stride-4 query) puts a rendered point within half a pixel of every
    /// query cell's true 3D point, so grid quantisation no longer limits the pose accuracy, at
    /// `stride²`-times the matching cost.
    pub map_stride: u32,
    /// Rendered cells with less accumulation are not matched.
    pub min_accumulation: f32,
    /// Render–match–PnP rounds; each later round renders at the previous estimate (beyond the
    /// paper, which stops after one round). Without sub-cell refinement
    /// ([`crate::SubcellConfig`]) this cannot fix quantisation: matching cell `i` to the point
    /// lifted at cell `i` reproduces the pose it was rendered at. With it (the default) later
    /// rounds converge (tiny preset, exact query features: 0.16 m after one round, 0.05 m
    /// after three).
    pub iterations: usize,
}

impl Default for LocalizeConfig {
    fn default() -> Self {
        LocalizeConfig {
            map_stride: 4,
            min_accumulation: 0.5,
            iterations: 1,
        }
    }
}

/// Result of [`localize`].
#[derive(Clone, Debug)]
pub struct LocalizeOutcome {
    /// Final estimate.
    pub cam_from_world: Pose,
    /// Matches of the last round.
    pub matches: Vec<Match2d3d>,
    /// PnP inliers of the last round.
    pub inliers: usize,
    /// Matching time of each round.
    pub match_time: Vec<Duration>,
}

/// Why [`localize`] failed.
#[derive(Debug, Error)]
pub enum LocalizeFailure {
    /// Rendering or matching failed.
    #[error(transparent)]
    Localize(#[from] LocalizeError),
    /// PnP failed (too few or inconsistent matches).
    #[error("PnP failed in round {round}: {source}")]
    Pnp {
        /// Round (0-based).
        round: usize,
        /// The solver's error.
        source: PnpError,
    },
}

/// Localizes a query from a coarse pose: per round, render `render_dims` at the current pose,
/// lift, match on `selection` (indices into `render_dims`, as in the query map), solve PnP.
#[allow(clippy::too_many_arguments)]
pub fn localize(
    renderer: &dyn ViewRenderer,
    matcher: &dyn Matcher,
    solver: &dyn PoseSolver,
    query: &QueryFeatures,
    camera: &Camera,
    coarse_cam_from_world: &Pose,
    render_dims: &[usize],
    selection: Option<&[usize]>,
    config: &LocalizeConfig,
    rng: &mut dyn RngCore,
) -> Result<LocalizeOutcome, LocalizeFailure> {
    let mut pose = *coarse_cam_from_world;
    let mut times = Vec::new();
    let mut last = None;
    for round in 0..config.iterations.max(1) {
        let map = render_map_points(
            renderer,
            camera,
            &pose,
            config.map_stride,
            render_dims,
            config.min_accumulation,
        )?;
        let tm = timed_match(matcher, query, &map, selection).map_err(LocalizeError::from)?;
        times.push(tm.elapsed);
        let res = solve_pose(&tm.matches, camera, solver, rng)
            .map_err(|source| LocalizeFailure::Pnp { round, source })?;
        pose = res.cam_from_world;
        last = Some((tm.matches, res.stats.num_inliers));
    }
    let (matches, inliers) = last.expect("at least one round");
    Ok(LocalizeOutcome {
        cam_from_world: pose,
        matches,
        inliers,
        match_time: times,
    })
}
