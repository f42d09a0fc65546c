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
    /// Two points are processed together so each weight row load feeds two FMAs.
    #[inline]
    pub fn forward<const O: usize>(&self, x: &[f32], y: &mut [f32], relu: bool) {
        assert_eq!(self.n_out, O, "Linear::forward called with the wrong output width");
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

    /// Backward for a batch: accumulates `∂L/∂W`, `∂L/∂b` into `grad` and, if `dx` is given,
    /// writes `∂L/∂x` (`n × n_in`). `dy` must already include the activation's derivative.
    pub fn backward(&self, x: &[f32], dy: &[f32], dx: Option<&mut [f32]>, grad: &mut LinearGrad) {
        let (ni, no) = (self.n_in, self.n_out);
        for (xr, dyr) in x.chunks_exact(ni).zip(dy.chunks_exact(no)) {
            for (gb, d) in grad.b.iter_mut().zip(dyr) {
                *gb += d;
            }
            for (gw, &xi) in grad.w.chunks_exact_mut(no).zip(xr) {
                if xi == 0.0 {
                    continue;
                }
                for (g, d) in gw.iter_mut().zip(dyr) {
                    *g = xi.mul_add(*d, *g);
                }
            }
        }
        if let Some(dx) = dx {
            for (dxr, dyr) in dx.chunks_exact_mut(ni).zip(dy.chunks_exact(no)) {
                for (d, wr) in dxr.iter_mut().zip(self.w.chunks_exact(no)) {
                    *d = dot8(wr, dyr);
                }
            }
        }
    }
}

/// Dot product with 8 independent partial sums so the compiler can vectorise it without
/// reassociation licence.
#[inline(always)]
fn dot8(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let mut ac = a.chunks_exact(8);
    let mut bc = b.chunks_exact(8);
    for (x, y) in (&mut ac).zip(&mut bc) {
        for l in 0..8 {
            acc[l] = x[l].mul_add(y[l], acc[l]);
        }
    }
    let mut s = 0.0;
    for (x, y) in ac.remainder().iter().zip(bc.remainder()) {
        s = x.mul_add(*y, s);
    }
    s + ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}
