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

#[test]
fn a_closed_or_full_stdout_is_handled_without_a_panic() {
    use std::process::{Command, Stdio};

    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("tiny");
    let o = matloc(&["synth", "--preset", "tiny", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));

    // A reader that is gone before the first line is written (`matloc dataset info D | true`;
    // the command reads and checks every image first): the command ends quietly, successfully.
    let mut child = Command::new(env!("CARGO_BIN_EXE_matloc"))
        .args(["dataset", "info", out.to_str().unwrap(), "--quiet"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "exit {:?}: {err}", o.status);
    assert!(!err.contains("panicked"), "{err}");

    // A full device: an error that names stdout, exit status 1, no panic.
    if std::path::Path::new("/dev/full").exists() {
        let full = std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/full")
            .unwrap();
        let o = Command::new(env!("CARGO_BIN_EXE_matloc"))
            .args(["dataset", "info", out.to_str().unwrap(), "--quiet"])
            .stdout(full)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(err.contains("stdout") && !err.contains("panicked"), "{err}");
    }
}
