//! Query encoder: learns a colour-to-feature mapping, checkpoints round-trip, typed errors.

use matloc_core::Image;
use matloc_encoder::*;
use matloc_match::FeatureStats;
use matloc_match::RenderedView;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Blocky random images; the target of a 4 × 4 cell is a fixed linear map of its mean colour.
fn samples(n: usize, size: usize, seed: u64) -> Vec<EncoderSample> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let g = size / 4;
    (0..n)
        .map(|_| {
            let mut img = Image::new(size, size, 3);
            let cols: Vec<[f32; 3]> = (0..g * g)
                .map(|_| [rng.random(), rng.random(), rng.random()])
                .collect();
            for y in 0..size {
                for x in 0..size {
                    img.pixel_mut(x, y)
                        .copy_from_slice(&cols[(y / 4) * g + x / 4]);
                }
            }
            let mut features = Vec::new();
            for c in &cols {
                features.extend_from_slice(&[
                    c[0] - c[1],
                    c[1] + c[2],
                    2.0 * c[2] - 1.0,
                    c[0] + 0.5 * c[1] - c[2],
                ]);
            }
            EncoderSample {
                image: img,
                target: RenderedView {
                    cols: g,
                    rows: g,
                    dims: 4,
                    features,
                    depth_z: vec![10.0; g * g],
                    accumulation: vec![1.0; g * g],
                },
                view: None,
            }
        })
        .collect()
}

fn stats_of(s: &[EncoderSample]) -> FeatureStats {
    let all: Vec<f32> = s.iter().flat_map(|x| x.target.features.clone()).collect();
    FeatureStats::from_features(&all, 4)
}

fn small_config(steps: usize) -> EncoderTrainConfig {
    EncoderTrainConfig {
        net: EncoderConfig {
            width: 16,
            dilations: vec![1],
            head_hidden: vec![16],
            local_contrast: false,
            shadow_invariant: false,
            standardize_input: false,
        },
        steps,
        batch: 4,
        learning_rate: 1e-2,
        nce_cells: 32,
        ..Default::default()
    }
}

#[test]
fn learns_and_roundtrips() {
    let s = samples(8, 32, 1);
    let stats = stats_of(&s);
    let mut losses = Vec::new();
    let enc = train_encoder(&s, vec![3, 5, 8, 9], stats, &small_config(80), &mut |p| {
        losses.push(p.mse)
    })
    .unwrap();
    assert_eq!(losses.len(), 80);
    let first: f32 = losses[..5].iter().sum::<f32>() / 5.0;
    let last: f32 = losses[75..].iter().sum::<f32>() / 5.0;
    assert!(last < 0.5 * first, "mse {first} -> {last}");
    let out = enc.encode(&s[0].image).unwrap();
    assert_eq!(out.shape(), (8, 8, 4));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("enc.safetensors");
    enc.save(&path).unwrap();
    let back = QueryEncoder::load(&path).unwrap();
    assert_eq!(back.dims(), &[3, 5, 8, 9]);
    let out2 = back.encode(&s[0].image).unwrap();
    for (a, b) in out.data().iter().zip(out2.data()) {
        assert!((a - b).abs() < 1e-5);
    }
    assert!(matches!(
        back.check_dims(&[3, 5, 8]),
        Err(EncoderError::DimensionMismatch {
            encoder: 4,
            field: 3
        })
    ));
    back.check_dims(&[3, 5, 8, 9]).unwrap();
}

#[test]
fn the_same_samples_and_seed_train_the_same_encoder() {
    let s = samples(6, 32, 2);
    let train = || {
        let mut cfg = small_config(20);
        cfg.head_phase.steps = 10;
        let enc = train_encoder(&s, vec![3, 5, 8, 9], stats_of(&s), &cfg, &mut |_| {}).unwrap();
        enc.encode(&s[0].image).unwrap()
    };
    assert_eq!(train().data(), train().data());
}

#[test]
fn typed_errors() {
    let s = samples(2, 32, 2);
    let stats = stats_of(&s);
    let cfg = small_config(1);
    let mut nop = |_: &EncoderProgress| {};
    assert!(matches!(
        train_encoder(&[], vec![0, 1, 2, 3], stats.clone(), &cfg, &mut nop),
        Err(EncoderError::NoSamples)
    ));
    // Three dims requested, four rendered: encoder vs field mismatch.
    let three = FeatureStats {
        mean: stats.mean[..3].to_vec(),
        std: stats.std[..3].to_vec(),
    };
    assert!(matches!(
        train_encoder(&s, vec![0, 1, 2], three, &cfg, &mut nop),
        Err(EncoderError::DimensionMismatch {
            encoder: 3,
            field: 4
        })
    ));
    let enc = train_encoder(&s, vec![0, 1, 2, 3], stats, &cfg, &mut nop).unwrap();
    let grey = Image::<f32>::new(32, 32, 1);
    assert!(matches!(enc.encode(&grey), Err(EncoderError::BadInput(_))));
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.safetensors");
    std::fs::write(&p, b"not a checkpoint").unwrap();
    assert!(matches!(
        QueryEncoder::load(&p),
        Err(EncoderError::Format { .. })
    ));
}

#[test]
fn head_phase_lowers_the_loss_and_roundtrips() {
    let s = samples(8, 32, 3);
    let stats = stats_of(&s);
    let cfg = EncoderTrainConfig {
        head_phase: HeadPhaseConfig {
            steps: 60,
            images: 4,
            cells: 32,
            learning_rate: 1e-2,
            copies: 2,
        },
        ..small_config(20)
    };
    assert_eq!(cfg.total_steps(), 80);
    let mut seen = Vec::new();
    let enc = train_encoder(&s, vec![0, 1, 2, 3], stats, &cfg, &mut |p| {
        seen.push((p.step, p.steps, p.mse))
    })
    .unwrap();
    assert_eq!(seen.len(), 80);
    assert!(
        seen.iter()
            .enumerate()
            .all(|(i, p)| p.0 == i + 1 && p.1 == 80)
    );
    // Head-phase mse (last 5 steps) below the end-to-end phase's last 5 steps.
    let e2e: f32 = seen[15..20].iter().map(|p| p.2).sum::<f32>() / 5.0;
    let head: f32 = seen[75..].iter().map(|p| p.2).sum::<f32>() / 5.0;
    assert!(head < e2e, "mse {e2e} -> {head}");
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("enc.safetensors");
    enc.save(&path).unwrap();
    let back = QueryEncoder::load(&path).unwrap();
    assert_eq!(back.config(), enc.config());
    let (a, b) = (
        enc.encode(&s[1].image).unwrap(),
        back.encode(&s[1].image).unwrap(),
    );
    for (x, y) in a.data().iter().zip(b.data()) {
        assert!((x - y).abs() < 1e-5);
    }
}

#[test]
fn format_1_checkpoint_is_refused_with_a_typed_error() {
    // A format-1 file: safetensors with the old `matloc_encoder` metadata and the old
    // convolutional-head tensor names.
    let meta = std::collections::HashMap::from([(
        "matloc_encoder".to_string(),
        r#"[{"width":16,"dilations":[1]},[0],{"mean":[0.0],"std":[1.0]}]"#.to_string(),
    )]);
    let w = vec![0u8; 4 * 16];
    let view = safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![1, 16, 1, 1], &w)
        .unwrap();
    let bytes = safetensors::serialize([("head.weight", view)], Some(meta)).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("v1.safetensors");
    std::fs::write(&p, bytes).unwrap();
    match QueryEncoder::load(&p) {
        Err(EncoderError::Format { reason, .. }) => {
            assert!(reason.contains("format 1"), "{reason}")
        }
        other => panic!("expected a format error, got {other:?}"),
    }
}

#[test]
fn standardised_input_divides_out_a_gain_per_channel() {
    let s = samples(6, 32, 3);
    let mut cfg = small_config(20);
    cfg.net.standardize_input = true;
    let enc = train_encoder(&s, vec![3, 5, 8, 9], stats_of(&s), &cfg, &mut |_| {}).unwrap();
    let img = &s[0].image;
    let mut warmer = img.clone();
    for (k, v) in warmer.data_mut().iter_mut().enumerate() {
        *v *= [1.3, 1.1, 0.8][k % 3];
    }
    let (a, b) = (enc.encode(img).unwrap(), enc.encode(&warmer).unwrap());
    for (x, y) in a.data().iter().zip(b.data()) {
        assert!((x - y).abs() < 1e-3 * (1.0 + x.abs()), "{x} vs {y}");
    }
    // Without standardisation the same gain moves the features.
    cfg.net.standardize_input = false;
    let raw = train_encoder(&s, vec![3, 5, 8, 9], stats_of(&s), &cfg, &mut |_| {}).unwrap();
    let (a, b) = (raw.encode(img).unwrap(), raw.encode(&warmer).unwrap());
    let moved = a
        .data()
        .iter()
        .zip(b.data())
        .map(|(x, y)| (x - y).abs())
        .sum::<f32>();
    assert!(moved > 1e-2, "{moved}");
}

#[test]
fn a_checkpoint_without_the_standardisation_field_loads_without_it() {
    let s = samples(4, 32, 4);
    let mut cfg = small_config(5);
    cfg.net.standardize_input = false;
    let enc = train_encoder(&s, vec![3, 5, 8, 9], stats_of(&s), &cfg, &mut |_| {}).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("enc.safetensors");
    enc.save(&path).unwrap();
    // Rewrite the metadata as an encoder trained before the field existed wrote it.
    let bytes = std::fs::read(&path).unwrap();
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let mut entries = meta.metadata().clone().unwrap();
    let json = entries.get(CHECKPOINT_KEY).unwrap().clone();
    assert!(json.contains(r#","standardize_input":false"#), "{json}");
    entries.insert(
        CHECKPOINT_KEY.to_string(),
        json.replace(r#","standardize_input":false"#, ""),
    );
    let tensors = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let old = safetensors::serialize(tensors.tensors(), Some(entries)).unwrap();
    let legacy = dir.path().join("legacy.safetensors");
    std::fs::write(&legacy, old).unwrap();
    let back = QueryEncoder::load(&legacy).unwrap();
    assert!(!back.config().standardize_input);
    assert_eq!(
        back.encode(&s[0].image).unwrap().data(),
        enc.encode(&s[0].image).unwrap().data()
    );
    // A configuration that does not name the field gets the default.
    let cfg: EncoderConfig = serde_json::from_str(r#"{"width": 16}"#).unwrap();
    assert!(cfg.standardize_input);
}

/// `img` with its left half in a cast shadow: each channel's linear light keeps only the sky's
/// share of sun (2.5× the sky) + sky, the light model the shadow-invariant input assumes.
fn left_half_shadowed(img: &Image<f32>) -> Image<f32> {
    use matloc_core::shadow::{SKY_COLOUR as sky, SUN_COLOUR as sun};
    let mut out = img.clone();
    let w = img.width();
    for (i, px) in out.data_mut().chunks_exact_mut(3).enumerate() {
        if i % w < w / 2 {
            for k in 0..3 {
                let ratio = sky[k] / (2.5 * sun[k] + sky[k]);
                px[k] = (px[k].powf(2.2) * ratio).powf(1.0 / 2.2);
            }
        }
    }
    out
}

#[test]
fn a_shadow_invariant_encoder_ignores_a_cast_shadow_and_roundtrips() {
    let s = samples(6, 32, 5);
    let mut cfg = small_config(20);
    cfg.net.shadow_invariant = true;
    let enc = train_encoder(&s, vec![3, 5, 8, 9], stats_of(&s), &cfg, &mut |_| {}).unwrap();
    let img = &s[0].image;
    let shadowed = left_half_shadowed(img);
    let moved = |e: &QueryEncoder| {
        let (a, b) = (e.encode(img).unwrap(), e.encode(&shadowed).unwrap());
        a.data()
            .iter()
            .zip(b.data())
            .map(|(x, y)| (x - y).abs())
            .sum::<f32>()
    };
    let invariant = moved(&enc);
    // The same shadow moves the features of an encoder on standardised RGB.
    cfg.net.shadow_invariant = false;
    cfg.net.standardize_input = true;
    let rgb = train_encoder(&s, vec![3, 5, 8, 9], stats_of(&s), &cfg, &mut |_| {}).unwrap();
    let seen = moved(&rgb);
    assert!(
        invariant < 0.1 * seen,
        "the shadow moved the invariant encoder's features by {invariant}, RGB's by {seen}"
    );
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("enc.safetensors");
    enc.save(&path).unwrap();
    let back = QueryEncoder::load(&path).unwrap();
    assert!(back.config().shadow_invariant);
    let (a, b) = (enc.encode(img).unwrap(), back.encode(img).unwrap());
    for (x, y) in a.data().iter().zip(b.data()) {
        assert!((x - y).abs() < 1e-5);
    }
}
