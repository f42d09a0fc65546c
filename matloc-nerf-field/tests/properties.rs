//! Contraction properties, feature subsets, serialisation and the optimiser.

use matloc_nerf_field::{
    Adam, AdamConfig, ExponentialDecay, F_MLP_DIMS, FEATURE_DIM, FeatureField, FieldConfig,
    FieldError, NerfactoField, SceneBox, contract, contract_to_unit,
};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn config() -> FieldConfig {
    FieldConfig {
        log2_table_size: 12,
        base_resolution: 8,
        max_resolution: 128,
        scene_box: SceneBox {
            min: [-10.0, -10.0, -2.0],
            max: [10.0, 10.0, 3.0],
        },
        num_images: 4,
        appearance_dim: 8,
        seed: 3,
        ..FieldConfig::default()
    }
}

fn field() -> NerfactoField {
    let mut f = NerfactoField::new(config()).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for v in &mut f.grid.table {
        *v = rng.random_range(-0.3..0.3);
    }
    for v in &mut f.appearance {
        *v = rng.random_range(-1.0..1.0);
    }
    f
}

fn points(n: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            [
                rng.random_range(-30.0..30.0),
                rng.random_range(-30.0..30.0),
                rng.random_range(-5.0..8.0),
            ]
        })
        .collect()
}

proptest! {
    #[test]
    fn contraction_lands_in_unit_cube(x in -1e6f32..1e6, y in -1e6f32..1e6, z in -1e6f32..1e6) {
        let sb = SceneBox { min: [-3.0, -1.0, 0.0], max: [5.0, 2.0, 1.0] };
        let u = contract_to_unit(&sb, [x, y, z]);
        for a in u {
            prop_assert!((0.0..=1.0).contains(&a));
        }
    }

    #[test]
    fn contraction_is_identity_inside(x in -1f32..=1.0, y in -1f32..=1.0, z in -1f32..=1.0) {
        prop_assert_eq!(contract([x, y, z]), [x, y, z]);
    }

    #[test]
    fn contraction_is_radially_monotone(
        dx in -1f32..1.0, dy in -1f32..1.0, dz in -1f32..1.0, s in 0.01f32..100.0, ds in 0.001f32..10.0,
    ) {
        prop_assume!(dx.abs().max(dy.abs()).max(dz.abs()) > 1e-3);
        let a = contract([dx * s, dy * s, dz * s]);
        let b = contract([dx * (s + ds), dy * (s + ds), dz * (s + ds)]);
        let na = a[0].abs().max(a[1].abs()).max(a[2].abs());
        let nb = b[0].abs().max(b[1].abs()).max(b[2].abs());
        prop_assert!(nb >= na - 1e-6, "{na} -> {nb}");
        prop_assert!(nb <= 2.0);
    }
}

#[test]
fn feature_subset_equals_slice_of_all_dims() {
    let f = field();
    let pts = points(300, 1);
    let all: Vec<usize> = (0..FEATURE_DIM).collect();
    let mut d_all = vec![0f32; pts.len()];
    let mut f_all = vec![0f32; pts.len() * FEATURE_DIM];
    f.density_and_features(&pts, &all, &mut d_all, &mut f_all)
        .unwrap();
    let dims = [40usize, 3, 0, 31, 46];
    let mut d_sub = vec![0f32; pts.len()];
    let mut f_sub = vec![0f32; pts.len() * dims.len()];
    f.density_and_features(&pts, &dims, &mut d_sub, &mut f_sub)
        .unwrap();
    assert_eq!(d_all, d_sub);
    for i in 0..pts.len() {
        for (j, &d) in dims.iter().enumerate() {
            assert_eq!(f_sub[i * dims.len() + j], f_all[i * FEATURE_DIM + d]);
        }
    }
    // The same numbers as the training forward.
    let dirs = vec![[0.0, 0.0, -1.0]; pts.len()];
    let c = f.forward_train(&pts, &dirs, &[]).unwrap();
    for i in 0..pts.len() {
        assert!((c.density()[i] - d_all[i]).abs() <= 1e-5 * d_all[i].abs().max(1.0));
        let fi = c.features(i);
        for d in 0..FEATURE_DIM {
            assert!((fi[d] - f_all[i * FEATURE_DIM + d]).abs() < 1e-5);
        }
    }
    // Colour through the trait equals the training forward with the fallback embedding.
    let fm: Vec<f32> = (0..pts.len())
        .flat_map(|i| f_all[i * FEATURE_DIM + F_MLP_DIMS.start..(i + 1) * FEATURE_DIM].to_vec())
        .collect();
    let mut rgb = vec![0f32; pts.len() * 3];
    f.colour(&fm, &dirs, None, &mut rgb).unwrap();
    for (a, b) in rgb.iter().zip(c.rgb()) {
        assert!((a - b).abs() < 1e-5);
    }
}

#[test]
fn bad_inputs_are_typed_errors() {
    let f = field();
    let pts = points(4, 2);
    let mut d = vec![0f32; 4];
    let mut feat = vec![0f32; 4];
    assert!(matches!(
        f.density_and_features(&pts, &[47], &mut d, &mut feat),
        Err(FieldError::DimOutOfRange { dim: 47, .. })
    ));
    assert!(matches!(
        f.density_and_features(&pts, &[1, 2], &mut d, &mut feat),
        Err(FieldError::LengthMismatch { .. })
    ));
    let mut rgb = vec![0f32; 12];
    assert!(matches!(
        f.colour(&[0.0; 60], &[[0.0, 0.0, 1.0]; 4], Some(9), &mut rgb),
        Err(FieldError::AppearanceOutOfRange { index: 9, count: 4 })
    ));
    let bad = FieldConfig {
        log2_table_size: 40,
        ..FieldConfig::default()
    };
    assert!(matches!(
        NerfactoField::new(bad),
        Err(FieldError::InvalidConfig {
            field: "log2_table_size",
            ..
        })
    ));
}

#[test]
fn save_load_round_trip_renders_identically() {
    let f = field();
    let dir = tempfile::tempdir().unwrap();
    f.save_dir(dir.path()).unwrap();
    assert!(!dir.path().join("field.safetensors.tmp").exists());
    let g = NerfactoField::load_dir(dir.path()).unwrap();
    assert_eq!(f.config(), g.config());
    let pts = points(200, 5);
    let dirs = vec![[0.6, 0.0, -0.8]; pts.len()];
    let app: Vec<u32> = (0..pts.len()).map(|i| (i % 4) as u32).collect();
    let a = f.forward_train(&pts, &dirs, &app).unwrap();
    let b = g.forward_train(&pts, &dirs, &app).unwrap();
    assert_eq!(a.density(), b.density());
    assert_eq!(a.rgb(), b.rgb());
}

#[test]
fn mismatched_config_is_an_error() {
    let f = field();
    let dir = tempfile::tempdir().unwrap();
    let w = dir.path().join("field.safetensors");
    let c = dir.path().join("field.json");
    f.save(&w, &c).unwrap();
    let other = FieldConfig {
        log2_table_size: 13,
        ..config()
    };
    match NerfactoField::load_weights(other, &w) {
        Err(FieldError::ShapeMismatch { name, .. }) => assert_eq!(name, "hash_table"),
        other => panic!("expected ShapeMismatch, got {other:?}"),
    }
    let other = FieldConfig {
        appearance_dim: 4,
        ..config()
    };
    assert!(matches!(
        NerfactoField::load_weights(other, &w),
        Err(FieldError::ShapeMismatch { .. })
    ));
    std::fs::write(&w, b"not a safetensors file").unwrap();
    assert!(matches!(
        NerfactoField::load(&w, &c),
        Err(FieldError::Safetensors { .. })
    ));
    assert!(matches!(
        NerfactoField::load(&dir.path().join("missing"), &c),
        Err(FieldError::Io { .. })
    ));
}

#[test]
fn adam_minimises_a_quadratic_and_consumes_gradients() {
    let target = [3.0f32, -2.0, 0.5];
    let mut p = vec![0f32; 3];
    let mut g = vec![0f32; 3];
    let mut adam = Adam::new(AdamConfig::default(), &[3]);
    let sched = ExponentialDecay {
        lr_init: 0.1,
        lr_final: 0.001,
        max_steps: 2000,
    };
    for step in 0..2000 {
        for i in 0..3 {
            g[i] = 2.0 * (p[i] - target[i]);
        }
        adam.step(sched.lr(step), &mut [&mut p], &mut [&mut g]);
        assert!(g.iter().all(|v| *v == 0.0));
    }
    for i in 0..3 {
        assert!((p[i] - target[i]).abs() < 1e-2, "{p:?}");
    }
    assert_eq!(adam.steps(), 2000);
    let s = ExponentialDecay::default();
    assert!((s.lr(0) - 1e-2).abs() < 1e-9);
    assert!((s.lr(s.max_steps) - 1e-4).abs() < 1e-9);
    assert!((s.lr(s.max_steps / 2) - 1e-3).abs() < 1e-7);
    assert_eq!(s.lr(10 * s.max_steps), s.lr(s.max_steps));
}
