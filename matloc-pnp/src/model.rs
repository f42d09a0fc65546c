//! The pose hypothesis type used inside the solvers.

use matloc_core::Pose;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// A `cam_from_world` rigid transform stored as a rotation matrix and a translation.
///
/// Hypotheses are scored against every correspondence, so the matrix form (one 3×3 product
/// per point) is what the inner loops want; [`Pose`] is used at the API boundary.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseMatrix {
    /// Rotation part of `cam_from_world`.
    pub rotation: Matrix3<f64>,
    /// Translation part of `cam_from_world` (world origin in camera coordinates).
    pub translation: Vector3<f64>,
}

impl PoseMatrix {
    /// A pose from its parts.
    pub fn new(rotation: Matrix3<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    /// Point in camera coordinates.
    #[inline]
    pub fn transform(&self, p_world: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p_world + self.translation
    }

    /// True when every entry is finite and the rotation is orthonormal with determinant +1.
    pub fn is_valid(&self) -> bool {
        self.rotation.iter().all(|v| v.is_finite())
            && self.translation.iter().all(|v| v.is_finite())
            && (self.rotation.transpose() * self.rotation - Matrix3::identity()).norm() < 1e-6
            && self.rotation.determinant() > 0.0
    }

    /// The nearest proper rigid transform as a [`Pose`].
    pub fn to_pose(&self) -> Pose {
        let rot = Rotation3::from_matrix_eps(&self.rotation, 1e-15, 50, Rotation3::identity());
        Isometry3::from_parts(
            Translation3::from(self.translation),
            UnitQuaternion::from_rotation_matrix(&rot),
        )
    }

    /// The matrix form of a [`Pose`].
    pub fn from_pose(pose: &Pose) -> Self {
        Self {
            rotation: pose.rotation.to_rotation_matrix().into_inner(),
            translation: pose.translation.vector,
        }
    }
}

/// Rotation matrix of a rotation vector (axis × angle), Rodrigues' formula.
pub(crate) fn exp_so3(omega: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = omega.norm_squared();
    let k = omega.cross_matrix();
    if theta2 < 1e-16 {
        // Second-order Taylor expansion; exact to rounding for such small angles.
        return Matrix3::identity() + k + 0.5 * k * k;
    }
    let theta = theta2.sqrt();
    Matrix3::identity() + (theta.sin() / theta) * k + ((1.0 - theta.cos()) / theta2) * k * k
}
