//! P3P minimal solver: Lambda Twist (Persson & Nordberg, "Lambda Twist: An Accurate Fast Robust
//! Perspective Three Point (P3P) Solver", ECCV 2018).
//!
//! The unknown depths `Λ = (λ1, λ2, λ3)` along the three unit bearings `y_i` satisfy
//! `λi² + λj² − 2 (y_i·y_j) λi λj = |X_i − X_j|²` for the three pairs. Two homogeneous
//! combinations of these quadrics span a pencil `D1 + γ D2`; a real root of `det(D1 + γ D2) = 0`
//! gives a degenerate conic, i.e. a pair of planes through the origin, each of which makes `Λ`
//! one linear constraint away from a quadratic in a single ratio. Depths are then polished with
//! Gauss–Newton and the pose follows from two matched triangles.

use nalgebra::{Matrix3, Vector3};

use crate::model::PoseMatrix;
use crate::poly::{cubic_roots, quadratic_roots};

/// Smallest squared world distance between sample points, relative to the largest, accepted.
const MIN_RELATIVE_SQ_DISTANCE: f64 = 1e-10;

/// Solves P3P: appends to `out` every pose (at most 4) with `λ_i y_i = R X_i + t`, `λ_i > 0`.
///
/// `bearings` must be unit vectors in camera coordinates. Degenerate samples (coincident or
/// collinear world points, parallel bearings) give no pose rather than a panic.
pub fn p3p(bearings: &[Vector3<f64>; 3], points: &[Vector3<f64>; 3], out: &mut Vec<PoseMatrix>) {
    let [y1, y2, y3] = bearings;
    let [x1, x2, x3] = points;
    let d12 = x1 - x2;
    let d13 = x1 - x3;
    let a12 = d12.norm_squared();
    let a13 = d13.norm_squared();
    let a23 = (x2 - x3).norm_squared();
    let a_max = a12.max(a13).max(a23);
    if !(a_max > 0.0)
        || !a_max.is_finite()
        || a12.min(a13).min(a23) < MIN_RELATIVE_SQ_DISTANCE * a_max
    {
        return;
    }
    // The world triangle's frame; singular when the points are collinear.
    let n = d12.cross(&d13);
    if n.norm_squared() < 1e-12 * a12 * a13 {
        return;
    }
    let Some(world_frame_inv) = Matrix3::from_columns(&[d12, d13, n]).try_inverse() else {
        return;
    };

    let b12 = y1.dot(y2);
    let b13 = y1.dot(y3);
    let b23 = y2.dot(y3);

    // Quadric of each pair: Λᵀ M_ij Λ = a_ij.
    let m12 = Matrix3::new(1.0, -b12, 0.0, -b12, 1.0, 0.0, 0.0, 0.0, 0.0);
    let m13 = Matrix3::new(1.0, 0.0, -b13, 0.0, 0.0, 0.0, -b13, 0.0, 1.0);
    let m23 = Matrix3::new(0.0, 0.0, 0.0, 0.0, 1.0, -b23, 0.0, -b23, 1.0);
    // Homogeneous combinations: Λᵀ D Λ = 0 at every solution.
    let d1 = a23 * m12 - a12 * m23;
    let d2 = a23 * m13 - a13 * m23;

    let (c3, c2, c1, c0) = det_pencil_coefficients(&d1, &d2);
    let mut gammas = [0.0; 3];
    let num_gammas = cubic_roots(c3, c2, c1, c0, &mut gammas);

    for &gamma in &gammas[..num_gammas] {
        let d0 = d1 + gamma * d2;
        let Some((e1, sigma1, e2, sigma2)) = eig_rank2_symmetric(&d0) else {
            continue;
        };
        // The plane pair only exists (is real) when the non-zero eigenvalues differ in sign.
        let ratio = -sigma2 / sigma1;
        if ratio < -1e-12 {
            continue;
        }
        let s = ratio.max(0.0).sqrt();
        // A second homogeneous quadric independent of d0, chosen to be far from it in the pencil.
        let other = if gamma.abs() <= 1.0 { &d2 } else { &d1 };
        let before = out.len();
        for sign in [1.0, -1.0] {
            let u = e1 - sign * s * e2;
            solve_on_plane(
                &u,
                other,
                [a12, a13, a23],
                [b12, b13, b23],
                bearings,
                points,
                &world_frame_inv,
                out,
            );
            if s == 0.0 {
                break;
            }
        }
        // Any real root with a valid plane pair gives every solution; the others are redundant.
        if out.len() > before {
            return;
        }
    }
}

/// Coefficients of `det(A + γ B) = c3 γ³ + c2 γ² + c1 γ + c0`.
fn det_pencil_coefficients(a: &Matrix3<f64>, b: &Matrix3<f64>) -> (f64, f64, f64, f64) {
    // Multilinearity of the determinant in columns: each coefficient is a sum of determinants
    // mixing columns of A and B.
    let mixed = |use_b: [bool; 3]| {
        let col = |i: usize| if use_b[i] { b.column(i) } else { a.column(i) };
        Matrix3::from_columns(&[col(0), col(1), col(2)]).determinant()
    };
    let c3 = b.determinant();
    let c0 = a.determinant();
    let c2 = mixed([false, true, true]) + mixed([true, false, true]) + mixed([true, true, false]);
    let c1 =
        mixed([true, false, false]) + mixed([false, true, false]) + mixed([false, false, true]);
    (c3, c2, c1, c0)
}

/// Eigen-pairs of the two largest-magnitude eigenvalues of a symmetric 3×3 matrix of rank ≤ 2,
/// ordered so that `|σ1| ≥ |σ2|`.
fn eig_rank2_symmetric(m: &Matrix3<f64>) -> Option<(Vector3<f64>, f64, Vector3<f64>, f64)> {
    // With one eigenvalue zero the characteristic polynomial is σ² − tr σ + (sum of 2×2 minors).
    let tr = m.trace();
    let minors = m[(0, 0)] * m[(1, 1)] - m[(0, 1)] * m[(1, 0)] + m[(0, 0)] * m[(2, 2)]
        - m[(0, 2)] * m[(2, 0)]
        + m[(1, 1)] * m[(2, 2)]
        - m[(1, 2)] * m[(2, 1)];
    let disc = (0.25 * tr * tr - minors).max(0.0).sqrt();
    let (mut s1, mut s2) = (0.5 * tr + disc, 0.5 * tr - disc);
    if s1.abs() < s2.abs() {
        std::mem::swap(&mut s1, &mut s2);
    }
    if !(s1.abs() > 1e-300) {
        return None;
    }
    let e1 = null_vector(&(m - Matrix3::from_diagonal_element(s1)))?;
    // For the second eigenvector, orthogonality to e1 is more reliable than a second null space
    // when σ2 ≈ 0 (a double plane).
    let e2 = match null_vector(&(m - Matrix3::from_diagonal_element(s2))) {
        Some(e) if s2.abs() > 1e-9 * s1.abs() => e,
        _ => {
            // Any unit vector orthogonal to e1 and to the zero-eigenvalue direction.
            let e0 = null_vector(m)?;
            e1.cross(&e0).try_normalize(1e-300)?
        }
    };
    Some((e1, s1, e2, s2))
}

/// Unit vector spanning the null space of a rank-2 3×3 matrix (largest cross product of rows).
fn null_vector(m: &Matrix3<f64>) -> Option<Vector3<f64>> {
    let r0 = m.row(0).transpose();
    let r1 = m.row(1).transpose();
    let r2 = m.row(2).transpose();
    let candidates = [r0.cross(&r1), r0.cross(&r2), r1.cross(&r2)];
    let best = candidates
        .iter()
        .max_by(|a, b| a.norm_squared().total_cmp(&b.norm_squared()))?;
    best.try_normalize(1e-300)
}

/// Intersects the plane `u·Λ = 0` with the quadric `Λᵀ D Λ = 0`, scales each ray to metric
/// depths and appends the resulting poses.
#[allow(clippy::too_many_arguments)]
fn solve_on_plane(
    u: &Vector3<f64>,
    d: &Matrix3<f64>,
    a: [f64; 3],
    b: [f64; 3],
    bearings: &[Vector3<f64>; 3],
    points: &[Vector3<f64>; 3],
    world_frame_inv: &Matrix3<f64>,
    out: &mut Vec<PoseMatrix>,
) {
    // Eliminate the depth with the largest coefficient; parametrise the rest by a ratio τ:
    // Λ ∝ v0 + τ v1.
    let k = u.iamax();
    if !(u[k].abs() > 1e-300) {
        return;
    }
    let (p, q) = match k {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let mut v0 = Vector3::zeros();
    let mut v1 = Vector3::zeros();
    v0[p] = 1.0;
    v0[k] = -u[p] / u[k];
    v1[q] = 1.0;
    v1[k] = -u[q] / u[k];
    let qa = v1.dot(&(d * v1));
    let qb = 2.0 * v0.dot(&(d * v1));
    let qc = v0.dot(&(d * v0));
    let mut taus = [0.0; 2];
    let num_taus = quadratic_roots(qa, qb, qc, &mut taus);
    let [a12, a13, a23] = a;
    let [b12, b13, b23] = b;
    for &tau in &taus[..num_taus] {
        let v = v0 + tau * v1;
        // Depths must all be positive (up to the common scale, whose sign is free).
        let v = if v.sum() < 0.0 { -v } else { v };
        if v.iter().any(|&x| x <= 0.0) {
            continue;
        }
        // Metric scale from the best-conditioned pair (the longest side).
        let q12 = v[0] * v[0] + v[1] * v[1] - 2.0 * b12 * v[0] * v[1];
        let q13 = v[0] * v[0] + v[2] * v[2] - 2.0 * b13 * v[0] * v[2];
        let q23 = v[1] * v[1] + v[2] * v[2] - 2.0 * b23 * v[1] * v[2];
        let (aa, qq) = if a12 >= a13 && a12 >= a23 {
            (a12, q12)
        } else if a13 >= a23 {
            (a13, q13)
        } else {
            (a23, q23)
        };
        if !(qq > 0.0) {
            continue;
        }
        let mut lambda = v * (aa / qq).sqrt();
        refine_depths(&mut lambda, a, b);
        if lambda.iter().any(|&l| !(l > 0.0)) {
            continue;
        }
        let [y1, y2, y3] = bearings;
        let c12 = lambda[0] * y1 - lambda[1] * y2;
        let c13 = lambda[0] * y1 - lambda[2] * y3;
        let cam_frame = Matrix3::from_columns(&[c12, c13, c12.cross(&c13)]);
        let rotation = cam_frame * world_frame_inv;
        let translation = lambda[0] * y1 - rotation * points[0];
        let pose = PoseMatrix::new(rotation, translation);
        if pose.is_valid() {
            out.push(pose);
        }
    }
}

/// Gauss–Newton on the three distance equations; the algebraic solution loses digits when the
/// cubic or quadratic roots are close, and a few Newton steps restore full precision.
fn refine_depths(lambda: &mut Vector3<f64>, a: [f64; 3], b: [f64; 3]) {
    let [a12, a13, a23] = a;
    let [b12, b13, b23] = b;
    for _ in 0..5 {
        let (l1, l2, l3) = (lambda[0], lambda[1], lambda[2]);
        let r = Vector3::new(
            l1 * l1 + l2 * l2 - 2.0 * b12 * l1 * l2 - a12,
            l1 * l1 + l3 * l3 - 2.0 * b13 * l1 * l3 - a13,
            l2 * l2 + l3 * l3 - 2.0 * b23 * l2 * l3 - a23,
        );
        if r.abs().sum() < 1e-13 * (a12 + a13 + a23) {
            return;
        }
        let j = Matrix3::new(
            2.0 * (l1 - b12 * l2),
            2.0 * (l2 - b12 * l1),
            0.0,
            2.0 * (l1 - b13 * l3),
            0.0,
            2.0 * (l3 - b13 * l1),
            0.0,
            2.0 * (l2 - b23 * l3),
            2.0 * (l3 - b23 * l2),
        );
        let Some(step) = j.lu().solve(&r) else {
            return;
        };
        let next = *lambda - step;
        if !next.iter().all(|x| x.is_finite()) {
            return;
        }
        *lambda = next;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    fn check_recovers(
        rotation: Matrix3<f64>,
        translation: Vector3<f64>,
        points: [Vector3<f64>; 3],
    ) {
        let gt = PoseMatrix::new(rotation, translation);
        let bearings = points.map(|p| gt.transform(&p).normalize());
        let mut out = Vec::new();
        p3p(&bearings, &points, &mut out);
        assert!(!out.is_empty() && out.len() <= 4, "{} solutions", out.len());
        let best = out
            .iter()
            .map(|m| (m.rotation - rotation).norm() + (m.translation - translation).norm())
            .fold(f64::INFINITY, f64::min);
        assert!(best < 1e-8, "best error {best}");
    }

    #[test]
    fn recovers_a_known_pose() {
        let r = Rotation3::from_euler_angles(0.1, -0.3, 0.7).into_inner();
        check_recovers(
            r,
            Vector3::new(0.3, -1.0, 20.0),
            [
                Vector3::new(1.0, 2.0, 3.0),
                Vector3::new(-4.0, 1.0, 0.5),
                Vector3::new(2.0, -3.0, -1.0),
            ],
        );
    }

    #[test]
    fn degenerate_samples_give_no_pose() {
        let bearings = [
            Vector3::z(),
            Vector3::new(0.1, 0.0, 1.0).normalize(),
            Vector3::new(0.0, 0.1, 1.0).normalize(),
        ];
        let mut out = Vec::new();
        let collinear = [
            Vector3::zeros(),
            Vector3::new(1.0, 1.0, 1.0),
            Vector3::new(2.0, 2.0, 2.0),
        ];
        p3p(&bearings, &collinear, &mut out);
        assert!(out.is_empty());
        let coincident = [
            Vector3::zeros(),
            Vector3::zeros(),
            Vector3::new(2.0, 2.0, 2.0),
        ];
        p3p(&bearings, &coincident, &mut out);
        assert!(out.is_empty());
        let nan = [
            Vector3::zeros(),
            Vector3::new(f64::NAN, 0.0, 0.0),
            Vector3::new(2.0, 2.0, 2.0),
        ];
        p3p(&bearings, &nan, &mut out);
        assert!(out.is_empty());
    }
}
