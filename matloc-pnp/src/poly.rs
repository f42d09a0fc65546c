//! Real roots of low-degree polynomials, as the minimal solvers need them.

/// Real roots of `a x² + b x + c`, written into `out`; returns how many.
///
/// Uses the cancellation-free form of the quadratic formula; a (numerically) zero leading
/// coefficient degrades to the linear equation.
pub(crate) fn quadratic_roots(a: f64, b: f64, c: f64, out: &mut [f64; 2]) -> usize {
    let scale = a.abs().max(b.abs()).max(c.abs());
    if !(scale > 0.0) || !scale.is_finite() {
        return 0;
    }
    if a.abs() <= 1e-14 * scale {
        if b.abs() <= 1e-14 * scale {
            return 0;
        }
        out[0] = -c / b;
        return 1;
    }
    let disc = b * b - 4.0 * a * c;
    // A slightly negative discriminant is a rounded double root: keep it.
    if disc < -1e-12 * (b * b).max((4.0 * a * c).abs()) {
        return 0;
    }
    let sq = disc.max(0.0).sqrt();
    let q = -0.5 * (b + b.signum() * sq);
    if q == 0.0 {
        out[0] = 0.0;
        return 1;
    }
    out[0] = q / a;
    out[1] = c / q;
    2
}

/// Real roots of `c3 x³ + c2 x² + c1 x + c0`, polished by Newton steps; returns how many.
pub(crate) fn cubic_roots(c3: f64, c2: f64, c1: f64, c0: f64, out: &mut [f64; 3]) -> usize {
    let scale = c3.abs().max(c2.abs()).max(c1.abs()).max(c0.abs());
    if !(scale > 0.0) || !scale.is_finite() {
        return 0;
    }
    if c3.abs() <= 1e-12 * scale {
        let mut q = [0.0; 2];
        let n = quadratic_roots(c2, c1, c0, &mut q);
        out[..n].copy_from_slice(&q[..n]);
        return n;
    }
    let (a, b, c) = (c2 / c3, c1 / c3, c0 / c3);
    // Depressed cubic t³ + p t + q with x = t - a/3.
    let p = b - a * a / 3.0;
    let q = 2.0 * a * a * a / 27.0 - a * b / 3.0 + c;
    let disc = 0.25 * q * q + p * p * p / 27.0;
    let shift = -a / 3.0;
    let n = if disc > 0.0 {
        let s = disc.sqrt();
        out[0] = (-0.5 * q + s).cbrt() + (-0.5 * q - s).cbrt() + shift;
        1
    } else if p == 0.0 {
        out[0] = shift;
        1
    } else {
        let r = 2.0 * (-p / 3.0).sqrt();
        let cos_arg = (1.5 * q / p * (-3.0 / p).sqrt()).clamp(-1.0, 1.0);
        let phi = cos_arg.acos() / 3.0;
        for (k, root) in out.iter_mut().enumerate() {
            *root = r * (phi - 2.0 * std::f64::consts::PI * k as f64 / 3.0).cos() + shift;
        }
        3
    };
    // The closed forms lose digits near multiple roots; Newton on the monic cubic recovers them.
    for root in out.iter_mut().take(n) {
        for _ in 0..2 {
            let x = *root;
            let f = ((x + a) * x + b) * x + c;
            let df = (3.0 * x + 2.0 * a) * x + b;
            if df.abs() > 1e-300 {
                let next = x - f / df;
                if next.is_finite() {
                    *root = next;
                }
            }
        }
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cubic_with_three_roots() {
        // (x - 1)(x + 2)(x - 3) = x³ - 2x² - 5x + 6
        let mut r = [0.0; 3];
        let n = cubic_roots(1.0, -2.0, -5.0, 6.0, &mut r);
        assert_eq!(n, 3);
        let mut r = r.to_vec();
        r.sort_by(f64::total_cmp);
        for (got, want) in r.iter().zip([-2.0, 1.0, 3.0]) {
            assert!((got - want).abs() < 1e-12);
        }
    }

    #[test]
    fn cubic_with_one_root_and_quadratic_fallback() {
        let mut r = [0.0; 3];
        // (x - 2)(x² + 1)
        assert_eq!(cubic_roots(2.0, -4.0, 2.0, -4.0, &mut r), 1);
        assert!((r[0] - 2.0).abs() < 1e-12);
        // 0 x³ + (x - 1)(x - 4)
        assert_eq!(cubic_roots(0.0, 1.0, -5.0, 4.0, &mut r), 2);
        let mut q = [0.0; 2];
        assert_eq!(quadratic_roots(1.0, 0.0, 1.0, &mut q), 0);
    }
}
