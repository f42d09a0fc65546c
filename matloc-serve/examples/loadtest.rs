//! Load test of `matloc serve`: starts the server as a child process on a map, then for each
//! client count runs closed-loop clients for a fixed time against the test views of a
//! dataset, with one malformed request in ten (each must get a 4xx), and prints throughput,
//! p50/p99 latency and the server's memory (VmRSS / VmHWM from `/proc`). Well-formed answers
//! are compared with `matloc localize` on the same images. A final burst of simultaneous
//! requests checks that a full queue answers 503 at once and that memory stays flat; the
//! server is then stopped with SIGTERM and must exit cleanly.
//!
//! ```text
//! cargo run --release -p matloc-serve --example loadtest -- \
//!     --matloc target/release/matloc --map MAP --data DATASET \
//!     [--seconds 60] [--clients 1,2,4,8] [--workers 2] [--queue 8] [--burst 64]
//! ```

use std::collections::HashMap;
use std::net::{SocketAddr, TcpListener};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Barrier, Mutex};
use std::time::{Duration, Instant};

use matloc_data::{Split, read_dataset};
use serde_json::Value;

const BOUNDARY: &str = "matloc-loadtest-boundary";

struct Args {
    matloc: PathBuf,
    map: PathBuf,
    data: PathBuf,
    seconds: u64,
    clients: Vec<usize>,
    workers: usize,
    queue: usize,
    burst: usize,
}

fn parse_args() -> Result<Args, String> {
    let mut a = Args {
        matloc: "target/release/matloc".into(),
        map: PathBuf::new(),
        data: PathBuf::new(),
        seconds: 60,
        clients: vec![1, 2, 4, 8],
        workers: 2,
        queue: 8,
        burst: 64,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        let num = |v: String| v.parse::<usize>().map_err(|e| format!("{flag}: {e}"));
        match flag.as_str() {
            "--matloc" => a.matloc = value()?.into(),
            "--map" => a.map = value()?.into(),
            "--data" => a.data = value()?.into(),
            "--seconds" => a.seconds = num(value()?)? as u64,
            "--workers" => a.workers = num(value()?)?,
            "--queue" => a.queue = num(value()?)?,
            "--burst" => a.burst = num(value()?)?,
            "--clients" => {
                a.clients = value()?
                    .split(',')
                    .map(|c| c.parse().map_err(|e| format!("--clients: {e}")))
                    .collect::<Result<_, _>>()?
            }
            other => return Err(format!("unknown argument {other}")),
        }
    }
    if a.map.as_os_str().is_empty() || a.data.as_os_str().is_empty() {
        return Err("--map and --data are required".into());
    }
    Ok(a)
}

/// One test view: the name the server and `matloc localize` record, the PNG bytes and the
/// camera JSON.
struct View {
    name: String,
    image: Vec<u8>,
    camera: String,
}

fn multipart(parts: &[(&str, &[u8])]) -> Vec<u8> {
    let mut body = Vec::new();
    for (name, data) in parts {
        body.extend_from_slice(
            format!("--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"{name}\"\r\n\r\n")
                .as_bytes(),
        );
        body.extend_from_slice(data);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
    body
}

fn query(v: &View) -> Vec<u8> {
    multipart(&[
        ("image", &v.image),
        ("camera", v.camera.as_bytes()),
        ("name", v.name.as_bytes()),
    ])
}

/// The malformed request of kind `k` (0..4): (content type, body).
fn malformed(v: &View, k: usize) -> (String, Vec<u8>) {
    let form = format!("multipart/form-data; boundary={BOUNDARY}");
    match k % 4 {
        0 => (
            form,
            multipart(&[
                ("image", &v.image[..v.image.len() / 3]),
                ("camera", v.camera.as_bytes()),
            ]),
        ),
        1 => (
            form,
            multipart(&[("image", &v.image), ("camera", b"{\"model\": 3")]),
        ),
        2 => (
            form,
            multipart(&[
                ("image", &v.image),
                (
                    "camera",
                    br#"{"model": "OPENCV_FISHEYE", "width": 320, "height": 240, "params": [1, 1, 1, 1, 0, 0, 0, 0]}"#,
                ),
            ]),
        ),
        _ => ("application/json".into(), b"{\"image\": \"\"}".to_vec()),
    }
}

fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(300)))
        .build()
        .into()
}

fn post(agent: &ureq::Agent, url: &str, content_type: &str, body: &[u8]) -> (u16, String) {
    match agent
        .post(url)
        .header("Content-Type", content_type)
        .send(body)
    {
        Ok(mut r) => {
            let status = r.status().as_u16();
            (status, r.body_mut().read_to_string().unwrap_or_default())
        }
        Err(e) => (0, e.to_string()),
    }
}

/// (VmRSS, VmHWM) of `pid` in MiB.
fn memory_mib(pid: u32) -> (f64, f64) {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let field = |k: &str| {
        text.lines()
            .find(|l| l.starts_with(k))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<f64>().ok())
            .map_or(f64::NAN, |kb| kb / 1024.0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// Whether a server answer and `matloc localize`'s record agree (pose to 1e-9, confidence).
fn same(got: &Value, want: &Value) -> bool {
    let close = |a: &Value, b: &Value| match (a.as_array(), b.as_array()) {
        (Some(x), Some(y)) => {
            x.len() == y.len()
                && x.iter().zip(y).all(|(p, q)| {
                    (p.as_f64().unwrap_or(f64::NAN) - q.as_f64().unwrap_or(f64::NAN)).abs() < 1e-9
                })
        }
        _ => a.is_null() && b.is_null(),
    };
    got["localized"] == want["localized"]
        && got["confidence"] == want["confidence"]
        && close(&got["qvec_wxyz"], &want["qvec_wxyz"])
        && close(&got["tvec"], &want["tvec"])
}

#[derive(Default)]
struct Tally {
    latencies: Vec<f64>,
    ok: usize,
    localized: usize,
    malformed: usize,
    malformed_4xx: usize,
    overloaded: usize,
    other: Vec<String>,
    mismatches: usize,
}

fn main() {
    let args = match parse_args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(2);
        }
    };
    let dataset = read_dataset(&args.data).expect("reading the dataset");
    let views: Vec<View> = dataset
        .split(Split::Test)
        .map(|f| {
            let c = f.camera;
            let path = dataset.image_path(f);
            View {
                name: path.display().to_string(),
                image: std::fs::read(&path).expect("reading a test image"),
                camera: serde_json::json!({
                    "model": "OPENCV", "width": c.width, "height": c.height,
                    "params": [c.fx, c.fy, c.cx, c.cy, c.distortion.k1, c.distortion.k2,
                               c.distortion.p1, c.distortion.p2],
                })
                .to_string(),
            }
        })
        .collect();
    println!("{} test views of {}", views.len(), args.data.display());

    // Reference: `matloc localize` on the same images.
    let t = Instant::now();
    let mut cmd = Command::new(&args.matloc);
    cmd.args(["--quiet", "localize", "--map"])
        .arg(&args.map)
        .arg("--data")
        .arg(&args.data)
        .arg("--images");
    for v in &views {
        cmd.arg(&v.name);
    }
    let out = cmd
        .stderr(Stdio::null())
        .output()
        .expect("running matloc localize");
    let reference: HashMap<String, Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter_map(|v| Some((v["name"].as_str()?.to_string(), v)))
        .collect();
    println!(
        "matloc localize: {} records in {:.1} s",
        reference.len(),
        t.elapsed().as_secs_f64()
    );

    let port = TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port");
    let addr = SocketAddr::from(([127, 0, 0, 1], port));
    let mut server: Child = Command::new(&args.matloc)
        .args(["--quiet", "serve", "--map"])
        .arg(&args.map)
        .args([
            "--listen",
            &addr.to_string(),
            "--workers",
            &args.workers.to_string(),
            "--queue",
            &args.queue.to_string(),
            "--timeout-s",
            "120",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting matloc serve");
    let pid = server.id();
    let base = format!("http://{addr}");
    let health = agent();
    let t = Instant::now();
    while health
        .get(format!("{base}/healthz"))
        .call()
        .map_or(true, |r| r.status().as_u16() != 200)
    {
        assert!(server.try_wait().unwrap().is_none(), "the server exited");
        std::thread::sleep(Duration::from_millis(100));
    }
    let (rss0, _) = memory_mib(pid);
    println!(
        "server pid {pid} ready in {:.1} s, VmRSS {rss0:.0} MiB; workers {}, queue {}",
        t.elapsed().as_secs_f64(),
        args.workers,
        args.queue
    );

    let views = Arc::new(views);
    let reference = Arc::new(reference);
    let url = format!("{base}/v1/localize");
    println!(
        "| clients | requests | well-formed/s | p50 s | p99 s | localized | malformed → 4xx | 503 | mismatches vs localize | VmRSS MiB | VmHWM MiB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for &clients in &args.clients {
        let deadline = Instant::now() + Duration::from_secs(args.seconds);
        let next = Arc::new(AtomicUsize::new(0));
        let tally = Arc::new(Mutex::new(Tally::default()));
        let start = Instant::now();
        let threads: Vec<_> = (0..clients)
            .map(|_| {
                let (views, reference, next, tally, url) = (
                    views.clone(),
                    reference.clone(),
                    next.clone(),
                    tally.clone(),
                    url.clone(),
                );
                std::thread::spawn(move || {
                    let agent = agent();
                    let form = format!("multipart/form-data; boundary={BOUNDARY}");
                    while Instant::now() < deadline {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let v = &views[i % views.len()];
                        if i % 10 == 9 {
                            let (ct, body) = malformed(v, i / 10);
                            let (status, _) = post(&agent, &url, &ct, &body);
                            let mut t = tally.lock().unwrap();
                            t.malformed += 1;
                            if (400..500).contains(&status) {
                                t.malformed_4xx += 1;
                            } else {
                                t.other.push(format!("malformed {}: {status}", i / 10 % 4));
                            }
                            continue;
                        }
                        let t0 = Instant::now();
                        let (status, text) = post(&agent, &url, &form, &query(v));
                        let s = t0.elapsed().as_secs_f64();
                        let mut t = tally.lock().unwrap();
                        match status {
                            200 => {
                                t.ok += 1;
                                t.latencies.push(s);
                                let got: Value = serde_json::from_str(&text).unwrap_or(Value::Null);
                                if got["localized"] == true {
                                    t.localized += 1;
                                }
                                if reference.get(&v.name).is_none_or(|want| !same(&got, want)) {
                                    t.mismatches += 1;
                                }
                            }
                            503 => t.overloaded += 1,
                            s => t.other.push(format!("{s}: {text}")),
                        }
                    }
                })
            })
            .collect();
        let mut rss_max: f64 = 0.0;
        while threads.iter().any(|t| !t.is_finished()) {
            rss_max = rss_max.max(memory_mib(pid).0);
            std::thread::sleep(Duration::from_millis(250));
        }
        for t in threads {
            t.join().expect("a client panicked");
        }
        let elapsed = start.elapsed().as_secs_f64();
        let mut t = tally.lock().unwrap();
        t.latencies.sort_by(f64::total_cmp);
        let (_, hwm) = memory_mib(pid);
        println!(
            "| {clients} | {} | {:.2} | {:.3} | {:.3} | {}/{} | {}/{} | {} | {} | {rss_max:.0} | {hwm:.0} |",
            t.ok + t.malformed + t.overloaded + t.other.len(),
            t.ok as f64 / elapsed,
            percentile(&t.latencies, 0.5),
            percentile(&t.latencies, 0.99),
            t.localized,
            t.ok,
            t.malformed_4xx,
            t.malformed,
            t.overloaded,
            t.mismatches,
        );
        for o in t.other.iter().take(5) {
            println!("  unexpected: {o}");
        }
        assert!(server.try_wait().unwrap().is_none(), "the server exited");
    }

    // Burst: more simultaneous requests than workers + queue.
    let (rss_before, _) = memory_mib(pid);
    let barrier = Arc::new(Barrier::new(args.burst));
    let results = Arc::new(Mutex::new(Vec::new()));
    let threads: Vec<_> = (0..args.burst)
        .map(|i| {
            let (views, barrier, results, url) =
                (views.clone(), barrier.clone(), results.clone(), url.clone());
            std::thread::spawn(move || {
                let agent = agent();
                let body = query(&views[i % views.len()]);
                let form = format!("multipart/form-data; boundary={BOUNDARY}");
                barrier.wait();
                let t0 = Instant::now();
                let (status, _) = post(&agent, &url, &form, &body);
                results
                    .lock()
                    .unwrap()
                    .push((status, t0.elapsed().as_secs_f64()));
            })
        })
        .collect();
    let mut rss_max: f64 = rss_before;
    while threads.iter().any(|t| !t.is_finished()) {
        rss_max = rss_max.max(memory_mib(pid).0);
        std::thread::sleep(Duration::from_millis(50));
    }
    for t in threads {
        t.join().expect("a burst client panicked");
    }
    let results = results.lock().unwrap();
    let mut shed: Vec<f64> = results.iter().filter(|r| r.0 == 503).map(|r| r.1).collect();
    shed.sort_by(f64::total_cmp);
    let served = results.iter().filter(|r| r.0 == 200).count();
    println!(
        "burst of {}: {served} answered 200, {} answered 503 (p50 {:.4} s, max {:.4} s), others {}; VmRSS {rss_before:.0} → max {rss_max:.0} MiB",
        args.burst,
        shed.len(),
        percentile(&shed, 0.5),
        shed.last().copied().unwrap_or(f64::NAN),
        results.len() - served - shed.len()
    );
    let metrics = health
        .get(format!("{base}/metrics"))
        .call()
        .ok()
        .and_then(|mut r| r.body_mut().read_to_string().ok())
        .unwrap_or_default();
    for line in metrics
        .lines()
        .filter(|l| l.starts_with("matloc_serve_requests_total"))
    {
        println!("  {line}");
    }

    // Graceful stop.
    let t = Instant::now();
    let _ = Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status();
    let status = server.wait().expect("waiting for the server");
    println!(
        "SIGTERM: server exited with {status} after {:.2} s",
        t.elapsed().as_secs_f64()
    );
}
