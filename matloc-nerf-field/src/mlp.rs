use rand::Rng;

/// A dense layer `y = x·W + b` with `W` stored input-major (`w[i * n_out + o]`).
///
/// Input-major storage makes the forward an axpy over outputs (vectorises over `o` with
/// the accumulator held in registers) and the weight gradient an outer-product axpy; the
/// input gradient uses lane-split dot products over `o`.
#[derive(Clone, Debug, PartialEq)]
pub struct Linear {
    /// Input width.
    pub n_in: usize,
    /// Output width.
    pub n_out: usize,
    /// Weights, `n_in × n_out`, input-major.
    pub w: Vec<f32>,
    /// Bias, `n_out`.
    pub b: Vec<f32>,
}

/// Gradient buffers matching a [`Linear`].
#[derive(Clone, Debug, PartialEq)]
pub struct LinearGrad {
    /// `∂L/∂w`, same layout as [`Linear::w`].
    pub w: Vec<f32>,
    /// `∂L/∂b`.
    pub b: Vec<f32>,
}

impl LinearGrad {
    /// Zero gradient for a layer of the given shape.
    pub fn zeros(n_in: usize, n_out: usize) -> Self {
        Self {
            w: vec![0.0; n_in * n_out],
            b: vec![0.0; n_out],
        }
    }

    /// `self += other`.
    pub fn add(&mut self, other: &Self) {
        for (a, b) in self.w.iter_mut().zip(&other.w) {
            *a += b;
        }
        for (a, b) in self.b.iter_mut().zip(&other.b) {
            *a += b;
        }
    }
}

impl Linear {
    /// Uniform init with bound `gain · sqrt(3 / n_in)` (gain √2 = Kaiming for ReLU), zero bias.
    pub fn new<R: Rng>(n_in: usize, n_out: usize, gain: f32, rng: &mut R) -> Self {
        let bound = gain * (3.0 / n_in as f32).sqrt();
        Self {
            n_in,
            n_out,
            w: (0..n_in * n_out)
                .map(|_| rng.random_range(-bound..bound))
                .collect(),
            b: vec![0.0; n_out],
        }
    }

    /// Zero gradient of this layer's shape.
    pub fn zero_grad(&self) -> LinearGrad {
        LinearGrad::zeros(self.n_in, self.n_out)
    }

    /// Forward for a batch (`x`: `n × n_in`, `y`: `n × O`), optionally ReLU.
    ///
    /// `O` must equal `n_out`; making it a const lets the accumulators live in registers.
    /// Register-blocked: a tile of [`TILE_P`] points × 16 outputs (12 vector accumulators)
    /// per pass over the inputs, so each weight load feeds 6 FMAs and nothing spills.
    #[inline]
    pub fn forward<const O: usize>(&self, x: &[f32], y: &mut [f32], relu: bool) {
        assert_eq!(
            self.n_out, O,
            "Linear::forward called with the wrong output width"
        );
        let ni = self.n_in;
        let bias: &[f32; O] = self.b.as_slice().try_into().expect("bias length");
        if !O.is_multiple_of(16) {
            return self.forward_narrow::<O>(x, y, relu);
        }
        let mut xs = x.chunks_exact(TILE_P * ni);
        let mut ys = y.chunks_exact_mut(TILE_P * O);
        for (xt, yt) in (&mut xs).zip(&mut ys) {
            fwd_tile::<TILE_P, O>(&self.w, bias, xt, ni, yt, relu);
        }
        let (xr, yr) = (xs.remainder(), ys.into_remainder());
        match yr.len() / O {
            0 => {}
            1 => fwd_tile::<1, O>(&self.w, bias, xr, ni, yr, relu),
            2 => fwd_tile::<2, O>(&self.w, bias, xr, ni, yr, relu),
            3 => fwd_tile::<3, O>(&self.w, bias, xr, ni, yr, relu),
            4 => fwd_tile::<4, O>(&self.w, bias, xr, ni, yr, relu),
            _ => fwd_tile::<5, O>(&self.w, bias, xr, ni, yr, relu),
        }
    }

    /// Forward for output widths that are not a multiple of 16 (the 3-wide RGB head): all
    /// outputs of two points in registers.
    fn forward_narrow<const O: usize>(&self, x: &[f32], y: &mut [f32], relu: bool) {
        let ni = self.n_in;
        let bias: &[f32; O] = self.b.as_slice().try_into().expect("bias length");
        let mut xs = x.chunks_exact(2 * ni);
        let mut ys = y.chunks_exact_mut(2 * O);
        for (x2, y2) in (&mut xs).zip(&mut ys) {
            let (xa, xb) = x2.split_at(ni);
            let mut a = *bias;
            let mut b = *bias;
            for ((wa, &va), &vb) in self.w.chunks_exact(O).zip(xa).zip(xb) {
                let wr: &[f32; O] = wa.try_into().expect("row");
                for o in 0..O {
                    a[o] = va.mul_add(wr[o], a[o]);
                    b[o] = vb.mul_add(wr[o], b[o]);
                }
            }
            if relu {
                for o in 0..O {
                    a[o] = a[o].max(0.0);
                    b[o] = b[o].max(0.0);
                }
            }
            y2[..O].copy_from_slice(&a);
            y2[O..].copy_from_slice(&b);
        }
        for (x1, y1) in xs
            .remainder()
            .chunks_exact(ni)
            .zip(ys.into_remainder().chunks_exact_mut(O))
        {
            let mut a = *bias;
            for (wa, &va) in self.w.chunks_exact(O).zip(x1) {
                let wr: &[f32; O] = wa.try_into().expect("row");
                for o in 0..O {
                    a[o] = va.mul_add(wr[o], a[o]);
                }
            }
            if relu {
                for v in &mut a {
                    *v = v.max(0.0);
                }
            }
            y1.copy_from_slice(&a);
        }
    }

    /// Transposed weights, `n_out` rows of `n_in` rounded up to a multiple of 8 (zero
    /// padded): the layout the input-gradient kernel wants.
    pub fn transposed(&self) -> Vec<f32> {
        let (ni, no) = (self.n_in, self.n_out);
        let stride = ni.next_multiple_of(8);
        let mut t = vec![0f32; stride * no];
        for i in 0..ni {
            for o in 0..no {
                t[o * stride + i] = self.w[i * no + o];
            }
        }
        t
    }

    /// Backward for a batch: accumulates `∂L/∂W`, `∂L/∂b` into `grad` and, if `dx` is given,
    /// writes `∂L/∂x` (`n × n_in`). `dy` must already include the activation's derivative.
    pub fn backward(&self, x: &[f32], dy: &[f32], dx: Option<&mut [f32]>, grad: &mut LinearGrad) {
        let wt = if dx.is_some() {
            self.transposed()
        } else {
            Vec::new()
        };
        self.backward_with(x, dy, dx, &wt, grad);
    }

    /// [`Self::backward`] with the transposed weights supplied (computed once per pass by
    /// the caller instead of once per chunk).
    pub fn backward_with(
        &self,
        x: &[f32],
        dy: &[f32],
        dx: Option<&mut [f32]>,
        wt: &[f32],
        grad: &mut LinearGrad,
    ) {
        match self.n_out {
            64 => self.weight_grad::<64>(x, dy, grad),
            32 => self.weight_grad::<32>(x, dy, grad),
            16 => self.weight_grad::<16>(x, dy, grad),
            _ => self.weight_grad_narrow(x, dy, grad),
        }
        if let Some(dx) = dx {
            input_grad(self.n_in, self.n_out, wt, dy, dx);
        }
    }

    /// `∂L/∂W += Xᵀ·dY`, register-blocked: a tile of 6 inputs × 16 outputs of `∂L/∂W`
    /// (12 vector accumulators) is held in registers across the whole batch.
    fn weight_grad<const O: usize>(&self, x: &[f32], dy: &[f32], grad: &mut LinearGrad) {
        let ni = self.n_in;
        let n = dy.len() / O;
        let mut gb = [0f32; O];
        for dyr in dy.chunks_exact(O) {
            for o in 0..O {
                gb[o] += dyr[o];
            }
        }
        for (g, v) in grad.b.iter_mut().zip(gb) {
            *g += v;
        }
        let x = &x[..n * ni];
        let mut i0 = 0;
        while i0 + 6 <= ni {
            wgrad_tile::<6, O>(x, ni, i0, dy, &mut grad.w);
            i0 += 6;
        }
        match ni - i0 {
            0 => {}
            1 => wgrad_tile::<1, O>(x, ni, i0, dy, &mut grad.w),
            2 => wgrad_tile::<2, O>(x, ni, i0, dy, &mut grad.w),
            3 => wgrad_tile::<3, O>(x, ni, i0, dy, &mut grad.w),
            4 => wgrad_tile::<4, O>(x, ni, i0, dy, &mut grad.w),
            _ => wgrad_tile::<5, O>(x, ni, i0, dy, &mut grad.w),
        }
    }

    /// `∂L/∂W += Xᵀ·dY` for narrow outputs (the 3-wide RGB head): one output column at a
    /// time, vectorised over inputs, summed over the batch in registers (accumulating
    /// straight into `grad` was a chain of scalar read-modify-writes per point).
    fn weight_grad_narrow(&self, x: &[f32], dy: &[f32], grad: &mut LinearGrad) {
        let (ni, no) = (self.n_in, self.n_out);
        if !ni.is_multiple_of(8) || no == 0 {
            return self.weight_grad_generic(x, dy, grad);
        }
        let n = dy.len() / no;
        let x = &x[..n * ni];
        for o in 0..no {
            let mut gb = 0f32;
            for dr in dy.chunks_exact(no) {
                gb += dr[o];
            }
            grad.b[o] += gb;
            let mut i0 = 0;
            while i0 + 32 <= ni {
                wgrad_column_tile::<4>(x, ni, i0, dy, no, o, &mut grad.w);
                i0 += 32;
            }
            while i0 < ni {
                wgrad_column_tile::<1>(x, ni, i0, dy, no, o, &mut grad.w);
                i0 += 8;
            }
        }
    }

    fn weight_grad_generic(&self, x: &[f32], dy: &[f32], grad: &mut LinearGrad) {
        let (ni, no) = (self.n_in, self.n_out);
        for (xr, dyr) in x.chunks_exact(ni).zip(dy.chunks_exact(no)) {
            for (gb, d) in grad.b.iter_mut().zip(dyr) {
                *gb += d;
            }
            for (gw, &xi) in grad.w.chunks_exact_mut(no).zip(xr) {
                for (g, d) in gw.iter_mut().zip(dyr) {
                    *g = xi.mul_add(*d, *g);
                }
            }
        }
    }
}

/// Points per register tile of the forward and input-gradient kernels.
const TILE_P: usize = 6;

/// Eight lanes; the kernels below are written so each `[f32; 8]` becomes one AVX register.
type V8 = [f32; 8];

#[inline(always)]
fn v8(s: &[f32]) -> V8 {
    s[..8].try_into().expect("8 lanes")
}

/// `acc += a · w` lane-wise.
#[inline(always)]
fn fma8(acc: &mut V8, a: f32, w: &V8) {
    for l in 0..8 {
        acc[l] = a.mul_add(w[l], acc[l]);
    }
}

/// `y = x·W + b` for `P` points (`x`: `P × ni`, `y`: `P × O`, `O` a multiple of 16).
#[inline(always)]
fn fwd_tile<const P: usize, const O: usize>(
    w: &[f32],
    bias: &[f32; O],
    x: &[f32],
    ni: usize,
    y: &mut [f32],
    relu: bool,
) {
    let rows: [&[f32]; P] = std::array::from_fn(|p| &x[p * ni..(p + 1) * ni]);
    let w = &w[..ni * O];
    for ob in (0..O).step_by(16) {
        let b0 = v8(&bias[ob..]);
        let b1 = v8(&bias[ob + 8..]);
        let mut acc = [[b0, b1]; P];
        for i in 0..ni {
            let wr = &w[i * O + ob..i * O + ob + 16];
            let w0 = v8(wr);
            let w1 = v8(&wr[8..]);
            for p in 0..P {
                let xv = rows[p][i];
                fma8(&mut acc[p][0], xv, &w0);
                fma8(&mut acc[p][1], xv, &w1);
            }
        }
        // Constant-index epilogue: iterator adaptors over `acc` made LLVM keep a stack copy
        // of every accumulator updated in the inner loop (12 extra stores per input).
        for p in 0..P {
            let out = &mut y[p * O + ob..p * O + ob + 16];
            for v in 0..2 {
                for l in 0..8 {
                    let a = acc[p][v][l];
                    out[8 * v + l] = if relu { a.max(0.0) } else { a };
                }
            }
        }
    }
}

/// `∂L/∂W[i0..i0+IB, :] += X[:, i0..i0+IB]ᵀ·dY` over all points (`O` a multiple of 16).
#[inline(always)]
fn wgrad_tile<const IB: usize, const O: usize>(
    x: &[f32],
    ni: usize,
    i0: usize,
    dy: &[f32],
    gw: &mut [f32],
) {
    for ob in (0..O).step_by(16) {
        let mut acc = [[[0f32; 8]; 2]; IB];
        for (xr, dr) in x.chunks_exact(ni).zip(dy.chunks_exact(O)) {
            let xr = &xr[i0..i0 + IB];
            let d0 = v8(&dr[ob..]);
            let d1 = v8(&dr[ob + 8..]);
            for k in 0..IB {
                fma8(&mut acc[k][0], xr[k], &d0);
                fma8(&mut acc[k][1], xr[k], &d1);
            }
        }
        for k in 0..IB {
            let g = &mut gw[(i0 + k) * O + ob..(i0 + k) * O + ob + 16];
            for v in 0..2 {
                for l in 0..8 {
                    g[8 * v + l] += acc[k][v][l];
                }
            }
        }
    }
}

/// `∂L/∂W[i0..i0+8·NV, o] += X[:, i0..i0+8·NV]ᵀ·dY[:, o]` over all points.
#[inline(always)]
fn wgrad_column_tile<const NV: usize>(
    x: &[f32],
    ni: usize,
    i0: usize,
    dy: &[f32],
    no: usize,
    o: usize,
    gw: &mut [f32],
) {
    let mut acc = [[0f32; 8]; NV];
    for (xr, dr) in x.chunks_exact(ni).zip(dy.chunks_exact(no)) {
        let d = dr[o];
        for v in 0..NV {
            fma8(&mut acc[v], d, &v8(&xr[i0 + 8 * v..]));
        }
    }
    for v in 0..NV {
        for l in 0..8 {
            gw[(i0 + 8 * v + l) * no + o] += acc[v][l];
        }
    }
}

/// `dX = dY·Wᵀ` for `P` points and the `NV × 8` inputs from `i0`, from the padded
/// transposed weights `wt` (row stride `stride`); writes the first `width` of them.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn igrad_tile<const P: usize, const NV: usize>(
    wt: &[f32],
    stride: usize,
    no: usize,
    i0: usize,
    width: usize,
    dy: &[f32],
    dx: &mut [f32],
    ni: usize,
) {
    let rows: [&[f32]; P] = std::array::from_fn(|p| &dy[p * no..(p + 1) * no]);
    let mut acc = [[[0f32; 8]; NV]; P];
    for o in 0..no {
        let wr = &wt[o * stride + i0..o * stride + i0 + 8 * NV];
        let wv: [V8; NV] = std::array::from_fn(|v| v8(&wr[8 * v..]));
        for p in 0..P {
            let d = rows[p][o];
            for v in 0..NV {
                fma8(&mut acc[p][v], d, &wv[v]);
            }
        }
    }
    for p in 0..P {
        let out = &mut dx[p * ni + i0..p * ni + i0 + width];
        for v in 0..NV {
            for l in 0..8 {
                if 8 * v + l < width {
                    out[8 * v + l] = acc[p][v][l];
                }
            }
        }
    }
}

/// `dX = dY·Wᵀ` for `P` points, all inputs.
#[inline(always)]
fn igrad_points<const P: usize>(
    ni: usize,
    no: usize,
    wt: &[f32],
    stride: usize,
    dy: &[f32],
    dx: &mut [f32],
) {
    let mut i0 = 0;
    while i0 + 16 <= ni {
        igrad_tile::<P, 2>(wt, stride, no, i0, 16, dy, dx, ni);
        i0 += 16;
    }
    while i0 < ni {
        let width = (ni - i0).min(8);
        igrad_tile::<P, 1>(wt, stride, no, i0, width, dy, dx, ni);
        i0 += 8;
    }
}

/// `dX = dY·Wᵀ` using the padded transposed weights `wt` of [`Linear::transposed`]:
/// tiles of 6 points × 16 inputs, one broadcast-FMA per output unit and point.
fn input_grad(ni: usize, no: usize, wt: &[f32], dy: &[f32], dx: &mut [f32]) {
    let stride = ni.next_multiple_of(8);
    assert!(wt.len() >= stride * no, "transposed weights too short");
    let mut dys = dy.chunks_exact(TILE_P * no);
    let mut dxs = dx.chunks_exact_mut(TILE_P * ni);
    for (d, x) in (&mut dys).zip(&mut dxs) {
        igrad_points::<TILE_P>(ni, no, wt, stride, d, x);
    }
    let (d, x) = (dys.remainder(), dxs.into_remainder());
    match x.len() / ni.max(1) {
        0 => {}
        1 => igrad_points::<1>(ni, no, wt, stride, d, x),
        2 => igrad_points::<2>(ni, no, wt, stride, d, x),
        3 => igrad_points::<3>(ni, no, wt, stride, d, x),
        4 => igrad_points::<4>(ni, no, wt, stride, d, x),
        _ => igrad_points::<5>(ni, no, wt, stride, d, x),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// The blocked kernels against a plain triple loop, for the layer shapes of the field
    /// and batch sizes that exercise every remainder path.
    #[test]
    fn blocked_kernels_match_naive() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for (ni, no) in [
            (32, 64),
            (64, 16),
            (39, 64),
            (64, 64),
            (64, 3),
            (5, 16),
            (13, 32),
        ] {
            let l = Linear {
                b: (0..no).map(|_| rng.random_range(-1.0..1.0)).collect(),
                ..Linear::new(ni, no, 1.0, &mut rng)
            };
            for n in [0usize, 1, 5, 6, 7, 13, 128] {
                let x: Vec<f32> = (0..n * ni).map(|_| rng.random_range(-1.0..1.0)).collect();
                let dy: Vec<f32> = (0..n * no).map(|_| rng.random_range(-1.0..1.0)).collect();
                let mut y = vec![0f32; n * no];
                match no {
                    64 => l.forward::<64>(&x, &mut y, true),
                    32 => l.forward::<32>(&x, &mut y, true),
                    16 => l.forward::<16>(&x, &mut y, true),
                    _ => l.forward::<3>(&x, &mut y, true),
                }
                let mut g = l.zero_grad();
                let mut dx = vec![f32::NAN; n * ni];
                l.backward(&x, &dy, Some(&mut dx), &mut g);
                for p in 0..n {
                    for o in 0..no {
                        let r: f32 = l.b[o]
                            + (0..ni)
                                .map(|i| x[p * ni + i] * l.w[i * no + o])
                                .sum::<f32>();
                        assert!(
                            (y[p * no + o] - r.max(0.0)).abs() < 1e-4,
                            "fwd {ni}x{no} n={n}"
                        );
                    }
                    for i in 0..ni {
                        let r: f32 = (0..no).map(|o| dy[p * no + o] * l.w[i * no + o]).sum();
                        assert!((dx[p * ni + i] - r).abs() < 1e-4, "dx {ni}x{no} n={n}");
                    }
                }
                for i in 0..ni {
                    for o in 0..no {
                        let r: f32 = (0..n).map(|p| x[p * ni + i] * dy[p * no + o]).sum();
                        assert!((g.w[i * no + o] - r).abs() < 1e-3, "dw {ni}x{no} n={n}");
                    }
                }
                for o in 0..no {
                    let r: f32 = (0..n).map(|p| dy[p * no + o]).sum();
                    assert!((g.b[o] - r).abs() < 1e-3, "db {ni}x{no} n={n}");
                }
            }
        }
    }
}
