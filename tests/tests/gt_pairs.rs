//! Ground-truth pair generation against the synthetic world's exact geometry.

use matloc_core::{Camera, Pose};
use matloc_match::{RenderFailure, RenderedView, ViewRenderer};
use matloc_pipeline::gt::*;
use matloc_synth::oracle::{SynthFeatureField, SynthFeatureRenderer, SynthFieldConfig};
use matloc_synth::{SynthConfig, World, plan_survey};
use nalgebra::{Point2, Point3};
use proptest::prelude::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::sync::OnceLock;

struct Scene {
    renderer: SynthFeatureRenderer,
    views: Vec<TrainingView>,
}

fn scene() -> &'static Scene {
    static SCENE: OnceLock<Scene> = OnceLock::new();
    SCENE.get_or_init(|| {
        let cfg = SynthConfig::preset("tiny").unwrap();
        let world = World::generate(&cfg.world, cfg.seed).unwrap();
        let plan = plan_survey(&world, &cfg.survey, cfg.seed).unwrap();
        let views = plan
            .frames
            .iter()
            .enumerate()
            .step_by(7)
            .take(5)
            .map(|(i, f)| TrainingView {
                index: i,
                camera: f.camera,
                cam_from_world: f.cam_from_world,
            })
            .collect();
        let field = SynthFeatureField::new(SynthFieldConfig::default());
        Scene {
            renderer: SynthFeatureRenderer::new(world, field),
            views,
        }
    })
}

fn centre(pose: &Pose) -> Point3<f64> {
    pose.inverse_transform_point(&Point3::origin())
}

#[test]
fn pairs_truly_correspond() {
    let s = scene();
    let cfg = GtConfig::default();
    let set = generate_pairs(&s.renderer, &s.views, &cfg, 11).unwrap();
    let cells = 40 * 30;
    assert!(
        set.len() > s.views.len() * cells / 4,
        "only {} pairs from {} views",
        set.len(),
        s.views.len()
    );
    let world = s.renderer.world();
    let mut exact = 0;
    for p in 0..set.len() {
        let prov = &set.provenance.renders[set.render[p] as usize];
        let view = &prov.view;
        let x = Point3::from(set.point_world[p]);
        // The stored projection is the point's projection at the true pose.
        let u = view.camera.project_world(&view.cam_from_world, &x).unwrap();
        assert!((u.x - set.query_px[p][0]).abs() < 1e-6 && (u.y - set.query_px[p][1]).abs() < 1e-6);
        // Within the threshold of its query cell centre.
        let q = set.query_index[p] as usize;
        let (cx, cy) = ((q % 40) as f64 * 4.0 + 2.0, (q / 40) as f64 * 4.0 + 2.0);
        assert!((u.x - cx).hypot(u.y - cy) <= cfg.reprojection_px + 1e-9);
        // The point lies on a surface, and that surface is what the training camera sees along
        // the ray through the projection: the pair truly corresponds.
        let c = centre(&view.cam_from_world);
        let dir = x - c;
        let hit = world.raycast(&c, &dir).expect("visible point");
        let dist = dir.norm();
        if (hit.t - dist).abs() <= 1e-4 * dist {
            exact += 1;
        } else {
            // Only grazing silhouettes may differ, and never by more than the depth tolerance.
            assert!(
                (hit.t - dist).abs() <= 0.05 * dist + 0.1,
                "pair {p}: hit at {} m, point at {dist} m",
                hit.t
            );
        }
    }
    let frac = exact as f64 / set.len() as f64;
    assert!(frac > 0.97, "only {frac:.3} of pairs exactly visible");
}

#[test]
fn zero_perturbation_pairs_every_surface_cell_with_itself() {
    let s = scene();
    let cfg = GtConfig {
        perturbation: Perturbation {
            translation_m: 0.0,
            rotation_deg: 0.0,
            ..Default::default()
        },
        ..Default::default()
    };
    let set = generate_pairs(&s.renderer, &s.views[..2], &cfg, 0).unwrap();
    for r in &set.provenance.renders {
        assert_eq!(r.counts.kept, r.counts.surface);
        assert_eq!(
            r.counts.occluded + r.counts.reprojection + r.counts.duplicate,
            0
        );
    }
    for p in 0..set.len() {
        assert_eq!(set.query_index[p], set.map_index[p]);
        assert!(set.reprojection_px[p] < 1e-6);
        assert_eq!(set.query_feature(p), set.map_feature(p));
    }
}

#[test]
fn deterministic_and_roundtrips_through_safetensors() {
    let s = scene();
    let cfg = GtConfig {
        dims: Some(vec![3, 40, 7]),
        perturbations_per_view: 2,
        ..Default::default()
    };
    let a = generate_pairs(&s.renderer, &s.views[..2], &cfg, 5).unwrap();
    let b = generate_pairs(&s.renderer, &s.views[..2], &cfg, 5).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.provenance.renders.len(), 4);
    assert_eq!(a.dims(), 3);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pairs.safetensors");
    a.save(&path).unwrap();
    let back = GtPairSet::load(&path).unwrap();
    assert_eq!(a, back);
    // A truncated file is a typed format error, not a panic.
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    assert!(matches!(
        GtPairSet::load(&path),
        Err(GtError::Format { .. })
    ));
    assert!(matches!(
        GtPairSet::load(&dir.path().join("missing")),
        Err(GtError::Io { .. })
    ));
}

struct BadRenderer;

impl ViewRenderer for BadRenderer {
    fn num_features(&self) -> usize {
        4
    }
    fn describe(&self) -> String {
        "bad".into()
    }
    fn render_view(
        &self,
        _camera: &Camera,
        _pose: &Pose,
        _stride: u32,
        dims: &[usize],
    ) -> Result<RenderedView, RenderFailure> {
        Ok(RenderedView {
            cols: 1,
            rows: 1,
            dims: dims.len(),
            features: vec![0.0; dims.len()],
            depth_z: vec![1.0],
            accumulation: vec![1.0],
        })
    }
}

#[test]
fn typed_errors() {
    let s = scene();
    let v = &s.views[..1];
    let r = &s.renderer;
    assert!(matches!(
        generate_pairs(r, &[], &GtConfig::default(), 0),
        Err(GtError::NoViews)
    ));
    let stride0 = GtConfig {
        stride: 0,
        ..Default::default()
    };
    assert!(matches!(
        generate_pairs(r, v, &stride0, 0),
        Err(GtError::InvalidConfig {
            field: "stride",
            ..
        })
    ));
    let out_of_range = GtConfig {
        dims: Some(vec![0, 47]),
        ..Default::default()
    };
    assert!(matches!(
        generate_pairs(r, v, &out_of_range, 0),
        Err(GtError::DimOutOfRange { dim: 47, dims: 47 })
    ));
    let neg = GtConfig {
        perturbation: Perturbation {
            translation_m: -1.0,
            ..Default::default()
        },
        ..Default::default()
    };
    assert!(matches!(
        generate_pairs(r, v, &neg, 0),
        Err(GtError::InvalidConfig { .. })
    ));
    assert!(matches!(
        generate_pairs(&BadRenderer, v, &GtConfig::default(), 0),
        Err(GtError::BadRender { .. })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn uniform_ball_perturbation_is_bounded(t in 0.0f64..10.0, r in 0.0f64..20.0, seed in any::<u64>()) {
        let pose = scene().views[0].cam_from_world;
        let p = Perturbation { kind: PerturbKind::UniformBall, translation_m: t, rotation_deg: r };
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let q = p.apply(&pose, &mut rng);
        let dt = (centre(&q) - centre(&pose)).norm();
        let dr = matloc_core::metrics::rotation_error_deg(&q, &pose);
        prop_assert!(dt <= t + 1e-9, "{dt} > {t}");
        prop_assert!(dr <= r + 1e-6, "{dr} > {r}");
        // The camera rotates about its own centre: the centre moves only by the translation.
        let q0 = Perturbation { kind: PerturbKind::Gaussian, translation_m: 0.0, rotation_deg: r }
            .apply(&pose, &mut rng);
        prop_assert!((centre(&q0) - centre(&pose)).norm() < 1e-9);
    }
}

#[test]
fn renderer_depth_lifts_onto_the_surface() {
    let s = scene();
    let v = &s.views[0];
    let r = s
        .renderer
        .render_view(&v.camera, &v.cam_from_world, 8, &[0, 1])
        .unwrap();
    let world_from_cam = v.cam_from_world.inverse();
    let c = centre(&v.cam_from_world);
    let mut hits = 0;
    for i in 0..r.cols * r.rows {
        if r.accumulation[i] < 0.5 {
            continue;
        }
        hits += 1;
        let px = Point2::new(
            (i % r.cols) as f64 * 8.0 + 4.0,
            (i / r.cols) as f64 * 8.0 + 4.0,
        );
        let b = v.camera.unproject(px).unwrap();
        let x = world_from_cam * Point3::from(b * (r.depth_z[i] as f64 / b.z));
        let hit = s.renderer.world().raycast(&c, &(x - c)).unwrap();
        assert!((hit.point - x).norm() < 1e-3 * hit.t.max(1.0));
    }
    assert!(hits > r.cols * r.rows / 2);
}
