//! The networks (burn, `flex` CPU backend): a small CNN backbone producing an L2-normalised
//! embedding, the ArcFace head over the pose groups and the PoseNet-style regression head, with
//! their losses.

use burn::module::Param;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::pool::{MaxPool2d, MaxPool2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, Linear, LinearConfig, PaddingConfig2d};
use burn::prelude::*;
use burn::tensor::activation::{log_softmax, relu};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Shape of the networks.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NetConfig {
    /// Input width, pixels (a multiple of 16: four 2× poolings).
    pub input_width: usize,
    /// Input height, pixels (a multiple of 16).
    pub input_height: usize,
    /// Channels of the four conv stages are `base, 2·base, 4·base, 4·base`.
    pub base_channels: usize,
    /// Embedding size.
    pub embedding_dim: usize,
    /// Feed the network the image's two shadow-invariant channels
    /// ([`matloc_core::shadow::shadow_invariant`], each standardised) instead of its RGB, so a
    /// photo under another sun, exposure or white balance looks like the map's. On for new
    /// maps (docs/DECISIONS.md, "The place predictor sees a shadow-invariant image"); models
    /// saved without the field read RGB.
    #[serde(default)]
    pub shadow_invariant: bool,
}

impl Default for NetConfig {
    fn default() -> Self {
        NetConfig {
            input_width: 64,
            input_height: 48,
            base_channels: 16,
            embedding_dim: 64,
            shadow_invariant: true,
        }
    }
}

impl NetConfig {
    /// Channels of the network input: RGB, or the two shadow-invariant channels.
    pub fn input_channels(&self) -> usize {
        if self.shadow_invariant { 2 } else { 3 }
    }

    /// Feature-map size after the four poolings.
    fn flat_features(&self) -> usize {
        4 * self.base_channels * (self.input_width / 16) * (self.input_height / 16)
    }
}

/// Uniform `[-bound, bound]` values from `rng` with `param`'s shape.
fn uniform_like<const D: usize>(
    param: &Param<Tensor<D>>,
    bound: f64,
    rng: &mut ChaCha8Rng,
    device: &Device,
) -> Param<Tensor<D>> {
    let shape = param.lazy_shape();
    let n = shape.num_elements();
    let v: Vec<f32> = (0..n)
        .map(|_| rng.random_range(-bound..=bound) as f32)
        .collect();
    Param::from_tensor(Tensor::from_data(TensorData::new(v, shape), device))
}

/// One conv stage: 3×3 conv, batch norm, ReLU, 2× max pooling.
#[derive(Module, Debug)]
pub struct ConvBlock {
    conv: Conv2d,
    norm: BatchNorm,
    pool: MaxPool2d,
}

impl ConvBlock {
    fn new(cin: usize, cout: usize, rng: &mut ChaCha8Rng, device: &Device) -> ConvBlock {
        let mut conv = Conv2dConfig::new([cin, cout], [3, 3])
            .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
            .with_bias(false)
            .init(device);
        // Kaiming-uniform for ReLU, drawn from our seeded RNG so a model is reproducible.
        conv.weight = uniform_like(&conv.weight, (6.0 / (9 * cin) as f64).sqrt(), rng, device);
        ConvBlock {
            conv,
            norm: BatchNormConfig::new(cout).init(device),
            pool: MaxPool2dConfig::new([2, 2]).init(),
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.pool
            .forward(relu(self.norm.forward(self.conv.forward(x))))
    }
}

/// The shared CNN backbone: four conv stages, flatten (keeping the spatial layout, which tells
/// headings apart), a linear layer to the embedding.
#[derive(Module, Debug)]
pub struct Backbone {
    b1: ConvBlock,
    b2: ConvBlock,
    b3: ConvBlock,
    b4: ConvBlock,
    fc: Linear,
}

fn linear(din: usize, dout: usize, rng: &mut ChaCha8Rng, device: &Device) -> Linear {
    let mut l = LinearConfig::new(din, dout).init(device);
    let bound = (1.0 / din as f64).sqrt();
    l.weight = uniform_like(&l.weight, bound, rng, device);
    if let Some(b) = l.bias.as_ref() {
        l.bias = Some(uniform_like(b, bound, rng, device));
    }
    l
}

impl Backbone {
    /// A backbone with weights drawn from `rng`.
    pub fn new(cfg: &NetConfig, rng: &mut ChaCha8Rng, device: &Device) -> Backbone {
        let c = cfg.base_channels;
        Backbone {
            b1: ConvBlock::new(cfg.input_channels(), c, rng, device),
            b2: ConvBlock::new(c, 2 * c, rng, device),
            b3: ConvBlock::new(2 * c, 4 * c, rng, device),
            b4: ConvBlock::new(4 * c, 4 * c, rng, device),
            fc: linear(cfg.flat_features(), cfg.embedding_dim, rng, device),
        }
    }

    /// `[B, C, H, W]` images → `[B, D]` raw (unnormalised) embeddings.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<2> {
        let x = self
            .b4
            .forward(self.b3.forward(self.b2.forward(self.b1.forward(x))));
        let [b, c, h, w] = x.dims();
        self.fc.forward(x.reshape([b, c * h * w]))
    }
}

/// Rows scaled to unit length (with a small floor so a zero row stays finite).
pub fn l2_normalize(x: Tensor<2>) -> Tensor<2> {
    let norm = x
        .clone()
        .powf_scalar(2.0)
        .sum_dim(1)
        .add_scalar(1e-12)
        .sqrt();
    x.div(norm)
}

/// The place classifier: backbone + one learnt unit centre per pose group.
#[derive(Module, Debug)]
pub struct ArcFaceNet {
    /// Shared backbone.
    pub backbone: Backbone,
    /// `[groups, D]` class centres (normalised in the forward pass).
    pub centers: Param<Tensor<2>>,
}

impl ArcFaceNet {
    /// A fresh network for `groups` classes, weights from `seed`.
    pub fn new(cfg: &NetConfig, groups: usize, seed: u64, device: &Device) -> ArcFaceNet {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let backbone = Backbone::new(cfg, &mut rng, device);
        let v: Vec<f32> = (0..groups * cfg.embedding_dim)
            .map(|_| rng.random_range(-1.0f32..=1.0))
            .collect();
        let centers = Param::from_tensor(Tensor::from_data(
            TensorData::new(v, [groups, cfg.embedding_dim]),
            device,
        ));
        ArcFaceNet { backbone, centers }
    }

    /// `[B, 3, H, W]` → `[B, D]` unit embeddings.
    pub fn embed(&self, x: Tensor<4>) -> Tensor<2> {
        l2_normalize(self.backbone.forward(x))
    }

    /// `[B, groups]` cosines between the embeddings of `x` and the class centres.
    pub fn cosines(&self, x: Tensor<4>) -> Tensor<2> {
        let e = self.embed(x);
        e.matmul(l2_normalize(self.centers.val()).transpose())
    }
}

/// ArcFace settings: logits `s · cos(θ_y + m)` for the true class, `s · cos θ_j` otherwise.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ArcFaceConfig {
    /// Scale `s`.
    pub scale: f32,
    /// Additive angular margin `m`, radians.
    pub margin: f32,
}

impl Default for ArcFaceConfig {
    fn default() -> Self {
        // s = 16 rather than the face-recognition 64: a few dozen classes need no more.
        ArcFaceConfig {
            scale: 16.0,
            margin: 0.3,
        }
    }
}

/// The ArcFace loss (mean over the batch) of unit embeddings `emb` `[B, D]`, raw class centres
/// `centers` `[C, D]` and class labels.
///
/// For `θ_y + m > π` (where `cos(θ + m)` stops decreasing) the target logit falls back to the
/// linear `cos θ − m·sin m` of the reference implementation, keeping the loss monotone.
pub fn arcface_loss(
    emb: Tensor<2>,
    centers: Tensor<2>,
    labels: Tensor<1, Int>,
    cfg: &ArcFaceConfig,
) -> Tensor<1> {
    let classes = centers.dims()[0];
    let cos = emb
        .matmul(l2_normalize(centers).transpose())
        .clamp(-1.0 + 1e-6, 1.0 - 1e-6);
    let (m, s) = (f64::from(cfg.margin), f64::from(cfg.scale));
    let sin = cos
        .clone()
        .powf_scalar(2.0)
        .neg()
        .add_scalar(1.0)
        .clamp_min(1e-12)
        .sqrt();
    let phi = cos.clone().mul_scalar(m.cos()) - sin.mul_scalar(m.sin());
    let threshold = (std::f64::consts::PI - m).cos();
    let fallback = cos.clone().sub_scalar(m * m.sin());
    let phi = phi.mask_where(cos.clone().lower_equal_elem(threshold), fallback);
    let onehot: Tensor<2> = labels.one_hot(classes).float();
    let logits = (onehot.clone() * phi + onehot.clone().neg().add_scalar(1.0) * cos).mul_scalar(s);
    let b = logits.dims()[0] as f64;
    (onehot * log_softmax(logits, 1)).sum().neg().div_scalar(b)
}

/// The pose-regression baseline: backbone + linear head to translation (3) and quaternion (4).
#[derive(Module, Debug)]
pub struct RegressionNet {
    /// Shared backbone.
    pub backbone: Backbone,
    /// `[D] → [7]` head.
    pub head: Linear,
}

impl RegressionNet {
    /// A fresh network, weights from `seed`.
    pub fn new(cfg: &NetConfig, seed: u64, device: &Device) -> RegressionNet {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let backbone = Backbone::new(cfg, &mut rng, device);
        let head = linear(cfg.embedding_dim, 7, &mut rng, device);
        RegressionNet { backbone, head }
    }

    /// `[B, 3, H, W]` → `[B, 7]`: normalised camera centre then an unnormalised quaternion.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<2> {
        self.head.forward(relu(self.backbone.forward(x)))
    }
}

/// PoseNet loss `‖t − t̂‖² + β ‖q − q̂/‖q̂‖‖²` averaged over the batch; `target` is `[B, 7]` with
/// normalised centres and unit quaternions on the `w ≥ 0` hemisphere.
pub fn regression_loss(pred: Tensor<2>, target: Tensor<2>, beta: f32) -> Tensor<1> {
    let [b, _] = pred.dims();
    let t = pred.clone().slice([0..b, 0..3]);
    let q = l2_normalize(pred.slice([0..b, 3..7]));
    let tt = target.clone().slice([0..b, 0..3]);
    let tq = target.slice([0..b, 3..7]);
    let lt = (t - tt).powf_scalar(2.0).sum();
    let lq = (q - tq).powf_scalar(2.0).sum().mul_scalar(f64::from(beta));
    (lt + lq).div_scalar(b as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Independent f64 ArcFace loss of raw embeddings `x` `[b, d]` and raw centres `w` `[c, d]`.
    fn reference(
        x: &[f64],
        w: &[f64],
        labels: &[usize],
        b: usize,
        d: usize,
        c: usize,
        cfg: &ArcFaceConfig,
    ) -> f64 {
        let unit = |v: &[f64]| {
            let n = (v.iter().map(|a| a * a).sum::<f64>() + 1e-12).sqrt();
            v.iter().map(|a| a / n).collect::<Vec<f64>>()
        };
        let (m, s) = (f64::from(cfg.margin), f64::from(cfg.scale));
        let mut total = 0.0;
        for i in 0..b {
            let e = unit(&x[i * d..(i + 1) * d]);
            let logits: Vec<f64> = (0..c)
                .map(|j| {
                    let wj = unit(&w[j * d..(j + 1) * d]);
                    let cos = e
                        .iter()
                        .zip(&wj)
                        .map(|(p, q)| p * q)
                        .sum::<f64>()
                        .clamp(-1.0 + 1e-6, 1.0 - 1e-6);
                    let v = if j == labels[i] {
                        if cos <= (std::f64::consts::PI - m).cos() {
                            cos - m * m.sin()
                        } else {
                            (cos.acos() + m).cos()
                        }
                    } else {
                        cos
                    };
                    s * v
                })
                .collect();
            let max = logits.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let lse = max + logits.iter().map(|l| (l - max).exp()).sum::<f64>().ln();
            total += lse - logits[labels[i]];
        }
        total / b as f64
    }

    #[test]
    fn arcface_gradient_matches_finite_differences() {
        let (b, d, c) = (3, 4, 5);
        let cfg = ArcFaceConfig {
            scale: 4.0,
            margin: 0.5,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut x: Vec<f64> = (0..b * d).map(|_| rng.random_range(-1.0..1.0)).collect();
        let w: Vec<f64> = (0..c * d).map(|_| rng.random_range(-1.0..1.0)).collect();
        let labels = [0usize, 3, 4];
        // Sample 2 points almost opposite its class centre: the fallback branch (θ + m > π).
        for k in 0..d {
            x[2 * d + k] = -w[4 * d + k] + 0.05 * (k as f64 - 1.5);
        }
        let device = Device::flex().autodiff();
        let f32s = |v: &[f64]| v.iter().map(|&a| a as f32).collect::<Vec<f32>>();
        let xt = Tensor::<2>::from_data(TensorData::new(f32s(&x), [b, d]), &device).require_grad();
        let wt = Tensor::<2>::from_data(TensorData::new(f32s(&w), [c, d]), &device).require_grad();
        let lt = Tensor::<1, Int>::from_data(
            TensorData::new(labels.iter().map(|&l| l as i64).collect::<Vec<_>>(), [b]),
            &device,
        );
        let loss = arcface_loss(l2_normalize(xt.clone()), wt.clone(), lt, &cfg);
        let value = loss.clone().into_scalar::<f32>() as f64;
        let want = reference(&x, &w, &labels, b, d, c, &cfg);
        assert!(
            (value - want).abs() < 1e-4 * want.abs().max(1.0),
            "{value} vs {want}"
        );
        let grads = loss.backward();
        let gx: Vec<f32> = xt.grad(&grads).unwrap().into_data().try_into_vec().unwrap();
        let gw: Vec<f32> = wt.grad(&grads).unwrap().into_data().try_into_vec().unwrap();
        let h = 1e-6;
        let check = |analytic: &[f32], which: usize| {
            for i in 0..analytic.len() {
                let (mut xp, mut wp) = (x.clone(), w.clone());
                let (mut xm, mut wm) = (x.clone(), w.clone());
                if which == 0 {
                    xp[i] += h;
                    xm[i] -= h;
                } else {
                    wp[i] += h;
                    wm[i] -= h;
                }
                let fd = (reference(&xp, &wp, &labels, b, d, c, &cfg)
                    - reference(&xm, &wm, &labels, b, d, c, &cfg))
                    / (2.0 * h);
                let a = f64::from(analytic[i]);
                assert!(
                    (a - fd).abs() < 2e-3 + 1e-2 * fd.abs(),
                    "param set {which} index {i}: autodiff {a} vs FD {fd}"
                );
            }
        };
        check(&gx, 0);
        check(&gw, 1);
        // The margin must matter: without it the loss is lower.
        let no_margin = ArcFaceConfig { margin: 0.0, ..cfg };
        assert!(reference(&x, &w, &labels, b, d, c, &no_margin) < want);
    }

    #[test]
    fn embeddings_are_unit_and_shapes_fit() {
        let device = Device::flex();
        let cfg = NetConfig::default();
        let net = ArcFaceNet::new(&cfg, 6, 1, &device).valid();
        let c = cfg.input_channels();
        let x = Tensor::<4>::zeros([2, c, cfg.input_height, cfg.input_width], &device);
        let e: Vec<f32> = net.embed(x.clone()).into_data().try_into_vec().unwrap();
        assert_eq!(e.len(), 2 * cfg.embedding_dim);
        for row in e.chunks(cfg.embedding_dim) {
            let n: f32 = row.iter().map(|v| v * v).sum();
            assert!((n - 1.0).abs() < 1e-4, "{n}");
        }
        let cos: Vec<f32> = net.cosines(x).into_data().try_into_vec().unwrap();
        assert_eq!(cos.len(), 12);
        assert!(cos.iter().all(|c| c.abs() <= 1.0 + 1e-5));
        let reg = RegressionNet::new(&cfg, 1, &device).valid();
        let out = reg.forward(Tensor::<4>::zeros(
            [3, c, cfg.input_height, cfg.input_width],
            &device,
        ));
        assert_eq!(out.dims(), [3, 7]);
    }

    /// New configurations read the shadow-invariant channels; a configuration saved before
    /// the field existed reads RGB, as its weights were trained on.
    #[test]
    fn the_input_is_shadow_invariant_unless_the_saved_config_predates_it() {
        let d = NetConfig::default();
        assert!(d.shadow_invariant);
        assert_eq!(d.input_channels(), 2);
        let old: NetConfig = serde_json::from_str(
            r#"{"input_width": 64, "input_height": 48, "base_channels": 16, "embedding_dim": 64}"#,
        )
        .unwrap();
        assert!(!old.shadow_invariant);
        assert_eq!(old.input_channels(), 3);
        let back: NetConfig = serde_json::from_str(&serde_json::to_string(&d).unwrap()).unwrap();
        assert_eq!(back, d);
    }
}
