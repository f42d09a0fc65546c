//! Sub-NeRF blocks trained side by side: both stages complete, their files are listed in the
//! manifest, and a second build skips them.

use std::panic::{AssertUnwindSafe, catch_unwind};

use matloc_data::read_dataset;
use matloc_pipeline::MapDir;
use matloc_pipeline::build::{BuildEvent, MapConfig, build_map};
use matloc_synth::{SynthConfig, synthesize};

#[test]
fn two_blocks_train_side_by_side_and_resume() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    synthesize(&SynthConfig::preset("tiny").unwrap(), &data, &|_| {}).unwrap();
    let dataset = read_dataset(&data).unwrap();
    let out = dir.path().join("map");
    let mut config = MapConfig::default();
    config.partition.num_blocks = Some(2);
    config.nerf.steps = 12;
    config.nerf.checkpoint_every = 100;
    config.nerf.parallel_blocks = 2;
    config.nerf.model_overrides = serde_json::json!({
        "field": {"log2_table_size": 12, "max_resolution": 128},
        "train": {"batch_rays": 256, "march": {"steps": 64, "max_samples": 16},
                  "occupancy_warmup_steps": 4},
    });
    // Stop the build once both NeRF stages are done (at the next stage's start). Two threads
    // whatever the machine has, so the two blocks get one each.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let mut events = Vec::new();
    let stopped = catch_unwind(AssertUnwindSafe(|| {
        pool.install(|| {
            build_map(&dataset, &out, &config, &mut |e| {
                events.push(e.clone());
                if let BuildEvent::StageStarted { name, .. } = e
                    && name.starts_with("pairs")
                {
                    panic!("stop after the NeRF stages");
                }
            })
        })
    }));
    assert!(stopped.is_err());
    let started: Vec<usize> = events
        .iter()
        .enumerate()
        .filter(|(_, e)| matches!(e, BuildEvent::StageStarted { name, .. } if name.starts_with("nerf/")))
        .map(|(i, _)| i)
        .collect();
    let first_finish = events
        .iter()
        .position(
            |e| matches!(e, BuildEvent::StageFinished { name, .. } if name.starts_with("nerf/")),
        )
        .unwrap();
    assert_eq!(started.len(), 2, "{events:?}");
    assert!(
        started[1] < first_finish,
        "the second block started after the first finished: {events:?}"
    );
    for b in 0..2 {
        let name = format!("nerf/{b}");
        assert!(
            events
                .iter()
                .any(|e| matches!(e, BuildEvent::StageProgressOf { name: n, .. } if *n == name)),
            "no progress of {name}"
        );
    }
    let map = MapDir::open(&out).unwrap();
    map.verify().unwrap();
    for b in 0..2 {
        assert!(map.stage_done(&format!("nerf/{b}")));
        assert!(
            map.manifest()
                .files
                .keys()
                .any(|k| k == &format!("blocks/{b}/model.safetensors")),
            "block {b}'s model is not listed"
        );
    }
    // Resuming skips both.
    let mut skipped = Vec::new();
    let _ = catch_unwind(AssertUnwindSafe(|| {
        build_map(&dataset, &out, &config, &mut |e| {
            if let BuildEvent::StageFinished {
                name,
                skipped: true,
                ..
            } = e
            {
                skipped.push(name.clone());
            }
            if let BuildEvent::StageStarted { name, .. } = e
                && name.starts_with("pairs")
            {
                panic!("stop again");
            }
        })
    }));
    assert!(skipped.contains(&"nerf/0".to_string()) && skipped.contains(&"nerf/1".to_string()));
}
