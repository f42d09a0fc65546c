//! `matloc nerf train` / `matloc nerf render` on the tiny synthetic preset, as a user runs them.

mod common;

use common::{matloc, text};

#[test]
fn train_resume_and_render_tiny() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("tiny");
    let model = dir.path().join("model");
    let renders = dir.path().join("renders");
    let o = matloc(&["synth", "--preset", "tiny", "--out", data.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    // A CI-sized field; the architecture is the default one.
    let cfg = dir.path().join("small.json");
    std::fs::write(
        &cfg,
        r#"{"field": {"log2_table_size": 14, "max_resolution": 256}, "train": {"batch_rays": 512}}"#,
    )
    .unwrap();
    let train = |steps: &str| {
        matloc(&[
            "nerf",
            "train",
            "--data",
            data.to_str().unwrap(),
            "--out",
            model.to_str().unwrap(),
            "--steps",
            steps,
            "--config",
            cfg.to_str().unwrap(),
            "--checkpoint-every",
            "5",
        ])
    };
    let o = train("10");
    assert!(o.status.success(), "{}", text(&o));
    assert!(model.join("model.safetensors").is_file());
    assert!(model.join("model.json").is_file());

    // The same command again resumes from the finished checkpoint and has nothing to do.
    let o = train("10");
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("resuming from step 10"), "{t}");

    // Same command with more steps: the schedule length differs, so the checkpoint's config
    // does not match and the command says so instead of silently mixing runs.
    let o = train("12");
    let t = text(&o);
    assert!(!o.status.success());
    assert!(
        t.contains("config mismatch") && t.contains("max_steps"),
        "{t}"
    );

    let o = matloc(&[
        "nerf",
        "render",
        "--model",
        model.to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
        "--out",
        renders.to_str().unwrap(),
        "--limit",
        "2",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("mean PSNR"), "{t}");
    for f in [
        "test_000_rgb.png",
        "test_000_depth.png",
        "test_000_features.png",
        "test_001_rgb.png",
        "metrics.json",
    ] {
        assert!(renders.join(f).is_file(), "{f} missing");
    }
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(renders.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(v["views"].as_array().unwrap().len(), 2);
    assert!(v["mean_psnr"].as_f64().unwrap() > 5.0);
}
