//! Localization as an HTTP service (`matloc serve`): a map is loaded once and
//! `POST /v1/localize` answers one query image with the same JSON record `matloc localize`
//! writes, with bounded workers and queue, a body limit, a timeout, Prometheus metrics and
//! graceful shutdown.
//!
//! - [`server`]: routes, admission, parsing, shutdown ([`ServeConfig`], [`run`],
//!   [`ServerHandle`]).
//! - [`camera`]: query intrinsics from a COLMAP model name + parameters, nerfstudio keys or a
//!   matloc camera; unsupported models are rejected by name (shared with the CLI's query
//!   lists).
//! - [`query`]: decoding query images from bytes and bringing them to the map's resolution
//!   (shared with the CLI).
//! - [`record`]: the JSON record of one query (shared with `matloc localize --format jsonl`).
//! - [`metrics`]: counters, gauges and the latency histogram in Prometheus text.
//!
//! The request is `multipart/form-data` with parts `image` (PNG or JPEG bytes), `camera`
//! (JSON) and optionally `name`; binary parts avoid base64's third more bytes and its decoding.

pub mod camera;
pub mod metrics;
pub mod query;
pub mod record;
pub mod server;

pub use server::{ServeConfig, ServeError, ServerHandle, Service, router, run, serve};
