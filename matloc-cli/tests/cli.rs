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
    let name = first.file_name().to_string_lossy().to_string();
    assert!(t.contains(&name), "{t}");
    // A script reading only stderr learns which file, in either output mode.
    for json in [false, true] {
        let mut args = vec!["dataset", "info", out.to_str().unwrap()];
        if json {
            args.push("--json");
        }
        let o = matloc(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.lines()
                .any(|l| l.starts_with("problem: ") && l.contains(&name)),
            "--json {json}: {err}"
        );
    }
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

/// An error that cannot be written because stderr is a full device still exits 1, not with
/// a panic (101).
#[test]
fn an_error_on_a_full_stderr_exits_1() {
    if !Path::new("/dev/full").exists() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let full = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/full")
        .unwrap();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_matloc"))
        .args(["dataset", "info"])
        .arg(dir.path().join("missing"))
        .stderr(full)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
}

/// A map with no blocks whose stages all completed and wrote their files (nothing trained).
fn hand_made_map(root: &Path) {
    use matloc_pipeline::map::layout::{required_stages, stage_files};
    let mut map = matloc_pipeline::MapDir::create_or_resume(root, serde_json::json!({})).unwrap();
    for s in required_stages(0) {
        for f in stage_files(&s) {
            map.write_file(&f, format!("{{\"file\": \"{f}\"}}").as_bytes())
                .unwrap();
        }
        map.complete_stage(&s, 0.5).unwrap();
    }
}

/// Runs `map info` and `map verify` on `root`: (info, verify).
fn info_and_verify(root: &Path) -> (std::process::Output, std::process::Output) {
    let root = root.to_str().unwrap();
    (
        matloc(&["map", "info", root]),
        matloc(&["map", "verify", root]),
    )
}

#[test]
fn map_info_and_verify_fail_on_a_corrupted_file() {
    let dir = tempfile::tempdir().unwrap();
    hand_made_map(dir.path());
    // Checksums match, but no file holds what its stage writes: both name each file.
    let (info, verify) = info_and_verify(dir.path());
    assert_eq!(info.status.code(), Some(1), "{}", text(&info));
    let out = String::from_utf8_lossy(&info.stdout);
    assert!(
        out.contains("checksums ok")
            && out.contains("contents     FAILED on 3 parts")
            && out.contains("status       complete"),
        "{out}"
    );
    assert_eq!(verify.status.code(), Some(1), "{}", text(&verify));
    let lines: Vec<String> = String::from_utf8_lossy(&verify.stdout)
        .lines()
        .map(String::from)
        .collect();
    assert_eq!(lines.len(), 3, "{lines:?}");
    for (file, field) in [
        ("partition.json", "Partition"),
        ("place/place.safetensors", "header"),
        ("confidence.json", "CalibrationRecord"),
    ] {
        assert!(
            lines
                .iter()
                .any(|l| l.contains(&format!("{file}: {field}: "))),
            "{file}: {lines:?}"
        );
        assert!(text(&info).contains(file), "{}", text(&info));
    }

    // Same size, other content: the checksum fails, and that file's content is not parsed.
    let file = dir.path().join("partition.json");
    let mut bytes = std::fs::read(&file).unwrap();
    bytes[2] ^= 1;
    std::fs::write(&file, bytes).unwrap();
    let (info, verify) = info_and_verify(dir.path());
    assert_eq!(info.status.code(), Some(1), "{}", text(&info));
    let out = String::from_utf8_lossy(&info.stdout);
    assert!(out.contains("checksums FAILED"), "{out}");
    assert!(out.contains("stages:"), "the summary is printed: {out}");
    let err = String::from_utf8_lossy(&info.stderr);
    assert!(err.contains("partition.json: checksum mismatch"), "{err}");
    assert_eq!(verify.status.code(), Some(1), "{}", text(&verify));
    let lines: Vec<String> = String::from_utf8_lossy(&verify.stdout)
        .lines()
        .map(String::from)
        .collect();
    assert_eq!(lines.len(), 3, "{lines:?}");
    assert!(
        lines[0].contains("partition.json: checksum mismatch"),
        "{lines:?}"
    );

    // A missing file: the summary still prints, both fail.
    std::fs::remove_file(dir.path().join("confidence.json")).unwrap();
    let (info, verify) = info_and_verify(dir.path());
    assert_eq!(info.status.code(), Some(1), "{}", text(&info));
    assert!(String::from_utf8_lossy(&info.stdout).contains("stages:"));
    assert!(text(&info).contains("confidence.json"), "{}", text(&info));
    assert_eq!(verify.status.code(), Some(1));
    assert_eq!(String::from_utf8_lossy(&verify.stdout).lines().count(), 3);
}

/// A manifest written by hand.
fn write_manifest(root: &Path, manifest: &serde_json::Value) {
    std::fs::create_dir_all(root).unwrap();
    std::fs::write(root.join("manifest.json"), manifest.to_string()).unwrap();
}

#[test]
fn a_manifest_claiming_every_stage_without_files_fails() {
    let dir = tempfile::tempdir().unwrap();
    let stages: Vec<serde_json::Value> = ["partition", "place", "calibration"]
        .iter()
        .map(|s| serde_json::json!({"name": s, "seconds": 1.0}))
        .collect();
    write_manifest(
        dir.path(),
        &serde_json::json!({
            "format": "matloc-map",
            "version": 1,
            "created_by": "hand",
            "config": {},
            "stages": stages,
            "files": {},
        }),
    );
    let (info, verify) = info_and_verify(dir.path());
    assert_eq!(info.status.code(), Some(1), "{}", text(&info));
    let out = String::from_utf8_lossy(&info.stdout);
    assert!(!out.contains("status       complete"), "{out}");
    assert!(
        out.contains("incomplete, 4 files of completed stages not listed"),
        "{out}"
    );
    let err = String::from_utf8_lossy(&info.stderr);
    assert!(
        err.contains("partition.json: written by stage partition"),
        "{err}"
    );
    assert_eq!(verify.status.code(), Some(1));
    let out = String::from_utf8_lossy(&verify.stdout);
    assert_eq!(out.lines().count(), 4, "{out}");
    for f in [
        "partition.json",
        "place/place.json",
        "place/place.safetensors",
        "confidence.json",
    ] {
        assert!(out.contains(f), "{f}: {out}");
    }

    let o = matloc(&["map", "info", dir.path().to_str().unwrap(), "--json"]);
    assert_eq!(o.status.code(), Some(1));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("valid JSON");
    assert_eq!(v["problems"].as_array().unwrap().len(), 4, "{v}");
}

#[test]
fn a_manifest_field_of_the_wrong_type_is_named() {
    let dir = tempfile::tempdir().unwrap();
    write_manifest(
        dir.path(),
        &serde_json::json!({
            "format": "matloc-map",
            "version": "1",
            "created_by": "hand",
            "config": {},
        }),
    );
    let (info, verify) = info_and_verify(dir.path());
    for o in [&info, &verify] {
        assert_eq!(o.status.code(), Some(1), "{}", text(o));
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("`version`: expected an integer, found a string"),
            "{err}"
        );
    }
}

#[test]
fn map_config_default_parses_back_and_unknown_keys_are_named() {
    let o = matloc(&["map", "config", "--print-default"]);
    assert!(o.status.success(), "{}", text(&o));
    let c: matloc_pipeline::build::MapConfig =
        serde_json::from_slice(&o.stdout).expect("the default config parses");
    assert_eq!(c, matloc_pipeline::build::MapConfig::default());

    let dir = tempfile::tempdir().unwrap();
    for (config, key) in [
        (serde_json::json!({"partiton": {}}), "partiton"),
        (
            serde_json::json!({"partition": {"voxel_size": 2.0, "voxel_sise": 2.0}}),
            "voxel_sise",
        ),
        (
            serde_json::json!({"localize": {"pnp": {"ransac": {"max_iters": 5}}}}),
            "max_iters",
        ),
    ] {
        let o = build_with_config(dir.path(), &config);
        assert!(!o.status.success());
        let t = text(&o);
        assert!(t.contains(&format!("unknown field `{key}`")), "{t}");
        assert!(!dir.path().join("map").exists());
    }
}

/// `matloc map build` of a dataset that does not exist, with `config` as DIR/config.json
/// (the config is read first); the map would go to DIR/map.
fn build_with_config(dir: &Path, config: &serde_json::Value) -> std::process::Output {
    let path = dir.join("config.json");
    std::fs::write(&path, config.to_string()).unwrap();
    matloc(&[
        "map",
        "build",
        "--data",
        dir.join("no-data").to_str().unwrap(),
        "--out",
        dir.join("map").to_str().unwrap(),
        "--config",
        path.to_str().unwrap(),
    ])
}

/// Values no stage can run with are refused when the config file is read, naming the file,
/// the field and its bound, before anything is written.
#[test]
fn impossible_config_values_are_named_when_the_file_is_read() {
    let dir = tempfile::tempdir().unwrap();
    for (config, field) in [
        (serde_json::json!({"nerf": {"steps": 0}}), "nerf.steps"),
        (
            serde_json::json!({"localize": {"top_k": 0}}),
            "localize.top_k",
        ),
        (
            serde_json::json!({"localize": {"window_fraction": -1.0}}),
            "localize.window_fraction",
        ),
        (serde_json::json!({"select": {"dims": 0}}), "select.dims"),
    ] {
        let o = build_with_config(dir.path(), &config);
        assert_eq!(o.status.code(), Some(1));
        let t = text(&o);
        assert!(
            t.contains(&format!("`{field}`")) && t.contains("config.json"),
            "{t}"
        );
        assert!(!t.contains("panicked"), "{t}");
        assert!(!dir.path().join("map").exists());
    }
}

/// A dataset refused by the plan step (an image that does not decode) leaves no map
/// directory behind, for `map build` and `map plan`; an existing directory is kept.
#[test]
fn a_refused_build_leaves_nothing_behind() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let o = matloc(&["synth", "--preset", "tiny", "--out", data.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let first = std::fs::read_dir(data.join("images"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .min()
        .unwrap();
    let bytes = std::fs::read(&first).unwrap();
    std::fs::write(&first, &bytes[..bytes.len() / 2]).unwrap();
    let kept = dir.path().join("kept");
    std::fs::create_dir(&kept).unwrap();
    for (command, out) in [
        ("build", dir.path().join("map")),
        ("plan", dir.path().join("planned")),
        ("build", kept.clone()),
    ] {
        let o = matloc(&[
            "map",
            command,
            "--data",
            data.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(
            t.contains(first.file_name().unwrap().to_str().unwrap()),
            "{t}"
        );
        if out == kept {
            assert_eq!(std::fs::read_dir(&kept).unwrap().count(), 0, "{t}");
        } else {
            assert!(!out.exists(), "map {command} left {}: {t}", out.display());
        }
    }
}

#[test]
fn refine_poses_writes_a_dataset_that_reads_back_and_names_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("tiny");
    let o = matloc(&["synth", "--preset", "tiny", "--out", data.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let out = dir.path().join("refined");
    let o = matloc(&[
        "--quiet",
        "dataset",
        "refine-poses",
        data.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains("reprojection error median") && t.contains("px"),
        "{t}"
    );
    let given = matloc_data::read_dataset(&data).unwrap();
    let refined = matloc_data::read_dataset(&out).unwrap();
    assert_eq!(given.frames.len(), refined.frames.len());
    let mut moved: Vec<f64> = Vec::new();
    for (a, b) in given.frames.iter().zip(&refined.frames) {
        // The same images (their paths resolve to the same files).
        assert_eq!(
            given.image_path(a).canonicalize().unwrap(),
            refined.image_path(b).canonicalize().unwrap()
        );
        moved.push(
            (matloc_core::pose::camera_center(&a.cam_from_world)
                - matloc_core::pose::camera_center(&b.cam_from_world))
            .norm(),
        );
    }
    // The exact survey's poses stay within what its short tracks pin (tiny's 160 × 120 views,
    // 2–3 views per point): measured 0.24 m at the median, 0.64 m at most.
    moved.sort_by(f64::total_cmp);
    let (median, largest) = (moved[moved.len() / 2], moved[moved.len() - 1]);
    assert!(
        median < 0.35 && largest < 1.0,
        "moved {median} m (median), {largest} m"
    );

    let o = matloc(&[
        "dataset",
        "refine-poses",
        "/definitely/not/here",
        "--out",
        out.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(
        !o.status.success() && t.contains("/definitely/not/here"),
        "{t}"
    );
    assert!(!t.contains("panicked"), "{t}");
}
