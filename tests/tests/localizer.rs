//! The localizer's composition logic (top-k fallback, refinement passes, refusal) on the
//! synthetic world's exact geometry with an analytic feature field: the "encoder" returns the
//! analytic features rendered at the query's true pose, so every failure here is the
//! composition's, not a network's.

use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::{Camera, FeatureMap, Image, Pose};
use matloc_data::Split;
use matloc_match::ViewRenderer;
use matloc_match::{MnnConfig, MnnMatcher};
use matloc_pipeline::FixedPlace;
use matloc_pipeline::localizer::confidence::ConfidenceModel;
use matloc_pipeline::{
    LocalizeOptions, Localizer, LocalizerBlock, PipelineError, QueryFeatureEncoder,
};
use matloc_place::PlaceHypothesis;
use matloc_pnp::LoRansacPnp;
use matloc_synth::oracle::{SynthFeatureField, SynthFeatureRenderer, SynthFieldConfig};
use matloc_synth::{SynthConfig, World, plan_survey};
use nalgebra::{Translation3, UnitQuaternion, Vector3};

const STRIDE: u32 = 4;

/// "Encoder" that renders the analytic features at a fixed true pose.
struct OracleEncoder<'a> {
    renderer: &'a SynthFeatureRenderer,
    camera: Camera,
    true_pose: Pose,
    dims: Vec<usize>,
    scramble: bool,
}

impl QueryFeatureEncoder for OracleEncoder<'_> {
    fn dims(&self) -> &[usize] {
        &self.dims
    }
    fn stride(&self) -> u32 {
        STRIDE
    }
    fn stats(&self) -> Option<&matloc_match::FeatureStats> {
        None
    }
    fn encode(&self, _image: &Image<f32>) -> Result<FeatureMap, PipelineError> {
        let v = self
            .renderer
            .render_view(&self.camera, &self.true_pose, STRIDE, &self.dims)
            .map_err(PipelineError::ViewRender)?;
        let mut data = v.features;
        if self.scramble {
            // An unrelated image: features from nowhere in this map.
            let mut s = 0x2545_f491_4f6c_dd1du64;
            for x in &mut data {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                *x = (s >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0;
            }
        }
        Ok(FeatureMap::from_vec(v.cols, v.rows, self.dims.len(), data).unwrap())
    }
}

fn perturbed(pose: &Pose, dx: f64, yaw_deg: f64) -> Pose {
    Pose::from_parts(
        Translation3::new(dx, -0.5 * dx, 0.3 * dx),
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians()),
    ) * pose
}

fn hyp(group: usize, pose: Pose, block: usize) -> PlaceHypothesis {
    PlaceHypothesis {
        group,
        score: 0.5,
        cam_from_world: pose,
        block: Some(block),
    }
}

struct Scene {
    renderer: SynthFeatureRenderer,
    camera: Camera,
    query_pose: Pose,
}

fn scene() -> Scene {
    let cfg = SynthConfig::preset("tiny").unwrap();
    let world = World::generate(&cfg.world, cfg.seed).unwrap();
    let plan = plan_survey(&world, &cfg.survey, cfg.seed).unwrap();
    let test: Vec<_> = plan
        .frames
        .iter()
        .filter(|f| f.split == Split::Test)
        .collect();
    let q = test[0];
    let field = SynthFeatureField::new(SynthFieldConfig::default());
    Scene {
        renderer: SynthFeatureRenderer::new(world, field),
        camera: q.camera,
        query_pose: q.cam_from_world,
    }
}

fn run(
    s: &Scene,
    hyps: Vec<PlaceHypothesis>,
    scramble: bool,
    options: LocalizeOptions,
) -> matloc_pipeline::Localization {
    let dims: Vec<usize> = (0..s.renderer.num_features()).collect();
    let encoder = OracleEncoder {
        renderer: &s.renderer,
        camera: s.camera,
        true_pose: s.query_pose,
        dims: dims.clone(),
        scramble,
    };
    let place = FixedPlace(hyps);
    let matcher = MnnMatcher::new(MnnConfig::default());
    let solver = LoRansacPnp::default();
    let localizer = Localizer {
        place: &place,
        blocks: vec![LocalizerBlock {
            renderer: &s.renderer,
            encoder: &encoder,
            matcher: &matcher,
            dims: dims[..12].to_vec(),
            match_dims: None,
        }],
        solver: &solver,
        options,
    };
    let image = Image::new(s.camera.width as usize, s.camera.height as usize, 3);
    localizer.localize(&image, &s.camera).unwrap()
}

#[test]
fn localizes_from_a_perturbed_coarse_pose_and_refines() {
    let s = scene();
    let coarse = perturbed(&s.query_pose, 2.0, 3.0);
    let start_t = translation_error_m(&coarse, &s.query_pose);
    let out = run(
        &s,
        vec![hyp(0, coarse, 0)],
        false,
        LocalizeOptions::default(),
    );
    let pose = out.cam_from_world.expect("localized");
    let t = translation_error_m(&pose, &s.query_pose);
    let r = rotation_error_deg(&pose, &s.query_pose);
    println!(
        "start {start_t:.2} m → {t:.3} m / {r:.3}°, confidence {:.3}, {:?}",
        out.confidence, out.hypotheses
    );
    // Measured: 0.044 m / 0.08° from this 2.3 m start with the feature-metric refinement
    // (0.056 m / 0.11° without it); 0.000 m from the true pose.
    assert!(t < 0.5 && r < 0.75 && t < start_t / 5.0, "{t} m {r}°");
    assert!(out.confidence >= 0.5);
    let h = &out.hypotheses[0];
    assert!(h.accepted && h.passes >= 2, "{h:?}");
    // From the true pose the composition is exact.
    let out = run(
        &s,
        vec![hyp(0, s.query_pose, 0)],
        false,
        LocalizeOptions::default(),
    );
    let pose = out.cam_from_world.expect("localized");
    assert!(translation_error_m(&pose, &s.query_pose) < 1e-3);
    let stages: Vec<&str> = out.stage_seconds.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        stages,
        ["place", "encode", "render", "match", "pnp", "refine"]
    );
}

#[test]
fn falls_back_to_the_next_hypothesis() {
    let s = scene();
    let good = perturbed(&s.query_pose, 1.5, -2.0);
    // A wrong hypothesis: the camera turned to face the sky (nothing to match).
    let sky = Pose::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
    ) * s.query_pose;
    let out = run(
        &s,
        vec![hyp(7, sky, 0), hyp(3, good, 0)],
        false,
        LocalizeOptions::default(),
    );
    assert_eq!(out.hypotheses.len(), 2, "{:?}", out.hypotheses);
    assert!(!out.hypotheses[0].accepted);
    assert!(out.hypotheses[1].accepted);
    let pose = out.cam_from_world.expect("second hypothesis localizes");
    assert!(translation_error_m(&pose, &s.query_pose) < 0.5);
    // A hypothesis naming a block the map does not have is skipped, not a crash.
    let out = run(
        &s,
        vec![hyp(1, good, 5), hyp(3, good, 0)],
        false,
        LocalizeOptions::default(),
    );
    assert!(out.hypotheses[0].failure.is_some());
    assert!(out.cam_from_world.is_some());
    // A later hypothesis the place stage all but rules out is not tried.
    let unlikely = PlaceHypothesis {
        score: 0.005,
        ..hyp(3, good, 0)
    };
    let out = run(
        &s,
        vec![hyp(7, sky, 0), unlikely.clone()],
        false,
        LocalizeOptions::default(),
    );
    assert_eq!(out.hypotheses.len(), 1, "{:?}", out.hypotheses);
    assert!(out.cam_from_world.is_none());
    let out = run(
        &s,
        vec![hyp(7, sky, 0), unlikely],
        false,
        LocalizeOptions {
            min_place_score: 0.0,
            ..LocalizeOptions::default()
        },
    );
    assert!(out.hypotheses[1].accepted);
}

#[test]
fn an_unrelated_image_is_refused() {
    let s = scene();
    let coarse = perturbed(&s.query_pose, 1.0, 1.0);
    let out = run(
        &s,
        vec![hyp(0, coarse, 0)],
        true,
        LocalizeOptions::default(),
    );
    assert!(
        out.cam_from_world.is_none(),
        "accepted with confidence {} and {} inliers",
        out.confidence,
        out.inliers
    );
}

#[test]
fn a_chance_consensus_is_refused_whatever_the_confidence_model_says() {
    let s = scene();
    let coarse = perturbed(&s.query_pose, 1.0, 1.0);
    // A confidence model that trusts any pose PnP returns, wherever it lands.
    let credulous = LocalizeOptions {
        max_correction_m: f64::INFINITY,
        max_correction_deg: 180.0,
        confidence: ConfidenceModel {
            weights: [10.0, 0.0, 0.0, 0.0],
            alignment_weight: 0.0,
            accept_threshold: 0.5,
        },
        ..LocalizeOptions::default()
    };
    let ungated = run(
        &s,
        vec![hyp(0, coarse, 0)],
        true,
        LocalizeOptions {
            max_log10_nfa: f64::INFINITY,
            ..credulous.clone()
        },
    );
    let h = &ungated.hypotheses[0];
    println!("ungated: {h:?}");
    assert!(
        ungated.cam_from_world.is_some(),
        "random features gave no pose at all, so this test shows nothing: {h:?}"
    );
    let gated = run(&s, vec![hyp(0, coarse, 0)], true, credulous.clone());
    let h = &gated.hypotheses[0];
    assert!(gated.cam_from_world.is_none(), "{h:?}");
    assert!(h.log10_nfa.is_none_or(|v| v > 0.0), "{h:?}");
    // The real query's consensus is far beyond chance.
    let real = run(&s, vec![hyp(0, coarse, 0)], false, credulous);
    let h = &real.hypotheses[0];
    assert!(real.cam_from_world.is_some(), "{h:?}");
    assert!(h.log10_nfa.is_some_and(|v| v < -20.0), "{h:?}");
}

#[test]
fn a_pose_rotated_beyond_the_accept_bound_from_its_coarse_pose_is_refused() {
    let s = scene();
    // The right place, but a coarse attitude 8° off: the pose lands on the truth, 8° from it.
    let coarse = perturbed(&s.query_pose, 1.0, 8.0);
    let bounded = |deg: f64| {
        run(
            &s,
            vec![hyp(0, coarse, 0)],
            false,
            LocalizeOptions {
                max_accept_rotation_deg: deg,
                ..LocalizeOptions::default()
            },
        )
    };
    let loose = bounded(180.0);
    let pose = loose.cam_from_world.expect("localized without the bound");
    let turned = rotation_error_deg(&pose, &coarse);
    assert!(
        turned > 6.0,
        "the pose turned only {turned:.2}° from its coarse pose"
    );
    let tight = bounded(6.0);
    assert!(tight.cam_from_world.is_none(), "{:?}", tight.hypotheses);
    // The bounded passes still ran (the bound scores a pass 0, it does not stop it).
    assert_eq!(tight.hypotheses[0].passes, loose.hypotheses[0].passes);
    assert!(bounded(turned + 1.0).cam_from_world.is_some());
}

#[test]
fn wrong_image_size_is_a_typed_error() {
    let s = scene();
    let dims: Vec<usize> = (0..8).collect();
    let encoder = OracleEncoder {
        renderer: &s.renderer,
        camera: s.camera,
        true_pose: s.query_pose,
        dims: dims.clone(),
        scramble: false,
    };
    let place = FixedPlace(vec![hyp(0, s.query_pose, 0)]);
    let matcher = MnnMatcher::new(MnnConfig::default());
    let solver = LoRansacPnp::default();
    let localizer = Localizer {
        place: &place,
        blocks: vec![LocalizerBlock {
            renderer: &s.renderer,
            encoder: &encoder,
            matcher: &matcher,
            dims: vec![40], // not produced by the encoder
            match_dims: None,
        }],
        solver: &solver,
        options: LocalizeOptions::default(),
    };
    let small = Image::new(10, 10, 3);
    assert!(matches!(
        localizer.localize(&small, &s.camera),
        Err(PipelineError::QueryShape { .. })
    ));
    let image = Image::new(s.camera.width as usize, s.camera.height as usize, 3);
    assert!(matches!(
        localizer.localize(&image, &s.camera),
        Err(PipelineError::DimsNotEncoded { dim: 40 })
    ));
}
