//! The ray-casting renderer: RGB with sun + sky lighting and hard shadows, and z-depth.

use matloc_core::{Camera, Image, Pose};
use nalgebra::{Point2, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::noise::Rgb;
use super::rng::{hash3, unit};
use super::world::World;

/// Renderer settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RenderOptions {
    /// Anti-aliasing: pixels on a silhouette or shadow edge are re-rendered with an `n × n`
    /// stratified, jittered grid of rays (1 disables). Texture detail is prefiltered instead.
    pub edge_samples: u32,
    /// Cast shadow rays towards the sun.
    pub shadows: bool,
    /// Sun irradiance relative to the sky's (sets the shadow contrast).
    pub sun_strength: f32,
    /// Overall exposure multiplier applied before the display transfer curve.
    pub exposure: f32,
    /// Per-channel (R, G, B) gains in linear light: the camera's white balance relative to the
    /// map's flight (1, 1, 1).
    pub white_balance: [f32; 3],
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            edge_samples: 2,
            shadows: true,
            sun_strength: 4.0,
            exposure: 1.0,
            white_balance: [1.0; 3],
        }
    }
}

/// One rendered view.
#[derive(Clone, Debug, PartialEq)]
pub struct Rendered {
    /// RGB, 3 channels in `[0, 1]`, display-encoded (what the PNG stores, divided by 255).
    pub rgb: Image<f32>,
    /// Z-depth along the camera's optical axis in metres, 1 channel; 0 where the ray sees sky.
    pub depth: Image<f32>,
}

/// Key that changes across silhouettes and shadow boundaries; pixels whose key differs from a
/// neighbour's get supersampled.
const SKY_KEY: u64 = u64::MAX;

struct Sample {
    rgb: Rgb,
    /// Distance along the unit ray, 0 for sky.
    t: f64,
    key: u64,
}

impl World {
    fn sky(&self, d: &Vector3<f64>) -> Rgb {
        let h = d.z.clamp(0.0, 1.0) as f32;
        let horizon = [0.78f32, 0.84, 0.90];
        let zenith = [0.36f32, 0.55, 0.85];
        let mut c = [0.0; 3];
        for k in 0..3 {
            c[k] = horizon[k] + (zenith[k] - horizon[k]) * h.sqrt();
        }
        c
    }

    /// Shades one ray. `pix_angle` is the angular size of a pixel (radians) for prefiltering.
    fn shade(
        &self,
        o: &Vector3<f64>,
        d: &Vector3<f64>,
        pix_angle: f64,
        opts: &RenderOptions,
    ) -> Sample {
        let Some(hit) = self.trace(o, d) else {
            return Sample {
                rgb: self.sky(d),
                t: 0.0,
                key: SKY_KEY,
            };
        };
        let p = o + d * hit.t;
        let n = hit.normal;
        let cos_v = n.dot(d).abs().max(0.2);
        let fw = (hit.t * pix_angle / cos_v) as f32;
        let albedo = self.albedo(&p, &n, hit.prim, fw);
        let ndl = n.dot(&self.sun);
        let mut lit = ndl > 0.0;
        if lit && opts.shadows {
            let start = p + n * (1e-4 * (1.0 + hit.t));
            // Nothing stands above `top_z`, so the shadow ray can stop there.
            let t1 = ((self.top_z + 0.01 - start.z) / self.sun.z).max(0.0);
            if self.occluded(&start, &self.sun, 1e-6, t1) {
                lit = false;
            }
        }
        let sun = if lit {
            opts.sun_strength * ndl as f32
        } else {
            0.0
        };
        // Hemispherical sky light: full from above, less on walls, little from below.
        let sky = 0.55 + 0.45 * n.z as f32;
        let sun_col = [1.0f32, 0.96, 0.88];
        let sky_col = [0.55f32, 0.65, 0.85];
        let scale = 0.3 * opts.exposure;
        let mut rgb = [0.0f32; 3];
        for k in 0..3 {
            let lin =
                albedo[k] * (sun * sun_col[k] + sky * sky_col[k]) * scale * opts.white_balance[k];
            // Soft shoulder instead of a hard clip keeps bright roofs textured.
            let mapped = lin / (1.0 + 0.25 * lin);
            rgb[k] = mapped.clamp(0.0, 1.0).powf(1.0 / 2.2);
        }
        let key = (hit.prim as u64) << 1 | u64::from(lit && ndl > 0.0);
        Sample { rgb, t: hit.t, key }
    }

    /// Renders RGB and z-depth for `camera` at `cam_from_world` (rayon over rows).
    ///
    /// Pixel centres are at `(col + 0.5, row + 0.5)`; depth is that centre ray's z-depth, so a
    /// depth pixel lifted with [`Camera::unproject`] lands exactly on the surface. Pixels whose
    /// ray cannot be undistorted render as sky with depth 0; an invalid camera or a non-finite
    /// pose gives an all-sky image.
    pub fn render(&self, camera: &Camera, cam_from_world: &Pose, opts: &RenderOptions) -> Rendered {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let finite = cam_from_world
            .to_homogeneous()
            .iter()
            .all(|v| v.is_finite())
            && camera.validate().is_ok();
        if w == 0 || h == 0 || !finite {
            // Nothing sensible to trace: an all-sky image with no depth.
            let sky = self.sky(&Vector3::z());
            return Rendered {
                rgb: Image::from_vec(w, h, 3, sky.repeat(w * h)).expect("buffer sized w*h*3"),
                depth: Image::new(w, h, 1),
            };
        }
        let world_from_cam = cam_from_world.inverse();
        let o = world_from_cam.translation.vector;
        let rot = world_from_cam.rotation;
        let pix_angle = 1.0 / camera.fx.max(camera.fy);
        let ray = |x: f64, y: f64| -> Option<(Vector3<f64>, f64)> {
            let b = camera.unproject(Point2::new(x, y))?;
            Some((rot * b, b.z))
        };

        let mut rgb = vec![0.0f32; w * h * 3];
        let mut depth = vec![0.0f32; w * h];
        let mut keys = vec![SKY_KEY; w * h];
        rgb.par_chunks_mut(w * 3)
            .zip(depth.par_chunks_mut(w))
            .zip(keys.par_chunks_mut(w))
            .enumerate()
            .for_each(|(row, ((rgb_row, depth_row), key_row))| {
                for col in 0..w {
                    let (c, t_z, key) = match ray(col as f64 + 0.5, row as f64 + 0.5) {
                        Some((d, bz)) => {
                            let s = self.shade(&o, &d, pix_angle, opts);
                            (s.rgb, s.t * bz, s.key)
                        }
                        None => (self.sky(&Vector3::z()), 0.0, SKY_KEY),
                    };
                    rgb_row[col * 3..col * 3 + 3].copy_from_slice(&c);
                    depth_row[col] = t_z as f32;
                    key_row[col] = key;
                }
            });

        let n = opts.edge_samples.max(1) as usize;
        if n > 1 {
            let keys = &keys;
            let depth_ref = &depth;
            let edge = |x: usize, y: usize| {
                let k = keys[y * w + x];
                let z = depth_ref[y * w + x];
                let mut e = false;
                for (dx, dy) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                    let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                    if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                        continue;
                    }
                    let j = ny as usize * w + nx as usize;
                    // Creases within one primitive (roof ridges, box corners) also alias.
                    if keys[j] != k || (depth_ref[j] - z).abs() > 0.05 * z.max(1e-3) {
                        e = true;
                    }
                }
                e
            };
            let seed = self.noise_seed ^ 0xA5A5;
            rgb.par_chunks_mut(w * 3)
                .enumerate()
                .for_each(|(row, rgb_row)| {
                    for col in 0..w {
                        if !edge(col, row) {
                            continue;
                        }
                        let mut acc = [0.0f32; 3];
                        let mut count = 0.0f32;
                        for sy in 0..n {
                            for sx in 0..n {
                                // Deterministic jitter inside each stratum.
                                let hsh = hash3(col as i32, row as i32, (sy * n + sx) as i32, seed);
                                let jx = unit(hsh) as f64;
                                let jy = unit(hsh.rotate_left(16) ^ 0x9E37_79B9) as f64;
                                let x = col as f64 + (sx as f64 + jx) / n as f64;
                                let y = row as f64 + (sy as f64 + jy) / n as f64;
                                let c = match ray(x, y) {
                                    Some((d, _)) => self.shade(&o, &d, pix_angle, opts).rgb,
                                    None => self.sky(&Vector3::z()),
                                };
                                for k in 0..3 {
                                    acc[k] += c[k];
                                }
                                count += 1.0;
                            }
                        }
                        for k in 0..3 {
                            rgb_row[col * 3 + k] = acc[k] / count;
                        }
                    }
                });
        }

        Rendered {
            rgb: Image::from_vec(w, h, 3, rgb).expect("buffer sized w*h*3"),
            depth: Image::from_vec(w, h, 1, depth).expect("buffer sized w*h"),
        }
    }
}
