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
        assert_eq!(
            self.n_out, O,
            "Linear::forward called with the wrong output width"
        );
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

    /// Transposed weights (`n_out × n_in`), the layout the input-gradient kernel wants.
    pub fn transposed(&self) -> Vec<f32> {
        let (ni, no) = (self.n_in, self.n_out);
        let mut t = vec![0f32; ni * no];
        for i in 0..ni {
            for o in 0..no {
                t[o * ni + i] = self.w[i * no + o];
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
            16 => self.weight_grad::<16>(x, dy, grad),
            _ => self.weight_grad_generic(x, dy, grad),
        }
        if let Some(dx) = dx {
            input_grad(self.n_in, self.n_out, wt, dy, dx);
        }
    }

    /// `∂L/∂W += Xᵀ·dY` with two rows of `∂L/∂W` held in registers across the whole batch,
    /// so the inner loop has no stores.
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
        let mut i = 0;
        while i + 1 < ni {
            let mut a = [0f32; O];
            let mut b = [0f32; O];
            for p in 0..n {
                let xa = x[p * ni + i];
                let xb = x[p * ni + i + 1];
                let d: &[f32; O] = dy[p * O..(p + 1) * O].try_into().expect("row");
                for o in 0..O {
                    a[o] = xa.mul_add(d[o], a[o]);
                    b[o] = xb.mul_add(d[o], b[o]);
                }
            }
            for o in 0..O {
                grad.w[i * O + o] += a[o];
                grad.w[(i + 1) * O + o] += b[o];
            }
            i += 2;
        }
        if i < ni {
            let mut a = [0f32; O];
            for p in 0..n {
                let xa = x[p * ni + i];
                for o in 0..O {
                    a[o] = xa.mul_add(dy[p * O + o], a[o]);
                }
            }
            for o in 0..O {
                grad.w[i * O + o] += a[o];
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

/// `dX = dY·Wᵀ` using the transposed weights `wt` (`n_out × n_in`): 8 outputs at a time in
/// one vector accumulator, one broadcast-FMA per output unit, no horizontal reductions.
fn input_grad(ni: usize, no: usize, wt: &[f32], dy: &[f32], dx: &mut [f32]) {
    for (dxr, dyr) in dx.chunks_exact_mut(ni).zip(dy.chunks_exact(no)) {
        let mut i0 = 0;
        while i0 + 16 <= ni {
            let mut a = [0f32; 16];
            for (o, &d) in dyr.iter().enumerate() {
                let w: &[f32; 16] = wt[o * ni + i0..o * ni + i0 + 16].try_into().expect("w");
                for l in 0..16 {
                    a[l] = d.mul_add(w[l], a[l]);
                }
            }
            dxr[i0..i0 + 16].copy_from_slice(&a);
            i0 += 16;
        }
        while i0 + 8 <= ni {
            let mut a = [0f32; 8];
            for (o, &d) in dyr.iter().enumerate() {
                let w: &[f32; 8] = wt[o * ni + i0..o * ni + i0 + 8].try_into().expect("w");
                for l in 0..8 {
                    a[l] = d.mul_add(w[l], a[l]);
                }
            }
            dxr[i0..i0 + 8].copy_from_slice(&a);
            i0 += 8;
        }
        for i in i0..ni {
            let mut a = 0f32;
            for (o, &d) in dyr.iter().enumerate() {
                a = d.mul_add(wt[o * ni + i], a);
            }
            dxr[i] = a;
        }
    }
}
