//! A hostile corpus run end to end through the `matloc` binary: several hundred broken,
//! impossible or malicious inputs (datasets, COLMAP models, images, depth maps, point clouds,
//! Mega-NeRF files, map directories, build configs, query lists), generated here from the
//! `tiny` synthetic world. Every case runs under an address-space cap and a time limit and
//! must end with exit 0 or 1: no panic, no abort, no signal. A physically impossible input must
//! fail, and a failure must name the file (and, where the case says so, the field).
//!
//! The binary is the workspace's `target/<profile>/matloc` (built by `cargo test --workspace`
//! or `cargo build -p matloc-cli`), or `MATLOC_BIN`.

mod bin_path;

use bin_path::matloc_bin;
mod fs_tree;
mod hostile_corpus;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use hostile_corpus::{Case, build_corpus};

/// Address-space cap of every case (the binary maps ~100 MiB and its thread pools reserve
/// more; a case that tries to allocate past this must get a typed memory error).
const MEMORY_CAP_BYTES: u64 = 3 << 30;

/// Wall-clock limit of one case.
const CASE_TIMEOUT: Duration = Duration::from_secs(60);

/// Worker threads running cases.
const WORKERS: usize = 4;

/// What one case did.
struct Outcome {
    code: Option<i32>,
    stderr: String,
    /// stdout and stderr together.
    report: String,
    seconds: f64,
    timed_out: bool,
}

fn run_case(bin: &std::path::Path, case: &Case) -> Outcome {
    let err_path = case.dir.join(".stderr");
    let err_file = std::fs::File::create(&err_path).expect("stderr file");
    let out_path = case.dir.join(".stdout");
    let out_file = std::fs::File::create(&out_path).expect("stdout file");
    let mut cmd = Command::new("prlimit");
    cmd.arg(format!("--as={MEMORY_CAP_BYTES}"))
        .arg("--core=0")
        .arg("--")
        .arg(bin)
        .args(&case.args)
        .env("RUST_BACKTRACE", "0")
        .env_remove("RUST_LOG")
        .env_remove("MATLOC_MEMORY_LIMIT")
        .stdin(Stdio::null())
        .stdout(out_file)
        .stderr(err_file);
    for (k, v) in &case.env {
        cmd.env(k, v);
    }
    let start = Instant::now();
    let mut child = cmd.spawn().expect("spawn prlimit");
    let mut timed_out = false;
    let status = loop {
        if let Some(s) = child.try_wait().expect("wait") {
            break s;
        }
        if start.elapsed() > CASE_TIMEOUT {
            timed_out = true;
            let _ = child.kill();
            break child.wait().expect("wait after kill");
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let read = |p: &std::path::Path| {
        String::from_utf8_lossy(&std::fs::read(p).unwrap_or_default()).into_owned()
    };
    let stderr = read(&err_path);
    // `dataset info` lists a dataset's problems on stdout and sums them up on stderr.
    let report = read(&out_path) + &stderr;
    Outcome {
        code: status.code(),
        stderr,
        report,
        seconds: start.elapsed().as_secs_f64(),
        timed_out,
    }
}

/// What is wrong with `outcome` for `case`, if anything.
fn judge(case: &Case, o: &Outcome) -> Option<String> {
    if o.timed_out {
        return Some(format!("ran past {CASE_TIMEOUT:?}"));
    }
    match o.code {
        None => return Some("killed by a signal (abort, or out of memory)".into()),
        Some(101) => return Some("panicked (exit 101)".into()),
        Some(0) | Some(1) => {}
        Some(c) => return Some(format!("exit {c}")),
    }
    if o.stderr.contains("panicked") {
        return Some("`panicked` on stderr".into());
    }
    if o.code == Some(0) {
        return case
            .must_fail
            .then(|| "exit 0 on an input that must be refused".into());
    }
    let missing: Vec<&String> = case
        .names
        .iter()
        .filter(|n| !n.split('|').any(|alt| o.report.contains(alt)))
        .collect();
    (!missing.is_empty()).then(|| format!("the error does not name {missing:?}"))
}

#[test]
fn the_hostile_corpus_never_panics_and_names_what_is_wrong() {
    let bin = matloc_bin();
    let root = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("hostile");
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).unwrap();
    let t0 = Instant::now();
    let cases = build_corpus(&root);
    let generated = t0.elapsed().as_secs_f64();

    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, Outcome)>> = Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..WORKERS {
            s.spawn(|| {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(case) = cases.get(i) else { break };
                    let o = run_case(&bin, case);
                    results.lock().unwrap().push((i, o));
                }
            });
        }
    });
    let mut results = results.into_inner().unwrap();
    results.sort_by_key(|r| r.0);

    let mut per_category: BTreeMap<&str, (usize, usize, usize)> = BTreeMap::new();
    let mut failures = Vec::new();
    let mut slowest = (0.0, String::new());
    for (i, o) in &results {
        let case = &cases[*i];
        let e = per_category.entry(case.category).or_default();
        e.0 += 1;
        if o.code == Some(0) {
            e.1 += 1;
        } else {
            e.2 += 1;
        }
        if o.seconds > slowest.0 {
            slowest = (o.seconds, case.name.clone());
        }
        if let Some(why) = judge(case, o) {
            let tail: String = o
                .report
                .lines()
                .rev()
                .take(4)
                .collect::<Vec<_>>()
                .into_iter()
                .rev()
                .collect::<Vec<_>>()
                .join(" | ");
            failures.push(format!(
                "[{}] {}: {why}\n    matloc {}\n    stderr: {tail}",
                case.category,
                case.name,
                case.args
                    .iter()
                    .map(|a| a.to_string_lossy())
                    .collect::<Vec<_>>()
                    .join(" ")
            ));
        }
    }
    eprintln!("hostile corpus: {} cases", cases.len());
    eprintln!(
        "{:<14} {:>6} {:>8} {:>8}",
        "category", "cases", "exit 0", "refused"
    );
    for (c, (n, ok, refused)) in &per_category {
        eprintln!("{c:<14} {n:>6} {ok:>8} {refused:>8}");
    }
    eprintln!(
        "generated in {generated:.1} s, ran in {:.1} s; slowest case {:.2} s ({})",
        t0.elapsed().as_secs_f64() - generated,
        slowest.0,
        slowest.1
    );
    assert!(cases.len() >= 300, "only {} cases", cases.len());
    assert!(
        failures.is_empty(),
        "{} of {} cases failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}
