//! A bounded load test on loopback: a few clients send absurd but well-formed cameras mixed
//! with valid queries to a server on `127.0.0.1:0`. Every absurd camera is answered 400 naming
//! the camera field and its bound in under 10 ms of server time (the `Server-Timing` header),
//! without taking a worker, while the valid queries (sizes written as whole-valued floats among
//! them) are answered 200.

mod common;

use std::sync::Mutex;
use std::time::{Duration, Instant};

use common::*;
use matloc_serve::{ServeConfig, ServerHandle};
use serde_json::{Value, json};

/// Clients sending at once.
const CLIENTS: usize = 3;

/// Rounds per client: each sends every absurd camera once and one valid query.
const ROUNDS: usize = 2;

/// Longest server time of a 400, milliseconds.
const MAX_REJECT_MS: f64 = 10.0;

/// The absurd cameras for a view of `width`×`height` with intrinsics `[fx, fy, cx, cy]`:
/// (what, camera JSON, the camera field the 400 names, text of the bound).
fn absurd_cameras(
    width: u32,
    height: u32,
    k: [f64; 4],
) -> Vec<(&'static str, String, &'static str, &'static str)> {
    let [fx, fy, cx, cy] = k;
    // A size of a billion pixels with the image's aspect ratio, intrinsics scaled with it, so
    // that the rescale rule alone would bring it to the image.
    let s = 1e9 / f64::from(width);
    let huge_h = (f64::from(height) * s).round() as u64;
    let pinhole = |w: Value, h: Value, p: [f64; 4]| {
        json!({"model": "PINHOLE", "width": w, "height": h, "params": p}).to_string()
    };
    let opencv = |d: [f64; 4]| {
        json!({"model": "OPENCV", "width": width, "height": height,
               "params": [fx, fy, cx, cy, d[0], d[1], d[2], d[3]]})
        .to_string()
    };
    vec![
        (
            "size 1e9 rescaled to the image",
            pinhole(
                json!(1_000_000_000u64),
                json!(huge_h),
                [fx * s, fy * s, cx * s, cy * s],
            ),
            "width",
            "1..=65536",
        ),
        (
            "focal length 1e308",
            pinhole(json!(width), json!(height), [1e308, 1e308, cx, cy]),
            "fx",
            "0.5–170°",
        ),
        (
            "focal length 1e-300 (a 180° view)",
            pinhole(json!(width), json!(height), [1e-300, fy, cx, cy]),
            "fx",
            "0.5–170°",
        ),
        (
            "principal point ±1e308",
            pinhole(json!(width), json!(height), [fx, fy, 1e308, -1e308]),
            "cx",
            "0.25 × the image side",
        ),
        (
            "OPENCV k1 1e30",
            opencv([1e30, 0.0, 0.0, 0.0]),
            "distortion",
            "4×",
        ),
        ("OPENCV p1 10", opencv([0.0, 0.0, 10.0, 0.0]), "p1", "±0.1"),
        (
            "nerfstudio focal length 1e308",
            json!({"w": width, "h": height, "fl_x": 1e308, "fl_y": fy, "cx": cx, "cy": cy})
                .to_string(),
            "fx",
            "0.5–170°",
        ),
    ]
}

/// The `total` duration of a `Server-Timing` header, milliseconds.
fn server_ms(header: Option<&str>) -> f64 {
    let h = header.unwrap_or_else(|| panic!("no Server-Timing header"));
    h.split(',')
        .find_map(|m| {
            let m = m.trim();
            m.strip_prefix("total;dur=")
                .and_then(|d| d.parse::<f64>().ok())
        })
        .unwrap_or_else(|| panic!("no total in Server-Timing {h:?}"))
}

/// What one request got: what was sent, whether it was valid, status, body, server ms.
struct Answer {
    what: String,
    valid: bool,
    want_field: &'static str,
    want_bound: &'static str,
    status: u16,
    body: Value,
    server_ms: f64,
}

#[test]
fn absurd_cameras_get_400_in_under_10_ms_among_valid_queries() {
    let config = ServeConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        workers: 2,
        queue: 2 * CLIENTS,
        max_body_bytes: 4 << 20,
        timeout: Duration::from_secs(120),
        ..ServeConfig::default()
    };
    let server = ServerHandle::start(full_map(), config).unwrap();
    let url = format!("http://{}/v1/localize", server.addr());
    let ds = &built().dataset;
    let views = test_views();
    let frames: Vec<_> = ds.split(matloc_data::Split::Test).collect();
    let answers = Mutex::new(Vec::new());
    let t = Instant::now();
    std::thread::scope(|scope| {
        for client in 0..CLIENTS {
            let (url, answers, views, frames) = (&url, &answers, &views, &frames);
            scope.spawn(move || {
                let agent = agent();
                for round in 0..ROUNDS {
                    let v = (client * ROUNDS + round) % views.len();
                    let (path, _) = &views[v];
                    let image = std::fs::read(path).unwrap();
                    let c = frames[v].camera;
                    let mut requests: Vec<(String, String, bool, &str, &str)> =
                        absurd_cameras(c.width, c.height, [c.fx, c.fy, c.cx, c.cy])
                            .into_iter()
                            .map(|(what, cam, field, bound)| {
                                (what.to_string(), cam, false, field, bound)
                            })
                            .collect();
                    // The valid query, its sizes written as Python's json.dumps writes floats.
                    let valid = format!(
                        r#"{{"model": "PINHOLE", "width": {:.1}, "height": {:.1}, "params": [{}, {}, {}, {}]}}"#,
                        f64::from(c.width),
                        f64::from(c.height),
                        c.fx,
                        c.fy,
                        c.cx,
                        c.cy
                    );
                    // Clients place their valid query at different points of the round.
                    let at = (client + round) % (requests.len() + 1);
                    requests.insert(at, (format!("view {v}"), valid, true, "", ""));
                    for (what, camera, valid, want_field, want_bound) in requests {
                        let body = query_body(&image, &camera, Some(&what));
                        let mut r = agent
                            .post(url)
                            .header("Content-Type", &form_type())
                            .send(&body[..])
                            .unwrap();
                        let status = r.status().as_u16();
                        let timing = r
                            .headers()
                            .get("server-timing")
                            .and_then(|h| h.to_str().ok())
                            .map(str::to_owned);
                        let text = r.body_mut().read_to_string().unwrap();
                        let body: Value = serde_json::from_str(&text)
                            .unwrap_or_else(|e| panic!("{what}: {e}: {text}"));
                        answers.lock().unwrap().push(Answer {
                            what,
                            valid,
                            want_field,
                            want_bound,
                            status,
                            body,
                            server_ms: server_ms(timing.as_deref()),
                        });
                    }
                }
            });
        }
    });
    let wall = t.elapsed();
    let answers = answers.into_inner().unwrap();
    let absurd_per_round = absurd_cameras(1, 1, [1.0; 4]).len();
    assert_eq!(answers.len(), CLIENTS * ROUNDS * (absurd_per_round + 1));
    let mut reject_ms = Vec::new();
    let mut valid_ms = Vec::new();
    for a in &answers {
        if a.valid {
            assert_eq!(a.status, 200, "{}: {}", a.what, a.body);
            let status = a.body["status"].as_str().unwrap_or("");
            assert!(
                ["localized", "refused", "outside_blocks"].contains(&status),
                "{}: {}",
                a.what,
                a.body
            );
            valid_ms.push(a.server_ms);
            continue;
        }
        assert_eq!(a.status, 400, "{}: {}", a.what, a.body);
        assert_eq!(a.body["status"], "bad_request", "{}: {}", a.what, a.body);
        assert_eq!(a.body["field"], "camera", "{}: {}", a.what, a.body);
        let camera_field = a.body["camera_field"].as_str().unwrap_or("");
        assert_eq!(camera_field, a.want_field, "{}: {}", a.what, a.body);
        let error = a.body["error"].as_str().unwrap();
        assert!(
            error.contains(&format!("`{camera_field}`")) && error.contains(a.want_bound),
            "{}: {error}",
            a.what
        );
        assert!(
            a.server_ms < MAX_REJECT_MS,
            "{}: {:.3} ms of server time",
            a.what,
            a.server_ms
        );
        reject_ms.push(a.server_ms);
    }
    reject_ms.sort_by(f64::total_cmp);
    valid_ms.sort_by(f64::total_cmp);
    eprintln!(
        "{} absurd cameras: 400 in {:.3} ms median, {:.3} ms max of server time; {} valid: 200 in \
         {:.0}–{:.0} ms; {:.1} s in all",
        reject_ms.len(),
        reject_ms[reject_ms.len() / 2],
        reject_ms[reject_ms.len() - 1],
        valid_ms.len(),
        valid_ms[0],
        valid_ms[valid_ms.len() - 1],
        wall.as_secs_f64()
    );
    // No absurd camera reached a worker: only the valid queries were localized.
    use matloc_serve::metrics::Outcome;
    let m = server.service().metrics();
    assert_eq!(m.count(Outcome::BadRequest), reject_ms.len() as u64);
    assert_eq!(
        m.count(Outcome::Localized) + m.count(Outcome::Refused) + m.count(Outcome::OutsideBlocks),
        valid_ms.len() as u64
    );
    server.shutdown().unwrap();
}
