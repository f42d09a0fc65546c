//! The stored structure: triangulated points and, per training image, the keypoints that
//! observe them (position, descriptor, point) and the image's camera and gray values (for
//! patch alignment), in one safetensors file.

use std::collections::HashMap;
use std::path::Path;

use matloc_core::Camera;
use matloc_core::pose::{Pose, camera_center, viewing_direction};
use matloc_keypoints::{Descriptor, GradientDescriptor};
use matloc_surface::triangulate::TrackedPoints;
use nalgebra::{Point3, Quaternion, Translation3, UnitQuaternion, Vector3};
use safetensors::{Dtype, SafeTensors, tensor::TensorView};

use crate::error::StructureError;

/// Format tag in the file's metadata: `/2` may carry the training images' cameras and gray
/// values for patch alignment and the observations' gradient descriptors; `/1` files
/// (without either) still load.
pub const STRUCTURE_FORMAT: &str = "matloc-structure/2";

/// The earlier format tag, read as `/2` without appearance.
const STRUCTURE_FORMAT_V1: &str = "matloc-structure/1";

/// One training image: its pose and the keypoints that observe a point.
#[derive(Clone, Debug, PartialEq)]
pub struct StructureImage {
    /// Dataset frame index.
    pub frame: u32,
    /// World → camera pose.
    pub cam_from_world: Pose,
    /// Per observation: the point it observes (index into [`StructureMap::points`]).
    pub point: Vec<u32>,
    /// Per observation: the keypoint's binary descriptor.
    pub descriptor: Vec<Descriptor>,
    /// Per observation: the keypoint's gradient-histogram descriptor (empty in maps built
    /// without them).
    pub gradient: Vec<GradientDescriptor>,
    /// Per observation: the keypoint's pixel at the detection size.
    pub pixel: Vec<[f32; 2]>,
    /// The image's camera and gray values at the detection size, for patch alignment
    /// (`None` in maps that did not keep them).
    pub appearance: Option<ImageAppearance>,
}

/// A training image as patch alignment reads it.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageAppearance {
    /// The camera at the detection size (the observations' pixels are in its image).
    pub camera: Camera,
    /// Gray values, 8-bit, row-major, `camera.width × camera.height`.
    pub gray: Vec<u8>,
}

impl StructureImage {
    /// Camera centre, world frame.
    pub fn center(&self) -> Point3<f64> {
        camera_center(&self.cam_from_world)
    }

    /// Unit viewing direction, world frame.
    pub fn viewing_direction(&self) -> Vector3<f64> {
        viewing_direction(&self.cam_from_world)
    }
}

/// How far the structure's points project from the keypoints that observe them, pixels.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ReprojectionStats {
    /// Observations measured.
    pub observations: usize,
    /// Mean error.
    pub mean_px: f64,
    /// Median error.
    pub median_px: f64,
    /// 95th percentile.
    pub p95_px: f64,
    /// Largest error.
    pub max_px: f64,
}

/// Triangulated points and the training images' observations of them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StructureMap {
    points: Vec<Point3<f64>>,
    images: Vec<StructureImage>,
    /// Per point, its observations as (image, observation), in CSR form: `track_start[p]
    /// ..track_start[p + 1]` indexes `track`.
    track_start: Vec<u32>,
    track: Vec<(u32, u32)>,
}

impl StructureMap {
    /// Keeps, per triangulated image, the keypoints that observe a point; `pose_of(frame)`
    /// gives a dataset frame's `cam_from_world`. Images without an observation are left out.
    pub fn from_tracks(tracks: &TrackedPoints, pose_of: impl Fn(usize) -> Pose) -> StructureMap {
        let mut per_image: Vec<Vec<(u32, u32)>> = vec![Vec::new(); tracks.images.len()];
        for (p, obs) in tracks.observations.iter().enumerate() {
            for &(img, k) in obs {
                per_image[img as usize].push((k, p as u32));
            }
        }
        let mut images = Vec::new();
        for (im, mut obs) in tracks.images.iter().zip(per_image) {
            if obs.is_empty() {
                continue;
            }
            obs.sort_unstable();
            images.push(StructureImage {
                frame: im.frame as u32,
                cam_from_world: pose_of(im.frame),
                point: obs.iter().map(|&(_, p)| p).collect(),
                descriptor: obs
                    .iter()
                    .map(|&(k, _)| im.descriptors[k as usize])
                    .collect(),
                gradient: if im.gradients.len() == im.descriptors.len() {
                    obs.iter().map(|&(k, _)| im.gradients[k as usize]).collect()
                } else {
                    Vec::new()
                },
                pixel: obs
                    .iter()
                    .map(|&(k, _)| {
                        let px = im.pixels[k as usize];
                        [px.x as f32, px.y as f32]
                    })
                    .collect(),
                appearance: (im.gray.len() == (im.camera.width * im.camera.height) as usize).then(
                    || ImageAppearance {
                        camera: im.camera,
                        gray: im.gray.clone(),
                    },
                ),
            });
        }
        StructureMap::indexed(tracks.xyz.clone(), images)
    }

    /// A structure from its parts; every observation must name an existing point and every
    /// image have as many descriptors and pixels as observations (and as many gradient
    /// descriptors, or none).
    pub fn new(
        points: Vec<Point3<f64>>,
        images: Vec<StructureImage>,
    ) -> Result<StructureMap, StructureError> {
        let bad = |reason: String| StructureError::Format {
            path: Default::default(),
            reason,
        };
        for (i, im) in images.iter().enumerate() {
            if im.descriptor.len() != im.point.len()
                || im.pixel.len() != im.point.len()
                || !(im.gradient.is_empty() || im.gradient.len() == im.point.len())
            {
                return Err(bad(format!(
                    "image {i}: {} points, {} descriptors, {} gradient descriptors, {} pixels",
                    im.point.len(),
                    im.descriptor.len(),
                    im.gradient.len(),
                    im.pixel.len()
                )));
            }
            if let Some(&p) = im.point.iter().find(|&&p| p as usize >= points.len()) {
                return Err(bad(format!(
                    "image {i} names point {p} of {}",
                    points.len()
                )));
            }
        }
        Ok(StructureMap::indexed(points, images))
    }

    /// The map with its point → observations index (observations must name existing points).
    fn indexed(points: Vec<Point3<f64>>, images: Vec<StructureImage>) -> StructureMap {
        let mut count = vec![0u32; points.len() + 1];
        for im in &images {
            for &p in &im.point {
                count[p as usize + 1] += 1;
            }
        }
        for k in 1..count.len() {
            count[k] += count[k - 1];
        }
        let mut fill = count.clone();
        let mut track = vec![(0u32, 0u32); *count.last().unwrap_or(&0) as usize];
        for (i, im) in images.iter().enumerate() {
            for (o, &p) in im.point.iter().enumerate() {
                track[fill[p as usize] as usize] = (i as u32, o as u32);
                fill[p as usize] += 1;
            }
        }
        StructureMap {
            points,
            images,
            track_start: count,
            track,
        }
    }

    /// The observations of point `p` as (image, observation in it).
    pub fn track(&self, p: usize) -> &[(u32, u32)] {
        match (self.track_start.get(p), self.track_start.get(p + 1)) {
            (Some(&a), Some(&b)) => &self.track[a as usize..b as usize],
            _ => &[],
        }
    }

    /// Points, world frame.
    pub fn points(&self) -> &[Point3<f64>] {
        &self.points
    }

    /// Images with observations.
    pub fn images(&self) -> &[StructureImage] {
        &self.images
    }

    /// The images looking within `max_view_angle_deg` of the viewing direction of
    /// `cam_from_world` (indices): a pose none of them looks like is one the survey never
    /// saw, so nothing in the map can confirm it.
    pub fn images_looking_like(
        &self,
        cam_from_world: &matloc_core::Pose,
        max_view_angle_deg: f64,
    ) -> impl Iterator<Item = usize> + '_ {
        let dir = matloc_core::pose::viewing_direction(cam_from_world);
        let cos_max = max_view_angle_deg.to_radians().cos();
        self.images
            .iter()
            .enumerate()
            .filter(move |(_, im)| im.viewing_direction().dot(&dir) >= cos_max)
            .map(|(i, _)| i)
    }

    /// Reprojection errors of the points in the images that observe them, at each image's
    /// detection size (the camera it keeps for patch alignment): how well the triangulated
    /// points fit the training poses. `None` when no image keeps its camera (maps from before
    /// the gray values were stored) or none of its observations projects.
    pub fn reprojection_errors(&self) -> Option<ReprojectionStats> {
        let mut errors: Vec<f64> = self
            .images
            .iter()
            .filter_map(|im| Some((im, im.appearance.as_ref()?.camera)))
            .flat_map(|(im, camera)| {
                im.point.iter().zip(&im.pixel).filter_map(move |(&p, px)| {
                    let x = self.points.get(p as usize)?;
                    let u = camera.project_world(&im.cam_from_world, x)?;
                    let e = ((u.x - f64::from(px[0])).powi(2) + (u.y - f64::from(px[1])).powi(2))
                        .sqrt();
                    e.is_finite().then_some(e)
                })
            })
            .collect();
        if errors.is_empty() {
            return None;
        }
        errors.sort_by(f64::total_cmp);
        let at = |q: f64| errors[((errors.len() - 1) as f64 * q).round() as usize];
        Some(ReprojectionStats {
            observations: errors.len(),
            mean_px: errors.iter().sum::<f64>() / errors.len() as f64,
            median_px: at(0.5),
            p95_px: at(0.95),
            max_px: at(1.0),
        })
    }

    /// Whether every image's observations carry gradient descriptors (and there is one).
    pub fn has_gradients(&self) -> bool {
        !self.images.is_empty()
            && self
                .images
                .iter()
                .all(|im| im.gradient.len() == im.point.len())
            && self.images.iter().any(|im| !im.gradient.is_empty())
    }

    /// Observations over all images.
    pub fn observations(&self) -> usize {
        self.images.iter().map(|i| i.point.len()).sum()
    }

    /// The safetensors bytes: `points` f64 [P, 3], `image_frame` u32 [I], `image_pose` f64
    /// [I, 7] (cam_from_world as qw qx qy qz tx ty tz), `image_start` u32 [I + 1] (offsets
    /// into the observations), `obs_point` u32 [O], `obs_descriptor` u8 [O, 32],
    /// `obs_pixel` f32 [O, 2]; when every image has gradient descriptors, `obs_gradient` u8
    /// [O, 128]; when every image has its appearance, `image_camera` f64
    /// [I, 11] (width, height, fx, fy, cx, cy, k1, k2, p1, p2, k3), `image_gray_start` u64
    /// [I + 1] and `image_gray` u8 [G] (row-major gray values, image after image).
    pub fn to_bytes(&self) -> Result<Vec<u8>, StructureError> {
        let fmt = |reason: String| StructureError::Format {
            path: Default::default(),
            reason,
        };
        let (p, i) = (self.points.len(), self.images.len());
        let o = self.observations();
        let mut points = Vec::with_capacity(p * 24);
        for x in &self.points {
            for v in x.iter() {
                points.extend_from_slice(&v.to_le_bytes());
            }
        }
        let (mut frame, mut pose, mut start) = (Vec::new(), Vec::new(), Vec::new());
        let (mut obs_point, mut obs_desc, mut obs_px) = (Vec::new(), Vec::new(), Vec::new());
        let mut offset = 0u32;
        for im in &self.images {
            frame.extend_from_slice(&im.frame.to_le_bytes());
            let q = im.cam_from_world.rotation.quaternion();
            let t = im.cam_from_world.translation.vector;
            for v in [q.w, q.i, q.j, q.k, t.x, t.y, t.z] {
                pose.extend_from_slice(&v.to_le_bytes());
            }
            start.extend_from_slice(&offset.to_le_bytes());
            offset += im.point.len() as u32;
            for ((pt, d), px) in im.point.iter().zip(&im.descriptor).zip(&im.pixel) {
                obs_point.extend_from_slice(&pt.to_le_bytes());
                for w in d {
                    obs_desc.extend_from_slice(&w.to_le_bytes());
                }
                for v in px {
                    obs_px.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        start.extend_from_slice(&offset.to_le_bytes());
        let cols: [(&str, Dtype, Vec<usize>, &[u8]); 7] = [
            ("points", Dtype::F64, vec![p, 3], &points),
            ("image_frame", Dtype::U32, vec![i], &frame),
            ("image_pose", Dtype::F64, vec![i, 7], &pose),
            ("image_start", Dtype::U32, vec![i + 1], &start),
            ("obs_point", Dtype::U32, vec![o], &obs_point),
            ("obs_descriptor", Dtype::U8, vec![o, 32], &obs_desc),
            ("obs_pixel", Dtype::F32, vec![o, 2], &obs_px),
        ];
        let (mut cams, mut gray_start, mut gray) = (Vec::new(), Vec::new(), Vec::new());
        let appearance: Option<Vec<&ImageAppearance>> = self
            .images
            .iter()
            .map(|im| im.appearance.as_ref())
            .collect();
        let mut cols = cols.to_vec();
        let obs_gradient: Vec<u8> = if self.has_gradients() {
            self.images
                .iter()
                .flat_map(|im| im.gradient.iter().flatten().copied())
                .collect()
        } else {
            Vec::new()
        };
        if self.has_gradients() {
            cols.push(("obs_gradient", Dtype::U8, vec![o, 128], &obs_gradient));
        }
        if let Some(apps) = appearance.filter(|a| !a.is_empty()) {
            for app in apps {
                let c = &app.camera;
                let d = &c.distortion;
                let row = [
                    f64::from(c.width),
                    f64::from(c.height),
                    c.fx,
                    c.fy,
                    c.cx,
                    c.cy,
                    d.k1,
                    d.k2,
                    d.p1,
                    d.p2,
                    d.k3,
                ];
                for v in row {
                    cams.extend_from_slice(&v.to_le_bytes());
                }
                gray_start.extend_from_slice(&(gray.len() as u64).to_le_bytes());
                gray.extend_from_slice(&app.gray);
            }
            gray_start.extend_from_slice(&(gray.len() as u64).to_le_bytes());
            cols.push(("image_camera", Dtype::F64, vec![i, 11], &cams));
            cols.push(("image_gray_start", Dtype::U64, vec![i + 1], &gray_start));
            cols.push(("image_gray", Dtype::U8, vec![gray.len()], &gray));
        }
        let mut views = Vec::with_capacity(cols.len());
        for (name, dtype, shape, bytes) in cols {
            views.push((
                name.to_string(),
                TensorView::new(dtype, shape, bytes).map_err(|e| fmt(format!("{name}: {e}")))?,
            ));
        }
        let meta = HashMap::from([("format".to_string(), STRUCTURE_FORMAT.to_string())]);
        safetensors::serialize(views, Some(meta)).map_err(|e| fmt(e.to_string()))
    }

    /// Parses [`StructureMap::to_bytes`] output, checking every shape, offset, index and
    /// value; `path` names the file in errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<StructureMap, StructureError> {
        let bad = |reason: String| StructureError::Format {
            path: path.to_path_buf(),
            reason,
        };
        let (_, meta) = SafeTensors::read_metadata(bytes).map_err(|e| bad(e.to_string()))?;
        let tag = meta.metadata().as_ref().and_then(|m| m.get("format"));
        let v1 = tag.map(String::as_str) == Some(STRUCTURE_FORMAT_V1);
        if tag.map(String::as_str) != Some(STRUCTURE_FORMAT) && !v1 {
            return Err(bad(format!(
                "metadata `format` is {tag:?}, expected {STRUCTURE_FORMAT:?} or \
                 {STRUCTURE_FORMAT_V1:?}"
            )));
        }
        let st = SafeTensors::deserialize(bytes).map_err(|e| bad(e.to_string()))?;
        let column = |name: &str, dtype: Dtype, width: Option<usize>| {
            let t = st
                .tensor(name)
                .map_err(|e| bad(format!("tensor `{name}`: {e}")))?;
            if t.dtype() != dtype {
                return Err(bad(format!(
                    "tensor `{name}` is {:?}, expected {dtype:?}",
                    t.dtype()
                )));
            }
            let shape = t.shape().to_vec();
            let ok = match width {
                None => shape.len() == 1,
                Some(w) => shape.len() == 2 && shape[1] == w,
            };
            if !ok {
                return Err(bad(format!(
                    "tensor `{name}` has shape {shape:?}, expected [n{}]",
                    width.map_or(String::new(), |w| format!(", {w}"))
                )));
            }
            Ok((shape[0], t.data().to_vec()))
        };
        let f64s = |b: &[u8]| -> Vec<f64> {
            b.chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect()
        };
        let u32s = |b: &[u8]| -> Vec<u32> {
            b.chunks_exact(4)
                .map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect()
        };
        let (p, raw) = column("points", Dtype::F64, Some(3))?;
        let xyz = f64s(&raw);
        if let Some(k) = xyz.iter().position(|v| !v.is_finite()) {
            return Err(bad(format!(
                "tensor `points`: point {} is not finite",
                k / 3
            )));
        }
        let points: Vec<Point3<f64>> = xyz
            .chunks_exact(3)
            .map(|c| Point3::new(c[0], c[1], c[2]))
            .collect();
        let (i, raw) = column("image_frame", Dtype::U32, None)?;
        let frames = u32s(&raw);
        let (ni, raw) = column("image_pose", Dtype::F64, Some(7))?;
        if ni != i {
            return Err(bad(format!(
                "tensor `image_pose` has {ni} rows for {i} images"
            )));
        }
        let poses = f64s(&raw);
        let (ns, raw) = column("image_start", Dtype::U32, None)?;
        if ns != i + 1 {
            return Err(bad(format!(
                "tensor `image_start` has {ns} entries for {i} images (expected {})",
                i + 1
            )));
        }
        let start = u32s(&raw);
        let (o, raw) = column("obs_point", Dtype::U32, None)?;
        let obs_point = u32s(&raw);
        let (nd, obs_desc) = column("obs_descriptor", Dtype::U8, Some(32))?;
        let (np, raw) = column("obs_pixel", Dtype::F32, Some(2))?;
        if nd != o || np != o {
            return Err(bad(format!(
                "observation tensors disagree: obs_point {o}, obs_descriptor {nd}, obs_pixel {np}"
            )));
        }
        let obs_px: Vec<f32> = raw
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
            .collect();
        if start.first() != Some(&0)
            || start.last().map(|&s| s as usize) != Some(o)
            || start.windows(2).any(|w| w[0] > w[1])
        {
            return Err(bad(format!(
                "tensor `image_start` must rise from 0 to {o} (the observations)"
            )));
        }
        if let Some(k) = obs_point.iter().position(|&q| q as usize >= p) {
            return Err(bad(format!(
                "tensor `obs_point`: observation {k} names point {} of {p}",
                obs_point[k]
            )));
        }
        if let Some(k) = obs_px.iter().position(|v| !v.is_finite()) {
            return Err(bad(format!(
                "tensor `obs_pixel`: observation {} is not finite",
                k / 2
            )));
        }
        let obs_gradient = if v1 || st.tensor("obs_gradient").is_err() {
            None
        } else {
            let (ng, raw) = column("obs_gradient", Dtype::U8, Some(128))?;
            if ng != o {
                return Err(bad(format!(
                    "tensor `obs_gradient` has {ng} rows for {o} observations"
                )));
            }
            Some(raw)
        };
        let appearance = if v1 || st.tensor("image_camera").is_err() {
            None
        } else {
            Some(read_appearance(&column, i, &bad)?)
        };
        let mut appearance = appearance.map(Vec::into_iter);
        let mut images = Vec::with_capacity(i);
        for k in 0..i {
            let v = &poses[7 * k..7 * k + 7];
            let q = Quaternion::new(v[0], v[1], v[2], v[3]);
            if v.iter().any(|x| !x.is_finite()) || (q.norm() - 1.0).abs() > 1e-6 {
                return Err(bad(format!(
                    "tensor `image_pose`: image {k} is not a finite unit quaternion and translation"
                )));
            }
            let pose = Pose::from_parts(
                Translation3::new(v[4], v[5], v[6]),
                UnitQuaternion::new_normalize(q),
            );
            let (a, b) = (start[k] as usize, start[k + 1] as usize);
            images.push(StructureImage {
                frame: frames[k],
                cam_from_world: pose,
                point: obs_point[a..b].to_vec(),
                descriptor: obs_desc[32 * a..32 * b]
                    .chunks_exact(32)
                    .map(|c| {
                        std::array::from_fn(|w| {
                            u64::from_le_bytes(c[8 * w..8 * w + 8].try_into().expect("8 bytes"))
                        })
                    })
                    .collect(),
                gradient: obs_gradient.as_ref().map_or_else(Vec::new, |g| {
                    g[128 * a..128 * b]
                        .chunks_exact(128)
                        .map(|c| c.try_into().expect("128 bytes"))
                        .collect()
                }),
                pixel: obs_px[2 * a..2 * b]
                    .chunks_exact(2)
                    .map(|c| [c[0], c[1]])
                    .collect(),
                appearance: appearance.as_mut().and_then(Iterator::next),
            });
        }
        Ok(StructureMap::indexed(points, images))
    }
}

/// Reads one tensor by name, dtype and row width: (rows, raw bytes).
type Column<'a> =
    dyn Fn(&str, Dtype, Option<usize>) -> Result<(usize, Vec<u8>), StructureError> + 'a;

/// The optional appearance tensors of a `/2` file: one camera and gray image per image.
fn read_appearance(
    column: &Column<'_>,
    images: usize,
    bad: &dyn Fn(String) -> StructureError,
) -> Result<Vec<ImageAppearance>, StructureError> {
    let (nc, raw) = column("image_camera", Dtype::F64, Some(11))?;
    let (ns, raw_start) = column("image_gray_start", Dtype::U64, None)?;
    let (ng, gray) = column("image_gray", Dtype::U8, None)?;
    if nc != images || ns != images + 1 {
        return Err(bad(format!(
            "tensors `image_camera` ({nc} rows) and `image_gray_start` ({ns} entries) do not \
             fit {images} images"
        )));
    }
    let cams: Vec<f64> = raw
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
        .collect();
    let start: Vec<u64> = raw_start
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
        .collect();
    let mut out = Vec::with_capacity(images);
    for k in 0..images {
        let v = &cams[11 * k..11 * k + 11];
        let size_ok = |x: f64| x.fract() == 0.0 && (1.0..=65_536.0).contains(&x);
        if !size_ok(v[0]) || !size_ok(v[1]) {
            return Err(bad(format!(
                "tensor `image_camera`: image {k} has size {} × {}",
                v[0], v[1]
            )));
        }
        let camera = Camera {
            width: v[0] as u32,
            height: v[1] as u32,
            fx: v[2],
            fy: v[3],
            cx: v[4],
            cy: v[5],
            distortion: matloc_core::Distortion {
                k1: v[6],
                k2: v[7],
                p1: v[8],
                p2: v[9],
                k3: v[10],
            },
        };
        camera
            .validate()
            .map_err(|e| bad(format!("tensor `image_camera`: image {k}: {e}")))?;
        let (a, b) = (start[k], start[k + 1]);
        let want = u64::from(camera.width) * u64::from(camera.height);
        if a > b || b > ng as u64 || b - a != want {
            return Err(bad(format!(
                "tensor `image_gray_start`: image {k} spans {a}..{b} of {ng} values, expected \
                 {want} ({} × {})",
                camera.width, camera.height
            )));
        }
        out.push(ImageAppearance {
            camera,
            gray: gray[a as usize..b as usize].to_vec(),
        });
    }
    if start.last() != Some(&(ng as u64)) {
        return Err(bad(format!(
            "tensor `image_gray` holds {ng} values, the images {}",
            start.last().copied().unwrap_or(0)
        )));
    }
    Ok(out)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use matloc_surface::triangulate::ImageKeypoints;
    use nalgebra::Point2;

    pub(crate) fn sample() -> StructureMap {
        let camera = Camera::pinhole(100, 80, 90.0, 90.0, 50.0, 40.0).unwrap();
        let kp = |n: usize, seed: u64| ImageKeypoints {
            frame: seed as usize,
            camera,
            pixels: (0..n)
                .map(|k| Point2::new(k as f64 + 0.25, seed as f64 + 0.5))
                .collect(),
            descriptors: (0..n)
                .map(|k| [k as u64, seed, u64::MAX - k as u64, 7])
                .collect(),
            gradients: (0..n)
                .map(|k| std::array::from_fn(|j| (j + k + seed as usize) as u8))
                .collect(),
            gray: (0..100 * 80)
                .map(|v| (v * 7 + seed as usize) as u8)
                .collect(),
        };
        let tracks = TrackedPoints {
            xyz: vec![Point3::new(1.0, 2.0, 3.0), Point3::new(-1.0, 0.5, 9.0)],
            observations: vec![vec![(0, 1), (1, 0)], vec![(0, 3), (2, 2)]],
            images: vec![kp(4, 3), kp(2, 5), kp(3, 8), kp(5, 9)],
        };
        StructureMap::from_tracks(&tracks, |f| {
            Pose::from_parts(
                Translation3::new(f as f64, 0.0, 1.0),
                UnitQuaternion::from_euler_angles(0.1 * f as f64, 0.0, 0.2),
            )
        })
    }

    #[test]
    fn images_looking_like_a_pose_are_those_within_the_angle() {
        let m = sample();
        // The images look 0.3, 0.5 and 0.8 rad about x away from a camera looking along +z.
        let like_first = m.images()[0].cam_from_world;
        let all: Vec<usize> = m.images_looking_like(&like_first, 37.0).collect();
        assert_eq!(all, vec![0, 1, 2]);
        let near: Vec<usize> = m.images_looking_like(&like_first, 12.0).collect();
        assert_eq!(near, vec![0, 1]);
        let turned = Pose::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.3 + std::f64::consts::PI, 0.0, 0.2),
        );
        assert_eq!(m.images_looking_like(&turned, 37.0).count(), 0);
    }

    #[test]
    fn tracks_become_per_image_observations_and_round_trip() {
        let m = sample();
        // The image without observations is left out.
        assert_eq!(m.images().len(), 3);
        assert_eq!(m.observations(), 4);
        let first = &m.images()[0];
        assert_eq!(first.frame, 3);
        assert_eq!(first.point, vec![0, 1]);
        assert_eq!(first.pixel[1], [3.25, 3.5]);
        let bytes = m.to_bytes().unwrap();
        let back = StructureMap::from_bytes(&bytes, Path::new("s.safetensors")).unwrap();
        assert_eq!(back.points(), m.points());
        for (a, b) in back.images().iter().zip(m.images()) {
            assert_eq!(a.frame, b.frame);
            assert_eq!(
                (&a.point, &a.descriptor, &a.gradient, &a.pixel),
                (&b.point, &b.descriptor, &b.gradient, &b.pixel)
            );
            assert!((a.cam_from_world.to_matrix() - b.cam_from_world.to_matrix()).norm() < 1e-12);
            assert!(a.appearance.is_some());
            assert_eq!(a.appearance, b.appearance);
        }
        // Point 0 is seen by images 0 and 1.
        assert_eq!(back.track(0), &[(0, 0), (1, 0)]);
        assert_eq!(back.track(7), &[]);
    }

    /// The file as the earlier format wrote it: no appearance tensors, tag `/1`.
    fn v1_bytes(m: &StructureMap) -> Vec<u8> {
        let mut m = m.clone();
        for im in &mut m.images {
            im.appearance = None;
        }
        let bytes = m.to_bytes().unwrap();
        let st = SafeTensors::deserialize(&bytes).unwrap();
        let views: Vec<(String, TensorView<'_>)> = st
            .tensors()
            .into_iter()
            .filter(|(n, _)| {
                !n.starts_with("image_gray") && n != "image_camera" && n != "obs_gradient"
            })
            .collect();
        let meta = HashMap::from([("format".to_string(), STRUCTURE_FORMAT_V1.to_string())]);
        safetensors::serialize(views, Some(meta)).unwrap()
    }

    #[test]
    fn earlier_files_load_without_appearance() {
        let m = sample();
        let back = StructureMap::from_bytes(&v1_bytes(&m), Path::new("s.safetensors")).unwrap();
        assert_eq!(back.images().len(), 3);
        assert!(back.images().iter().all(|im| im.appearance.is_none()));
        assert!(!back.has_gradients());
        assert_eq!(back.images()[1].descriptor, m.images()[1].descriptor);
    }

    #[test]
    fn a_corrupt_appearance_is_refused_naming_the_tensor() {
        let path = Path::new("map/structure.safetensors");
        // A gray image one value short of its camera.
        let mut m = sample();
        m.images[1].appearance.as_mut().unwrap().gray.pop();
        let err = StructureMap::from_bytes(&m.to_bytes().unwrap(), path).unwrap_err();
        assert!(err.to_string().contains("image_gray_start"), "{err}");
        // An impossible camera.
        let mut m = sample();
        m.images[2].appearance.as_mut().unwrap().camera.fx = -1.0;
        let err = StructureMap::from_bytes(&m.to_bytes().unwrap(), path).unwrap_err();
        assert!(err.to_string().contains("image_camera"), "{err}");
        assert!(
            err.to_string().starts_with("map/structure.safetensors"),
            "{err}"
        );
    }

    #[test]
    fn corrupt_files_are_refused_naming_file_and_tensor() {
        let path = Path::new("map/structure.safetensors");
        let err = StructureMap::from_bytes(b"not a file", path).unwrap_err();
        assert!(
            err.to_string().starts_with("map/structure.safetensors"),
            "{err}"
        );
        // A point index past the points.
        let mut m = sample();
        m.images[1].point[0] = 99;
        let err = StructureMap::from_bytes(&m.to_bytes().unwrap(), path).unwrap_err();
        assert!(err.to_string().contains("obs_point"), "{err}");
        // Gradient descriptors for fewer observations than there are.
        let mut m = sample();
        m.images[0].gradient.pop();
        assert!(StructureMap::new(m.points.clone(), m.images.clone()).is_err());
        let mut bytes_of = sample();
        bytes_of.images[0].gradient.clear();
        bytes_of.images[1].gradient.clear();
        bytes_of.images[2].gradient.clear();
        let without = StructureMap::from_bytes(&bytes_of.to_bytes().unwrap(), path).unwrap();
        assert!(!without.has_gradients());
        // A file whose gradient tensor is one observation short.
        let bytes = sample().to_bytes().unwrap();
        let st = SafeTensors::deserialize(&bytes).unwrap();
        let short: Vec<u8> = st.tensor("obs_gradient").unwrap().data()[128..].to_vec();
        let views: Vec<(String, TensorView<'_>)> = st
            .tensors()
            .into_iter()
            .map(|(n, v)| {
                if n == "obs_gradient" {
                    let t = TensorView::new(Dtype::U8, vec![3, 128], &short).unwrap();
                    (n, t)
                } else {
                    (n, v)
                }
            })
            .collect();
        let meta = HashMap::from([("format".to_string(), STRUCTURE_FORMAT.to_string())]);
        let bad = safetensors::serialize(views, Some(meta)).unwrap();
        let err = StructureMap::from_bytes(&bad, path).unwrap_err();
        assert!(err.to_string().contains("obs_gradient"), "{err}");
        // A non-finite point.
        let mut m = sample();
        m.points[1].x = f64::NAN;
        let err = StructureMap::from_bytes(&m.to_bytes().unwrap(), path).unwrap_err();
        assert!(err.to_string().contains("`points`"), "{err}");
    }
}

#[cfg(test)]
mod reprojection_tests {
    use super::*;
    use nalgebra::Point2;

    /// Points seen exactly where they project have no error; a keypoint moved 3 px shows as
    /// the largest error; a map without cameras has none to report.
    #[test]
    fn reprojection_errors_measure_the_points_against_their_keypoints() {
        let camera = Camera::pinhole(100, 80, 90.0, 90.0, 50.0, 40.0).unwrap();
        let pose = Pose::from_parts(
            Translation3::new(0.2, -0.1, 0.0),
            UnitQuaternion::from_euler_angles(0.05, 0.0, 0.1),
        );
        let points: Vec<Point3<f64>> = (0..5)
            .map(|k| Point3::new(k as f64 * 0.3 - 0.6, 0.1 * k as f64, 6.0 + k as f64))
            .collect();
        let pixel = |x: &Point3<f64>| -> Point2<f64> { camera.project_world(&pose, x).unwrap() };
        let mut px: Vec<[f32; 2]> = points
            .iter()
            .map(|x| {
                let u = pixel(x);
                [u.x as f32, u.y as f32]
            })
            .collect();
        px[2][0] += 3.0;
        let image = |appearance: bool, pixels: Vec<[f32; 2]>| StructureImage {
            frame: 0,
            cam_from_world: pose,
            point: (0..5).collect(),
            descriptor: vec![[0; 4]; 5],
            gradient: Vec::new(),
            pixel: pixels,
            appearance: appearance.then(|| ImageAppearance {
                camera,
                gray: vec![0; 100 * 80],
            }),
        };
        let m = StructureMap::new(points.clone(), vec![image(true, px.clone())]).unwrap();
        let r = m.reprojection_errors().unwrap();
        assert_eq!(r.observations, 5);
        assert!(r.median_px < 1e-3, "{r:?}");
        assert!((r.max_px - 3.0).abs() < 1e-3, "{r:?}");
        let none = StructureMap::new(points, vec![image(false, px)]).unwrap();
        assert_eq!(none.reprojection_errors(), None);
    }
}
