//! Sample points of a pose: points along its camera rays up to the surface.
//!
//! The surface distance of each ray comes from a
//! [`SurfaceSource`]: a depth map ([`DepthMapSurface`]) or anything that can cast rays (the
//! synthetic world in tests). Rays are taken on a pixel grid (every `pixel_stride`-th pixel,
//! centres at `+0.5`) and each contributes `points_per_ray` stratified points between `near` and
//! the surface plus the surface point itself. Sky rays (no surface) are governed by
//! [`SkyPolicy`]: skipped by default, because a NeRF's far samples in the sky say nothing about
//! which part of the scene a pose needs.

use matloc_core::Camera;
use matloc_core::image::Image;
use matloc_core::pose::{Pose, camera_center, viewing_direction};
use matloc_data::Dataset;
use nalgebra::{Point2, Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::PartitionError;

/// What a ray that hits no surface contributes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SkyPolicy {
    /// Nothing (the default).
    Skip,
    /// Points up to this distance along the ray, metres, without a surface point.
    Far(f64),
}

/// How rays and points are subsampled.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SampleConfig {
    /// Take every `pixel_stride`-th pixel in x and y.
    pub pixel_stride: u32,
    /// Points along each ray between `near` and the surface (the surface point is extra).
    pub points_per_ray: usize,
    /// Distance from the camera where sampling starts, metres.
    pub near: f64,
    /// Rays without a surface.
    pub sky: SkyPolicy,
}

impl Default for SampleConfig {
    fn default() -> Self {
        SampleConfig {
            pixel_stride: 8,
            points_per_ray: 8,
            near: 0.5,
            sky: SkyPolicy::Skip,
        }
    }
}

impl SampleConfig {
    /// Checks the values are usable.
    pub fn validate(&self) -> Result<(), PartitionError> {
        if self.pixel_stride == 0 {
            return Err(PartitionError::InvalidConfig {
                field: "pixel_stride",
                reason: "must be at least 1".into(),
            });
        }
        if !(self.near.is_finite() && self.near >= 0.0) {
            return Err(PartitionError::InvalidConfig {
                field: "near",
                reason: format!("must be finite and >= 0, got {}", self.near),
            });
        }
        if let SkyPolicy::Far(f) = self.sky
            && !(f.is_finite() && f > self.near)
        {
            return Err(PartitionError::InvalidConfig {
                field: "sky",
                reason: format!("far distance must be finite and beyond near, got {f}"),
            });
        }
        Ok(())
    }
}

/// One ray of a pose, in every frame a surface source may want it.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceRay {
    /// Continuous pixel coordinate of the ray (centre of the pixel at `+0.5`).
    pub pixel: Point2<f64>,
    /// Unit bearing in camera coordinates (OpenCV axes).
    pub bearing_cam: Vector3<f64>,
    /// Camera centre, world frame.
    pub origin: Point3<f64>,
    /// Unit direction, world frame.
    pub dir: Vector3<f64>,
}

/// Gives the distance along a ray to the first surface, or `None` for sky.
pub trait SurfaceSource: Sync {
    /// Distance in metres along `ray.dir` from `ray.origin` to the surface.
    fn surface_distance(&self, ray: &SurfaceRay) -> Option<f64>;
}

/// A z-depth map (metres, `0` or non-finite = no surface) for the camera it was rendered with;
/// its resolution may differ from the camera's as long as the aspect ratio matches.
pub struct DepthMapSurface<'a> {
    depth: &'a Image<f32>,
    sx: f64,
    sy: f64,
}

impl<'a> DepthMapSurface<'a> {
    /// Wraps `depth` for rays of `camera`.
    pub fn new(depth: &'a Image<f32>, camera: &Camera) -> Self {
        DepthMapSurface {
            depth,
            sx: depth.width() as f64 / camera.width as f64,
            sy: depth.height() as f64 / camera.height as f64,
        }
    }
}

impl SurfaceSource for DepthMapSurface<'_> {
    fn surface_distance(&self, ray: &SurfaceRay) -> Option<f64> {
        let (w, h) = (self.depth.width(), self.depth.height());
        let x = (ray.pixel.x * self.sx).floor();
        let y = (ray.pixel.y * self.sy).floor();
        if !(x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h) {
            return None;
        }
        let z = f64::from(self.depth.data()[y as usize * w + x as usize]);
        // z-depth is measured along the optical axis; the ray distance divides by cos(angle).
        (z.is_finite() && z > 0.0 && ray.bearing_cam.z > 1e-9).then(|| z / ray.bearing_cam.z)
    }
}

/// The sample points of one pose.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseSamples {
    /// Caller's id of the pose (the frame index for datasets).
    pub id: usize,
    /// `cam_from_world`, OpenCV axes.
    pub cam_from_world: Pose,
    /// World points along the pose's rays.
    pub points: Vec<Point3<f64>>,
}

impl PoseSamples {
    /// Camera centre, world frame.
    pub fn center(&self) -> Point3<f64> {
        camera_center(&self.cam_from_world)
    }

    /// Unit viewing direction, world frame.
    pub fn viewing_direction(&self) -> Vector3<f64> {
        viewing_direction(&self.cam_from_world)
    }

    /// Mean of the sample points (`None` when there are none).
    pub fn mean_point(&self) -> Option<Point3<f64>> {
        if self.points.is_empty() {
            return None;
        }
        let s = self
            .points
            .iter()
            .fold(Vector3::zeros(), |acc, p| acc + p.coords);
        Some(Point3::from(s / self.points.len() as f64))
    }
}

/// Bytes one sample point takes: the point (3 × f64) and its voxel id in the occupancy.
pub const SAMPLE_POINT_BYTES: u64 = 24 + 8;

/// Most sample points a view of `camera` gives with `config` (every ray hitting a surface).
pub fn max_points(camera: &Camera, config: &SampleConfig) -> u64 {
    let stride = u64::from(config.pixel_stride.max(1));
    let off = stride / 2;
    let along = |n: u32| u64::from(n).saturating_sub(off).div_ceil(stride);
    along(camera.width)
        .saturating_mul(along(camera.height))
        .saturating_mul(config.points_per_ray as u64 + 1)
}

/// The memory `points` sample points take.
fn samples_request(what: &'static str, points: u64) -> matloc_core::limits::MemoryRequest {
    matloc_core::limits::MemoryRequest {
        what,
        count: points,
        unit: "sample points",
        bytes_each: SAMPLE_POINT_BYTES,
        remedy: "raise `samples.pixel_stride` or lower `samples.points_per_ray`",
    }
}

/// True when every component of the pose is finite.
pub(crate) fn pose_is_finite(p: &Pose) -> bool {
    p.translation.vector.iter().all(|v| v.is_finite())
        && p.rotation.coords.iter().all(|v| v.is_finite())
}

/// Samples one pose's rays against `surface`.
pub fn sample_pose(
    id: usize,
    camera: &Camera,
    cam_from_world: &Pose,
    surface: &dyn SurfaceSource,
    config: &SampleConfig,
) -> Result<PoseSamples, PartitionError> {
    config.validate()?;
    if !pose_is_finite(cam_from_world) {
        return Err(PartitionError::NonFinitePose { index: id });
    }
    matloc_core::limits::check_memory(&samples_request(
        "partition samples of one view",
        max_points(camera, config),
    ))?;
    let world_from_cam = cam_from_world.inverse();
    let origin = camera_center(cam_from_world);
    let stride = config.pixel_stride as usize;
    let n = config.points_per_ray;
    let mut points = Vec::new();
    // Start half a stride in so the grid is centred in the image.
    let off = stride / 2;
    for row in (off..camera.height as usize).step_by(stride) {
        for col in (off..camera.width as usize).step_by(stride) {
            let pixel = Point2::new(col as f64 + 0.5, row as f64 + 0.5);
            let Some(bearing) = camera.unproject(pixel) else {
                continue;
            };
            let dir = world_from_cam.transform_vector(&bearing);
            let ray = SurfaceRay {
                pixel,
                bearing_cam: bearing,
                origin,
                dir,
            };
            let (end, with_surface) = match (surface.surface_distance(&ray), config.sky) {
                (Some(t), _) if t.is_finite() && t > 0.0 => (t, true),
                (_, SkyPolicy::Far(f)) => (f, false),
                (_, SkyPolicy::Skip) => continue,
            };
            if end > config.near {
                let step = (end - config.near) / n as f64;
                for i in 0..n {
                    let t = config.near + step * (i as f64 + 0.5);
                    points.push(origin + dir * t);
                }
            }
            if with_surface {
                points.push(origin + dir * end);
            }
        }
    }
    Ok(PoseSamples {
        id,
        cam_from_world: *cam_from_world,
        points,
    })
}

/// Samples the frames `indices` of `dataset` from their depth maps (in parallel); `progress` is
/// called once per finished frame.
pub fn samples_from_dataset(
    dataset: &Dataset,
    indices: &[usize],
    config: &SampleConfig,
    progress: &(dyn Fn() + Sync),
) -> Result<Vec<PoseSamples>, PartitionError> {
    config.validate()?;
    // Every view's samples are kept until the partition is made.
    let total = indices
        .iter()
        .filter_map(|&i| dataset.frames.get(i))
        .map(|f| max_points(&f.camera, config))
        .fold(0u64, u64::saturating_add);
    matloc_core::limits::check_memory(&samples_request("partition samples of all views", total))?;
    indices
        .par_iter()
        .map(|&index| {
            let frame = dataset
                .frames
                .get(index)
                .ok_or_else(|| PartitionError::Inconsistent(format!("no frame {index}")))?;
            let depth = matloc_data::images::load_frame_depth(dataset, frame, 1)
                .map_err(|e| PartitionError::Depth {
                    index,
                    message: e.to_string(),
                })?
                .ok_or(PartitionError::MissingDepth { index })?;
            let surface = DepthMapSurface::new(&depth, &frame.camera);
            let s = sample_pose(
                index,
                &frame.camera,
                &frame.cam_from_world,
                &surface,
                config,
            );
            progress();
            s
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_core::pose::look_at;

    struct Plane(f64);
    impl SurfaceSource for Plane {
        fn surface_distance(&self, ray: &SurfaceRay) -> Option<f64> {
            (ray.dir.z < -1e-9).then(|| (self.0 - ray.origin.z) / ray.dir.z)
        }
    }

    #[test]
    fn depth_map_and_raycast_agree_on_a_plane() {
        let cam = Camera::pinhole(40, 30, 30.0, 30.0, 20.0, 15.0).unwrap();
        let pose = look_at(
            &Point3::new(0.0, 0.0, 20.0),
            &Point3::new(5.0, 3.0, 0.0),
            &Vector3::z(),
        )
        .unwrap();
        // Render the plane z = 0 into a z-depth map.
        let mut depth = Image::<f32>::new(40, 30, 1);
        let wfc = pose.inverse();
        for r in 0..30 {
            for c in 0..40 {
                let b = cam
                    .unproject(Point2::new(c as f64 + 0.5, r as f64 + 0.5))
                    .unwrap();
                let d = wfc.transform_vector(&b);
                let t = -20.0 / d.z;
                depth.data_mut()[r * 40 + c] = (t * b.z) as f32;
            }
        }
        let cfg = SampleConfig {
            pixel_stride: 4,
            points_per_ray: 3,
            ..SampleConfig::default()
        };
        let a = sample_pose(0, &cam, &pose, &DepthMapSurface::new(&depth, &cam), &cfg).unwrap();
        let b = sample_pose(0, &cam, &pose, &Plane(0.0), &cfg).unwrap();
        assert_eq!(a.points.len(), 10 * 7 * 4);
        assert_eq!(a.points.len(), b.points.len());
        for (p, q) in a.points.iter().zip(&b.points) {
            assert!((p - q).norm() < 1e-3, "{p} vs {q}");
        }
        // Every fourth point is a surface point on z = 0.
        assert!(a.points.iter().skip(3).step_by(4).all(|p| p.z.abs() < 1e-3));
    }

    #[test]
    fn sky_policy() {
        struct Sky;
        impl SurfaceSource for Sky {
            fn surface_distance(&self, _: &SurfaceRay) -> Option<f64> {
                None
            }
        }
        let cam = Camera::pinhole(16, 16, 10.0, 10.0, 8.0, 8.0).unwrap();
        let pose = Pose::identity();
        let cfg = SampleConfig::default();
        let s = sample_pose(3, &cam, &pose, &Sky, &cfg).unwrap();
        assert!(s.points.is_empty());
        let far = SampleConfig {
            sky: SkyPolicy::Far(50.0),
            ..cfg
        };
        let s = sample_pose(3, &cam, &pose, &Sky, &far).unwrap();
        assert_eq!(s.points.len(), 4 * 8);
        assert!(s.points.iter().all(|p| p.coords.norm() <= 50.0));
    }

    #[test]
    fn non_finite_pose_is_rejected() {
        let cam = Camera::pinhole(16, 16, 10.0, 10.0, 8.0, 8.0).unwrap();
        let mut pose = Pose::identity();
        pose.translation.vector.x = f64::NAN;
        let e = sample_pose(7, &cam, &pose, &Plane(0.0), &SampleConfig::default()).unwrap_err();
        assert!(matches!(e, PartitionError::NonFinitePose { index: 7 }));
    }

    #[test]
    fn samples_beyond_the_memory_budget_are_refused_before_sampling() {
        use matloc_core::limits::{BudgetSource, MemoryBudget, check_against};
        let cam = Camera::pinhole(4000, 3000, 3000.0, 3000.0, 2000.0, 1500.0).unwrap();
        let cfg = SampleConfig::default();
        // 500 × 375 rays, 9 points each.
        assert_eq!(max_points(&cam, &cfg), 500 * 375 * 9);
        let budget = Some(MemoryBudget {
            bytes: 1 << 20,
            source: BudgetSource::Explicit,
        });
        let e = check_against(
            &samples_request("partition samples of one view", max_points(&cam, &cfg)),
            budget,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("1687500 sample points") && e.contains("samples.pixel_stride"),
            "{e}"
        );
        // A camera no memory holds the samples of is refused by `sample_pose` itself.
        let huge = Camera::pinhole(u32::MAX, u32::MAX, 1e9, 1e9, 2e9, 2e9).unwrap();
        let one = SampleConfig {
            pixel_stride: 1,
            points_per_ray: 1000,
            ..cfg
        };
        let e = sample_pose(0, &huge, &Pose::identity(), &Plane(0.0), &one).unwrap_err();
        assert!(matches!(e, PartitionError::Limit(_)), "{e}");
    }
}
