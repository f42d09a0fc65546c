//! Localization as an HTTP service (`matloc serve`): a map is loaded once and
//! `POST /v1/localize` answers one query image with the same JSON record `matloc localize`
//! writes, with bounded workers and queue, a body limit, a timeout, Prometheus metrics and
//! graceful shutdown.
//!
//! - [`server`]: routes, admission, parsing, shutdown ([`ServeConfig`], [`run`],
//!   [`ServerHandle`]). A query's intrinsics, image and record are the library's query path
//!   ([`matloc_data::query`], [`matloc_pipeline::query`]), the same as `matloc localize`'s.
//! - [`metrics`]: counters, gauges and the latency histogram in Prometheus text.
//!
//! The request is `multipart/form-data` with parts `image` (PNG or JPEG bytes), `camera`
//! (JSON) and optionally `name`; binary parts avoid base64's third more bytes and its decoding.

pub mod metrics;
pub mod server;

pub use server::{ServeConfig, ServeError, ServerHandle, Service, router, run, serve};
