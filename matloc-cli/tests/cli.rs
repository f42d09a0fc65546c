//! Runs the `matloc` binary as a user would.

use std::path::Path;

mod common;

use common::{matloc, text};

#[test]
fn synth_tiny_then_info() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("tiny");
    let o = matloc(&[
        "synth",
        "--preset",
        "tiny",
        "--out",
        out.to_str().unwrap(),
        "--seed",
        "3",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(out.join("transforms.json").is_file());

    let o = matloc(&["dataset", "info", out.to_str().unwrap()]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("format: Nerfstudio"), "{t}");
    assert!(t.contains("preset: tiny"), "{t}");
    assert!(t.contains("all referenced images"), "{t}");

    let o = matloc(&["dataset", "info", out.to_str().unwrap(), "--json"]);
    assert!(o.status.success());
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("valid JSON");
    assert!(v["summary"]["num_frames"].as_u64().unwrap() > 10);

    // A missing image is reported by name and fails the command.
    let first = std::fs::read_dir(out.join("images"))
        .unwrap()
        .next()
        .unwrap()
        .unwrap();
    std::fs::remove_file(first.path()).unwrap();
    let o = matloc(&["dataset", "info", out.to_str().unwrap()]);
    let t = text(&o);
    assert!(!o.status.success());
    assert!(
        t.contains(&first.file_name().to_string_lossy().to_string()),
        "{t}"
    );
}

#[test]
fn unknown_preset_lists_valid_names() {
    let dir = tempfile::tempdir().unwrap();
    let o = matloc(&[
        "synth",
        "--preset",
        "nope",
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(!o.status.success());
    assert!(
        t.contains("nope") && t.contains("tiny") && t.contains("building"),
        "{t}"
    );
}

#[test]
fn info_on_missing_or_malformed_dataset_is_a_clear_error() {
    let o = matloc(&["dataset", "info", "/definitely/not/here"]);
    let t = text(&o);
    assert!(!o.status.success());
    assert!(t.contains("/definitely/not/here"), "{t}");
    assert!(!t.contains("panicked"), "{t}");

    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("transforms.json");
    std::fs::write(&bad, "{ \"frames\": [ {").unwrap();
    let o = matloc(&["dataset", "info", dir.path().to_str().unwrap()]);
    let t = text(&o);
    assert!(!o.status.success());
    assert!(t.contains("transforms.json"), "{t}");
    assert!(!t.contains("panicked"), "{t}");
    assert!(Path::new(&bad).exists());
}
