//! Faults through the `matloc` binary: a map build killed with SIGKILL at seeded moments
//! resumes to a map that verifies, and a full disk gives a clear error while the complete map
//! already in the directory keeps verifying (every write is atomic).
//!
//! The binary is the workspace's `target/<profile>/matloc` (built by `cargo test --workspace`
//! or `cargo build -p matloc-cli`), or `MATLOC_BIN`. The full-disk test mounts a small tmpfs
//! (root only); without permission it limits the file size instead (`RLIMIT_FSIZE`, with
//! SIGXFSZ ignored so writes fail with EFBIG).

mod bin_path;

use bin_path::matloc_bin;
mod fs_tree;
use fs_tree::copy_tree;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use matloc_core::hash::splitmix64_next;
use matloc_synth::{SynthConfig, synthesize};

/// The cheapest map config of the end-to-end tests (`tests/tests/end_to_end.rs`), without the
/// encoder's head-only phase (nothing here measures the learned encoder).
const TINY_CONFIG: &str = r#"{
  "nerf": {"steps": 300, "checkpoint_every": 100,
    "model_overrides": {"field": {"log2_table_size": 15, "max_resolution": 512},
      "train": {"batch_rays": 1024, "march": {"steps": 128, "max_samples": 24},
                "occupancy_warmup_steps": 32},
      "render": {"march": {"steps": 128}}}},
  "encoder": {"train": {"steps": 150, "head_phase": {"steps": 0}}},
  "place": {"train": {"epochs": 20}},
  "calibration": {"max_views": 8}
}"#;

/// Seed of the kill moments.
const SEED: u64 = 0x6b69_6c6c;

fn matloc(args: &[&Path]) -> Output {
    Command::new(matloc_bin())
        .args(args)
        .stdin(Stdio::null())
        .output()
        .expect("run matloc")
}

/// Panics unless `o` ended with exit 0 or 1, without a panic message.
fn no_crash(what: &str, o: &Output) {
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        matches!(o.status.code(), Some(0) | Some(1)) && !stderr.contains("panicked"),
        "{what}: {:?}\n{stderr}",
        o.status
    );
}

struct Fixture {
    dir: PathBuf,
    data: PathBuf,
    config: PathBuf,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("faults");
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let data = dir.join("data");
        synthesize(&SynthConfig::preset("tiny").unwrap(), &data, &|_| {}).unwrap();
        let config = dir.join("tiny.json");
        std::fs::write(&config, TINY_CONFIG).unwrap();
        Fixture { dir, data, config }
    })
}

fn build_args<'a>(f: &'a Fixture, out: &'a Path) -> Vec<&'a Path> {
    vec![
        Path::new("map"),
        Path::new("build"),
        Path::new("--quiet"),
        Path::new("--data"),
        &f.data,
        Path::new("--out"),
        out,
        Path::new("--config"),
        &f.config,
    ]
}

/// The complete map of the kill test, built once.
fn killed_and_resumed_map() -> &'static PathBuf {
    static MAP: OnceLock<PathBuf> = OnceLock::new();
    MAP.get_or_init(|| {
        let f = fixture();
        let map = f.dir.join("killed");
        let t0 = Instant::now();
        let mut state = SEED;
        // Kill k comes a seeded 0.5 to 8 s after the manifest records at least AFTER[k]
        // stages (partition, nerf, pairs + encoder, place), so the kills land in successive
        // stages; each rerun resumes.
        const AFTER: [usize; 4] = [1, 2, 4, 6];
        for (k, after) in AFTER.into_iter().enumerate() {
            let delay = Duration::from_millis(500 + splitmix64_next(&mut state) % 7_500);
            let mut child = Command::new(matloc_bin())
                .args(build_args(f, &map))
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .expect("start map build");
            let mut finished = None;
            let mut reached: Option<Instant> = None;
            loop {
                if let Some(s) = child.try_wait().unwrap() {
                    finished = Some(s);
                    break;
                }
                if reached.is_none() && manifest_stages(&map).len() >= after {
                    reached = Some(Instant::now());
                }
                if reached.is_some_and(|r| r.elapsed() >= delay) {
                    break;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            if let Some(s) = finished {
                let o = child.wait_with_output().unwrap();
                assert!(
                    s.success(),
                    "build {k} failed: {}",
                    String::from_utf8_lossy(&o.stderr)
                );
                eprintln!("build {k} finished before its kill");
                break;
            }
            child.kill().expect("SIGKILL");
            let status = child.wait().unwrap();
            let stages = manifest_stages(&map);
            eprintln!(
                "build {k} killed {:.1} s after stage {after} at {:.1} s ({status:?}); stages \
                 done: {stages:?}",
                delay.as_secs_f64(),
                t0.elapsed().as_secs_f64()
            );
            // A killed build leaves a map that says it is incomplete, and never crashes a reader.
            if map.join("manifest.json").exists() {
                let v = matloc(&[Path::new("map"), Path::new("verify"), &map]);
                no_crash("map verify of a killed build", &v);
                let i = matloc(&[Path::new("map"), Path::new("info"), &map]);
                no_crash("map info of a killed build", &i);
            }
        }
        let o = matloc(&build_args(f, &map));
        assert!(
            o.status.success(),
            "the resumed build failed: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        eprintln!(
            "kill and resume: complete after {:.1} s",
            t0.elapsed().as_secs_f64()
        );
        map
    })
}

/// Names of the stages the manifest records as done.
fn manifest_stages(map: &Path) -> Vec<String> {
    let Ok(bytes) = std::fs::read(map.join("manifest.json")) else {
        return Vec::new();
    };
    let v: serde_json::Value = serde_json::from_slice(&bytes).expect("manifest is JSON");
    v["stages"]
        .as_array()
        .map(|a| {
            a.iter()
                .filter_map(|s| s["name"].as_str().map(str::to_string))
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn a_build_killed_at_seeded_moments_resumes_to_a_map_that_verifies() {
    let map = killed_and_resumed_map();
    let v = matloc(&[Path::new("map"), Path::new("verify"), map]);
    assert!(
        v.status.success(),
        "map verify: {}{}",
        String::from_utf8_lossy(&v.stdout),
        String::from_utf8_lossy(&v.stderr)
    );
}

/// A small filesystem at `dir`: tmpfs of `bytes` when mounting is permitted.
struct SmallDisk {
    dir: PathBuf,
    mounted: bool,
}

impl SmallDisk {
    fn new(dir: PathBuf, bytes: u64) -> SmallDisk {
        std::fs::create_dir_all(&dir).unwrap();
        let mounted = Command::new("mount")
            .args(["-t", "tmpfs", "-o"])
            .arg(format!("size={bytes}"))
            .arg("tmpfs")
            .arg(&dir)
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        SmallDisk { dir, mounted }
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        if self.mounted {
            let _ = Command::new("umount").arg(&self.dir).status();
        }
    }
}

/// `matloc args`, limited to files of `fsize` bytes when `limit_files` (SIGXFSZ ignored).
fn matloc_small_files(args: &[&Path], limit_files: Option<u64>) -> Output {
    let mut cmd = match limit_files {
        Some(n) => {
            let mut c = Command::new("bash");
            c.arg("-c")
                .arg(r#"trap '' XFSZ; exec prlimit --fsize="$0" -- "$@""#)
                .arg(n.to_string())
                .arg(matloc_bin());
            c
        }
        None => Command::new(matloc_bin()),
    };
    cmd.args(args)
        .stdin(Stdio::null())
        .output()
        .expect("run matloc")
}

fn tree_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            if e.file_type().unwrap().is_dir() {
                tree_bytes(&e.path())
            } else {
                e.metadata().unwrap().len()
            }
        })
        .sum()
}

#[test]
fn a_full_disk_gives_a_clear_error_and_leaves_a_complete_map_verifying() {
    let f = fixture();
    let complete = killed_and_resumed_map();

    // A fresh build on a disk far too small for it.
    let disk = SmallDisk::new(f.dir.join("small-disk"), 512 << 10);
    let out = disk.dir.join("map");
    let limit = (!disk.mounted).then_some(256 << 10);
    let o = matloc_small_files(&build_args(f, &out), limit);
    no_crash("a build on a full disk", &o);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert!(
        (stderr.contains("No space left") || stderr.contains("File too large"))
            && stderr.contains(&*out.to_string_lossy()),
        "{stderr}"
    );
    drop(disk);

    // A complete map on a disk with no room left: rerunning the build and reading the map may
    // fail for want of space, but the map stays complete and verifies.
    let bytes = tree_bytes(complete);
    let disk = SmallDisk::new(f.dir.join("full-disk"), bytes + (1 << 20));
    let map = disk.dir.join("map");
    copy_tree(complete, &map);
    if disk.mounted {
        // Fill what is left.
        let filler = disk.dir.join("filler");
        let mut file = std::fs::File::create(&filler).unwrap();
        let block = vec![0u8; 64 << 10];
        while std::io::Write::write_all(&mut file, &block).is_ok() {}
    }
    let limit = (!disk.mounted).then_some(1);
    for args in [
        build_args(f, &map),
        vec![Path::new("map"), Path::new("info"), &map],
    ] {
        let o = matloc_small_files(&args, limit);
        no_crash("a command on a full disk", &o);
        let stderr = String::from_utf8_lossy(&o.stderr);
        if o.status.code() == Some(1) {
            assert!(
                stderr.contains("No space left") || stderr.contains("File too large"),
                "{stderr}"
            );
        }
        let v = matloc(&[Path::new("map"), Path::new("verify"), &map]);
        assert!(
            v.status.success(),
            "the complete map no longer verifies after `{}`: {}{}",
            args.iter()
                .map(|a| a.to_string_lossy())
                .collect::<Vec<_>>()
                .join(" "),
            String::from_utf8_lossy(&v.stdout),
            String::from_utf8_lossy(&v.stderr)
        );
    }
}

/// Hostile `localize --queries` lists against the built map (they need a complete map, so they
/// live here rather than in `hostile.rs`): every one ends with exit 0 or 1, no panic, and a
/// list where no query is usable fails, naming the list and the line.
#[test]
fn hostile_query_lists_fail_per_line_without_crashing() {
    let f = fixture();
    let map = killed_and_resumed_map();
    let dir = f.dir.join("queries");
    std::fs::create_dir_all(&dir).unwrap();
    let image = "images/frame_00000.png";
    let good = format!("{image} PINHOLE 160 120 138.56 138.56 80 60");
    let cases: Vec<(&str, String, bool)> = vec![
        (
            "unknown model",
            format!("{image} FISHEYE_X 160 120 1 1 1 1"),
            true,
        ),
        (
            "unsupported model",
            format!("{image} OPENCV_FISHEYE 160 120 100 100 80 60 0 0 0 0"),
            true,
        ),
        (
            "too few params",
            format!("{image} PINHOLE 160 120 100 100"),
            true,
        ),
        (
            "too many params",
            format!("{image} PINHOLE 160 120 100 100 80 60 1"),
            true,
        ),
        (
            "zero width",
            format!("{image} PINHOLE 0 120 100 100 80 60"),
            true,
        ),
        (
            "negative height",
            format!("{image} PINHOLE 160 -120 100 100 80 60"),
            true,
        ),
        (
            "width 2^32",
            format!("{image} PINHOLE 4294967296 120 100 100 80 60"),
            true,
        ),
        (
            "huge size",
            format!("{image} PINHOLE 4294967295 4294967295 100 100 80 60"),
            true,
        ),
        (
            "NaN focal",
            format!("{image} PINHOLE 160 120 nan nan 80 60"),
            true,
        ),
        (
            "inf focal",
            format!("{image} PINHOLE 160 120 inf 100 80 60"),
            true,
        ),
        (
            "negative focal",
            format!("{image} PINHOLE 160 120 -100 -100 80 60"),
            true,
        ),
        (
            "text parameter",
            format!("{image} PINHOLE 160 120 f f 80 60"),
            true,
        ),
        ("name only", image.to_string(), true),
        (
            "missing image",
            "images/nope.png PINHOLE 160 120 100 100 80 60".into(),
            true,
        ),
        (
            "image is a directory",
            "images PINHOLE 160 120 100 100 80 60".into(),
            true,
        ),
        (
            "image escapes",
            "../../../../../etc/passwd PINHOLE 160 120 100 100 80 60".into(),
            true,
        ),
        (
            "wrong aspect",
            format!("{image} PINHOLE 100 100 100 100 50 50"),
            true,
        ),
        ("empty list", String::new(), true),
        ("comments only", "# a\n# b\n".into(), true),
        (
            "binary garbage",
            String::from_utf8_lossy(&[0xff, 0xfe, 0, 1, 2, 0x80, b'\n']).into_owned(),
            true,
        ),
        (
            "one bad line among good",
            format!("{good}\nimages/nope.png PINHOLE 160 120 1 1 1 1"),
            false,
        ),
        (
            "a very long line",
            format!("{image} PINHOLE 160 120 {}", "1 ".repeat(100_000)),
            true,
        ),
    ];
    let t0 = Instant::now();
    let mut failures = Vec::new();
    for (i, (label, text, must_fail)) in cases.iter().enumerate() {
        let list = dir.join(format!("queries_{i:02}.txt"));
        std::fs::write(&list, text).unwrap();
        let o = matloc(&[
            Path::new("localize"),
            Path::new("--map"),
            map,
            Path::new("--queries"),
            &list,
            Path::new("--images"),
            &f.data,
        ]);
        let stderr = String::from_utf8_lossy(&o.stderr);
        let stdout = String::from_utf8_lossy(&o.stdout);
        let crashed = !matches!(o.status.code(), Some(0) | Some(1)) || stderr.contains("panicked");
        let wrongly_ok = *must_fail && o.status.success();
        // A query that fails is an error record naming the query (jsonl), a line of the list
        // is named with the list's path, and an empty list is said to be empty.
        let named = o.status.success()
            || stderr.contains(&*list.to_string_lossy())
            || stdout.contains("\"error\"")
            || stderr.contains("no queries");
        if crashed || wrongly_ok || !named {
            failures.push(format!(
                "{label}: {:?}\n  stdout: {}\n  stderr: {}",
                o.status,
                stdout.lines().take(3).collect::<Vec<_>>().join(" | "),
                stderr.lines().rev().take(3).collect::<Vec<_>>().join(" | ")
            ));
        }
    }
    eprintln!(
        "hostile query lists: {} cases in {:.1} s",
        cases.len(),
        t0.elapsed().as_secs_f64()
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
