//! A two-block map of the synthetic `tiny` world, built once per test binary with the cheapest
//! settings (quality does not matter here: the tests compare the server with the localizer on
//! the same map), and a small multipart HTTP client over `ureq`.

#![allow(dead_code)]

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use matloc_data::{Dataset, Split, read_dataset};
use matloc_pipeline::LoadedMap;
use matloc_pipeline::build::{MapConfig, build_map};
use matloc_synth::{SynthConfig, synthesize};

/// The built map's dataset and directory.
pub struct Built {
    pub dataset: Dataset,
    pub map_dir: PathBuf,
}

fn cheap_config() -> MapConfig {
    let mut c = MapConfig::default();
    c.partition.num_blocks = Some(2);
    c.nerf.steps = 200;
    c.nerf.checkpoint_every = 100;
    // The end-to-end tests' small field and batch: the fewest steps that render a surface.
    c.nerf.model_overrides = serde_json::json!({
        "field": {"log2_table_size": 15, "max_resolution": 512},
        "train": {"batch_rays": 1024, "march": {"steps": 128, "max_samples": 24},
                  "occupancy_warmup_steps": 32},
        "render": {"march": {"steps": 128}},
    });
    c.pairs.views_per_block = 6;
    c.encoder.views_per_block = 6;
    c.encoder.train.steps = 20;
    c.encoder.train.head_phase.steps = 0;
    c.select.renders.max_views = 2;
    c.place.train.epochs = 2;
    c.place.rendered.per_view = 0;
    c.calibration.max_views = 4;
    c
}

/// The map, built at most once per test binary (a complete map from an earlier run of the
/// same binary is reused: the build skips finished stages).
pub fn built() -> &'static Built {
    static BUILT: OnceLock<Built> = OnceLock::new();
    BUILT.get_or_init(|| {
        let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("serve_tiny");
        let data = dir.join("data");
        if read_dataset(&data).is_err() {
            let _ = std::fs::remove_dir_all(&dir);
            synthesize(&SynthConfig::preset("tiny").unwrap(), &data, &|_| {}).unwrap();
        }
        let dataset = read_dataset(&data).unwrap();
        let map_dir = dir.join("map");
        let t = std::time::Instant::now();
        if build_map(&dataset, &map_dir, &cheap_config(), &mut |_| {}).is_err() {
            // A map left by another config or a broken run: build it afresh.
            let _ = std::fs::remove_dir_all(&map_dir);
            build_map(&dataset, &map_dir, &cheap_config(), &mut |_| {}).unwrap();
        }
        eprintln!("test map ready in {:.1} s", t.elapsed().as_secs_f64());
        Built { dataset, map_dir }
    })
}

/// The whole map, loaded once.
pub fn full_map() -> Arc<LoadedMap> {
    static MAP: OnceLock<Arc<LoadedMap>> = OnceLock::new();
    MAP.get_or_init(|| Arc::new(LoadedMap::open(&built().map_dir).unwrap()))
        .clone()
}

/// The test views: image path and the camera JSON (COLMAP PINHOLE) of each.
pub fn test_views() -> Vec<(PathBuf, String)> {
    let ds = &built().dataset;
    ds.split(Split::Test)
        .map(|f| {
            let c = f.camera;
            let camera = serde_json::json!({
                "model": "PINHOLE", "width": c.width, "height": c.height,
                "params": [c.fx, c.fy, c.cx, c.cy],
            })
            .to_string();
            (ds.image_path(f), camera)
        })
        .collect()
}

/// One multipart part.
pub struct Part<'a> {
    pub name: &'a str,
    pub filename: Option<&'a str>,
    pub content_type: &'a str,
    pub data: &'a [u8],
}

pub const BOUNDARY: &str = "matloc-test-boundary-7d1f";

/// A multipart/form-data body of `parts`.
pub fn multipart(parts: &[Part<'_>]) -> Vec<u8> {
    let mut body = Vec::new();
    for p in parts {
        body.extend_from_slice(format!("--{BOUNDARY}\r\n").as_bytes());
        let filename = p
            .filename
            .map(|f| format!("; filename=\"{f}\""))
            .unwrap_or_default();
        body.extend_from_slice(
            format!(
                "Content-Disposition: form-data; name=\"{}\"{filename}\r\nContent-Type: {}\r\n\r\n",
                p.name, p.content_type
            )
            .as_bytes(),
        );
        body.extend_from_slice(p.data);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
    body
}

/// A query body: `image` bytes and `camera` JSON, optionally `name`.
pub fn query_body(image: &[u8], camera: &str, name: Option<&str>) -> Vec<u8> {
    let mut parts = vec![
        Part {
            name: "image",
            filename: Some("q.png"),
            content_type: "image/png",
            data: image,
        },
        Part {
            name: "camera",
            filename: None,
            content_type: "application/json",
            data: camera.as_bytes(),
        },
    ];
    if let Some(n) = name {
        parts.push(Part {
            name: "name",
            filename: None,
            content_type: "text/plain",
            data: n.as_bytes(),
        });
    }
    multipart(&parts)
}

/// An HTTP agent that returns every status as a response (no error for 4xx/5xx).
pub fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(120)))
        .build()
        .into()
}

/// POSTs `body` with `content_type`; returns the status and the body as text.
pub fn post(agent: &ureq::Agent, url: &str, content_type: &str, body: &[u8]) -> (u16, String) {
    let mut r = agent
        .post(url)
        .header("Content-Type", content_type)
        .send(body)
        .unwrap();
    let status = r.status().as_u16();
    let text = r
        .body_mut()
        .with_config()
        .limit(64 << 20)
        .read_to_string()
        .unwrap();
    (status, text)
}

/// GETs `url`; returns the status and the body.
pub fn get(agent: &ureq::Agent, url: &str) -> (u16, String) {
    let mut r = agent.get(url).call().unwrap();
    let status = r.status().as_u16();
    (status, r.body_mut().read_to_string().unwrap())
}

/// The multipart content type of [`multipart`] bodies.
pub fn form_type() -> String {
    format!("multipart/form-data; boundary={BOUNDARY}")
}
