//! The HTTP server: routes, admission (bounded workers and queue), request parsing, the
//! localizer on blocking threads, timeouts and graceful shutdown.
//!
//! A `POST /v1/localize` request goes through, in order: the shutdown check (503), the
//! declared body size (413), admission (503 at once when `workers + queue` requests are
//! already admitted, so memory never grows with load: only admitted requests keep their
//! bodies), body parsing (4xx naming the part or field), a free worker (queue), then decoding
//! and localization on a blocking thread. The query camera is checked while the body is parsed
//! (plausible intrinsics, a size the image's header matches or rescales to), so an impossible
//! camera is answered 400 without taking a worker. A request answered with an error before its body
//! was read has the rest of its body read and discarded first (bounded in bytes and time, a
//! "lingering close"): a client still sending then gets the answer, not a broken pipe. Everything after admission runs under the timeout
//! (504); a localization still running at the timeout keeps its worker until it ends, so the
//! number of running localizations never exceeds `workers`.
//!
//! Every error response has a JSON body `{"status", "error"[, "field"]}`, those of axum's
//! own routing (405, 404) included, and every `POST /v1/localize` response carries a
//! `Server-Timing: total;dur=MS` header: the server's time on the request, in milliseconds,
//! from the handler's start to the response.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::{DefaultBodyLimit, FromRequest, Multipart, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use matloc_core::Camera;
use matloc_pipeline::methods::{LocalizationMethod, Method, MethodOptions, localize_with};
use matloc_pipeline::{LoadedMap, PipelineError};
use serde_json::{Value, json};
use tokio::net::TcpListener;
use tokio::sync::{Semaphore, oneshot};

use crate::metrics::{Metrics, Outcome};
use matloc_data::query::camera::{CameraSpecError, check_plausible, parse_camera_json};
use matloc_data::query::image::{
    DecodeLimits, decode_rgb, fit_to_image, image_dimensions, to_map_resolution,
};
use matloc_pipeline::query::localization_record;

/// Server settings.
#[derive(Clone, Debug)]
pub struct ServeConfig {
    /// Address to listen on (port 0: any free port).
    pub listen: SocketAddr,
    /// Localizations run at once (blocking threads).
    pub workers: usize,
    /// Requests admitted beyond the running ones (reading their body or waiting for a
    /// worker); more are answered 503 at once.
    pub queue: usize,
    /// Largest request body, bytes (413 beyond).
    pub max_body_bytes: usize,
    /// Time from admission to response (504 beyond).
    pub timeout: Duration,
    /// Limits on the decoded query image.
    pub decode: DecodeLimits,
    /// The method every request runs (a built-in [`Method`] or any other
    /// [`LocalizationMethod`]).
    pub method: Arc<dyn LocalizationMethod>,
}

impl Default for ServeConfig {
    /// `127.0.0.1:8080`, one worker per core, a queue of twice that, 16 MiB bodies, 30 s,
    /// the default method.
    fn default() -> Self {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        ServeConfig {
            listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
            workers: cores,
            queue: 2 * cores,
            max_body_bytes: 16 << 20,
            timeout: Duration::from_secs(30),
            decode: DecodeLimits::default(),
            method: Arc::new(Method::DEFAULT),
        }
    }
}

/// Errors of starting or running the server.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The settings cannot work.
    #[error("{0}")]
    Config(String),
    /// Binding the listening socket failed.
    #[error("listening on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The error.
        source: std::io::Error,
    },
    /// The async runtime or the server's socket failed.
    #[error("server: {0}")]
    Io(#[from] std::io::Error),
    /// The server thread panicked (a bug).
    #[error("the server thread panicked")]
    Panicked,
}

/// The loaded map and the state every request shares.
pub struct Service {
    map: Arc<LoadedMap>,
    config: ServeConfig,
    metrics: Metrics,
    /// Admitted requests: `workers + queue` permits.
    admission: Arc<Semaphore>,
    /// Running localizations: `workers` permits.
    workers: Arc<Semaphore>,
    draining: AtomicBool,
    served: Vec<usize>,
}

impl Service {
    /// The service over `map` with `config` (workers and queue at least 1 and 0).
    pub fn new(map: Arc<LoadedMap>, config: ServeConfig) -> Result<Arc<Self>, ServeError> {
        if config.workers == 0 {
            return Err(ServeError::Config("--workers must be at least 1".into()));
        }
        if config.max_body_bytes == 0 {
            return Err(ServeError::Config(
                "--max-body-bytes must be positive".into(),
            ));
        }
        let served = map.served_blocks();
        Ok(Arc::new(Service {
            admission: Arc::new(Semaphore::new(config.workers + config.queue)),
            workers: Arc::new(Semaphore::new(config.workers)),
            metrics: Metrics::default(),
            draining: AtomicBool::new(false),
            served,
            map,
            config,
        }))
    }

    /// The metrics recorded so far.
    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// The settings.
    pub fn config(&self) -> &ServeConfig {
        &self.config
    }

    /// Stops admitting localization requests (503) and reports unhealthy, ahead of shutdown.
    pub fn drain(&self) {
        self.draining.store(true, Ordering::SeqCst);
    }
}

/// The routes: `POST /v1/localize`, `GET /healthz`, `GET /metrics`; every error answered
/// with a JSON body.
pub fn router(service: Arc<Service>) -> Router {
    let limit = service.config.max_body_bytes;
    let routes = Router::new()
        .route("/v1/localize", post(localize))
        .route("/healthz", get(healthz))
        .route("/metrics", get(metrics))
        .fallback(not_found)
        .layer(DefaultBodyLimit::max(limit))
        .with_state(service);
    // Around the finished routes, so it sees their responses as sent (a 405 with its `Allow`
    // header, which a layer on the routes themselves would see before it is added).
    Router::new()
        .fallback_service(routes)
        .layer(axum::middleware::from_fn(json_errors))
}

/// Longest error body of axum's own read back to be wrapped in JSON; a longer one is replaced
/// by the status's reason.
const MAX_PLAIN_ERROR_BYTES: usize = 4096;

/// Gives an error response without a JSON body (axum's 405 for a wrong method, or a
/// rejection's plain text) the JSON body of every other error: `status` is the HTTP reason in
/// snake case, `error` says what happened. Headers such as `Allow` are kept.
async fn json_errors(request: Request, next: Next) -> Response {
    let method = request.method().clone();
    let path = request.uri().path().to_owned();
    let response = next.run(request).await;
    let status = response.status();
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return response;
    }
    let (mut parts, body) = response.into_parts();
    let reason = status.canonical_reason().unwrap_or("error");
    let text = axum::body::to_bytes(body, MAX_PLAIN_ERROR_BYTES)
        .await
        .ok()
        .map(|b| String::from_utf8_lossy(&b).trim().to_owned())
        .filter(|t| !t.is_empty());
    let error = if status == StatusCode::METHOD_NOT_ALLOWED {
        let allowed = parts
            .headers
            .get(header::ALLOW)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_owned();
        format!("method {method} is not allowed on {path} (allowed: {allowed})")
    } else {
        text.unwrap_or_else(|| reason.to_owned())
    };
    let name: String = reason
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || *c == ' ')
        .map(|c| {
            if c == ' ' {
                '_'
            } else {
                c.to_ascii_lowercase()
            }
        })
        .collect();
    let body = json!({"status": name, "error": error}).to_string();
    parts.headers.remove(header::CONTENT_LENGTH);
    parts.headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    Response::from_parts(parts, axum::body::Body::from(body))
}

/// Serves `service` on `listener` until `shutdown` completes, then stops accepting
/// connections, refuses further localization requests with 503 and waits for those in flight.
pub async fn serve(
    listener: TcpListener,
    service: Arc<Service>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServeError> {
    let drain = service.clone();
    axum::serve(listener, router(service))
        .with_graceful_shutdown(async move {
            shutdown.await;
            drain.drain();
            tracing::info!("shutting down: finishing the requests in flight");
        })
        .await?;
    Ok(())
}

/// Completes on SIGINT (Ctrl-C) or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}

/// Runs the server on the current thread until SIGINT or SIGTERM: binds `config.listen`,
/// logs the address, serves, and returns once the requests in flight have finished.
pub fn run(map: Arc<LoadedMap>, config: ServeConfig) -> Result<(), ServeError> {
    let service = Service::new(map, config)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async move {
        let addr = service.config.listen;
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|source| ServeError::Bind { addr, source })?;
        tracing::info!(
            addr = %listener.local_addr()?,
            workers = service.config.workers,
            queue = service.config.queue,
            blocks = ?service.served,
            "listening"
        );
        serve(listener, service, shutdown_signal()).await
    })
}

/// A server on its own thread and runtime (tests, embedding): started by
/// [`ServerHandle::start`], stopped gracefully by [`ServerHandle::shutdown`] or on drop.
pub struct ServerHandle {
    addr: SocketAddr,
    service: Arc<Service>,
    stop: Option<oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<Result<(), ServeError>>>,
}

impl ServerHandle {
    /// Binds `config.listen` and serves `map` on a background thread.
    pub fn start(map: Arc<LoadedMap>, config: ServeConfig) -> Result<Self, ServeError> {
        let service = Service::new(map, config)?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?;
        let addr = service.config.listen;
        let listener = runtime
            .block_on(TcpListener::bind(addr))
            .map_err(|source| ServeError::Bind { addr, source })?;
        let addr = listener.local_addr()?;
        let (stop, stopped) = oneshot::channel::<()>();
        let s = service.clone();
        let thread = std::thread::Builder::new()
            .name("matloc-serve".into())
            .spawn(move || {
                runtime.block_on(serve(listener, s, async move {
                    let _ = stopped.await;
                }))
            })?;
        Ok(ServerHandle {
            addr,
            service,
            stop: Some(stop),
            thread: Some(thread),
        })
    }

    /// The address the server listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The shared state (metrics, settings).
    pub fn service(&self) -> &Arc<Service> {
        &self.service
    }

    /// Stops accepting, waits for the requests in flight, and joins the server thread.
    pub fn shutdown(mut self) -> Result<(), ServeError> {
        self.stop_and_join()
    }

    fn stop_and_join(&mut self) -> Result<(), ServeError> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        match self.thread.take() {
            Some(t) => t.join().map_err(|_| ServeError::Panicked)?,
            None => Ok(()),
        }
    }
}

impl Drop for ServerHandle {
    fn drop(&mut self) {
        let _ = self.stop_and_join();
    }
}

/// An error response: `{"status": ..., "error": ..., "field": ...}`, with `camera_field`
/// naming the field inside the `camera` part where one is at fault.
struct ApiError {
    status: StatusCode,
    outcome: Outcome,
    message: String,
    field: Option<&'static str>,
    camera_field: Option<&'static str>,
}

impl ApiError {
    fn bad(field: &'static str, message: impl Into<String>) -> Self {
        ApiError {
            status: StatusCode::BAD_REQUEST,
            outcome: Outcome::BadRequest,
            message: message.into(),
            field: Some(field),
            camera_field: None,
        }
    }

    /// A 400 for the `camera` part.
    fn camera(e: CameraSpecError) -> Self {
        ApiError {
            camera_field: e.field(),
            ..ApiError::bad("camera", format!("part `camera`: {e}"))
        }
    }

    fn too_large(limit: usize) -> Self {
        ApiError {
            status: StatusCode::PAYLOAD_TOO_LARGE,
            outcome: Outcome::PayloadTooLarge,
            message: format!("the request body is larger than the {limit}-byte limit"),
            field: Some("body"),
            camera_field: None,
        }
    }

    fn response(&self) -> Response {
        let mut body = json!({"status": self.outcome.name(), "error": self.message});
        if let Some(f) = self.field {
            body["field"] = json!(f);
        }
        if let Some(f) = self.camera_field {
            body["camera_field"] = json!(f);
        }
        let mut r = (self.status, axum::Json(body)).into_response();
        if self.status == StatusCode::SERVICE_UNAVAILABLE {
            r.headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from_static("1"));
        }
        r
    }
}

async fn not_found() -> Response {
    (
        StatusCode::NOT_FOUND,
        axum::Json(json!({
            "status": "not_found",
            "error": "no such route (POST /v1/localize, GET /healthz, GET /metrics)"
        })),
    )
        .into_response()
}

async fn healthz(State(s): State<Arc<Service>>) -> Response {
    let (in_flight, queued) = s.metrics.gauges();
    let draining = s.draining.load(Ordering::SeqCst);
    let body = json!({
        "status": if draining { "shutting_down" } else { "ok" },
        "blocks": s.served,
        "workers": s.config.workers,
        "queue": s.config.queue,
        "in_flight": in_flight,
        "queued": queued,
    });
    let code = if draining {
        StatusCode::SERVICE_UNAVAILABLE
    } else {
        StatusCode::OK
    };
    (code, axum::Json(body)).into_response()
}

async fn metrics(State(s): State<Arc<Service>>) -> Response {
    (
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
        )],
        s.metrics.render(s.config.workers, s.config.queue),
    )
        .into_response()
}

async fn localize(State(s): State<Arc<Service>>, request: Request) -> Response {
    let start = Instant::now();
    let (outcome, response) = match handle(&s, request, start).await {
        Ok((outcome, body)) => (outcome, (StatusCode::OK, axum::Json(body)).into_response()),
        Err(e) => {
            if e.status.is_server_error() {
                tracing::warn!(status = e.status.as_u16(), "{}", e.message);
            } else {
                tracing::debug!(status = e.status.as_u16(), "{}", e.message);
            }
            (e.outcome, e.response())
        }
    };
    let elapsed = start.elapsed();
    s.metrics.observe(outcome, elapsed);
    let mut response = response;
    if let Ok(v) = HeaderValue::from_str(&format!("total;dur={:.3}", elapsed.as_secs_f64() * 1e3)) {
        response.headers_mut().insert("server-timing", v);
    }
    response
}

/// The parts of a localization request.
struct Parts {
    name: String,
    image: axum::body::Bytes,
    camera: Camera,
}

async fn handle(
    s: &Arc<Service>,
    request: Request,
    start: Instant,
) -> Result<(Outcome, Value), ApiError> {
    if s.draining.load(Ordering::SeqCst) {
        return Err(ApiError {
            status: StatusCode::SERVICE_UNAVAILABLE,
            outcome: Outcome::ShuttingDown,
            message: "the server is shutting down".into(),
            field: None,
            camera_field: None,
        });
    }
    let (head, mut body) = request.into_parts();
    let limit = s.config.max_body_bytes;
    let declared = head
        .headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|n| n > limit as u64) {
        // A client that declared a body within the discard allowance is still sending it.
        if declared.is_some_and(|n| n <= discard_allowance(limit)) {
            discard(&mut body, discard_allowance(limit)).await;
        }
        return Err(ApiError::too_large(limit));
    }
    let content_type = head
        .headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_owned();
    if !content_type
        .to_ascii_lowercase()
        .starts_with("multipart/form-data")
    {
        discard(&mut body, discard_allowance(limit)).await;
        return Err(ApiError {
            status: StatusCode::UNSUPPORTED_MEDIA_TYPE,
            outcome: Outcome::BadRequest,
            message: format!(
                "content type {:?}: expected multipart/form-data with parts `image` (PNG/JPEG) and `camera` (JSON)",
                content_type
            ),
            field: Some("content-type"),
            camera_field: None,
        });
    }
    let Ok(admitted) = s.admission.clone().try_acquire_owned() else {
        discard(&mut body, discard_allowance(limit)).await;
        return Err(ApiError {
            status: StatusCode::SERVICE_UNAVAILABLE,
            outcome: Outcome::Overloaded,
            message: format!(
                "overloaded: {} workers busy and {} queued; retry later",
                s.config.workers, s.config.queue
            ),
            field: None,
            camera_field: None,
        });
    };
    let timeout = s.config.timeout;
    let work = async {
        let queued = s.metrics.queued();
        let bytes = read_body(body, limit).await?;
        let parts = read_parts(Request::from_parts(head, axum::body::Body::from(bytes))).await?;
        let worker = s
            .workers
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| ApiError {
                status: StatusCode::SERVICE_UNAVAILABLE,
                outcome: Outcome::ShuttingDown,
                message: "the server is shutting down".into(),
                field: None,
                camera_field: None,
            })?;
        drop(queued);
        let queue_s = start.elapsed().as_secs_f64();
        let service = s.clone();
        // The permits move into the blocking task: a localization still running after the
        // timeout keeps its worker (and its place in the queue) until it ends.
        let job = tokio::task::spawn_blocking(move || {
            let _permits = (admitted, worker);
            let _running = service.metrics.in_flight();
            localize_parts(&service, parts, start, queue_s)
        });
        job.await.map_err(|_| ApiError {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            outcome: Outcome::Error,
            message: "the localization task failed".into(),
            field: None,
            camera_field: None,
        })?
    };
    match tokio::time::timeout(timeout, work).await {
        Ok(r) => r,
        Err(_) => Err(ApiError {
            status: StatusCode::GATEWAY_TIMEOUT,
            outcome: Outcome::Timeout,
            message: format!(
                "no answer within the {:.1} s request timeout",
                timeout.as_secs_f64()
            ),
            field: None,
            camera_field: None,
        }),
    }
}

/// How much of a refused request's body is read and discarded before the answer: four times
/// the body limit, at least 1 MiB.
fn discard_allowance(limit: usize) -> u64 {
    (4 * limit as u64).max(1 << 20)
}

/// The longest wait for the rest of a refused request's body.
const DISCARD_WAIT: Duration = Duration::from_secs(2);

/// Reads and discards what is left of a request body, at most `allowance` bytes and
/// [`DISCARD_WAIT`], so that a client still sending it reads the error response instead of
/// failing its write on a closed connection.
async fn discard(body: &mut axum::body::Body, allowance: u64) {
    use http_body_util::BodyExt;
    let drain = async {
        let mut seen = 0u64;
        while let Some(Ok(frame)) = body.frame().await {
            if let Some(data) = frame.data_ref() {
                seen += data.len() as u64;
                if seen > allowance {
                    break;
                }
            }
        }
    };
    let _ = tokio::time::timeout(DISCARD_WAIT, drain).await;
}

/// Reads the whole body, at most `limit` bytes; a longer one (chunked, or longer than its
/// declared length) is discarded up to the allowance and answered 413.
async fn read_body(
    mut body: axum::body::Body,
    limit: usize,
) -> Result<axum::body::Bytes, ApiError> {
    use http_body_util::BodyExt;
    let mut buf = Vec::new();
    while let Some(frame) = body.frame().await {
        let frame = frame.map_err(|e| ApiError::bad("body", format!("reading the body: {e}")))?;
        if let Some(data) = frame.data_ref() {
            if buf.len() + data.len() > limit {
                discard(&mut body, discard_allowance(limit)).await;
                return Err(ApiError::too_large(limit));
            }
            buf.extend_from_slice(data);
        }
    }
    Ok(buf.into())
}

/// Parses the multipart body (already read in full): `image` (required), `camera`
/// (required, JSON) and `name` (optional, echoed in the record).
async fn read_parts(request: Request) -> Result<Parts, ApiError> {
    let multipart_error = |field: &'static str, e: axum::extract::multipart::MultipartError| {
        ApiError::bad(field, format!("part `{field}`: {}", e.body_text()))
    };
    let mut multipart = Multipart::from_request(request, &())
        .await
        .map_err(|e| ApiError {
            status: StatusCode::BAD_REQUEST,
            outcome: Outcome::BadRequest,
            message: format!("multipart body: {}", e.body_text()),
            field: Some("body"),
            camera_field: None,
        })?;
    let (mut name, mut image, mut camera) = (None, None, None);
    loop {
        let field = match multipart.next_field().await {
            Ok(Some(f)) => f,
            Ok(None) => break,
            Err(e) => return Err(multipart_error("body", e)),
        };
        match field.name().unwrap_or("") {
            "image" => {
                let bytes = field
                    .bytes()
                    .await
                    .map_err(|e| multipart_error("image", e))?;
                image = Some(bytes);
            }
            "camera" => {
                let text = field
                    .text()
                    .await
                    .map_err(|e| multipart_error("camera", e))?;
                let parsed = parse_camera_json(&text).map_err(ApiError::camera)?;
                check_plausible(&parsed).map_err(ApiError::camera)?;
                camera = Some(parsed);
            }
            "name" => {
                let text = field.text().await.map_err(|e| multipart_error("name", e))?;
                name = Some(text);
            }
            other => {
                return Err(ApiError::bad(
                    "body",
                    format!("unknown part `{other}` (expected `image`, `camera`, `name`)"),
                ));
            }
        }
    }
    let image = image.ok_or_else(|| ApiError::bad("image", "missing part `image`"))?;
    if image.is_empty() {
        return Err(ApiError::bad("image", "part `image` is empty"));
    }
    let camera = camera.ok_or_else(|| ApiError::bad("camera", "missing part `camera`"))?;
    let name = name.unwrap_or_else(|| "query".into());
    // The image's size from its header: a camera it neither matches nor rescales to is
    // answered now. An unreadable header is left to the decoder, which names the problem.
    if let Some((w, h)) = image_dimensions(&image) {
        fit_to_image(camera, w, h, &name)
            .map_err(|e| ApiError::bad("camera", format!("part `camera`: {e}")))?;
    }
    Ok(Parts {
        name,
        image,
        camera,
    })
}

/// Decodes, brings the query to the map's resolution, localizes (on a blocking thread) and
/// makes the response record.
fn localize_parts(
    s: &Service,
    parts: Parts,
    start: Instant,
    queue_s: f64,
) -> Result<(Outcome, Value), ApiError> {
    let t = Instant::now();
    let image = decode_rgb(&parts.image, s.config.decode)
        .map_err(|e| ApiError::bad("image", format!("part `image`: {e}")))?;
    drop(parts.image);
    let (image, camera) =
        to_map_resolution(image, parts.camera, s.map.camera().as_ref(), &parts.name)
            .map_err(|e| ApiError::bad("camera", format!("part `camera`: {e}")))?;
    let decode_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let result = localize_with(
        &s.map,
        s.config.method.as_ref(),
        &parts.name,
        &image,
        &camera,
        &MethodOptions::default(),
    )
    .map_err(|e| match e {
        // The camera as brought to the map's resolution (checked as given while parsing).
        PipelineError::ImplausibleCamera(p) => ApiError::camera(CameraSpecError::Implausible(p)),
        e => ApiError {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            outcome: Outcome::Error,
            message: format!("localizing {}: {e}", parts.name),
            field: None,
            camera_field: None,
        },
    })?;
    let localize_s = t.elapsed().as_secs_f64();
    let outside = result
        .hypotheses
        .first()
        .map(|h| h.block)
        .filter(|&b| !s.map.serves(b));
    let outcome = match (result.localized, outside) {
        (true, _) => Outcome::Localized,
        (false, Some(_)) => Outcome::OutsideBlocks,
        (false, None) => Outcome::Refused,
    };
    let mut record = localization_record(&result, "data", &|p| *p, None).map_err(|e| ApiError {
        status: StatusCode::INTERNAL_SERVER_ERROR,
        outcome: Outcome::Error,
        message: format!("writing the record: {e}"),
        field: None,
        camera_field: None,
    })?;
    if let Value::Object(obj) = &mut record {
        obj.insert("status".into(), json!(outcome.name()));
        if let Some(b) = outside {
            obj.insert("block".into(), json!(b));
            obj.insert("served_blocks".into(), json!(s.served));
        }
        obj.insert(
            "server_seconds".into(),
            json!({
                "queue": queue_s,
                "decode": decode_s,
                "localize": localize_s,
                "total": start.elapsed().as_secs_f64(),
            }),
        );
    }
    tracing::debug!(
        query = %parts.name,
        status = outcome.name(),
        seconds = start.elapsed().as_secs_f64(),
        "query answered"
    );
    Ok((outcome, record))
}
