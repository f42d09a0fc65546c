//! The drone capture plan: lawnmower mapping lines with overlap from the camera footprint, and
//! held-out query views between training frames.

use std::path::PathBuf;

use matloc_core::pose::{camera_center, look_at};
use matloc_core::{Camera, Pose};
use nalgebra::{Point3, Rotation3, Unit, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::error::SynthError;
use super::rng::Rng;
use super::world::World;
use matloc_data::dataset::{Frame, Split};

/// Capture parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SurveyConfig {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Horizontal field of view, degrees (pinhole, principal point at the centre).
    pub hfov_deg: f64,
    /// Flight altitude above the terrain below the drone, m.
    pub altitude_m: f64,
    /// Camera tilt off nadir, degrees, looking forward along the flight line.
    pub pitch_deg: f64,
    /// Forward overlap of consecutive images on a line (fraction of the footprint length).
    pub forward_overlap: f64,
    /// Side overlap of adjacent lines (fraction of the footprint width at its centre).
    pub side_overlap: f64,
    /// Fly a second pass with lines rotated by 90°; lines alternate direction in any case.
    pub cross_pass: bool,
    /// Number of held-out query views.
    pub test_views: usize,
    /// Random horizontal/vertical position jitter of training views, m.
    pub position_jitter_m: f64,
    /// Random yaw jitter of training views, degrees.
    pub yaw_jitter_deg: f64,
    /// Position jitter of query views around the midpoint of two training views, m.
    pub test_position_jitter_m: f64,
    /// Rotation jitter of query views, degrees.
    pub test_rotation_jitter_deg: f64,
    /// Smallest allowed distance between a query camera and any training camera, m.
    pub min_test_train_distance_m: f64,
}

impl Default for SurveyConfig {
    fn default() -> Self {
        SurveyConfig {
            width: 320,
            height: 240,
            hfov_deg: 60.0,
            altitude_m: 40.0,
            pitch_deg: 30.0,
            forward_overlap: 0.75,
            side_overlap: 0.6,
            cross_pass: true,
            test_views: 30,
            position_jitter_m: 0.4,
            yaw_jitter_deg: 2.0,
            test_position_jitter_m: 1.5,
            test_rotation_jitter_deg: 4.0,
            min_test_train_distance_m: 1.0,
        }
    }
}

impl SurveyConfig {
    pub(crate) fn validate(&self) -> Result<(), SynthError> {
        let bad =
            |field: &'static str, reason: String| Err(SynthError::InvalidConfig { field, reason });
        if self.width == 0 || self.height == 0 || self.width > 16384 || self.height > 16384 {
            return bad(
                "survey.width",
                format!(
                    "image size {}x{} must be within 1..=16384",
                    self.width, self.height
                ),
            );
        }
        if !(self.hfov_deg > 1.0 && self.hfov_deg < 170.0) {
            return bad(
                "survey.hfov_deg",
                format!("must be in (1, 170), got {}", self.hfov_deg),
            );
        }
        if !(self.altitude_m.is_finite() && self.altitude_m > 1.0) {
            return bad(
                "survey.altitude_m",
                format!("must be > 1 m, got {}", self.altitude_m),
            );
        }
        if !(self.pitch_deg >= 0.0 && self.pitch_deg < 80.0) {
            return bad(
                "survey.pitch_deg",
                format!("must be in [0, 80), got {}", self.pitch_deg),
            );
        }
        for (field, v) in [
            ("survey.forward_overlap", self.forward_overlap),
            ("survey.side_overlap", self.side_overlap),
        ] {
            if !(0.0..=0.95).contains(&v) {
                return bad(field, format!("must be in [0, 0.95], got {v}"));
            }
        }
        for (field, v) in [
            ("survey.position_jitter_m", self.position_jitter_m),
            ("survey.yaw_jitter_deg", self.yaw_jitter_deg),
            ("survey.test_position_jitter_m", self.test_position_jitter_m),
            (
                "survey.test_rotation_jitter_deg",
                self.test_rotation_jitter_deg,
            ),
            (
                "survey.min_test_train_distance_m",
                self.min_test_train_distance_m,
            ),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, format!("must be a non-negative number, got {v}"));
            }
        }
        Ok(())
    }

    /// The survey camera.
    pub fn camera(&self) -> Result<Camera, SynthError> {
        Camera::from_hfov(self.width, self.height, self.hfov_deg).map_err(|e| {
            SynthError::InvalidConfig {
                field: "survey.hfov_deg",
                reason: e.to_string(),
            }
        })
    }
}

/// Ground footprint of one survey image over flat ground and the spacings derived from it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurveyGeometry {
    /// Footprint length along the flight direction (centre column), m.
    pub along_m: f64,
    /// Footprint width across the flight direction at the image's centre row, m.
    pub across_m: f64,
    /// Distance of the footprint's along-track midpoint ahead of the drone, m.
    pub ahead_m: f64,
    /// Distance between consecutive exposures on a line, m.
    pub forward_spacing_m: f64,
    /// Distance between adjacent flight lines, m.
    pub line_spacing_m: f64,
}

/// A planned capture.
#[derive(Clone, Debug, PartialEq)]
pub struct SurveyPlan {
    /// Training views in flight order, then query views; paths `images/frame_NNNNN.png` and
    /// `depth/frame_NNNNN.npy` relative to the dataset root.
    pub frames: Vec<Frame>,
    /// Flight line of each frame (a query view takes the line of the pair it was placed between).
    pub line: Vec<u32>,
    /// Footprint and spacing.
    pub geometry: SurveyGeometry,
}

/// Ground point of the ray through pixel `(x, y)` on the plane `z = 0`, or `None` above the horizon.
fn ground_point(camera: &Camera, cam_from_world: &Pose, x: f64, y: f64) -> Option<Point3<f64>> {
    let b = camera.unproject(nalgebra::Point2::new(x, y))?;
    let world_from_cam = cam_from_world.inverse();
    let d = world_from_cam.rotation * b;
    let o = world_from_cam.translation.vector;
    if d.z >= -1e-9 {
        return None;
    }
    let t = -o.z / d.z;
    Some(Point3::from(o + d * t))
}

/// `cam_from_world` of a drone at `eye` flying along unit `heading` (horizontal), camera tilted
/// `pitch` radians off nadir towards the heading, image top pointing forward.
pub(crate) fn drone_pose(eye: &Point3<f64>, heading: &Vector3<f64>, pitch: f64) -> Option<Pose> {
    let forward = heading * pitch.sin() - Vector3::z() * pitch.cos();
    let up = heading * pitch.cos() + Vector3::z() * pitch.sin();
    look_at(eye, &(eye + forward), &up)
}

/// Footprint and spacings for a survey configuration over flat ground.
pub fn survey_geometry(cfg: &SurveyConfig) -> Result<SurveyGeometry, SynthError> {
    cfg.validate()?;
    let camera = cfg.camera()?;
    let pitch = cfg.pitch_deg.to_radians();
    let eye = Point3::new(0.0, 0.0, cfg.altitude_m);
    let pose = drone_pose(&eye, &Vector3::y(), pitch).ok_or_else(|| SynthError::InvalidConfig {
        field: "survey.pitch_deg",
        reason: "degenerate camera orientation".into(),
    })?;
    let (w, h) = (cfg.width as f64, cfg.height as f64);
    let above_horizon = || SynthError::InvalidConfig {
        field: "survey.pitch_deg",
        reason: format!(
            "pitch {}° plus half the vertical field of view reaches the horizon",
            cfg.pitch_deg
        ),
    };
    let far = ground_point(&camera, &pose, 0.5 * w, 0.0).ok_or_else(above_horizon)?;
    let near = ground_point(&camera, &pose, 0.5 * w, h).ok_or_else(above_horizon)?;
    let left = ground_point(&camera, &pose, 0.0, 0.5 * h).ok_or_else(above_horizon)?;
    let right = ground_point(&camera, &pose, w, 0.5 * h).ok_or_else(above_horizon)?;
    let along = far.y - near.y;
    let across = (right.x - left.x).abs();
    Ok(SurveyGeometry {
        along_m: along,
        across_m: across,
        ahead_m: 0.5 * (far.y + near.y),
        forward_spacing_m: (1.0 - cfg.forward_overlap) * along,
        line_spacing_m: (1.0 - cfg.side_overlap) * across,
    })
}

/// Centred positions with a fixed spacing whose span covers `extent` given a footprint `size`.
fn positions(extent: f64, size: f64, spacing: f64) -> Vec<f64> {
    let n = if extent <= size {
        1
    } else {
        ((extent - size) / spacing).ceil() as usize + 1
    };
    let n = n.clamp(1, 10_000);
    (0..n)
        .map(|i| (i as f64 - 0.5 * (n - 1) as f64) * spacing)
        .collect()
}

fn frame(index: usize, camera: Camera, cam_from_world: Pose, split: Split) -> Frame {
    Frame {
        image_path: PathBuf::from(format!("images/frame_{index:05}.png")),
        depth_path: Some(PathBuf::from(format!("depth/frame_{index:05}.npy"))),
        camera,
        cam_from_world,
        split,
    }
}

/// Plans the survey over `world`: training views on lawnmower lines covering the content area,
/// then `test_views` query views between consecutive training views. Deterministic in `seed`.
pub fn plan_survey(world: &World, cfg: &SurveyConfig, seed: u64) -> Result<SurveyPlan, SynthError> {
    let geom = survey_geometry(cfg)?;
    let camera = cfg.camera()?;
    let pitch = cfg.pitch_deg.to_radians();
    let extent = world.config().extent_m;
    let mut rng = Rng::new(seed).fork(0x5E7);
    let mut train: Vec<(Pose, u32)> = Vec::new();
    let mut line_id = 0u32;
    let passes: &[Vector3<f64>] = if cfg.cross_pass {
        &[Vector3::new(0.0, 1.0, 0.0), Vector3::new(1.0, 0.0, 0.0)]
    } else {
        &[Vector3::new(0.0, 1.0, 0.0)]
    };
    for axis in passes {
        let across_dir = Vector3::new(axis.y, -axis.x, 0.0);
        let lines = positions(extent, geom.across_m, geom.line_spacing_m);
        let stops = positions(extent, geom.along_m, geom.forward_spacing_m);
        for (li, &q) in lines.iter().enumerate() {
            // Lawnmower: every other line is flown the opposite way, camera facing forward.
            let sign = if li % 2 == 0 { 1.0 } else { -1.0 };
            let heading = axis * sign;
            let order: Vec<f64> = if sign > 0.0 {
                stops.clone()
            } else {
                stops.iter().rev().copied().collect()
            };
            for &s in &order {
                // `s` is where the footprint midpoint should be; the drone flies behind it.
                let target = across_dir * q + axis * s;
                let base = target - heading * geom.ahead_m;
                let jitter = Vector3::new(
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-0.5, 0.5),
                ) * cfg.position_jitter_m;
                let xy = base + jitter;
                let z = world.height_at(xy.x, xy.y) + cfg.altitude_m + jitter.z;
                let eye = Point3::new(xy.x, xy.y, z);
                let yaw = rng.range(-1.0, 1.0) * cfg.yaw_jitter_deg.to_radians();
                let h = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw) * heading;
                let p = rng.range(-0.5, 0.5) * cfg.yaw_jitter_deg.to_radians();
                let pose = drone_pose(&eye, &h, pitch + p).ok_or(SynthError::InvalidConfig {
                    field: "survey.pitch_deg",
                    reason: "degenerate camera orientation".into(),
                })?;
                train.push((pose, line_id));
            }
            line_id += 1;
        }
    }
    for (index, (pose, _)) in train.iter().enumerate() {
        check_clear(world, index, pose)?;
    }

    let mut tests: Vec<(Pose, u32)> = Vec::new();
    let pairs: Vec<usize> = (0..train.len().saturating_sub(1))
        .filter(|&i| train[i].1 == train[i + 1].1)
        .collect();
    let n_test = cfg.test_views.min(pairs.len());
    let centers: Vec<Point3<f64>> = train.iter().map(|(p, _)| camera_center(p)).collect();
    for k in 0..n_test {
        let i = pairs[((k as f64 + 0.5) * pairs.len() as f64 / n_test as f64) as usize];
        let (a, b) = (&train[i].0, &train[i + 1].0);
        let mid_rot = a.rotation.slerp(&b.rotation, 0.5);
        let mid_c = Point3::from(0.5 * (centers[i].coords + centers[i + 1].coords));
        for _attempt in 0..32 {
            let dir = Vector3::new(rng.normal(), rng.normal(), rng.normal());
            let off = dir.try_normalize(1e-12).unwrap_or(Vector3::x())
                * cfg.test_position_jitter_m
                * rng.f64().cbrt();
            let c = mid_c + off;
            if centers
                .iter()
                .any(|t| (t - c).norm() < cfg.min_test_train_distance_m)
            {
                continue;
            }
            let axis = Unit::try_new(
                Vector3::new(rng.normal(), rng.normal(), rng.normal()),
                1e-12,
            )
            .unwrap_or(Vector3::z_axis());
            let angle = rng.range(0.3, 1.0) * cfg.test_rotation_jitter_deg.to_radians();
            // Perturb in the camera frame: world_from_cam ← world_from_cam · R.
            let r_cw = UnitQuaternion::from_axis_angle(&axis, angle).inverse() * mid_rot;
            let t = -(r_cw * c.coords);
            let pose = Pose::from_parts(t.into(), r_cw);
            tests.push((pose, train[i].1));
            break;
        }
    }
    for (k, (pose, _)) in tests.iter().enumerate() {
        check_clear(world, train.len() + k, pose)?;
    }

    let mut frames = Vec::with_capacity(train.len() + tests.len());
    let mut line = Vec::with_capacity(frames.capacity());
    for (pose, l) in train {
        frames.push(frame(frames.len(), camera, pose, Split::Train));
        line.push(l);
    }
    for (pose, l) in tests {
        frames.push(frame(frames.len(), camera, pose, Split::Test));
        line.push(l);
    }
    Ok(SurveyPlan {
        frames,
        line,
        geometry: geom,
    })
}

/// A camera must be above the terrain and have nothing above it (else it is inside an object).
fn check_clear(world: &World, index: usize, pose: &Pose) -> Result<(), SynthError> {
    let c = camera_center(pose);
    let under = c.z < world.height_at(c.x, c.y) + 1.0;
    let inside = world.trace(&c.coords, &Vector3::z()).is_some();
    let near_roof = world.raycast(&c, &-Vector3::z()).is_some_and(|h| h.t < 3.0);
    if under || inside || near_roof {
        return Err(SynthError::CameraInsideScene {
            index,
            position: [c.x, c.y, c.z],
        });
    }
    Ok(())
}
