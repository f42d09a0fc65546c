//! Selection on ground-truth pairs generated from the synthetic world (grouped by render).

use matloc_pipeline::gt::{GtConfig, TrainingView, generate_pairs};
use matloc_select::*;
use matloc_synth::oracle::{SynthFeatureField, SynthFeatureRenderer, SynthFieldConfig};
use matloc_synth::{SynthConfig, World, plan_survey};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[test]
fn greedy_selection_on_gt_pairs_beats_long_wavelength_dims() {
    let cfg = SynthConfig::preset("tiny").unwrap();
    let world = World::generate(&cfg.world, cfg.seed).unwrap();
    let plan = plan_survey(&world, &cfg.survey, cfg.seed).unwrap();
    let views: Vec<TrainingView> = plan
        .frames
        .iter()
        .enumerate()
        .step_by(9)
        .take(4)
        .map(|(i, f)| TrainingView {
            index: i,
            camera: f.camera,
            cam_from_world: f.cam_from_world,
        })
        .collect();
    let renderer =
        SynthFeatureRenderer::new(world, SynthFeatureField::new(SynthFieldConfig::default()));
    let gt = generate_pairs(&renderer, &views, &GtConfig::default(), 3).unwrap();
    // Query-side noise as an encoder would add it: then dims that hardly vary within one view
    // (long wavelengths) stop discriminating, while exact analytic features match on any dims.
    let mut nrng = ChaCha8Rng::seed_from_u64(9);
    let noisy: Vec<f32> = gt
        .query_features
        .iter()
        .map(|v| v + nrng.random_range(-0.3f32..0.3))
        .collect();
    let pairs = gt.to_pair_set(Some(noisy)).unwrap();
    assert_eq!(pairs.groups().unwrap().len(), pairs.len());
    let greedy = MatchingSelector {
        config: MatchingSelectorConfig {
            swap_refinement: false,
            ..Default::default()
        },
    };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let sel = greedy.select(&pairs, 5, &mut rng).unwrap();
    assert_eq!(sel.dims.len(), 5);
    // Score the selection and the five longest positional wavelengths (nearly constant over
    // the scene) with the same criterion: the one-dim-at-a-time costs are negated scores.
    let long: Vec<usize> = (27..32).collect();
    let score_of = |dims: &[usize]| {
        let sub = MatchingSelector {
            config: MatchingSelectorConfig {
                swap_refinement: false,
                ..Default::default()
            },
        };
        // Restrict the pair set to `dims` and let the selector take all of them.
        let pick = |src: &[f32]| -> Vec<f32> {
            src.chunks_exact(pairs.dims())
                .flat_map(|r| dims.iter().map(move |&d| r[d]))
                .collect()
        };
        let p = PairSet::new(dims.len(), pick(pairs.f2d()), pick(pairs.f3d()))
            .unwrap()
            .with_groups(pairs.groups().unwrap().to_vec())
            .unwrap();
        sub.select(&p, dims.len(), &mut ChaCha8Rng::seed_from_u64(0))
            .unwrap()
            .report
            .objective
    };
    let (s_sel, s_long) = (score_of(&sel.dims), score_of(&long));
    assert!(s_sel > 0.2 && s_sel > 10.0 * s_long, "{s_sel} vs {s_long}");
    // The paper's BIP picks one dim whatever the budget.
    let bip = PaperBipSelector::default()
        .select(&pairs, 10, &mut rng)
        .unwrap();
    assert_eq!(bip.dims.len(), 1);
    // Group ids must cover every pair.
    assert!(matches!(
        PairSet::new(2, vec![0.0; 4], vec![0.0; 4])
            .unwrap()
            .with_groups(vec![0]),
        Err(SelectError::Shape(_))
    ));
}
