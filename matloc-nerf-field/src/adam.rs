use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Adam hyper-parameters (no weight decay).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AdamConfig {
    /// First-moment decay.
    pub beta1: f32,
    /// Second-moment decay.
    pub beta2: f32,
    /// Denominator epsilon; 1e-15 as instant-ngp/nerfacto so rarely-touched hash entries
    /// still get full-size steps.
    pub eps: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

/// Exponential learning-rate decay from `lr_init` to `lr_final` over `max_steps`, constant after.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ExponentialDecay {
    /// Learning rate at step 0.
    pub lr_init: f32,
    /// Learning rate at `max_steps` and after.
    pub lr_final: f32,
    /// Length of the decay.
    pub max_steps: u64,
}

impl Default for ExponentialDecay {
    fn default() -> Self {
        Self {
            lr_init: 1e-2,
            lr_final: 1e-4,
            max_steps: 10_000,
        }
    }
}

impl ExponentialDecay {
    /// Learning rate at `step`: `lr_init · (lr_final/lr_init)^(step/max_steps)`.
    pub fn lr(&self, step: u64) -> f32 {
        let t = if self.max_steps == 0 {
            1.0
        } else {
            (step as f64 / self.max_steps as f64).min(1.0)
        };
        (self.lr_init as f64 * (self.lr_final as f64 / self.lr_init as f64).powf(t)) as f32
    }
}

/// Elements per parallel work item of the fused update.
const ADAM_CHUNK: usize = 1 << 15;

/// Fused Adam over a list of parameter groups; state is kept per group.
#[derive(Clone, Debug)]
pub struct Adam {
    /// Hyper-parameters.
    pub config: AdamConfig,
    step: u64,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
}

impl Adam {
    /// State for groups of the given sizes.
    pub fn new(config: AdamConfig, sizes: &[usize]) -> Self {
        Self {
            config,
            step: 0,
            m: sizes.iter().map(|&s| vec![0.0; s]).collect(),
            v: sizes.iter().map(|&s| vec![0.0; s]).collect(),
        }
    }

    /// Number of steps taken.
    pub fn steps(&self) -> u64 {
        self.step
    }

    /// Moment estimates `(m, v)` per group, for checkpoints.
    pub fn moments(&self) -> (&[Vec<f32>], &[Vec<f32>]) {
        (&self.m, &self.v)
    }

    /// Restores state saved from [`Adam::steps`] and [`Adam::moments`]; `None` if the group
    /// count or any group's size differs from this optimiser's.
    pub fn restore(&mut self, steps: u64, m: Vec<Vec<f32>>, v: Vec<Vec<f32>>) -> Option<()> {
        let same = |a: &[Vec<f32>], b: &[Vec<f32>]| {
            a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.len() == y.len())
        };
        if !same(&m, &self.m) || !same(&v, &self.v) {
            return None;
        }
        self.step = steps;
        self.m = m;
        self.v = v;
        Some(())
    }

    /// One update with learning rate `lr`; every gradient is zeroed as it is consumed, which
    /// saves a separate pass over the (large) table gradient.
    ///
    /// Groups must come in the order and sizes given to [`Adam::new`].
    pub fn step(&mut self, lr: f32, params: &mut [&mut [f32]], grads: &mut [&mut [f32]]) {
        self.step += 1;
        let c = self.config;
        let bc1 = 1.0 - (c.beta1 as f64).powi(self.step as i32);
        let bc2 = 1.0 - (c.beta2 as f64).powi(self.step as i32);
        // Bias corrections folded into the step size and epsilon (the usual fused form).
        let step_size = (lr as f64 / bc1) as f32;
        let sqrt_bc2 = bc2.sqrt() as f32;
        for (((p, g), m), v) in params
            .iter_mut()
            .zip(grads.iter_mut())
            .zip(&mut self.m)
            .zip(&mut self.v)
        {
            p.par_chunks_mut(ADAM_CHUNK)
                .zip(g.par_chunks_mut(ADAM_CHUNK))
                .zip(m.par_chunks_mut(ADAM_CHUNK))
                .zip(v.par_chunks_mut(ADAM_CHUNK))
                .for_each(|(((p, g), m), v)| {
                    for i in 0..p.len() {
                        let gi = g[i];
                        let mi = c.beta1 * m[i] + (1.0 - c.beta1) * gi;
                        let vi = c.beta2 * v[i] + (1.0 - c.beta2) * gi * gi;
                        m[i] = mi;
                        v[i] = vi;
                        p[i] -= step_size * mi / (vi.sqrt() / sqrt_bc2 + c.eps);
                        g[i] = 0.0;
                    }
                });
        }
    }
}
