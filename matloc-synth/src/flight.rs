//! A second flight over the same scene: the map's query views re-shot on another day.
//!
//! Real queries are not taken in the light and with the camera the map was built from: the sun
//! has moved (shadows change length and direction), exposure and white balance differ, the lens
//! distorts, the optics blur and the sensor adds noise before 8-bit quantisation. A
//! [`SecondFlight`] re-renders the test views of a synthetic dataset at the same poses with those
//! changes, so each second-flight query has a same-flight twin to compare against.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use matloc_core::{Distortion, Image};
use matloc_data::dataset::{Dataset, Frame, Split};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::config::SynthConfig;
use super::error::SynthError;
use super::rng::Rng;
use super::world::World;
use super::write::{Progress, generate, write_png};

/// What changes between the map's flight and the second flight.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SecondFlight {
    /// Sun azimuth change, degrees clockwise.
    pub sun_azimuth_shift_deg: f64,
    /// Sun elevation above the horizon, degrees (`None`: the map's).
    pub sun_elevation_deg: Option<f64>,
    /// Exposure change in stops (EV).
    pub exposure_ev: f32,
    /// White balance: per-channel (R, G, B) gains in linear light.
    pub white_balance: [f32; 3],
    /// Lens radial distortion (OpenCV `k1`, `k2`); the transforms say `camera_model` OPENCV.
    pub k1: f64,
    /// Second radial coefficient.
    pub k2: f64,
    /// Gaussian blur of the optics, standard deviation in pixels (0: none).
    pub blur_sigma_px: f32,
    /// Signal-independent sensor noise, standard deviation on the `[0, 1]` display scale.
    pub read_noise: f32,
    /// Signal-dependent noise: standard deviation `shot_noise · √value`.
    pub shot_noise: f32,
    /// Seed of the noise.
    pub seed: u64,
}

impl Default for SecondFlight {
    /// A later flight: sun turned 55° and lowered to 22°, +0.4 EV, warmer light, a barrel
    /// lens (k1 = −0.05), 0.5 px blur and sensor noise.
    fn default() -> Self {
        SecondFlight {
            sun_azimuth_shift_deg: 55.0,
            sun_elevation_deg: Some(22.0),
            exposure_ev: 0.4,
            white_balance: [1.10, 1.0, 0.85],
            k1: -0.05,
            k2: 0.0,
            blur_sigma_px: 0.5,
            read_noise: 0.006,
            shot_noise: 0.012,
            seed: 0,
        }
    }
}

impl SecondFlight {
    /// The map's own flight again (every change off): renders the test views unchanged.
    pub fn same_flight() -> Self {
        SecondFlight {
            sun_azimuth_shift_deg: 0.0,
            sun_elevation_deg: None,
            exposure_ev: 0.0,
            white_balance: [1.0; 3],
            k1: 0.0,
            k2: 0.0,
            blur_sigma_px: 0.0,
            read_noise: 0.0,
            shot_noise: 0.0,
            seed: 0,
        }
    }

    /// Only a distorting lens (radial `k1`), everything else as the map's flight: the
    /// distorted twin of each test view.
    pub fn lens_only(k1: f64) -> Self {
        SecondFlight {
            k1,
            ..SecondFlight::same_flight()
        }
    }

    /// Checks every field.
    pub fn validate(&self) -> Result<(), SynthError> {
        let bad =
            |field: &'static str, reason: String| Err(SynthError::InvalidConfig { field, reason });
        if !self.sun_azimuth_shift_deg.is_finite() {
            return bad(
                "second_flight.sun_azimuth_shift_deg",
                "must be finite".into(),
            );
        }
        if let Some(el) = self.sun_elevation_deg
            && !(el > 5.0 && el <= 90.0)
        {
            return bad(
                "second_flight.sun_elevation_deg",
                format!("must be in (5, 90], got {el}"),
            );
        }
        if !(self.exposure_ev.is_finite() && self.exposure_ev.abs() <= 8.0) {
            return bad(
                "second_flight.exposure_ev",
                format!("must be within ±8 stops, got {}", self.exposure_ev),
            );
        }
        if !self.white_balance.iter().all(|g| g.is_finite() && *g > 0.0) {
            return bad(
                "second_flight.white_balance",
                format!("gains must be positive, got {:?}", self.white_balance),
            );
        }
        if !(self.k1.is_finite()
            && self.k1.abs() <= 0.5
            && self.k2.is_finite()
            && self.k2.abs() <= 0.5)
        {
            return bad(
                "second_flight.k1",
                format!(
                    "k1 and k2 must be within ±0.5, got {} and {}",
                    self.k1, self.k2
                ),
            );
        }
        for (field, v) in [
            ("second_flight.blur_sigma_px", self.blur_sigma_px),
            ("second_flight.read_noise", self.read_noise),
            ("second_flight.shot_noise", self.shot_noise),
        ] {
            if !(v.is_finite() && (0.0..=5.0).contains(&v)) {
                return bad(field, format!("must be in [0, 5], got {v}"));
            }
        }
        Ok(())
    }

    fn distortion(&self) -> Distortion {
        Distortion {
            k1: self.k1,
            k2: self.k2,
            ..Distortion::NONE
        }
    }
}

/// The world under the second flight's sun and the test views of `config`'s survey as the
/// flight sees them: same poses, the flight's lens, image paths `images/frame_NNNNN.png`
/// relative to the flight's folder.
pub fn second_flight_frames(
    config: &SynthConfig,
    flight: &SecondFlight,
) -> Result<(World, Vec<Frame>), SynthError> {
    flight.validate()?;
    let (world, plan) = generate(config)?;
    let (az, el) = flight_sun(config, flight);
    let world = world.with_sun(az, el)?;
    let distortion = flight.distortion();
    let frames = plan
        .frames
        .into_iter()
        .filter(|f| f.split == Split::Test)
        .map(|mut f| {
            f.camera.distortion = distortion;
            f.depth_path = None;
            f
        })
        .collect::<Vec<_>>();
    for f in &frames {
        f.camera.validate().map_err(|e| SynthError::InvalidConfig {
            field: "second_flight.k1",
            reason: format!("the lens is not valid for {}: {e}", f.image_path.display()),
        })?;
    }
    Ok((world, frames))
}

/// Renders one second-flight view of `world` (from [`second_flight_frames`], which sets the
/// flight's sun): exposure and white balance in the renderer, then blur and noise on the
/// display-encoded image (8-bit quantisation happens when it is written).
pub fn render_second_flight(
    world: &World,
    config: &SynthConfig,
    flight: &SecondFlight,
    frame: &Frame,
    index: usize,
) -> Image<f32> {
    let mut opts = config.render.clone();
    opts.exposure *= 2f32.powf(flight.exposure_ev);
    for k in 0..3 {
        opts.white_balance[k] *= flight.white_balance[k];
    }
    let rgb = world
        .render(&frame.camera, &frame.cam_from_world, &opts)
        .rgb;
    let blurred = rgb.gaussian_blur(flight.blur_sigma_px);
    add_noise(blurred, flight, index)
}

fn add_noise(mut img: Image<f32>, flight: &SecondFlight, index: usize) -> Image<f32> {
    if flight.read_noise <= 0.0 && flight.shot_noise <= 0.0 {
        return img;
    }
    let mut rng = Rng::new(flight.seed).fork(0xF11E_0000 + index as u64);
    for v in img.data_mut() {
        let sd = (flight.read_noise.powi(2) + flight.shot_noise.powi(2) * v.max(0.0)).sqrt();
        *v = (*v + sd * rng.normal() as f32).clamp(0.0, 1.0);
    }
    img
}

/// The sun of the second flight for a world generated with `config`.
fn flight_sun(config: &SynthConfig, flight: &SecondFlight) -> (f64, f64) {
    (
        config.world.sun_azimuth_deg + flight.sun_azimuth_shift_deg,
        flight
            .sun_elevation_deg
            .unwrap_or(config.world.sun_elevation_deg),
    )
}

/// Name of the hloc query list a second flight writes beside its `transforms.json`.
pub const QUERY_LIST: &str = "queries_with_intrinsics.txt";

/// Renders the second flight of `config`'s test views into `out_dir`: `images/frame_NNNNN.png`,
/// `transforms.json` (test views only, ground-truth poses in the map's world frame, the lens as
/// `camera_model` OPENCV) and an hloc query list [`QUERY_LIST`] (`NAME OPENCV W H fx fy cx cy k1
/// k2 p1 p2`, names relative to `out_dir`) for `matloc localize --queries`.
pub fn synthesize_second_flight(
    config: &SynthConfig,
    flight: &SecondFlight,
    out_dir: &Path,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<Dataset, SynthError> {
    let (world, frames) = second_flight_frames(config, flight)?;
    let images = out_dir.join("images");
    std::fs::create_dir_all(&images).map_err(|source| SynthError::Io {
        path: images.clone(),
        source,
    })?;
    let total = frames.len();
    let done = AtomicUsize::new(0);
    progress(Progress { done: 0, total });
    frames
        .par_iter()
        .enumerate()
        .try_for_each(|(i, frame)| -> Result<(), SynthError> {
            let rgb = render_second_flight(&world, config, flight, frame, i);
            write_png(&rgb, &out_dir.join(&frame.image_path))?;
            let d = done.fetch_add(1, Ordering::Relaxed) + 1;
            progress(Progress { done: d, total });
            Ok(())
        })?;
    let list: String = frames.iter().map(query_line).collect();
    let list_path = out_dir.join(QUERY_LIST);
    matloc_core::fsutil::write_atomic(&list_path, list.as_bytes()).map_err(|source| {
        SynthError::Io {
            path: list_path.clone(),
            source,
        }
    })?;
    let dataset = Dataset {
        root: out_dir.to_path_buf(),
        frames,
        points: None,
        metadata: matloc_data::dataset::SceneMetadata {
            generator: Some("matloc-synth second flight".into()),
            ..super::write::metadata(config, &world)
        },
    };
    matloc_data::nerfstudio::write_nerfstudio(&dataset, &out_dir.join("transforms.json"))
        .map_err(|e| SynthError::Dataset(Box::new(e)))?;
    Ok(dataset)
}

/// One hloc query-list line (COLMAP OPENCV parameter order).
fn query_line(frame: &Frame) -> String {
    let c = &frame.camera;
    let d = &c.distortion;
    format!(
        "{} OPENCV {} {} {} {} {} {} {} {} {} {}\n",
        path_name(&frame.image_path),
        c.width,
        c.height,
        c.fx,
        c.fy,
        c.cx,
        c.cy,
        d.k1,
        d.k2,
        d.p1,
        d.p2
    )
}

fn path_name(p: &Path) -> String {
    PathBuf::from(p).to_string_lossy().replace('\\', "/")
}

/// A viewpoint the survey never flew, made from the view at `cam_from_world`: turned by
/// `yaw_deg` about the vertical through the terrain point it looks at (the terrain height
/// under the camera), brought `closer` of the way to that point, then pitched `tilt_deg`
/// about its own x axis (positive: towards the horizon). `None` when the view does not look
/// down.
pub fn turned_view(
    world: &World,
    cam_from_world: &matloc_core::Pose,
    yaw_deg: f64,
    closer: f64,
    tilt_deg: f64,
) -> Option<matloc_core::Pose> {
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    let world_from_cam = cam_from_world.inverse();
    let c = world_from_cam.translation.vector;
    let dir = world_from_cam.rotation * Vector3::z();
    if dir.z >= -1e-3 {
        return None;
    }
    let ground = world.height_at(c.x, c.y);
    let look = c + dir * ((ground - c.z) / dir.z);
    let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_deg.to_radians());
    let moved = look + (turn * (c - look)) * (1.0 - closer);
    let tilt = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), tilt_deg.to_radians());
    Some(
        matloc_core::Pose::from_parts(
            Translation3::from(moved),
            turn * world_from_cam.rotation * tilt,
        )
        .inverse(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_seeded_and_bounded() {
        let img = Image::from_vec(8, 8, 3, vec![0.5; 192]).unwrap();
        let f = SecondFlight::default();
        let a = add_noise(img.clone(), &f, 3);
        assert_eq!(a, add_noise(img.clone(), &f, 3));
        assert_ne!(a, add_noise(img.clone(), &f, 4));
        let sd = (a.data().iter().map(|v| (v - 0.5).powi(2)).sum::<f32>() / 192.0).sqrt();
        let want = (f.read_noise.powi(2) + f.shot_noise.powi(2) * 0.5).sqrt();
        assert!((sd / want - 1.0).abs() < 0.3, "{sd} vs {want}");
        assert_eq!(add_noise(img.clone(), &SecondFlight::same_flight(), 3), img);
    }

    #[test]
    fn the_same_flight_renders_the_test_views_unchanged() {
        let config = crate::SynthConfig::preset("tiny").unwrap();
        let (world, plan) = generate(&config).unwrap();
        let (w2, frames) = second_flight_frames(&config, &SecondFlight::same_flight()).unwrap();
        let test: Vec<&Frame> = plan
            .frames
            .iter()
            .filter(|f| f.split == Split::Test)
            .collect();
        assert_eq!(frames.len(), test.len());
        let (f, t) = (&frames[0], test[0]);
        assert_eq!(f.cam_from_world, t.cam_from_world);
        let a = render_second_flight(&w2, &config, &SecondFlight::same_flight(), f, 0);
        let b = world
            .render(&t.camera, &t.cam_from_world, &config.render)
            .rgb;
        assert_eq!(a, b);
    }

    #[test]
    fn bad_fields_are_named() {
        let f = SecondFlight {
            sun_elevation_deg: Some(2.0),
            ..SecondFlight::default()
        };
        let e = f.validate().unwrap_err().to_string();
        assert!(e.contains("sun_elevation_deg"), "{e}");
        let f = SecondFlight {
            k1: f64::NAN,
            ..SecondFlight::default()
        };
        assert!(f.validate().unwrap_err().to_string().contains("k1"));
    }
}
