//! The [`PlacePredictor`] trait, training of the ArcFace classifier and the pose-regression
//! baseline, prediction, and model files (safetensors weights + JSON description).

use std::path::{Path, PathBuf};

use burn::optim::{AdamConfig, GradientsParams};
use burn::prelude::*;
use burn::store::{ModuleSnapshot, SafetensorsStore};
use matloc_core::backend::seeded_module;
use matloc_core::pose::{camera_center, interpolate, viewing_direction};
use matloc_core::shadow::{shadow_invariant, standardise};
use matloc_core::{Camera, Image, Pose};
use nalgebra::{Point3, Quaternion, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::augment::{AugmentConfig, augment};
use crate::error::PlaceError;
use crate::groups::{PoseGroups, check_poses};
use crate::model::{
    ArcFaceConfig, ArcFaceNet, NetConfig, RegressionNet, arcface_loss, regression_loss,
};
use matloc_core::image::resize_area;

/// Format version of the model's JSON file.
pub const PLACE_MODEL_VERSION: u32 = 1;
/// Name of the JSON file inside a model directory.
pub const MODEL_JSON: &str = "place.json";
/// Name of the weights file inside a model directory.
pub const MODEL_WEIGHTS: &str = "place.safetensors";

/// One answer of a place predictor.
#[derive(Clone, Debug, PartialEq)]
pub struct PlaceHypothesis {
    /// Pose group.
    pub group: usize,
    /// Score (softmax probability for the classifier, `exp(−distance)` for regression).
    pub score: f32,
    /// Coarse `cam_from_world`: the group's medoid (classifier) or the regressed pose (the
    /// regression baseline's first hypothesis).
    pub cam_from_world: Pose,
    /// Sub-NeRF block that serves the coarse pose, if the groups know their blocks.
    pub block: Option<usize>,
}

/// Image → top-k pose groups with scores, coarse poses and the sub-NeRF that serves each.
pub trait PlacePredictor {
    /// Best `k` hypotheses for a query, best first (fewer when there are fewer groups).
    fn predict(
        &self,
        image: &Image<f32>,
        camera: &Camera,
        k: usize,
    ) -> Result<Vec<PlaceHypothesis>, PlaceError>;
}

/// Which network a [`PlaceModel`] uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PlaceMethod {
    /// CNN embedding + ArcFace classifier over pose groups.
    ArcFace,
    /// PoseNet-style regression of translation + quaternion on the same backbone.
    Regression,
}

/// Training settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Network shape.
    pub net: NetConfig,
    /// ArcFace scale and margin.
    pub arcface: ArcFaceConfig,
    /// Augmentation ranges.
    pub augment: AugmentConfig,
    /// Passes over the training images (each pass draws fresh augmentations).
    pub epochs: usize,
    /// Images per step.
    pub batch_size: usize,
    /// Adam learning rate at the start (cosine decay to 5 % of it).
    pub learning_rate: f64,
    /// Weight of the quaternion term of the regression loss.
    pub quaternion_weight: f32,
    /// Seed of weights, shuffling and augmentation.
    pub seed: u64,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            net: NetConfig::default(),
            arcface: ArcFaceConfig::default(),
            augment: AugmentConfig::default(),
            epochs: 30,
            batch_size: 16,
            learning_rate: 2e-3,
            quaternion_weight: 1.0,
            seed: 0,
        }
    }
}

impl TrainConfig {
    fn validate(&self) -> Result<(), PlaceError> {
        let bad =
            |field: &'static str, reason: String| Err(PlaceError::InvalidConfig { field, reason });
        let n = &self.net;
        if n.input_width < 16
            || n.input_height < 16
            || !n.input_width.is_multiple_of(16)
            || !n.input_height.is_multiple_of(16)
        {
            return bad(
                "net.input_width",
                format!(
                    "input {}x{} must be positive multiples of 16",
                    n.input_width, n.input_height
                ),
            );
        }
        if n.base_channels == 0 || n.embedding_dim == 0 {
            return bad(
                "net.base_channels",
                "channels and embedding size must be positive".into(),
            );
        }
        if self.epochs == 0 {
            return bad("epochs", "must be at least 1".into());
        }
        if self.batch_size < 2 {
            return bad("batch_size", "must be at least 2 (batch norm)".into());
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return bad(
                "learning_rate",
                format!("must be > 0, got {}", self.learning_rate),
            );
        }
        let a = &self.arcface;
        if !(a.scale.is_finite()
            && a.scale > 0.0
            && a.margin.is_finite()
            && (0.0..1.5).contains(&a.margin))
        {
            return bad(
                "arcface",
                format!(
                    "scale {} must be > 0, margin {} in [0, 1.5)",
                    a.scale, a.margin
                ),
            );
        }
        Ok(())
    }
}

/// Loss of one epoch, reported during training.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpochReport {
    /// Epoch (0-based).
    pub epoch: usize,
    /// Mean training loss.
    pub loss: f32,
}

enum Net {
    ArcFace(ArcFaceNet),
    Regression(RegressionNet),
}

/// A trained place predictor: the network, the pose groups it predicts and what it needs to
/// turn outputs into poses.
pub struct PlaceModel {
    method: PlaceMethod,
    config: TrainConfig,
    groups: PoseGroups,
    /// Regression targets are `(centre − mean) / scale`.
    center_mean: [f64; 3],
    center_scale: f64,
    /// Unit embeddings of the training images (classifier only), row-major `[n, D]`.
    member_embeddings: Vec<f32>,
    /// `cam_from_world` of the training images.
    member_poses: Vec<Pose>,
    /// Return the group member nearest in embedding space instead of the medoid.
    refine_within_group: bool,
    /// Weight of the best member similarity in a group's score (0 = class centres only).
    member_weight: f32,
    /// Softmax temperature of the blend of the nearest member with its best neighbour
    /// (0 = no blend).
    member_blend: f32,
    /// Keep the nearest member as the top hypothesis and add the blend as a second one.
    blend_as_extra: bool,
    net: Net,
    device: Device,
}

/// The JSON half of a saved model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct ModelFile {
    version: u32,
    method: PlaceMethod,
    config: TrainConfig,
    groups: PoseGroups,
    center_mean: [f64; 3],
    center_scale: f64,
    #[serde(default)]
    member_embeddings: Vec<f32>,
    #[serde(default)]
    member_poses: Vec<Pose>,
}

/// Checks a batch of images: non-empty, RGB, finite.
fn check_images(images: &[Image<f32>]) -> Result<(), PlaceError> {
    for (index, img) in images.iter().enumerate() {
        if img.width() == 0 || img.height() == 0 || img.channels() != 3 {
            return Err(PlaceError::EmptyImage {
                index,
                width: img.width(),
                height: img.height(),
                channels: img.channels(),
            });
        }
        if !img.data().iter().all(|v| v.is_finite()) {
            return Err(PlaceError::NonFiniteImage { index });
        }
    }
    Ok(())
}

/// An HWC `[0, 1]` image → the network's CHW input, appended to `out`: its shadow-invariant
/// channels standardised to unit spread, or its RGB centred at 0.5 (spread about 1).
fn push_chw(img: &Image<f32>, cfg: &NetConfig, out: &mut Vec<f32>) {
    let (w, h) = (img.width(), img.height());
    if cfg.shadow_invariant {
        let mut planes = shadow_invariant(img);
        for plane in planes.chunks_exact_mut(w * h) {
            standardise(plane, 1.0);
        }
        out.extend(planes);
        return;
    }
    let d = img.data();
    for k in 0..3 {
        for i in 0..w * h {
            out.push((d[i * 3 + k] - 0.5) * 4.0);
        }
    }
}

fn input_tensor(images: &[Image<f32>], cfg: &NetConfig, device: &Device) -> Tensor<4> {
    let c = cfg.input_channels();
    let mut buf = Vec::with_capacity(images.len() * c * cfg.input_width * cfg.input_height);
    for img in images {
        push_chw(img, cfg, &mut buf);
    }
    Tensor::from_data(
        TensorData::new(buf, [images.len(), c, cfg.input_height, cfg.input_width]),
        device,
    )
}

fn tensor_to_vec(t: Tensor<2>) -> Vec<f32> {
    // The networks compute in f32, so the cast is exact; an empty result would only follow a
    // backend bug and shows up as no hypotheses rather than a panic.
    t.into_data().try_into_vec_as::<f32>().unwrap_or_default()
}

/// Camera orientation (`world_from_cam` rotation) as a unit quaternion with `w ≥ 0`.
fn orientation(cam_from_world: &Pose) -> UnitQuaternion<f64> {
    let q = cam_from_world.rotation.inverse();
    if q.w < 0.0 {
        UnitQuaternion::new_unchecked(-q.into_inner())
    } else {
        q
    }
}

/// Extra training views that are not group members: e.g. views rendered by the map's NeRFs at
/// poses near the training poses (more images per group than the survey took). They are
/// trained on like the members (same augmentation, every epoch) but do not become group
/// members: coarse poses and within-group refinement use the real views only.
#[derive(Clone, Copy, Debug, Default)]
pub struct ExtraViews<'a> {
    /// Images (any size; resized like the members).
    pub images: &'a [Image<f32>],
    /// Their `cam_from_world` (the regression baseline's targets).
    pub poses: &'a [Pose],
    /// Their group labels.
    pub labels: &'a [usize],
}

impl PlaceModel {
    /// Trains a place model on `images` whose poses were grouped into `groups`
    /// (`groups.labels[i]` is the group of image `i`). `poses[i]` is image `i`'s
    /// `cam_from_world` (used by the regression baseline). `progress` hears every epoch.
    pub fn train(
        method: PlaceMethod,
        images: &[Image<f32>],
        poses: &[Pose],
        groups: &PoseGroups,
        config: &TrainConfig,
        progress: &mut dyn FnMut(EpochReport),
    ) -> Result<PlaceModel, PlaceError> {
        Self::train_with_extra(
            method,
            images,
            poses,
            groups,
            ExtraViews::default(),
            config,
            progress,
        )
    }

    /// [`PlaceModel::train`] with [`ExtraViews`] in the training set.
    pub fn train_with_extra(
        method: PlaceMethod,
        images: &[Image<f32>],
        poses: &[Pose],
        groups: &PoseGroups,
        extra: ExtraViews<'_>,
        config: &TrainConfig,
        progress: &mut dyn FnMut(EpochReport),
    ) -> Result<PlaceModel, PlaceError> {
        config.validate()?;
        if extra.images.len() != extra.poses.len() || extra.images.len() != extra.labels.len() {
            return Err(PlaceError::LengthMismatch {
                what: "extra images vs extra poses / labels",
                a: extra.images.len(),
                b: if extra.images.len() != extra.poses.len() {
                    extra.poses.len()
                } else {
                    extra.labels.len()
                },
            });
        }
        for (k, &label) in extra.labels.iter().enumerate() {
            if label >= groups.len() {
                return Err(PlaceError::BadLabel {
                    index: images.len() + k,
                    label,
                    groups: groups.len(),
                });
            }
        }
        check_images(extra.images)?;
        check_poses(extra.poses)?;
        if images.len() != poses.len() {
            return Err(PlaceError::LengthMismatch {
                what: "images vs poses",
                a: images.len(),
                b: poses.len(),
            });
        }
        if groups.labels.len() != images.len() {
            return Err(PlaceError::LengthMismatch {
                what: "images vs group labels",
                a: images.len(),
                b: groups.labels.len(),
            });
        }
        if images.len() < 2 {
            return Err(PlaceError::TooFewPoses {
                poses: images.len(),
                groups: groups.len(),
                min_group_size: 1,
            });
        }
        for (index, &label) in groups.labels.iter().enumerate() {
            if label >= groups.len() {
                return Err(PlaceError::BadLabel {
                    index,
                    label,
                    groups: groups.len(),
                });
            }
        }
        check_images(images)?;
        check_poses(poses)?;

        let net_cfg = config.net;
        let (w, h) = (net_cfg.input_width, net_cfg.input_height);
        // Augmentation samples from twice the input size, so crops and rotations keep detail.
        let sources: Vec<Image<f32>> = images
            .par_iter()
            .chain(extra.images.par_iter())
            .map(|img| resize_area(img, 2 * w, 2 * h))
            .collect();
        let labels: Vec<usize> = groups.labels.iter().chain(extra.labels).copied().collect();

        let centers: Vec<Vector3<f64>> = poses.iter().map(|p| camera_center(p).coords).collect();
        let mean = centers.iter().fold(Vector3::zeros(), |s, c| s + c) / centers.len() as f64;
        let scale = (centers
            .iter()
            .map(|c| (c - mean).norm_squared())
            .sum::<f64>()
            / centers.len() as f64)
            .sqrt()
            .max(1e-6);
        let targets: Vec<[f32; 7]> = poses
            .iter()
            .chain(extra.poses)
            .map(|p| {
                let t = (camera_center(p).coords - mean) / scale;
                let q = orientation(p);
                [t.x, t.y, t.z, q.w, q.i, q.j, q.k].map(|v| v as f32)
            })
            .collect();

        let device = Device::flex().autodiff();
        // Whatever the backend draws from its own generator is seeded too, under the
        // process-wide lock so a concurrent training cannot draw in between.
        let mut net = match method {
            PlaceMethod::ArcFace => Net::ArcFace(seeded_module(&device, config.seed, || {
                ArcFaceNet::new(&net_cfg, groups.len(), config.seed, &device)
            })),
            PlaceMethod::Regression => Net::Regression(seeded_module(&device, config.seed, || {
                RegressionNet::new(&net_cfg, config.seed, &device)
            })),
        };
        let mut optim = AdamConfig::new().init();
        let n = sources.len();
        let bs = config.batch_size.min(n);
        let steps_per_epoch = n.div_ceil(bs);
        let total_steps = (steps_per_epoch * config.epochs).max(1);
        let mut order: Vec<usize> = (0..n).collect();
        let mut shuffle_rng = ChaCha8Rng::seed_from_u64(config.seed ^ 0x005E_ED0F_5A3C);
        let mut step = 0usize;
        for epoch in 0..config.epochs {
            order.shuffle(&mut shuffle_rng);
            let (mut loss_sum, mut batches) = (0.0f64, 0usize);
            for batch in order.chunks(bs) {
                // A lone trailing image would give batch norm a batch of one.
                if batch.len() < 2 {
                    continue;
                }
                let augmented: Vec<Image<f32>> = batch
                    .par_iter()
                    .map(|&i| {
                        // One RNG per (epoch, image): augmentations do not depend on threads.
                        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
                        rng.set_stream(((epoch as u64) << 32) | i as u64);
                        augment(&sources[i], w, h, &config.augment, &mut rng)
                    })
                    .collect();
                let x = input_tensor(&augmented, &net_cfg, &device);
                let progress_frac = step as f64 / total_steps as f64;
                let lr = config.learning_rate
                    * (0.05 + 0.95 * 0.5 * (1.0 + (std::f64::consts::PI * progress_frac).cos()));
                step += 1;
                let loss_value;
                net = match net {
                    Net::ArcFace(model) => {
                        let labels: Vec<i64> = batch.iter().map(|&i| labels[i] as i64).collect();
                        let labels = Tensor::<1, Int>::from_data(
                            TensorData::new(labels, [batch.len()]),
                            &device,
                        );
                        let loss = arcface_loss(
                            model.embed(x),
                            model.centers.val(),
                            labels,
                            &config.arcface,
                        );
                        loss_value = loss.clone().into_scalar::<f32>();
                        let grads = GradientsParams::from_grads(loss.backward(), &model);
                        Net::ArcFace(optim.step(lr, model, grads))
                    }
                    Net::Regression(model) => {
                        let t: Vec<f32> = batch.iter().flat_map(|&i| targets[i]).collect();
                        let target =
                            Tensor::<2>::from_data(TensorData::new(t, [batch.len(), 7]), &device);
                        let loss =
                            regression_loss(model.forward(x), target, config.quaternion_weight);
                        loss_value = loss.clone().into_scalar::<f32>();
                        let grads = GradientsParams::from_grads(loss.backward(), &model);
                        Net::Regression(optim.step(lr, model, grads))
                    }
                };
                if !loss_value.is_finite() {
                    return Err(PlaceError::Diverged {
                        epoch,
                        loss: loss_value,
                    });
                }
                loss_sum += f64::from(loss_value);
                batches += 1;
            }
            progress(EpochReport {
                epoch,
                loss: (loss_sum / batches.max(1) as f64) as f32,
            });
        }
        let plain = Device::flex();
        let net = match net {
            Net::ArcFace(m) => Net::ArcFace(m.valid().to_device(&plain)),
            Net::Regression(m) => Net::Regression(m.valid().to_device(&plain)),
        };
        let mut model = PlaceModel {
            method,
            config: *config,
            groups: groups.clone(),
            center_mean: [mean.x, mean.y, mean.z],
            center_scale: scale,
            member_embeddings: Vec::new(),
            member_poses: poses.to_vec(),
            refine_within_group: false,
            member_weight: 0.0,
            member_blend: 0.0,
            blend_as_extra: false,
            net,
            device: plain,
        };
        if method == PlaceMethod::ArcFace {
            let mut emb = Vec::new();
            for chunk in images.chunks(64) {
                emb.extend(model.arcface_outputs(chunk)?.1);
            }
            model.member_embeddings = emb;
        }
        Ok(model)
    }

    /// The method.
    pub fn method(&self) -> PlaceMethod {
        self.method
    }

    /// The pose groups the model predicts.
    pub fn groups(&self) -> &PoseGroups {
        &self.groups
    }

    /// `cam_from_world` of the training images, in the order of `groups().labels`.
    pub fn training_poses(&self) -> &[Pose] {
        &self.member_poses
    }

    /// Mutable pose groups (e.g. to attach partition blocks after training).
    pub fn groups_mut(&mut self) -> &mut PoseGroups {
        &mut self.groups
    }

    /// The training settings.
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// Makes the classifier return, for each predicted group, the training pose of the member
    /// whose image embedding is closest to the query's instead of the group medoid (no effect
    /// on the regression baseline).
    pub fn set_refine_within_group(&mut self, on: bool) {
        self.refine_within_group = on;
    }

    /// Blends the nearest member's pose with its most similar neighbour's (within two group
    /// radii and the group angle), weighting the neighbour by `1 / (1 + exp((s₁ − s₂) / t))`
    /// for embedding cosines `s₁ ≥ s₂`: a query taken between two survey poses gets a coarse
    /// pose between them. `t = 0` (or not finite) turns the blend off. Needs
    /// [`Self::set_refine_within_group`].
    pub fn set_member_blend(&mut self, t: f32) {
        self.member_blend = if t.is_finite() { t.max(0.0) } else { 0.0 };
    }

    /// With a blend temperature set: keep the nearest member as the top group's coarse pose
    /// and return the blended pose as an extra second hypothesis of the same group (tried
    /// only when the first fails) instead of replacing it.
    pub fn set_blend_as_extra(&mut self, on: bool) {
        self.blend_as_extra = on;
    }

    /// Scores groups by `(1 − w) ·` the cosine to the class centre `+ w ·` the best cosine to
    /// one of the group's training images (classifier only; `w` is clamped to `[0, 1]`).
    pub fn set_member_weight(&mut self, w: f32) {
        self.member_weight = if w.is_finite() {
            w.clamp(0.0, 1.0)
        } else {
            0.0
        };
    }

    /// Best cosine between `emb` and a training embedding of each group (`-1` for a group
    /// without stored embeddings).
    fn member_similarities(&self, emb: &[f32]) -> Vec<f32> {
        let mut best = vec![-1.0f32; self.groups.len()];
        let Some(cos) = self.member_cosines(emb) else {
            return best;
        };
        for (j, c) in cos.into_iter().enumerate() {
            let Some(&g) = self.groups.labels.get(j) else {
                continue;
            };
            if let Some(b) = best.get_mut(g) {
                *b = b.max(c);
            }
        }
        best
    }

    /// Cosines to the class centres `[B, groups]` and unit embeddings `[B, D]` (classifier only;
    /// empty vectors for the regression baseline).
    fn arcface_outputs(&self, images: &[Image<f32>]) -> Result<(Vec<f32>, Vec<f32>), PlaceError> {
        check_images(images)?;
        let Net::ArcFace(m) = &self.net else {
            return Ok((Vec::new(), Vec::new()));
        };
        let (w, h) = (self.config.net.input_width, self.config.net.input_height);
        let small: Vec<Image<f32>> = images.iter().map(|img| resize_area(img, w, h)).collect();
        let x = input_tensor(&small, &self.config.net, &self.device);
        let e = m.embed(x);
        let cos = e
            .clone()
            .matmul(crate::model::l2_normalize(m.centers.val()).transpose());
        Ok((tensor_to_vec(cos), tensor_to_vec(e)))
    }

    /// Cosine between `emb` and every training embedding (`None` without stored embeddings
    /// of that size).
    fn member_cosines(&self, emb: &[f32]) -> Option<Vec<f32>> {
        let d = emb.len();
        if d == 0 || self.member_embeddings.len() != d * self.member_poses.len() {
            return None;
        }
        Some(
            self.member_embeddings
                .chunks_exact(d)
                .map(|row| row.iter().zip(emb).map(|(a, b)| a * b).sum())
                .collect(),
        )
    }

    /// The pose the classifier returns for `group` when refining within the group: the member
    /// whose training embedding is closest to `emb`, blended with its best neighbour when a
    /// blend temperature is set.
    fn member_pose(&self, group: usize, emb: &[f32], blend: bool) -> Option<Pose> {
        let cos = self.member_cosines(emb)?;
        // Most similar index; ties go to the lower index.
        let most_similar = |it: &mut dyn Iterator<Item = usize>| {
            it.max_by(|&a, &b| cos[a].total_cmp(&cos[b]).then(b.cmp(&a)))
        };
        let j1 = most_similar(
            &mut self.groups.groups[group]
                .members
                .iter()
                .copied()
                .filter(|&j| j < cos.len()),
        )?;
        let p1 = self.member_poses[j1];
        if !blend || self.member_blend <= 0.0 {
            return Some(p1);
        }
        // The best neighbour of any group: a query between two survey poses is usually
        // nearest one of them and about as similar to the other, which can sit across a group
        // boundary. Neighbours are within two group radii and the groups' angle bound.
        let (c1, v1) = (camera_center(&p1), viewing_direction(&p1));
        let radius = 2.0 * self.groups.spatial_radius_m;
        let max_angle = self.groups.config.max_angle_deg.to_radians();
        let Some(j2) = most_similar(&mut (0..cos.len()).filter(|&j| {
            let p = &self.member_poses[j];
            j != j1
                && (camera_center(p) - c1).norm() <= radius
                && viewing_direction(p).dot(&v1).clamp(-1.0, 1.0).acos() <= max_angle
        })) else {
            return Some(p1);
        };
        let (s1, s2) = (cos[j1], cos[j2]);
        // Softmax weight of the neighbour: ½ for equal similarities, → 0 as it falls behind.
        let w2 = 1.0 / (1.0 + ((s1 - s2) / self.member_blend).exp());
        Some(interpolate(&p1, &self.member_poses[j2], f64::from(w2)))
    }

    /// Raw network outputs for a batch of images: `[B, groups]` cosines (ArcFace) or `[B, 7]`
    /// pose vectors (regression), row-major.
    pub fn forward_batch(&self, images: &[Image<f32>]) -> Result<Vec<f32>, PlaceError> {
        check_images(images)?;
        let (w, h) = (self.config.net.input_width, self.config.net.input_height);
        let small: Vec<Image<f32>> = images.iter().map(|img| resize_area(img, w, h)).collect();
        let x = input_tensor(&small, &self.config.net, &self.device);
        Ok(match &self.net {
            Net::ArcFace(m) => tensor_to_vec(m.cosines(x)),
            Net::Regression(m) => tensor_to_vec(m.forward(x)),
        })
    }

    /// Turns a regression output row into `cam_from_world`.
    fn pose_from_regression(&self, row: &[f32]) -> Pose {
        let c = Vector3::new(f64::from(row[0]), f64::from(row[1]), f64::from(row[2]))
            * self.center_scale
            + Vector3::from(self.center_mean);
        let q = Quaternion::new(
            f64::from(row[3]),
            f64::from(row[4]),
            f64::from(row[5]),
            f64::from(row[6]),
        );
        let world_from_cam_rot = if q.norm() > 1e-12 {
            UnitQuaternion::from_quaternion(q)
        } else {
            UnitQuaternion::identity()
        };
        let world_from_cam = Pose::from_parts(Translation3::from(c), world_from_cam_rot);
        world_from_cam.inverse()
    }

    /// Hypotheses from one row of [`PlaceModel::forward_batch`].
    pub fn hypotheses_from_output(&self, row: &[f32], k: usize) -> Vec<PlaceHypothesis> {
        let g = &self.groups.groups;
        match self.method {
            PlaceMethod::ArcFace => {
                let s = self.config.arcface.scale;
                let max = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let exp: Vec<f32> = row.iter().map(|&c| ((c - max) * s).exp()).collect();
                let total: f32 = exp.iter().sum();
                let mut idx: Vec<usize> = (0..row.len()).collect();
                idx.sort_by(|&a, &b| row[b].total_cmp(&row[a]).then(a.cmp(&b)));
                idx.into_iter()
                    .take(k)
                    .map(|i| PlaceHypothesis {
                        group: i,
                        score: exp[i] / total,
                        cam_from_world: g[i].coarse_pose,
                        block: g[i].block,
                    })
                    .collect()
            }
            PlaceMethod::Regression => {
                let pose = self.pose_from_regression(row);
                let c = camera_center(&pose);
                let r = self.groups.spatial_radius_m.max(1e-9);
                let dir = matloc_core::pose::viewing_direction(&pose);
                let alpha = self.groups.config.max_angle_deg.to_radians();
                // Groups ranked by the same scaled distance the medoids minimise.
                let dist = |i: usize| {
                    let gc = camera_center(&g[i].coarse_pose);
                    let gd = Vector3::from(g[i].direction);
                    (gc - c).norm() / r + gd.dot(&dir).clamp(-1.0, 1.0).acos() / alpha
                };
                let mut idx: Vec<usize> = (0..g.len()).collect();
                idx.sort_by(|&a, &b| dist(a).total_cmp(&dist(b)).then(a.cmp(&b)));
                let first = self.groups.assign(&pose);
                if let Some(f) = first {
                    idx.retain(|&i| i != f);
                    idx.insert(0, f);
                }
                idx.into_iter()
                    .take(k)
                    .enumerate()
                    .map(|(rank, i)| PlaceHypothesis {
                        group: i,
                        score: (-dist(i) as f32).exp(),
                        cam_from_world: if rank == 0 { pose } else { g[i].coarse_pose },
                        block: g[i].block,
                    })
                    .collect()
            }
        }
    }

    /// Saves the model into directory `dir` (created if needed): weights first, then the JSON
    /// description, each written atomically, so a reader never sees a JSON without its weights.
    pub fn save(&self, dir: &Path) -> Result<(), PlaceError> {
        std::fs::create_dir_all(dir).map_err(|source| PlaceError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let wpath = dir.join(MODEL_WEIGHTS);
        let mut store = SafetensorsStore::from_bytes(None);
        let res = match &self.net {
            Net::ArcFace(m) => m.save_into(&mut store),
            Net::Regression(m) => m.save_into(&mut store),
        };
        let weights_err = |message: String| PlaceError::Weights {
            path: wpath.clone(),
            message,
        };
        res.map_err(|e| weights_err(format!("{e:?}")))?;
        let bytes = store
            .get_bytes()
            .map_err(|e| weights_err(format!("{e:?}")))?;
        matloc_core::fsutil::write_atomic(&wpath, &bytes).map_err(|source| PlaceError::Io {
            path: wpath.clone(),
            source,
        })?;
        let jpath = dir.join(MODEL_JSON);
        let file = ModelFile {
            version: PLACE_MODEL_VERSION,
            method: self.method,
            config: self.config,
            groups: self.groups.clone(),
            center_mean: self.center_mean,
            center_scale: self.center_scale,
            member_embeddings: self.member_embeddings.clone(),
            member_poses: self.member_poses.clone(),
        };
        let json = serde_json::to_vec_pretty(&file).map_err(|source| PlaceError::Json {
            path: jpath.clone(),
            source,
        })?;
        matloc_core::fsutil::write_atomic(&jpath, &json).map_err(|source| PlaceError::Io {
            path: jpath,
            source,
        })
    }

    /// Loads a model saved by [`PlaceModel::save`].
    pub fn load(dir: &Path) -> Result<PlaceModel, PlaceError> {
        let jpath = dir.join(MODEL_JSON);
        let bytes = std::fs::read(&jpath).map_err(|source| PlaceError::Io {
            path: jpath.clone(),
            source,
        })?;
        let file: ModelFile =
            serde_json::from_slice(&bytes).map_err(|source| PlaceError::Json {
                path: jpath.clone(),
                source,
            })?;
        if file.version != PLACE_MODEL_VERSION {
            return Err(PlaceError::UnsupportedVersion {
                found: file.version,
                expected: PLACE_MODEL_VERSION,
            });
        }
        file.config.validate()?;
        let wpath: PathBuf = dir.join(MODEL_WEIGHTS);
        let weights = std::fs::read(&wpath).map_err(|source| PlaceError::Io {
            path: wpath.clone(),
            source,
        })?;
        let device = Device::flex();
        let mut store = SafetensorsStore::from_bytes(Some(weights));
        let weights_err = |message: String| PlaceError::Weights {
            path: wpath.clone(),
            message,
        };
        let net = match file.method {
            PlaceMethod::ArcFace => {
                let mut m = ArcFaceNet::new(&file.config.net, file.groups.len(), 0, &device);
                let r = m
                    .load_from(&mut store)
                    .map_err(|e| weights_err(format!("{e:?}")))?;
                if !r.errors.is_empty() || !r.missing.is_empty() {
                    return Err(weights_err(format!("{r:?}")));
                }
                Net::ArcFace(m.valid())
            }
            PlaceMethod::Regression => {
                let mut m = RegressionNet::new(&file.config.net, 0, &device);
                let r = m
                    .load_from(&mut store)
                    .map_err(|e| weights_err(format!("{e:?}")))?;
                if !r.errors.is_empty() || !r.missing.is_empty() {
                    return Err(weights_err(format!("{r:?}")));
                }
                Net::Regression(m.valid())
            }
        };
        Ok(PlaceModel {
            method: file.method,
            config: file.config,
            groups: file.groups,
            center_mean: file.center_mean,
            center_scale: file.center_scale,
            member_embeddings: file.member_embeddings,
            member_poses: file.member_poses,
            refine_within_group: false,
            member_weight: 0.0,
            member_blend: 0.0,
            blend_as_extra: false,
            net,
            device,
        })
    }
}

impl PlacePredictor for PlaceModel {
    fn predict(
        &self,
        image: &Image<f32>,
        camera: &Camera,
        k: usize,
    ) -> Result<Vec<PlaceHypothesis>, PlaceError> {
        check_images(std::slice::from_ref(image))?;
        // The camera must describe this image; a mismatch means the caller mixed up inputs.
        let (cw, ch) = (camera.width as f64, camera.height as f64);
        let (iw, ih) = (image.width() as f64, image.height() as f64);
        if ((cw / ch) - (iw / ih)).abs() > 0.02 * (iw / ih) {
            return Err(PlaceError::InvalidConfig {
                field: "camera",
                reason: format!("camera {cw}x{ch} does not match the image {iw}x{ih}"),
            });
        }
        if (self.refine_within_group || self.member_weight > 0.0)
            && self.method == PlaceMethod::ArcFace
        {
            let (mut cos, emb) = self.arcface_outputs(std::slice::from_ref(image))?;
            if self.member_weight > 0.0 {
                let w = self.member_weight;
                for (c, m) in cos.iter_mut().zip(self.member_similarities(&emb)) {
                    *c = (1.0 - w) * *c + w * m;
                }
            }
            let mut h = self.hypotheses_from_output(&cos, k);
            if self.refine_within_group {
                let extra = self.blend_as_extra && self.member_blend > 0.0;
                for x in &mut h {
                    if let Some(p) = self.member_pose(x.group, &emb, !extra) {
                        x.cam_from_world = p;
                    }
                }
                if extra
                    && let Some(first) = h.first()
                    && let Some(p) = self.member_pose(first.group, &emb, true)
                {
                    let second = PlaceHypothesis {
                        cam_from_world: p,
                        ..first.clone()
                    };
                    h.insert(1, second);
                }
            }
            return Ok(h);
        }
        let out = self.forward_batch(std::slice::from_ref(image))?;
        Ok(self.hypotheses_from_output(&out, k))
    }
}

/// Mean of the surface points a pose sees, from its z-depth map (every `stride`-th pixel):
/// the "view point" [`PoseGroups::build`] measures viewing distances to.
pub fn view_point_from_depth(
    camera: &Camera,
    cam_from_world: &Pose,
    depth: &Image<f32>,
    stride: usize,
) -> Option<Point3<f64>> {
    let pts = surface_points(camera, cam_from_world, depth, stride);
    if pts.is_empty() {
        return None;
    }
    let s = pts.iter().fold(Vector3::zeros(), |s, p| s + p.coords);
    Some(Point3::from(s / pts.len() as f64))
}

/// World points of every `stride`-th depth pixel with a surface.
pub fn surface_points(
    camera: &Camera,
    cam_from_world: &Pose,
    depth: &Image<f32>,
    stride: usize,
) -> Vec<Point3<f64>> {
    let stride = stride.max(1);
    let (dw, dh) = (depth.width(), depth.height());
    if dw == 0 || dh == 0 {
        return Vec::new();
    }
    let (sx, sy) = (
        camera.width as f64 / dw as f64,
        camera.height as f64 / dh as f64,
    );
    let world_from_cam = cam_from_world.inverse();
    let mut out = Vec::new();
    for r in (stride / 2..dh).step_by(stride) {
        for c in (stride / 2..dw).step_by(stride) {
            let z = f64::from(depth.data()[r * dw + c]);
            if !(z.is_finite() && z > 0.0) {
                continue;
            }
            let px = nalgebra::Point2::new((c as f64 + 0.5) * sx, (r as f64 + 0.5) * sy);
            let Some(b) = camera.unproject(px) else {
                continue;
            };
            if b.z <= 1e-9 {
                continue;
            }
            out.push(world_from_cam * Point3::from(b * (z / b.z)));
        }
    }
    out
}

/// Fraction of the ground seen by `truth` (its depth map) that also lies inside the image of
/// `other` (in front of the camera, within the frame). Occlusion at `other` is not tested: the
/// aerial views here see the same ground from above, where it rarely matters, and predicted
/// poses have no depth map to test it against.
pub fn view_overlap(
    camera: &Camera,
    truth: &Pose,
    depth: &Image<f32>,
    other_camera: &Camera,
    other: &Pose,
    stride: usize,
) -> f64 {
    let pts = surface_points(camera, truth, depth, stride);
    if pts.is_empty() {
        return 0.0;
    }
    let seen = pts
        .iter()
        .filter(|p| {
            let pc = other * **p;
            pc.z > 1e-6
                && other_camera
                    .project(&pc.coords)
                    .is_some_and(|px| other_camera.contains(px))
        })
        .count();
    seen as f64 / pts.len() as f64
}
