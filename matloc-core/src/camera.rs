//! Camera intrinsics: pinhole and OpenCV (Brown–Conrady: k1, k2, p1, p2, k3) models.
//!
//! One struct covers every model the project reads: a pinhole camera is an OpenCV camera whose
//! distortion is zero, and COLMAP's SIMPLE_RADIAL / RADIAL are OpenCV cameras with `p1 = p2 = 0`.
//! Pixel coordinates are continuous with the centre of pixel `(col, row)` at
//! `(col + 0.5, row + 0.5)`.

use nalgebra::{Isometry3, Matrix2, Matrix3, Point2, Point3, Vector2, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Errors raised when building or rescaling a camera.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum CameraError {
    /// A parameter is NaN or infinite.
    #[error("camera parameter `{field}` is not finite ({value})")]
    NonFinite {
        /// Name of the offending parameter.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// A focal length is zero or negative.
    #[error("camera focal length `{field}` must be positive, got {value}")]
    NonPositiveFocal {
        /// `fx` or `fy`.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// The image has zero width or height.
    #[error("camera image size must be positive, got {width}x{height}")]
    EmptyImage {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
    },
    /// Rescaling to a size with a different aspect ratio would distort the intrinsics.
    #[error(
        "cannot rescale intrinsics for {from_width}x{from_height} to {to_width}x{to_height}: aspect ratios differ"
    )]
    AspectMismatch {
        /// Width the intrinsics were given for.
        from_width: u32,
        /// Height the intrinsics were given for.
        from_height: u32,
        /// Requested width.
        to_width: u32,
        /// Requested height.
        to_height: u32,
    },
}

/// Largest image side a real camera has, pixels (a 65 536-pixel side is beyond any survey
/// camera; a size claiming more would have the pipeline allocate for it).
pub const MAX_IMAGE_SIDE: u32 = 65_536;

/// Narrowest and widest horizontal / vertical field of view of a real lens, degrees (a
/// 0.5° telephoto to a 170° wide angle; fisheye models are not read).
pub const FOV_RANGE_DEG: (f64, f64) = (0.5, 170.0);

/// How far outside the image the principal point may lie, as a fraction of the image side on
/// each border (a shifted sensor or a crop moves it; a quarter of the image is beyond both).
pub const PRINCIPAL_POINT_MARGIN: f64 = 0.25;

/// Largest magnitude of a tangential coefficient `p1`, `p2` (decentring of real lenses stays
/// below 0.01).
pub const MAX_TANGENTIAL: f64 = 0.1;

/// Largest factor by which the lens distortion may change the ray radius at the image border
/// (either way).
pub const MAX_RADIUS_CHANGE: f64 = 4.0;

/// Intrinsics that are well formed but no real camera has (see [`Camera::plausibility`]).
#[derive(Debug, Error, Clone, PartialEq)]
pub enum ImplausibleCamera {
    /// An image side is zero or larger than [`MAX_IMAGE_SIDE`].
    #[error("`{field}`: {value} px is outside 1..={max}")]
    Side {
        /// `width` or `height`.
        field: &'static str,
        /// Its value.
        value: u32,
        /// The largest side accepted.
        max: u32,
    },
    /// A focal length gives a field of view outside [`FOV_RANGE_DEG`] (or is not finite or
    /// positive).
    #[error(
        "`{field}`: {focal} px gives a {fov_deg:.3}° field of view over {side} px, outside {min_deg}–{max_deg}°"
    )]
    FieldOfView {
        /// `fx` or `fy`.
        field: &'static str,
        /// The focal length, pixels.
        focal: f64,
        /// The image side it spans, pixels.
        side: u32,
        /// The field of view it gives, degrees.
        fov_deg: f64,
        /// Narrowest accepted, degrees.
        min_deg: f64,
        /// Widest accepted, degrees.
        max_deg: f64,
    },
    /// The principal point lies farther outside the image than [`PRINCIPAL_POINT_MARGIN`]
    /// (or is not finite).
    #[error(
        "`{field}`: {value} px lies more than {margin} × the image side ({side} px) outside it"
    )]
    PrincipalPoint {
        /// `cx` or `cy`.
        field: &'static str,
        /// Its value, pixels.
        value: f64,
        /// The image side, pixels.
        side: u32,
        /// The margin accepted on each border, as a fraction of the side.
        margin: f64,
    },
    /// A distortion coefficient is NaN or infinite.
    #[error("`{field}`: {value} is not finite")]
    NonFiniteDistortion {
        /// `k1`, `k2`, `p1`, `p2` or `k3`.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// A tangential coefficient is larger in magnitude than [`MAX_TANGENTIAL`].
    #[error("`{field}`: {value} is outside ±{max}")]
    Tangential {
        /// `p1` or `p2`.
        field: &'static str,
        /// Its value.
        value: f64,
        /// The largest magnitude accepted.
        max: f64,
    },
    /// The distortion cannot be inverted at a border pixel (or only by a ray on the far side of
    /// the centre): the lens model folds over there.
    #[error(
        "`distortion`: cannot be inverted at pixel ({x}, {y}): the lens model folds over there"
    )]
    NotInvertible {
        /// Pixel x.
        x: f64,
        /// Pixel y.
        y: f64,
    },
    /// The distortion changes the ray radius at a border pixel by more than
    /// [`MAX_RADIUS_CHANGE`] either way.
    #[error(
        "`distortion`: changes the ray radius at pixel ({x}, {y}) by {ratio:.3e}×, beyond {max}×"
    )]
    RadiusChange {
        /// Pixel x.
        x: f64,
        /// Pixel y.
        y: f64,
        /// Undistorted over distorted radius.
        ratio: f64,
        /// The largest factor accepted.
        max: f64,
    },
}

impl ImplausibleCamera {
    /// The offending field: `width`, `height`, `fx`, `fy`, `cx`, `cy`, `k1`…`k3`, `p1`, `p2`,
    /// or `distortion` for the lens model as a whole.
    pub fn field(&self) -> &'static str {
        match self {
            ImplausibleCamera::Side { field, .. }
            | ImplausibleCamera::FieldOfView { field, .. }
            | ImplausibleCamera::PrincipalPoint { field, .. }
            | ImplausibleCamera::NonFiniteDistortion { field, .. }
            | ImplausibleCamera::Tangential { field, .. } => field,
            ImplausibleCamera::NotInvertible { .. } | ImplausibleCamera::RadiusChange { .. } => {
                "distortion"
            }
        }
    }

    /// The message without the leading field name.
    pub fn reason(&self) -> String {
        let text = self.to_string();
        let prefix = format!("`{}`: ", self.field());
        match text.strip_prefix(&prefix) {
            Some(rest) => rest.to_string(),
            None => text,
        }
    }
}

/// Brown–Conrady lens distortion in OpenCV's parameterisation (normalised coordinates).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Distortion {
    /// First radial coefficient.
    pub k1: f64,
    /// Second radial coefficient.
    pub k2: f64,
    /// First tangential coefficient.
    pub p1: f64,
    /// Second tangential coefficient.
    pub p2: f64,
    /// Third radial coefficient (optional in most formats; zero when absent).
    #[serde(default)]
    pub k3: f64,
}

impl Distortion {
    /// The coefficients with their OpenCV names, in OpenCV's order.
    pub fn named(&self) -> [(&'static str, f64); 5] {
        [
            ("k1", self.k1),
            ("k2", self.k2),
            ("p1", self.p1),
            ("p2", self.p2),
            ("k3", self.k3),
        ]
    }

    /// No distortion (a pinhole camera).
    pub const NONE: Distortion = Distortion {
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    };

    /// True when every coefficient is exactly zero.
    pub fn is_none(&self) -> bool {
        *self == Self::NONE
    }

    /// Applies the distortion to an undistorted normalised point.
    pub fn apply(&self, n: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        Vector2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Jacobian of [`Distortion::apply`] with respect to the undistorted point.
    pub fn jacobian(&self, n: Vector2<f64>) -> Matrix2<f64> {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d(radial)/d(r2)
        let dr = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2);
        let (p1, p2) = (self.p1, self.p2);
        Matrix2::new(
            radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x,
            2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y,
            2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y,
            radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x,
        )
    }

    /// Inverts the distortion by Newton's method (as COLMAP does).
    ///
    /// Returns `None` when the iteration does not converge, which happens only far outside the
    /// region where the distortion polynomial is monotonic.
    pub fn remove(&self, distorted: Vector2<f64>) -> Option<Vector2<f64>> {
        if self.is_none() {
            return Some(distorted);
        }
        let mut n = distorted;
        for _ in 0..100 {
            let residual = self.apply(n) - distorted;
            if residual.norm() < 1e-14 {
                return Some(n);
            }
            let step = self.jacobian(n).try_inverse()? * residual;
            n -= step;
            if !n.x.is_finite() || !n.y.is_finite() {
                return None;
            }
            if step.norm() < 1e-15 {
                break;
            }
        }
        let residual = (self.apply(n) - distorted).norm();
        (residual < 1e-10).then_some(n)
    }
}

/// Intrinsics of one camera together with the image size they refer to.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels (continuous coordinates, see module docs).
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Lens distortion; [`Distortion::NONE`] for a pinhole camera.
    #[serde(default)]
    pub distortion: Distortion,
}

impl Camera {
    /// A validated pinhole camera.
    pub fn pinhole(
        width: u32,
        height: u32,
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
    ) -> Result<Self, CameraError> {
        Self::opencv(width, height, fx, fy, cx, cy, Distortion::NONE)
    }

    /// A validated OpenCV camera.
    pub fn opencv(
        width: u32,
        height: u32,
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        distortion: Distortion,
    ) -> Result<Self, CameraError> {
        let cam = Camera {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            distortion,
        };
        cam.validate()?;
        Ok(cam)
    }

    /// A pinhole camera from a horizontal field of view, principal point at the image centre.
    pub fn from_hfov(width: u32, height: u32, hfov_deg: f64) -> Result<Self, CameraError> {
        let f = 0.5 * width as f64 / (0.5 * hfov_deg.to_radians()).tan();
        Self::pinhole(width, height, f, f, 0.5 * width as f64, 0.5 * height as f64)
    }

    /// Checks that every parameter is finite, focal lengths are positive and the image is not empty.
    pub fn validate(&self) -> Result<(), CameraError> {
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::EmptyImage {
                width: self.width,
                height: self.height,
            });
        }
        let intrinsics = [
            ("fx", self.fx),
            ("fy", self.fy),
            ("cx", self.cx),
            ("cy", self.cy),
        ];
        for (field, value) in intrinsics.into_iter().chain(self.distortion.named()) {
            if !value.is_finite() {
                return Err(CameraError::NonFinite { field, value });
            }
        }
        for (field, value) in [("fx", self.fx), ("fy", self.fy)] {
            if value <= 0.0 {
                return Err(CameraError::NonPositiveFocal { field, value });
            }
        }
        Ok(())
    }

    /// Every way the intrinsics break the bounds of a real camera, checked in constant time
    /// (no allocation sized by the input): sides in `1..=`[`MAX_IMAGE_SIDE`] (nothing else is
    /// checked when one is not); focal lengths finite, positive and giving a field of view
    /// inside [`FOV_RANGE_DEG`] over their side; the principal point finite and within
    /// [`PRINCIPAL_POINT_MARGIN`] of the image outside its borders; distortion coefficients
    /// finite with `|p1|, |p2| ≤` [`MAX_TANGENTIAL`], and the lens invertible at the image's
    /// corners and edge midpoints (by a ray on the same side of the centre), changing the ray
    /// radius there by at most [`MAX_RADIUS_CHANGE`]×. Radial coefficients have no bound of
    /// their own: what they do at the image border is bounded instead, whatever the field of
    /// view. Empty = plausible.
    pub fn plausibility(&self) -> Vec<ImplausibleCamera> {
        let mut problems = Vec::new();
        for (field, value) in [("width", self.width), ("height", self.height)] {
            if value == 0 || value > MAX_IMAGE_SIDE {
                problems.push(ImplausibleCamera::Side {
                    field,
                    value,
                    max: MAX_IMAGE_SIDE,
                });
            }
        }
        if !problems.is_empty() {
            return problems;
        }
        let (min_deg, max_deg) = FOV_RANGE_DEG;
        for (field, focal, side) in [("fx", self.fx, self.width), ("fy", self.fy, self.height)] {
            let fov_deg = 2.0 * (f64::from(side) / (2.0 * focal)).atan().to_degrees();
            if !(focal.is_finite() && focal > 0.0 && (min_deg..=max_deg).contains(&fov_deg)) {
                problems.push(ImplausibleCamera::FieldOfView {
                    field,
                    focal,
                    side,
                    fov_deg,
                    min_deg,
                    max_deg,
                });
            }
        }
        for (field, value, side) in [("cx", self.cx, self.width), ("cy", self.cy, self.height)] {
            let s = f64::from(side);
            let m = PRINCIPAL_POINT_MARGIN;
            if !(value.is_finite() && value >= -m * s && value <= (1.0 + m) * s) {
                problems.push(ImplausibleCamera::PrincipalPoint {
                    field,
                    value,
                    side,
                    margin: m,
                });
            }
        }
        let d = &self.distortion;
        if d.is_none() {
            return problems;
        }
        let mut coefficients_ok = true;
        for (field, value) in d.named() {
            if !value.is_finite() {
                problems.push(ImplausibleCamera::NonFiniteDistortion { field, value });
                coefficients_ok = false;
            } else if matches!(field, "p1" | "p2") && value.abs() > MAX_TANGENTIAL {
                problems.push(ImplausibleCamera::Tangential {
                    field,
                    value,
                    max: MAX_TANGENTIAL,
                });
                coefficients_ok = false;
            }
        }
        if !coefficients_ok {
            return problems;
        }
        let (w, h) = (f64::from(self.width), f64::from(self.height));
        let probes = [
            (0.0, 0.0),
            (w, 0.0),
            (0.0, h),
            (w, h),
            (w / 2.0, 0.0),
            (w / 2.0, h),
            (0.0, h / 2.0),
            (w, h / 2.0),
        ];
        for (x, y) in probes {
            let px = Point2::new(x, y);
            let distorted_point = self.pixel_to_distorted_normalized(px);
            let distorted = distorted_point.norm();
            // A root on the far side of the centre is the polynomial folding over, not a ray.
            let undistorted = self
                .pixel_to_normalized(px)
                .filter(|n| distorted <= 1e-9 || n.dot(&distorted_point) > 0.0);
            match undistorted {
                None => {
                    problems.push(ImplausibleCamera::NotInvertible { x, y });
                    break;
                }
                Some(n) => {
                    let ratio = n.norm() / distorted;
                    let max = MAX_RADIUS_CHANGE;
                    if distorted > 1e-9 && !(1.0 / max..=max).contains(&ratio) {
                        problems.push(ImplausibleCamera::RadiusChange { x, y, ratio, max });
                        break;
                    }
                }
            }
        }
        problems
    }

    /// The first way the intrinsics break the bounds of a real camera
    /// ([`Camera::plausibility`]), if any.
    pub fn check_plausible(&self) -> Result<(), ImplausibleCamera> {
        match self.plausibility().into_iter().next() {
            Some(problem) => Err(problem),
            None => Ok(()),
        }
    }

    /// True when the camera has no lens distortion.
    pub fn is_pinhole(&self) -> bool {
        self.distortion.is_none()
    }

    /// The 3×3 calibration matrix K.
    pub fn k_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// Normalised (distorted) image coordinates of a pixel.
    pub fn pixel_to_distorted_normalized(&self, px: Point2<f64>) -> Vector2<f64> {
        Vector2::new((px.x - self.cx) / self.fx, (px.y - self.cy) / self.fy)
    }

    /// Pixel of a normalised (distorted) image point.
    pub fn distorted_normalized_to_pixel(&self, n: Vector2<f64>) -> Point2<f64> {
        Point2::new(self.fx * n.x + self.cx, self.fy * n.y + self.cy)
    }

    /// Pixel of an undistorted normalised point (applies the lens distortion).
    pub fn normalized_to_pixel(&self, n: Vector2<f64>) -> Point2<f64> {
        self.distorted_normalized_to_pixel(self.distortion.apply(n))
    }

    /// Undistorted normalised coordinates of a pixel; `None` if undistortion does not converge.
    pub fn pixel_to_normalized(&self, px: Point2<f64>) -> Option<Vector2<f64>> {
        self.distortion
            .remove(self.pixel_to_distorted_normalized(px))
    }

    /// Projects a point in camera coordinates to a pixel; `None` if it is not in front of the
    /// camera.
    pub fn project(&self, p_cam: &Vector3<f64>) -> Option<Point2<f64>> {
        // Also rejects NaN depth.
        if p_cam.z.is_nan() || p_cam.z <= 1e-12 {
            return None;
        }
        Some(self.normalized_to_pixel(Vector2::new(p_cam.x / p_cam.z, p_cam.y / p_cam.z)))
    }

    /// Projects a world point through a `cam_from_world` pose.
    pub fn project_world(
        &self,
        cam_from_world: &Isometry3<f64>,
        p_world: &Point3<f64>,
    ) -> Option<Point2<f64>> {
        self.project(&(cam_from_world * p_world).coords)
    }

    /// Unit bearing (camera frame) of the ray through a pixel, lens distortion removed.
    pub fn unproject(&self, px: Point2<f64>) -> Option<Vector3<f64>> {
        let n = self.pixel_to_normalized(px)?;
        Some(Vector3::new(n.x, n.y, 1.0).normalize())
    }

    /// True when a continuous pixel coordinate lies inside the image.
    pub fn contains(&self, px: Point2<f64>) -> bool {
        px.x >= 0.0 && px.y >= 0.0 && px.x < self.width as f64 && px.y < self.height as f64
    }

    /// Intrinsics for the same lens at another image size with the same aspect ratio
    /// (relative tolerance 1 % — sizes are integers, so odd-sized downscales round).
    pub fn rescaled(&self, width: u32, height: u32) -> Result<Camera, CameraError> {
        let mismatch = CameraError::AspectMismatch {
            from_width: self.width,
            from_height: self.height,
            to_width: width,
            to_height: height,
        };
        if width == 0 || height == 0 {
            return Err(CameraError::EmptyImage { width, height });
        }
        let sx = width as f64 / self.width as f64;
        let sy = height as f64 / self.height as f64;
        if ((sx - sy) / sx).abs() > 0.01 {
            return Err(mismatch);
        }
        Ok(Camera {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
            distortion: self.distortion,
        })
    }

    /// Intrinsics for the image downscaled by an integer factor (sizes rounded down, as image
    /// libraries do; the exact per-axis scale is used).
    pub fn downscaled(&self, factor: u32) -> Result<Camera, CameraError> {
        let factor = factor.max(1);
        let width = (self.width / factor).max(1);
        let height = (self.height / factor).max(1);
        let sx = width as f64 / self.width as f64;
        let sy = height as f64 / self.height as f64;
        Ok(Camera {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
            distortion: self.distortion,
        })
    }

    /// Horizontal field of view in degrees (pinhole approximation).
    pub fn hfov_deg(&self) -> f64 {
        2.0 * (0.5 * self.width as f64 / self.fx).atan().to_degrees()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn distortion_strategy() -> impl Strategy<Value = Distortion> {
        // Realistic lenses: moderate barrel/pincushion, small tangential terms.
        (
            -0.3..0.3f64,
            -0.1..0.1f64,
            -0.002..0.002f64,
            -0.002..0.002f64,
            -0.02..0.02f64,
        )
            .prop_map(|(k1, k2, p1, p2, k3)| Distortion { k1, k2, p1, p2, k3 })
    }

    fn camera_strategy() -> impl Strategy<Value = Camera> {
        (
            64u32..2000,
            48u32..1500,
            0.5..1.5f64,
            -0.05..0.05f64,
            -0.05..0.05f64,
            distortion_strategy(),
        )
            .prop_map(|(w, h, ff, dx, dy, d)| {
                // Focal lengths keep the field of view below ~90°, where such lenses are valid.
                let f = (w.max(h) as f64) * ff;
                Camera::opencv(
                    w,
                    h,
                    f,
                    f * 1.01,
                    w as f64 * (0.5 + dx),
                    h as f64 * (0.5 + dy),
                    d,
                )
                .unwrap()
            })
            .prop_filter("lens must be invertible over the image", radially_monotonic)
    }

    /// A physical lens maps radius monotonically: the distorted radius must keep growing up to
    /// (beyond) the image corners, or the corners are unreachable by any ray.
    fn radially_monotonic(cam: &Camera) -> bool {
        let corners = [
            (0.0, 0.0),
            (cam.width as f64, 0.0),
            (0.0, cam.height as f64),
            (cam.width as f64, cam.height as f64),
        ];
        let r_max = corners
            .iter()
            .map(|&(x, y)| cam.pixel_to_distorted_normalized(Point2::new(x, y)).norm())
            .fold(0.0, f64::max)
            * 1.3;
        let d = cam.distortion;
        let radial = |r: f64| {
            let r2 = r * r;
            r * (1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3)))
        };
        let steps = 200;
        let mut prev = 0.0;
        for i in 1..=steps {
            let r = r_max * i as f64 / steps as f64;
            let f = radial(r);
            if f <= prev || f < 0.7 * r {
                return false;
            }
            prev = f;
        }
        // The distorted radius must actually reach the corners.
        prev >= r_max / 1.3
    }

    proptest! {
        #[test]
        fn distort_undistort_identity_over_image(cam in camera_strategy(), u in 0.0..1.0f64, v in 0.0..1.0f64) {
            let px = Point2::new(u * cam.width as f64, v * cam.height as f64);
            let n = cam.pixel_to_normalized(px).expect("undistortion converges inside the image");
            let back = cam.normalized_to_pixel(n);
            prop_assert!((back - px).norm() < 1e-6, "round trip error {}", (back - px).norm());
        }

        #[test]
        fn project_unproject_round_trip(cam in camera_strategy(), u in 0.0..1.0f64, v in 0.0..1.0f64, depth in 0.1..500.0f64) {
            let px = Point2::new(u * cam.width as f64, v * cam.height as f64);
            let bearing = cam.unproject(px).unwrap();
            prop_assert!((bearing.norm() - 1.0).abs() < 1e-12);
            let back = cam.project(&(bearing * depth)).unwrap();
            prop_assert!((back - px).norm() < 1e-6);
        }

        #[test]
        fn rescale_preserves_rays(cam in camera_strategy(), u in 0.0..1.0f64, v in 0.0..1.0f64) {
            let small = cam.rescaled(cam.width / 2 * 2 / 2, cam.height / 2 * 2 / 2);
            if let Ok(small) = small {
                let px = Point2::new(u * cam.width as f64, v * cam.height as f64);
                let px_small = Point2::new(px.x * small.width as f64 / cam.width as f64, px.y * small.height as f64 / cam.height as f64);
                let a = cam.unproject(px).unwrap();
                let b = small.unproject(px_small).unwrap();
                prop_assert!((a - b).norm() < 1e-9);
            }
        }
    }

    #[test]
    fn distortion_jacobian_matches_finite_differences() {
        let d = Distortion {
            k1: -0.21,
            k2: 0.05,
            p1: 0.001,
            p2: -0.0015,
            k3: 0.01,
        };
        let n = Vector2::new(0.31, -0.22);
        let j = d.jacobian(n);
        let h = 1e-7;
        for c in 0..2 {
            let mut e = Vector2::zeros();
            e[c] = h;
            let fd = (d.apply(n + e) - d.apply(n - e)) / (2.0 * h);
            for r in 0..2 {
                assert!((fd[r] - j[(r, c)]).abs() < 1e-7, "J[{r},{c}]");
            }
        }
    }

    #[test]
    fn bad_parameters_are_typed_errors() {
        assert!(matches!(
            Camera::pinhole(10, 10, f64::NAN, 1.0, 5.0, 5.0),
            Err(CameraError::NonFinite { field: "fx", .. })
        ));
        assert!(matches!(
            Camera::pinhole(10, 10, 1.0, -1.0, 5.0, 5.0),
            Err(CameraError::NonPositiveFocal { field: "fy", .. })
        ));
        assert!(matches!(
            Camera::pinhole(0, 10, 1.0, 1.0, 5.0, 5.0),
            Err(CameraError::EmptyImage { .. })
        ));
        let cam = Camera::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0).unwrap();
        assert!(matches!(
            cam.rescaled(640, 640),
            Err(CameraError::AspectMismatch { .. })
        ));
        let half = cam.rescaled(320, 240).unwrap();
        assert_eq!(half.fx, 250.0);
        assert_eq!(half.cx, 160.0);
    }

    /// A camera built field by field (bypassing the constructor's checks), as readers do.
    fn raw(width: u32, height: u32, f: f64, cx: f64, cy: f64, d: Distortion) -> Camera {
        Camera {
            width,
            height,
            fx: f,
            fy: f,
            cx,
            cy,
            distortion: d,
        }
    }

    #[test]
    fn implausible_intrinsics_name_the_field_and_the_bound() {
        let ok = raw(160, 120, 150.0, 80.0, 60.0, Distortion::NONE);
        assert_eq!(ok.check_plausible(), Ok(()));
        let lens = |k1: f64, p1: f64| Distortion {
            k1,
            p1,
            ..Distortion::NONE
        };
        let cases = [
            (
                raw(
                    1_000_000_000,
                    750_000_000,
                    150.0,
                    80.0,
                    60.0,
                    Distortion::NONE,
                ),
                "width",
                "1..=65536",
            ),
            (
                raw(160, 0, 150.0, 80.0, 60.0, Distortion::NONE),
                "height",
                "1..=65536",
            ),
            (
                raw(160, 120, 1e308, 80.0, 60.0, Distortion::NONE),
                "fx",
                "0.5–170°",
            ),
            (
                raw(160, 120, 1e-3, 80.0, 60.0, Distortion::NONE),
                "fx",
                "0.5–170°",
            ),
            (
                raw(160, 120, -150.0, 80.0, 60.0, Distortion::NONE),
                "fx",
                "outside",
            ),
            (
                raw(160, 120, 150.0, 1e308, 60.0, Distortion::NONE),
                "cx",
                "0.25 × the image side",
            ),
            (
                raw(160, 120, 150.0, 80.0, -1e308, Distortion::NONE),
                "cy",
                "0.25 × the image side",
            ),
            (
                raw(160, 120, 150.0, 80.0, 60.0, lens(1e30, 0.0)),
                "distortion",
                "beyond 4×",
            ),
            (
                raw(160, 120, 150.0, 80.0, 60.0, lens(-0.3, 10.0)),
                "p1",
                "±0.1",
            ),
            (
                raw(160, 120, 150.0, 80.0, 60.0, lens(f64::NAN, 0.0)),
                "k1",
                "not finite",
            ),
        ];
        for (cam, field, bound) in cases {
            let e = cam.check_plausible().unwrap_err();
            assert_eq!(e.field(), field, "{e}");
            let text = e.to_string();
            assert!(
                text.starts_with(&format!("`{field}`: ")) && text.contains(bound),
                "{text}"
            );
            assert!(!e.reason().starts_with('`'), "{}", e.reason());
        }
        // Barrel distortion so strong that no ray reaches the corners.
        let strong = raw(160, 120, 100.0, 80.0, 60.0, lens(-1.0, 0.0));
        assert!(
            strong
                .plausibility()
                .iter()
                .any(|p| p.field() == "distortion"),
            "{:?}",
            strong.plausibility()
        );
        // Sides beyond the bound are the only problem reported (nothing else is checked).
        let huge = raw(100_000, 0, f64::NAN, f64::NAN, 1.0, Distortion::NONE);
        assert_eq!(huge.plausibility().len(), 2);
    }

    fn plausible_strategy() -> impl Strategy<Value = Camera> {
        (
            1u32..=MAX_IMAGE_SIDE,
            1u32..=MAX_IMAGE_SIDE,
            1.0..169.0f64,
            -0.2..1.2f64,
            -0.2..1.2f64,
            -0.1..0.1f64,
            -0.01..0.01f64,
            -0.01..0.01f64,
        )
            .prop_map(|(w, h, hfov, u, v, k1, p1, p2)| {
                let f = 0.5 * f64::from(w) / (0.5 * hfov.to_radians()).tan();
                // fy keeps the vertical field of view inside the range too.
                let fy = f.max(0.5 * f64::from(h) / (0.5 * 169f64.to_radians()).tan());
                let fy = fy.min(0.5 * f64::from(h) / (0.5 * 1f64.to_radians()).tan());
                // Lens distortion only where real lenses of that kind have it: up to a 90°
                // field of view with the principal point near the centre.
                let centred = (0.4..0.6).contains(&u) && (0.4..0.6).contains(&v);
                let distortion = if hfov <= 90.0 && centred {
                    Distortion {
                        k1,
                        p1,
                        p2,
                        ..Distortion::NONE
                    }
                } else {
                    Distortion::NONE
                };
                Camera {
                    width: w,
                    height: h,
                    fx: f,
                    fy,
                    cx: u * f64::from(w),
                    cy: v * f64::from(h),
                    distortion,
                }
            })
            .prop_filter("lens must be invertible over the image", radially_monotonic)
    }

    proptest! {
        #[test]
        fn plausible_cameras_pass(cam in plausible_strategy()) {
            prop_assert_eq!(cam.check_plausible(), Ok(()), "{:?}", cam);
        }

        #[test]
        fn a_non_finite_parameter_fails(
            cam in plausible_strategy(),
            which in 0usize..9,
            bad in prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY)],
        ) {
            let mut cam = cam;
            let d = &mut cam.distortion;
            let (field, slot) = match which {
                0 => ("fx", &mut cam.fx),
                1 => ("fy", &mut cam.fy),
                2 => ("cx", &mut cam.cx),
                3 => ("cy", &mut cam.cy),
                4 => ("k1", &mut d.k1),
                5 => ("k2", &mut d.k2),
                6 => ("p1", &mut d.p1),
                7 => ("p2", &mut d.p2),
                _ => ("k3", &mut d.k3),
            };
            *slot = bad;
            let problems = cam.plausibility();
            prop_assert!(problems.iter().any(|p| p.field() == field), "{:?}", problems);
        }
    }

    #[test]
    fn points_behind_camera_do_not_project() {
        let cam = Camera::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0).unwrap();
        assert!(cam.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
        assert!(cam.project(&Vector3::new(0.0, 0.0, 0.0)).is_none());
        assert!(cam.project(&Vector3::new(0.0, 0.0, f64::NAN)).is_none());
        let c = cam.project(&Vector3::new(0.0, 0.0, 2.0)).unwrap();
        assert_eq!(c, Point2::new(320.0, 240.0));
    }
}
