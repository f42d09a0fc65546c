//! Virtual viewpoints: camera poses the survey never flew — lower and higher than it, from
//! near-nadir to oblique, at every heading — sampled where the training cameras saw the ground,
//! so a block's NeRF can render them.
//!
//! The rule ([`sample_viewpoints`]), per block: draw a camera position uniformly over the
//! block's scene box seen from above, a height above the surface under it from
//! [`VirtualViewsConfig::altitude_band`] × the survey's median height above its ground, a
//! pitch below the horizon from [`VirtualViewsConfig::pitch_deg`] and a uniform heading; keep
//! the pose only when
//! - the observed surface lies under the camera and, within `min_clearance_m` around it, at
//!   least `min_clearance_m` below it (no camera inside or against geometry);
//! - its optical axis meets the surface inside the block's box, on ground at least `min_views`
//!   training cameras saw;
//! - at least `min_coverage` of its footprint (rays on an 8 × 8 grid over the image) meets
//!   ground that `min_views` training cameras saw.
//!
//! The surface is a height field of the points each training camera saw ([`SurfaceGrid`]:
//! highest point per cell and the number of distinct cameras with a point in it). Draws are
//! deterministic from the seed and the block index.

mod grid;
#[cfg(test)]
mod tests;

use matloc_core::hash::{mix64, splitmix64_next};
use matloc_core::{Camera, Pose};
use nalgebra::{
    Isometry3, Matrix3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};
use serde::{Deserialize, Serialize};

pub use grid::{GroundFrame, SurfaceGrid};

use crate::error::SurfaceError;

/// Settings of the virtual viewpoints (the map's `virtual` section).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VirtualViewsConfig {
    /// Sample virtual viewpoints at map build: the place stage renders them with the block
    /// NeRFs into the place classifier's training views. Off by default.
    pub enabled: bool,
    /// Poses accepted per block (fewer when `max_candidates_per_pose` draws run out).
    pub per_block: usize,
    /// A block stops drawing after `per_block × max_candidates_per_pose` candidates.
    pub max_candidates_per_pose: usize,
    /// Camera height above the surface under it, as multiples `[lowest, highest]` of the
    /// survey's median height above the ground it saw.
    pub altitude_band: [f64; 2],
    /// Pitch of the optical axis below the horizon, degrees `[least, most]` (90 = nadir).
    pub pitch_deg: [f64; 2],
    /// The observed surface within this horizontal distance of the camera lies at least this
    /// far below it, metres.
    pub min_clearance_m: f64,
    /// Ground counts as covered where at least this many training cameras saw it.
    pub min_views: u32,
    /// Fraction of a pose's footprint (rays on an 8 × 8 grid over the image) that must meet
    /// covered ground, in `[0, 1]`.
    pub min_coverage: f64,
    /// Edge of the height field's cells, metres; 0 = a tenth of the survey's median height
    /// above its ground.
    pub cell_m: f64,
    /// Seed of the draws.
    pub seed: u64,
}

impl Default for VirtualViewsConfig {
    fn default() -> Self {
        VirtualViewsConfig {
            enabled: false,
            per_block: 64,
            max_candidates_per_pose: 20,
            altitude_band: [0.4, 1.3],
            pitch_deg: [20.0, 90.0],
            min_clearance_m: 2.0,
            min_views: 2,
            min_coverage: 0.5,
            cell_m: 0.0,
            seed: 0,
        }
    }
}

/// One out-of-range setting: the field (as the map config names it), its value, the bound.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConfigProblem {
    /// Field path in the map config, e.g. `virtual.pitch_deg`.
    pub field: &'static str,
    /// The value given.
    pub value: String,
    /// What it must be.
    pub bound: &'static str,
}

impl VirtualViewsConfig {
    /// Whether this is the default (off) configuration.
    pub fn is_default(&self) -> bool {
        *self == VirtualViewsConfig::default()
    }

    /// Every out-of-range field (empty when the config is usable).
    pub fn problems(&self) -> Vec<ConfigProblem> {
        let mut out = Vec::new();
        let mut check = |ok: bool, field: &'static str, value: String, bound: &'static str| {
            if !ok {
                out.push(ConfigProblem {
                    field,
                    value,
                    bound,
                });
            }
        };
        let [a0, a1] = self.altitude_band;
        check(
            a0.is_finite() && a1.is_finite() && a0 > 0.0 && a0 <= a1 && a1 <= 100.0,
            "virtual.altitude_band",
            format!("{:?}", self.altitude_band),
            "must be [lowest, highest] with 0 < lowest ≤ highest ≤ 100",
        );
        let [p0, p1] = self.pitch_deg;
        check(
            p0.is_finite() && p1.is_finite() && p0 > 0.0 && p0 <= p1 && p1 <= 90.0,
            "virtual.pitch_deg",
            format!("{:?}", self.pitch_deg),
            "must be [least, most] degrees below the horizon with 0 < least ≤ most ≤ 90",
        );
        check(
            self.min_clearance_m.is_finite() && self.min_clearance_m >= 0.0,
            "virtual.min_clearance_m",
            self.min_clearance_m.to_string(),
            "must be finite and at least 0",
        );
        check(
            self.min_views >= 1,
            "virtual.min_views",
            self.min_views.to_string(),
            "must be at least 1",
        );
        check(
            (0.0..=1.0).contains(&self.min_coverage),
            "virtual.min_coverage",
            self.min_coverage.to_string(),
            "must be within [0, 1]",
        );
        check(
            self.cell_m.is_finite() && self.cell_m >= 0.0,
            "virtual.cell_m",
            self.cell_m.to_string(),
            "must be finite and at least 0 (0: a tenth of the survey's height)",
        );
        check(
            self.max_candidates_per_pose >= 1 && self.max_candidates_per_pose <= 10_000,
            "virtual.max_candidates_per_pose",
            self.max_candidates_per_pose.to_string(),
            "must be within [1, 10000]",
        );
        check(
            self.per_block <= 100_000,
            "virtual.per_block",
            self.per_block.to_string(),
            "must be at most 100000",
        );
        out
    }

    /// The first out-of-range field as an error.
    pub fn validate(&self) -> Result<(), SurfaceError> {
        match self.problems().into_iter().next() {
            None => Ok(()),
            Some(p) => Err(SurfaceError::InvalidConfig {
                field: p.field,
                reason: format!("= {}: {}", p.value, p.bound),
            }),
        }
    }
}

/// An axis-aligned box, world frame, metres (a block's scene box).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneBox {
    /// Minimum corner.
    pub min: [f64; 3],
    /// Maximum corner.
    pub max: [f64; 3],
}

impl SceneBox {
    /// Ground-coordinate rectangle `([u0, v0], [u1, v1])` the box covers seen along `frame.up`
    /// (exact when `up` is a world axis).
    pub fn ground_rect(&self, frame: &GroundFrame) -> ([f64; 2], [f64; 2]) {
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for k in 0..8 {
            let c = Point3::new(
                if k & 1 == 0 { self.min[0] } else { self.max[0] },
                if k & 2 == 0 { self.min[1] } else { self.max[1] },
                if k & 4 == 0 { self.min[2] } else { self.max[2] },
            );
            let l = frame.local(&c);
            for a in 0..2 {
                lo[a] = lo[a].min(l[a]);
                hi[a] = hi[a].max(l[a]);
            }
        }
        (lo, hi)
    }
}

/// What the sampler knows of the scene.
pub struct ViewpointScene<'a> {
    /// World up axis (need not be unit).
    pub up: Vector3<f64>,
    /// Intrinsics of the virtual views (their footprint).
    pub camera: &'a Camera,
    /// Camera centres of the training views.
    pub training_centres: &'a [Point3<f64>],
    /// Surface points each training view saw (same order as `training_centres`).
    pub seen: &'a [Vec<Point3<f64>>],
    /// The blocks' scene boxes; poses are sampled per block.
    pub blocks: &'a [SceneBox],
}

/// One accepted virtual viewpoint.
#[derive(Clone, Debug, PartialEq)]
pub struct VirtualPose {
    /// `cam_from_world`, OpenCV camera axes (the camera looks along its +z).
    pub cam_from_world: Pose,
    /// Block whose box it was drawn over.
    pub block: usize,
    /// Height above the surface under the camera, metres.
    pub height_m: f64,
    /// Pitch below the horizon, degrees.
    pub pitch_deg: f64,
    /// Heading of the optical axis in the ground frame (from `e1` towards `e2`), degrees in
    /// `[0, 360)`.
    pub heading_deg: f64,
    /// Where the optical axis meets the surface.
    pub target: Point3<f64>,
    /// Fraction of the footprint rays that meet covered ground.
    pub coverage: f64,
}

/// Candidates dropped, by the first rule each failed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rejections {
    /// No observed surface under the camera (nothing to set its height from).
    pub no_ground_below: usize,
    /// The surface within `min_clearance_m` around the camera comes closer than that.
    pub clearance: usize,
    /// The optical axis meets no observed surface.
    pub axis_misses_ground: usize,
    /// The optical axis meets the surface outside the block's box.
    pub target_outside_block: usize,
    /// The optical axis meets ground fewer than `min_views` training cameras saw.
    pub axis_not_covered: usize,
    /// Less than `min_coverage` of the footprint meets covered ground.
    pub low_coverage: usize,
}

impl Rejections {
    /// All rejected candidates.
    pub fn total(&self) -> usize {
        self.no_ground_below
            + self.clearance
            + self.axis_misses_ground
            + self.target_outside_block
            + self.axis_not_covered
            + self.low_coverage
    }
}

/// The sampler's answer.
#[derive(Clone, Debug, PartialEq)]
pub struct VirtualViews {
    /// Accepted poses, block by block.
    pub poses: Vec<VirtualPose>,
    /// Candidates drawn (accepted + rejected).
    pub candidates: usize,
    /// Why the others were dropped.
    pub rejected: Rejections,
    /// The survey's median camera height above the ground it saw, metres.
    pub survey_height_m: f64,
    /// Edge of the height field's cells, metres.
    pub cell_m: f64,
}

/// Footprint rays per image side.
const FOOTPRINT_GRID: usize = 8;

/// Median over the training cameras of their height above the median height of the surface
/// points each saw (cameras that saw none are skipped; `None` when none saw any).
pub fn survey_height(
    frame: &GroundFrame,
    centres: &[Point3<f64>],
    seen: &[Vec<Point3<f64>>],
) -> Option<f64> {
    let mut heights: Vec<f64> = centres
        .iter()
        .zip(seen)
        .filter_map(|(c, pts)| {
            let mut h: Vec<f64> = pts
                .iter()
                .map(|p| frame.local(p)[2])
                .filter(|h| h.is_finite())
                .collect();
            if h.is_empty() {
                return None;
            }
            let mid = h.len() / 2;
            let (_, m, _) = h.select_nth_unstable_by(mid, f64::total_cmp);
            let d = frame.local(c)[2] - *m;
            d.is_finite().then_some(d)
        })
        .collect();
    if heights.is_empty() {
        return None;
    }
    let mid = heights.len() / 2;
    let (_, m, _) = heights.select_nth_unstable_by(mid, f64::total_cmp);
    Some(*m)
}

/// World points of every `stride`-th cell of a view's z-depth map (`0` or non-finite: no
/// surface); the map may be coarser than the image, with its aspect (as
/// [`crate::FrameSurfaces::depth`] gives it): cell centres are scaled to the image's pixels.
pub fn points_from_depth(
    camera: &Camera,
    cam_from_world: &Pose,
    depth: &matloc_core::Image<f32>,
    stride: usize,
) -> Vec<Point3<f64>> {
    let (w, h) = (depth.width(), depth.height());
    if w == 0 || h == 0 || depth.channels() != 1 {
        return Vec::new();
    }
    let (sx, sy) = (
        camera.width as f64 / w as f64,
        camera.height as f64 / h as f64,
    );
    let world_from_cam = cam_from_world.inverse();
    let data = depth.data();
    let stride = stride.max(1);
    let mut out = Vec::new();
    for r in (0..h).step_by(stride) {
        for c in (0..w).step_by(stride) {
            let z = f64::from(data[r * w + c]);
            if !(z.is_finite() && z > 0.0) {
                continue;
            }
            let px = Point2::new((c as f64 + 0.5) * sx, (r as f64 + 0.5) * sy);
            if let Some(n) = camera.pixel_to_normalized(px) {
                out.push(world_from_cam * Point3::new(n.x * z, n.y * z, z));
            }
        }
    }
    out
}

/// The cells of `grid` where a camera's footprint rays (pixel centres of an 8 × 8 grid of
/// cells over the image) first meet the observed surface, one entry per ray that meets it, in
/// ray order (a cell seen by several rays repeats).
pub fn footprint_cells(grid: &SurfaceGrid, camera: &Camera, cam_from_world: &Pose) -> Vec<usize> {
    let world_from_cam = cam_from_world.inverse();
    let eye = Point3::from(world_from_cam.translation.vector);
    let max_t = grid.reach(&eye);
    let frame = grid.frame();
    footprint_bearings(camera)
        .0
        .iter()
        .filter_map(|b| {
            let p = grid.cast(&eye, &world_from_cam.transform_vector(b), max_t)?;
            let [u, v, _] = frame.local(&p);
            grid.cell(u, v)
        })
        .collect()
}

/// The world's up axis for a survey without one recorded: minus the mean of the training
/// views' unit viewing directions (an aerial survey looks down). `None` when the directions
/// cancel out or there are none.
pub fn up_from_views(cam_from_world: &[Pose]) -> Option<Vector3<f64>> {
    let sum: Vector3<f64> = cam_from_world
        .iter()
        .map(|p| p.inverse_transform_vector(&Vector3::z()))
        .sum();
    (-sum).try_normalize(1e-6 * cam_from_world.len() as f64)
}

/// `cam_from_world` of a camera at `eye` whose optical axis points along `heading_rad` in the
/// ground frame, `pitch_rad` below the horizon; image right is horizontal, image top towards
/// the heading (also at nadir).
pub fn heading_pitch_pose(
    frame: &GroundFrame,
    eye: &Point3<f64>,
    heading_rad: f64,
    pitch_rad: f64,
) -> Pose {
    let h = frame.e1 * heading_rad.cos() + frame.e2 * heading_rad.sin();
    let forward = h * pitch_rad.cos() - frame.up * pitch_rad.sin();
    let right = h.cross(&frame.up);
    let down = forward.cross(&right);
    // Rows of the cam_from_world rotation are the camera axes in world coordinates.
    let r = Matrix3::from_rows(&[right.transpose(), down.transpose(), forward.transpose()]);
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let t = -(rot * eye.coords);
    Isometry3::from_parts(Translation3::from(t), rot)
}

/// A uniform draw in `[0, 1)`.
fn unit(state: &mut u64) -> f64 {
    (splitmix64_next(state) >> 11) as f64 / (1u64 << 53) as f64
}

/// Samples virtual viewpoints over each block of `scene` by the rule in the module docs.
/// Errors: a config out of range, an unusable `up`, no surface seen.
pub fn sample_viewpoints(
    config: &VirtualViewsConfig,
    scene: &ViewpointScene<'_>,
) -> Result<VirtualViews, SurfaceError> {
    config.validate()?;
    let frame = GroundFrame::new(scene.up).ok_or_else(|| SurfaceError::InvalidConfig {
        field: "up",
        reason: format!("must be a finite non-zero vector, got {:?}", scene.up),
    })?;
    let survey_height_m = survey_height(&frame, scene.training_centres, scene.seen)
        .filter(|h| *h > 0.0)
        .ok_or(SurfaceError::NoSurfaceSeen)?;
    let cell_m = if config.cell_m > 0.0 {
        config.cell_m
    } else {
        0.1 * survey_height_m
    };
    let grid = SurfaceGrid::build(frame, cell_m, scene.seen)?;
    let (g0, g1) = grid.extent();
    // Long enough to cross the grid from the highest camera.
    let max_t =
        (g1[0] - g0[0]).hypot(g1[1] - g0[1]) + 4.0 * config.altitude_band[1] * survey_height_m;
    let bearings = footprint_bearings(scene.camera);
    let mut out = VirtualViews {
        poses: Vec::new(),
        candidates: 0,
        rejected: Rejections::default(),
        survey_height_m,
        cell_m,
    };
    for (b, bx) in scene.blocks.iter().enumerate() {
        let (lo, hi) = bx.ground_rect(&frame);
        let mut state = mix64(config.seed ^ mix64(b as u64 + 1));
        let mut accepted = 0;
        let budget = config
            .per_block
            .saturating_mul(config.max_candidates_per_pose);
        for _ in 0..budget {
            if accepted == config.per_block {
                break;
            }
            out.candidates += 1;
            let u = lo[0] + unit(&mut state) * (hi[0] - lo[0]);
            let v = lo[1] + unit(&mut state) * (hi[1] - lo[1]);
            let [a0, a1] = config.altitude_band;
            let height_m = (a0 + unit(&mut state) * (a1 - a0)) * survey_height_m;
            let [p0, p1] = config.pitch_deg;
            let pitch_deg = p0 + unit(&mut state) * (p1 - p0);
            let heading_deg = 360.0 * unit(&mut state);
            let candidate = Candidate {
                u,
                v,
                height_m,
                pitch_deg,
                heading_deg,
            };
            match judge(config, &grid, bx, &bearings, max_t, &candidate) {
                Ok((cam_from_world, target, coverage)) => {
                    accepted += 1;
                    out.poses.push(VirtualPose {
                        cam_from_world,
                        block: b,
                        height_m,
                        pitch_deg,
                        heading_deg,
                        target,
                        coverage,
                    });
                }
                Err(reason) => {
                    let r = &mut out.rejected;
                    *match reason {
                        Reject::NoGroundBelow => &mut r.no_ground_below,
                        Reject::Clearance => &mut r.clearance,
                        Reject::AxisMissesGround => &mut r.axis_misses_ground,
                        Reject::TargetOutsideBlock => &mut r.target_outside_block,
                        Reject::AxisNotCovered => &mut r.axis_not_covered,
                        Reject::LowCoverage => &mut r.low_coverage,
                    } += 1;
                }
            }
        }
    }
    Ok(out)
}

/// One drawn candidate, in ground coordinates.
struct Candidate {
    u: f64,
    v: f64,
    height_m: f64,
    pitch_deg: f64,
    heading_deg: f64,
}

enum Reject {
    NoGroundBelow,
    Clearance,
    AxisMissesGround,
    TargetOutsideBlock,
    AxisNotCovered,
    LowCoverage,
}

/// Camera-frame bearings of the footprint rays: pixel centres of an 8 × 8 grid of cells over
/// the image (rays whose undistortion fails are left out, and count as uncovered).
fn footprint_bearings(camera: &Camera) -> (Vec<Vector3<f64>>, usize) {
    let n = FOOTPRINT_GRID;
    let mut out = Vec::with_capacity(n * n);
    for r in 0..n {
        for c in 0..n {
            let px = Point2::new(
                (c as f64 + 0.5) * camera.width as f64 / n as f64,
                (r as f64 + 0.5) * camera.height as f64 / n as f64,
            );
            if let Some(b) = camera.unproject(px) {
                out.push(b);
            }
        }
    }
    (out, n * n)
}

/// The pose of `c`, where its axis meets the surface and its coverage, or why it is dropped.
fn judge(
    config: &VirtualViewsConfig,
    grid: &SurfaceGrid,
    bx: &SceneBox,
    (bearings, rays): &(Vec<Vector3<f64>>, usize),
    max_t: f64,
    c: &Candidate,
) -> Result<(Pose, Point3<f64>, f64), Reject> {
    let frame = grid.frame();
    let ground = grid
        .height(c.u, c.v)
        .or_else(|| grid.max_height_within(c.u, c.v, grid.cell_m()))
        .ok_or(Reject::NoGroundBelow)?;
    let eye_h = ground + c.height_m;
    let near = grid
        .max_height_within(c.u, c.v, config.min_clearance_m)
        .unwrap_or(ground);
    if eye_h - near < config.min_clearance_m {
        return Err(Reject::Clearance);
    }
    let eye = frame.world(c.u, c.v, eye_h);
    let pose = heading_pitch_pose(
        frame,
        &eye,
        c.heading_deg.to_radians(),
        c.pitch_deg.to_radians(),
    );
    let world_from_cam = pose.inverse();
    let axis = world_from_cam.transform_vector(&Vector3::z());
    let target = grid
        .cast(&eye, &axis, max_t)
        .ok_or(Reject::AxisMissesGround)?;
    let [tu, tv, _] = frame.local(&target);
    let (lo, hi) = bx.ground_rect(frame);
    if !(lo[0] <= tu && tu <= hi[0] && lo[1] <= tv && tv <= hi[1]) {
        return Err(Reject::TargetOutsideBlock);
    }
    if grid.views(tu, tv) < config.min_views {
        return Err(Reject::AxisNotCovered);
    }
    let covered = bearings
        .iter()
        .filter(|b| {
            grid.cast(&eye, &world_from_cam.transform_vector(b), max_t)
                .is_some_and(|p| {
                    let [u, v, _] = frame.local(&p);
                    grid.views(u, v) >= config.min_views
                })
        })
        .count();
    let coverage = covered as f64 / *rays as f64;
    if coverage < config.min_coverage {
        return Err(Reject::LowCoverage);
    }
    Ok((pose, target, coverage))
}
