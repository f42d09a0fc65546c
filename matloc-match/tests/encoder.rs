//! Query encoder: learns a colour-to-feature mapping, checkpoints round-trip, typed errors.
#![cfg(feature = "encoder")]

use matloc_core::Image;
use matloc_match::FeatureStats;
use matloc_match::encoder::*;
use matloc_match::gt::RenderedView;
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
