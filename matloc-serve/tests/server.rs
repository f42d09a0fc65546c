//! The server against a real (cheaply built) two-block map of the `tiny` world: answers equal
//! the localizer's on the same image; malformed requests get a 4xx naming the field; a full
//! queue answers 503 at once and a stalled request 504; metrics parse as Prometheus text;
//! shutdown finishes the request in flight; a subset of blocks refuses queries placed outside.

mod common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::*;
use matloc_core::pose::cam_from_world_from_colmap;
use matloc_data::query::to_map_resolution;
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::{MethodOptions, localize_with};
use matloc_serve::{ServeConfig, ServerHandle};
use serde_json::Value;

fn config() -> ServeConfig {
    ServeConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        workers: 2,
        queue: 4,
        max_body_bytes: 4 << 20,
        timeout: Duration::from_secs(60),
        ..ServeConfig::default()
    }
}

fn url(h: &ServerHandle, path: &str) -> String {
    format!("http://{}{path}", h.addr())
}

fn json(text: &str) -> Value {
    serde_json::from_str(text).unwrap_or_else(|e| panic!("{e}: {text}"))
}

/// The record `localize_with` gives for the view at `path` (as `matloc localize` runs it).
fn expected(map: &LoadedMap, path: &std::path::Path, camera: &str) -> Value {
    let image = matloc_data::images::load_rgb(path).unwrap();
    let camera = matloc_data::query::parse_camera_json(camera).unwrap();
    let (image, camera) = to_map_resolution(image, camera, map.camera().as_ref(), "q").unwrap();
    let r = localize_with(
        map,
        config().method.as_ref(),
        "q",
        &image,
        &camera,
        &MethodOptions::default(),
    )
    .unwrap();
    matloc_pipeline::query::localization_record(&r, "data", &|p| *p, None).unwrap()
}

fn assert_same_answer(got: &Value, want: &Value) {
    assert_eq!(got["localized"], want["localized"], "{got}\n{want}");
    assert_eq!(got["confidence"], want["confidence"], "{got}\n{want}");
    assert_eq!(got["inliers"], want["inliers"]);
    assert_eq!(got["iterations"], want["iterations"]);
    if want["localized"] == true {
        let pose = |v: &Value| {
            let q: [f64; 4] = serde_json::from_value(v["qvec_wxyz"].clone()).unwrap();
            let t: [f64; 3] = serde_json::from_value(v["tvec"].clone()).unwrap();
            cam_from_world_from_colmap(q, t).unwrap()
        };
        let (a, b) = (pose(got), pose(want));
        assert!(a.rotation.angle_to(&b.rotation) < 1e-9, "{a} vs {b}");
        assert!((a.translation.vector - b.translation.vector).norm() < 1e-9);
    } else {
        assert!(got["qvec_wxyz"].is_null());
    }
    let hyps = |v: &Value| {
        v["hypotheses"]
            .as_array()
            .unwrap()
            .iter()
            .map(|h| {
                (
                    h["block"].clone(),
                    h["group"].clone(),
                    h["matches"].clone(),
                    h["inliers"].clone(),
                    h["coarse_tvec"].clone(),
                )
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(hyps(got), hyps(want));
}

#[test]
fn well_formed_queries_answer_as_the_localizer_does() {
    let map = full_map();
    let server = ServerHandle::start(map.clone(), config()).unwrap();
    let agent = agent();
    for (i, (path, camera)) in test_views().iter().take(4).enumerate() {
        let image = std::fs::read(path).unwrap();
        let name = format!("view{i}.png");
        let (status, text) = post(
            &agent,
            &url(&server, "/v1/localize"),
            &form_type(),
            &query_body(&image, camera, Some(&name)),
        );
        assert_eq!(status, 200, "{text}");
        let got = json(&text);
        assert_eq!(got["name"], name.as_str());
        assert_eq!(got["method"], config().method.name());
        assert_eq!(got["world"], "data");
        let status = got["status"].as_str().unwrap();
        assert_eq!(status == "localized", got["localized"] == true, "{got}");
        assert!(got["server_seconds"]["total"].as_f64().unwrap() > 0.0);
        assert!(got["stage_seconds"].is_array() && got["total_seconds"].is_number());
        assert_same_answer(&got, &expected(&map, path, camera));
    }
    let m = server.service().metrics();
    use matloc_serve::metrics::Outcome;
    assert_eq!(m.count(Outcome::Localized) + m.count(Outcome::Refused), 4);
    server.shutdown().unwrap();
}

/// A malformed request: what, content type, body, status, field, text in the error.
type Case = (
    &'static str,
    String,
    Vec<u8>,
    u16,
    &'static str,
    &'static str,
);

#[test]
fn malformed_requests_get_a_4xx_naming_the_field() {
    let mut cfg = config();
    cfg.max_body_bytes = 300_000;
    let server = ServerHandle::start(full_map(), cfg).unwrap();
    let agent = agent();
    let (path, camera) = test_views().into_iter().next().unwrap();
    let image = std::fs::read(&path).unwrap();
    let u = url(&server, "/v1/localize");
    let form = form_type();
    let other_size =
        r#"{"model": "PINHOLE", "width": 100, "height": 100, "params": [80, 80, 50, 50]}"#;
    let fisheye = r#"{"model": "OPENCV_FISHEYE", "width": 320, "height": 240, "params": [200, 200, 160, 120, 0, 0, 0, 0]}"#;
    let cases: Vec<Case> = vec![
        (
            "json content type",
            "application/json".into(),
            b"{}".to_vec(),
            415,
            "content-type",
            "multipart/form-data",
        ),
        (
            "truncated image",
            form.clone(),
            query_body(&image[..image.len() / 3], &camera, None),
            400,
            "image",
            "decode",
        ),
        (
            "not an image",
            form.clone(),
            query_body(b"hello, world", &camera, None),
            400,
            "image",
            "PNG or JPEG",
        ),
        (
            "empty image",
            form.clone(),
            query_body(b"", &camera, None),
            400,
            "image",
            "empty",
        ),
        (
            "bad camera JSON",
            form.clone(),
            query_body(&image, "{\"model\": ", None),
            400,
            "camera",
            "not valid JSON",
        ),
        (
            "unsupported camera model",
            form.clone(),
            query_body(&image, fisheye, None),
            400,
            "camera",
            "OPENCV_FISHEYE",
        ),
        (
            "camera of another size",
            form.clone(),
            query_body(&image, other_size, None),
            400,
            "camera",
            "100×100",
        ),
        (
            "missing camera",
            form.clone(),
            multipart(&[Part {
                name: "image",
                filename: Some("q.png"),
                content_type: "image/png",
                data: &image,
            }]),
            400,
            "camera",
            "missing part `camera`",
        ),
        (
            "unknown part",
            form.clone(),
            multipart(&[Part {
                name: "picture",
                filename: None,
                content_type: "image/png",
                data: &image,
            }]),
            400,
            "body",
            "unknown part `picture`",
        ),
        (
            "not multipart",
            form.clone(),
            b"this is not a multipart body".to_vec(),
            400,
            "body",
            "",
        ),
        (
            "oversized body",
            form.clone(),
            query_body(&vec![7u8; 400_000], &camera, None),
            413,
            "body",
            "300000-byte limit",
        ),
    ];
    for (what, content_type, body, want_status, field, want_text) in &cases {
        let (status, text) = post(&agent, &u, content_type, body);
        assert_eq!(status, *want_status, "{what}: {text}");
        let v = json(&text);
        assert_eq!(v["field"], *field, "{what}: {text}");
        let error = v["error"].as_str().unwrap();
        assert!(error.contains(want_text), "{what}: {error}");
    }
    // A chunked oversized body (no Content-Length) is cut off at the limit too.
    let mut r = agent
        .post(&u)
        .header("Content-Type", &form)
        .send(ureq::SendBody::from_reader(
            &mut &query_body(&vec![7u8; 400_000], &camera, None)[..],
        ))
        .unwrap();
    assert_eq!(
        r.status().as_u16(),
        413,
        "{}",
        r.body_mut().read_to_string().unwrap()
    );
    // A client that writes its oversized body slowly, as a slow link does, can write all of
    // it and then read the 413 (the server reads and discards the rest before answering).
    let body = query_body(&vec![7u8; 400_000], &camera, None);
    let mut s = stalled_request(&server, &body, 0);
    for chunk in body.chunks(body.len() / 8 + 1) {
        std::thread::sleep(Duration::from_millis(30));
        s.write_all(chunk)
            .expect("the server closed the connection before the client had sent its body");
    }
    let (status, text) = read_response(s);
    assert_eq!(status, 413, "{text}");
    // axum's own errors have JSON bodies too.
    let (status, text) = get(&agent, &u);
    assert_eq!(status, 405, "{text}");
    let v = json(&text);
    assert_eq!(v["status"], "method_not_allowed", "{text}");
    let error = v["error"].as_str().unwrap();
    assert!(error.contains("GET") && error.contains("POST"), "{error}");
    let (status, text) = post(&agent, &url(&server, "/healthz"), "text/plain", b"x");
    assert_eq!(status, 405, "{text}");
    assert_eq!(json(&text)["status"], "method_not_allowed", "{text}");
    let (status, text) = get(&agent, &url(&server, "/v2/nothing"));
    assert_eq!(status, 404, "{text}");
    assert_eq!(json(&text)["status"], "not_found", "{text}");
    // The server is still up and counted every case.
    let (status, text) = get(&agent, &url(&server, "/healthz"));
    assert_eq!((status, json(&text)["status"].as_str()), (200, Some("ok")));
    use matloc_serve::metrics::Outcome;
    let m = server.service().metrics();
    assert_eq!(m.count(Outcome::BadRequest), cases.len() as u64 - 1);
    assert_eq!(m.count(Outcome::PayloadTooLarge), 3);
    server.shutdown().unwrap();
}

/// Opens a localization request and sends its headers and the first `sent` bytes of `body`.
fn stalled_request(server: &ServerHandle, body: &[u8], sent: usize) -> TcpStream {
    let mut s = TcpStream::connect(server.addr()).unwrap();
    write!(
        s,
        "POST /v1/localize HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Type: {}\r\nContent-Length: {}\r\n\r\n",
        form_type(),
        body.len()
    )
    .unwrap();
    s.write_all(&body[..sent]).unwrap();
    s.flush().unwrap();
    s
}

fn wait_for(what: &str, mut cond: impl FnMut() -> bool) {
    let start = Instant::now();
    while !cond() {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

fn read_response(mut s: TcpStream) -> (u16, String) {
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text.split("\r\n\r\n").nth(1).unwrap_or("").to_string();
    (status, body)
}

#[test]
fn a_full_queue_answers_503_at_once_and_a_stalled_request_504() {
    let mut cfg = config();
    cfg.workers = 1;
    cfg.queue = 0;
    cfg.timeout = Duration::from_secs(2);
    let server = ServerHandle::start(full_map(), cfg).unwrap();
    let (path, camera) = test_views().into_iter().next().unwrap();
    let body = query_body(&std::fs::read(&path).unwrap(), &camera, None);
    let stalled = stalled_request(&server, &body, body.len() / 2);
    let metrics = server.service().metrics();
    wait_for("the stalled request to be admitted", || {
        metrics.gauges().1 == 1
    });

    let agent = agent();
    let t = Instant::now();
    let (status, text) = post(&agent, &url(&server, "/v1/localize"), &form_type(), &body);
    let took = t.elapsed();
    assert_eq!(status, 503, "{text}");
    assert_eq!(json(&text)["status"], "overloaded");
    assert!(took < Duration::from_millis(500), "503 took {took:?}");

    let (status, text) = read_response(stalled);
    assert_eq!(status, 504, "{text}");
    assert!(json(&text)["error"].as_str().unwrap().contains("timeout"));
    wait_for("the queue to empty", || metrics.gauges() == (0, 0));
    // Capacity is back.
    let (status, text) = post(&agent, &url(&server, "/v1/localize"), &form_type(), &body);
    assert_eq!(status, 200, "{text}");
    server.shutdown().unwrap();
}

/// Checks Prometheus text exposition: `# HELP`/`# TYPE` lines, then samples
/// `name{label="value",...} number` of declared metrics; returns (name with labels, value).
fn parse_prometheus(text: &str) -> Vec<(String, f64)> {
    let mut types = std::collections::HashMap::new();
    let mut samples = Vec::new();
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix("# ") {
            let mut f = rest.splitn(3, ' ');
            let (kind, name, what) = (f.next().unwrap(), f.next().unwrap(), f.next().unwrap());
            assert!(kind == "HELP" || kind == "TYPE", "{line}");
            if kind == "TYPE" {
                assert!(
                    ["counter", "gauge", "histogram", "summary", "untyped"].contains(&what),
                    "{line}"
                );
                types.insert(name.to_string(), what.to_string());
            }
            continue;
        }
        let (series, value) = line.rsplit_once(' ').unwrap();
        let value: f64 = value.parse().unwrap_or_else(|_| panic!("{line}"));
        let name = series.split('{').next().unwrap();
        assert!(
            name.chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == ':'),
            "{line}"
        );
        if let Some(labels) = series.strip_prefix(name)
            && !labels.is_empty()
        {
            let inner = labels.strip_prefix('{').unwrap().strip_suffix('}').unwrap();
            for pair in inner.split(',') {
                let (k, v) = pair.split_once('=').unwrap();
                assert!(
                    !k.is_empty() && v.starts_with('"') && v.ends_with('"'),
                    "{line}"
                );
            }
        }
        let base = ["_bucket", "_sum", "_count"]
            .iter()
            .find_map(|s| {
                name.strip_suffix(s)
                    .filter(|b| types.get(*b).is_some_and(|t| t == "histogram"))
            })
            .unwrap_or(name);
        assert!(types.contains_key(base), "sample before its TYPE: {line}");
        samples.push((series.to_string(), value));
    }
    samples
}

#[test]
fn metrics_parse_as_prometheus_text_and_healthz_is_ok() {
    let server = ServerHandle::start(full_map(), config()).unwrap();
    let agent = agent();
    let (status, text) = get(&agent, &url(&server, "/healthz"));
    assert_eq!(status, 200);
    let h = json(&text);
    assert_eq!(h["status"], "ok");
    assert_eq!(h["blocks"], serde_json::json!([0, 1]));
    let (path, camera) = test_views().into_iter().next().unwrap();
    let body = query_body(&std::fs::read(&path).unwrap(), &camera, None);
    post(&agent, &url(&server, "/v1/localize"), &form_type(), &body);
    post(&agent, &url(&server, "/v1/localize"), "text/plain", b"x");
    let mut r = agent.get(url(&server, "/metrics")).call().unwrap();
    let ct = r
        .headers()
        .get("content-type")
        .unwrap()
        .to_str()
        .unwrap()
        .to_string();
    assert!(ct.starts_with("text/plain; version=0.0.4"), "{ct}");
    let text = r.body_mut().read_to_string().unwrap();
    let samples = parse_prometheus(&text);
    let value = |s: &str| {
        samples
            .iter()
            .find(|(n, _)| n == s)
            .unwrap_or_else(|| panic!("{s} missing:\n{text}"))
            .1
    };
    assert_eq!(value("matloc_serve_request_duration_seconds_count"), 2.0);
    assert_eq!(
        value("matloc_serve_requests_total{outcome=\"bad_request\"}"),
        1.0
    );
    assert_eq!(
        value("matloc_serve_requests_total{outcome=\"localized\"}")
            + value("matloc_serve_requests_total{outcome=\"refused\"}"),
        1.0
    );
    assert_eq!(value("matloc_serve_in_flight"), 0.0);
    assert_eq!(value("matloc_serve_queue_depth"), 0.0);
    let buckets: Vec<f64> = samples
        .iter()
        .filter(|(n, _)| n.starts_with("matloc_serve_request_duration_seconds_bucket"))
        .map(|s| s.1)
        .collect();
    assert!(buckets.windows(2).all(|w| w[0] <= w[1]), "{buckets:?}");
    assert_eq!(buckets.last(), Some(&2.0));
    server.shutdown().unwrap();
}

#[test]
fn shutdown_finishes_the_request_in_flight_and_refuses_others() {
    let server = ServerHandle::start(full_map(), config()).unwrap();
    let addr = server.addr();
    let (path, camera) = test_views().into_iter().next().unwrap();
    let body = query_body(&std::fs::read(&path).unwrap(), &camera, None);
    let mut stalled = stalled_request(&server, &body, body.len() / 2);
    let service = server.service().clone();
    wait_for("the request to be admitted", || {
        service.metrics().gauges().1 == 1
    });
    let stopper = std::thread::spawn(move || server.shutdown());
    wait_for("draining", || {
        agent()
            .get(format!("http://{addr}/healthz"))
            .call()
            .map_or(true, |r| r.status().as_u16() == 503)
    });
    stalled.write_all(&body[body.len() / 2..]).unwrap();
    let (status, text) = read_response(stalled);
    assert_eq!(status, 200, "{text}");
    stopper.join().unwrap().unwrap();
    assert!(TcpStream::connect(addr).is_err(), "still accepting");
}

#[test]
fn a_subset_of_blocks_refuses_queries_placed_outside_it() {
    let full = full_map();
    assert!(LoadedMap::open_blocks(&built().map_dir, Some(&[5])).is_err());
    // The top place hypothesis of each test view, by the whole map's localizer.
    let views = test_views();
    let mut top = Vec::new();
    for (path, camera) in &views {
        let v = expected(&full, path, camera);
        top.push(v["hypotheses"][0]["block"].as_u64().unwrap() as usize);
    }
    let outside_block = top[0];
    let served = 1 - outside_block;
    let subset = Arc::new(LoadedMap::open_blocks(&built().map_dir, Some(&[served])).unwrap());
    assert_eq!(subset.served_blocks(), [served]);
    assert!(subset.nerf(outside_block).is_none() && subset.nerf(served).is_some());
    let server = ServerHandle::start(subset, config()).unwrap();
    let agent = agent();
    let (status, text) = get(&agent, &url(&server, "/healthz"));
    assert_eq!(
        (status, json(&text)["blocks"].clone()),
        (200, serde_json::json!([served]))
    );
    for (i, (path, camera)) in views.iter().enumerate().take(6) {
        let body = query_body(&std::fs::read(path).unwrap(), camera, None);
        let (status, text) = post(&agent, &url(&server, "/v1/localize"), &form_type(), &body);
        assert_eq!(status, 200, "{text}");
        let v = json(&text);
        if top[i] == outside_block {
            assert_eq!(v["status"], "outside_blocks", "{v}");
            assert_eq!(v["block"], outside_block);
            assert_eq!(v["localized"], false);
            assert_eq!(v["hypotheses"].as_array().unwrap().len(), 1);
            let failure = v["hypotheses"][0]["failure"].as_str().unwrap();
            assert!(failure.contains("not served"), "{failure}");
        } else {
            assert_ne!(v["status"], "outside_blocks", "{v}");
        }
    }
    server.shutdown().unwrap();
}
