//! EPnP non-minimal solver (Lepetit, Moreno-Noguer & Fua, "EPnP: An Accurate O(n) Solution to
//! the PnP Problem", IJCV 2009), with the planar case on three control points.
//!
//! World points are written as barycentric combinations of 4 control points (3 when the points
//! lie on a plane — the aerial case); the camera-frame control points then satisfy a homogeneous
//! linear system whose null space is at most 4-dimensional. The null-space coefficients β follow
//! from the preserved distances between control points: linearised estimates for 1, 2 and 3
//! null vectors, each polished by Gauss–Newton on all of them, and the candidate with the
//! smallest reprojection error wins. The pose is the absolute orientation (Kabsch) between the
//! reconstructed camera-frame points and the world points.

use nalgebra::{DMatrix, DVector, Matrix3, SymmetricEigen, Vector2, Vector3};

use crate::model::PoseMatrix;

/// Smallest-to-largest spread ratio (variance) below which the points count as planar.
const PLANAR_RATIO: f64 = 1e-8;
/// Second-to-largest spread ratio (variance) below which the points count as collinear.
const COLLINEAR_RATIO: f64 = 1e-12;

/// Estimates `cam_from_world` from `n ≥ 4` correspondences between undistorted normalised image
/// points (`x/z`, `y/z`) and world points; `None` for degenerate input (fewer than 4 points,
/// collinear or coincident points, non-finite values).
///
/// Noise-free input in general position gives the exact pose; with noise the result is a good
/// initial value for [`crate::refine_pose`].
pub fn epnp(normalized: &[Vector2<f64>], points_world: &[Vector3<f64>]) -> Option<PoseMatrix> {
    let n = points_world.len();
    if n < 4 || normalized.len() != n {
        return None;
    }
    let centroid = points_world.iter().sum::<Vector3<f64>>() / n as f64;
    let mut cov = Matrix3::zeros();
    for p in points_world {
        let d = p - centroid;
        cov += d * d.transpose();
    }
    cov /= n as f64;
    if !cov.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eig = SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let spread: [f64; 3] = order.map(|k| eig.eigenvalues[k]);
    let axes: [Vector3<f64>; 3] = order.map(|k| eig.eigenvectors.column(k).into_owned());
    if !(spread[0] > 0.0) || spread[1] < COLLINEAR_RATIO * spread[0] {
        return None;
    }
    let planar = spread[2] < PLANAR_RATIO * spread[0];
    let num_ctrl = if planar { 3 } else { 4 };

    // Control points: the centroid plus one step of one standard deviation along each axis.
    let mut ctrl_world = vec![centroid];
    for k in 0..num_ctrl - 1 {
        ctrl_world.push(centroid + spread[k].sqrt() * axes[k]);
    }
    let alphas: Vec<[f64; 4]> = points_world
        .iter()
        .map(|p| {
            let d = p - centroid;
            let mut a = [0.0; 4];
            for k in 0..num_ctrl - 1 {
                a[k + 1] = axes[k].dot(&d) / spread[k].sqrt();
            }
            a[0] = 1.0 - a[1..].iter().sum::<f64>();
            a
        })
        .collect();

    // MᵀM accumulated point by point; M has two rows per point and 3 columns per control point.
    let dim = 3 * num_ctrl;
    let mut mtm = DMatrix::<f64>::zeros(dim, dim);
    let mut ru = DVector::<f64>::zeros(dim);
    let mut rv = DVector::<f64>::zeros(dim);
    for (a, m) in alphas.iter().zip(normalized) {
        for j in 0..num_ctrl {
            ru[3 * j] = a[j];
            ru[3 * j + 1] = 0.0;
            ru[3 * j + 2] = -a[j] * m.x;
            rv[3 * j] = 0.0;
            rv[3 * j + 1] = a[j];
            rv[3 * j + 2] = -a[j] * m.y;
        }
        mtm.ger(1.0, &ru, &ru, 1.0);
        mtm.ger(1.0, &rv, &rv, 1.0);
    }
    if !mtm.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eig = SymmetricEigen::new(mtm);
    let mut idx: Vec<usize> = (0..dim).collect();
    idx.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let num_null = num_ctrl;
    let null: Vec<DVector<f64>> = idx[..num_null]
        .iter()
        .map(|&k| eig.eigenvectors.column(k).into_owned())
        .collect();

    // Distance constraints between every pair of control points.
    let mut pairs = Vec::new();
    for a in 0..num_ctrl {
        for b in a + 1..num_ctrl {
            let rho = (ctrl_world[a] - ctrl_world[b]).norm_squared();
            let diffs: Vec<Vector3<f64>> = null
                .iter()
                .map(|v| {
                    Vector3::new(
                        v[3 * a] - v[3 * b],
                        v[3 * a + 1] - v[3 * b + 1],
                        v[3 * a + 2] - v[3 * b + 2],
                    )
                })
                .collect();
            pairs.push((rho, diffs));
        }
    }

    let mut candidates: Vec<Vec<f64>> = Vec::new();
    // One null vector: β minimising the mismatch of distances (not of squared distances).
    {
        let (mut num, mut den) = (0.0, 0.0);
        for (rho, d) in &pairs {
            num += rho.sqrt() * d[0].norm();
            den += d[0].norm_squared();
        }
        if den > 0.0 {
            candidates.push(vec![num / den]);
        }
    }
    // Two and three null vectors: linear in the products β_k β_l.
    for k in 2..=3.min(num_null) {
        let products: Vec<(usize, usize)> =
            (0..k).flat_map(|i| (i..k).map(move |j| (i, j))).collect();
        if products.len() > pairs.len() {
            continue;
        }
        let l = DMatrix::from_fn(pairs.len(), products.len(), |r, c| {
            let (i, j) = products[c];
            let d = &pairs[r].1;
            if i == j {
                d[i].norm_squared()
            } else {
                2.0 * d[i].dot(&d[j])
            }
        });
        let rho = DVector::from_iterator(pairs.len(), pairs.iter().map(|(r, _)| *r));
        let Some(bb) = l.clone().svd(true, true).solve(&rho, 1e-12).ok() else {
            continue;
        };
        let mut beta = vec![0.0; k];
        beta[0] = bb[0].abs().sqrt();
        for i in 1..k {
            let sq = products
                .iter()
                .position(|&p| p == (i, i))
                .map(|c| bb[c])
                .unwrap_or(0.0);
            let cross = products
                .iter()
                .position(|&p| p == (0, i))
                .map(|c| bb[c])
                .unwrap_or(0.0);
            beta[i] = sq.abs().sqrt() * if cross < 0.0 { -1.0 } else { 1.0 };
        }
        candidates.push(beta);
    }

    let mut best: Option<(f64, PoseMatrix)> = None;
    for beta in candidates {
        let mut full = vec![0.0; num_null];
        full[..beta.len()].copy_from_slice(&beta);
        refine_betas(&pairs, &mut full);
        let Some(pose) = pose_from_betas(&full, &null, &alphas, points_world, num_ctrl) else {
            continue;
        };
        let err = reprojection_error(&pose, normalized, points_world);
        if err.is_finite() && best.as_ref().is_none_or(|(e, _)| err < *e) {
            best = Some((err, pose));
        }
    }
    best.map(|(_, p)| p)
}

/// Gauss–Newton on the control-point distance constraints over all null-space coefficients.
fn refine_betas(pairs: &[(f64, Vec<Vector3<f64>>)], beta: &mut [f64]) {
    let k = beta.len();
    for _ in 0..5 {
        let mut jtj = DMatrix::<f64>::zeros(k, k);
        let mut jtr = DVector::<f64>::zeros(k);
        for (rho, d) in pairs {
            let v: Vector3<f64> = d.iter().zip(beta.iter()).map(|(dk, b)| dk * *b).sum();
            let r = v.norm_squared() - rho;
            let j = DVector::from_iterator(k, d.iter().map(|dk| 2.0 * v.dot(dk)));
            jtj.ger(1.0, &j, &j, 1.0);
            jtr.axpy(r, &j, 1.0);
        }
        // Tiny damping: with fewer constraints than unknowns (planar) JᵀJ is singular.
        let damping = 1e-12 * jtj.diagonal().max().max(1e-300);
        for i in 0..k {
            jtj[(i, i)] += damping;
        }
        let Some(step) = jtj.cholesky().map(|c| c.solve(&jtr)) else {
            return;
        };
        if !step.iter().all(|s| s.is_finite()) {
            return;
        }
        for i in 0..k {
            beta[i] -= step[i];
        }
    }
}

/// Camera-frame points from null-space coefficients, then absolute orientation to the world.
fn pose_from_betas(
    beta: &[f64],
    null: &[DVector<f64>],
    alphas: &[[f64; 4]],
    points_world: &[Vector3<f64>],
    num_ctrl: usize,
) -> Option<PoseMatrix> {
    let mut ctrl_cam = [Vector3::zeros(); 4];
    for (j, c) in ctrl_cam.iter_mut().enumerate().take(num_ctrl) {
        for (b, v) in beta.iter().zip(null) {
            *c += *b * Vector3::new(v[3 * j], v[3 * j + 1], v[3 * j + 2]);
        }
    }
    let mut pts_cam: Vec<Vector3<f64>> = alphas
        .iter()
        .map(|a| (0..num_ctrl).map(|j| a[j] * ctrl_cam[j]).sum())
        .collect();
    // The null space fixes the points only up to sign: the scene is in front of the camera.
    let mean_depth: f64 = pts_cam.iter().map(|p| p.z).sum();
    if mean_depth < 0.0 {
        for p in &mut pts_cam {
            *p = -*p;
        }
    }
    absolute_orientation(points_world, &pts_cam)
}

/// Rigid transform `T` minimising `Σ |T p_world − p_cam|²` (Kabsch / Umeyama without scale).
pub(crate) fn absolute_orientation(
    points_world: &[Vector3<f64>],
    points_cam: &[Vector3<f64>],
) -> Option<PoseMatrix> {
    let n = points_world.len() as f64;
    let cw = points_world.iter().sum::<Vector3<f64>>() / n;
    let cc = points_cam.iter().sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    for (pw, pc) in points_world.iter().zip(points_cam) {
        h += (pc - cc) * (pw - cw).transpose();
    }
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let rotation = u * d * v_t;
    let pose = PoseMatrix::new(rotation, cc - rotation * cw);
    pose.is_valid().then_some(pose)
}

/// Sum of squared reprojection errors in normalised coordinates (points behind: infinite).
fn reprojection_error(
    pose: &PoseMatrix,
    normalized: &[Vector2<f64>],
    points: &[Vector3<f64>],
) -> f64 {
    normalized
        .iter()
        .zip(points)
        .map(|(m, p)| {
            let pc = pose.transform(p);
            if pc.z <= 0.0 {
                return f64::INFINITY;
            }
            (Vector2::new(pc.x / pc.z, pc.y / pc.z) - m).norm_squared()
        })
        .sum()
}
