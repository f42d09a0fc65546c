//! `matloc serve`: loads a map once and answers localization requests over HTTP (see
//! `matloc_serve` for the protocol).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::Args;
use matloc_pipeline::LoadedMap;
use matloc_pipeline::methods::Method;
use matloc_serve::ServeConfig;

/// Arguments of `matloc serve`.
#[derive(Args)]
pub struct ServeArgs {
    /// Map directory (from `matloc map build`).
    #[arg(long)]
    map: PathBuf,
    /// Address and port to listen on (port 0: any free port, logged at start).
    #[arg(long, default_value = "127.0.0.1:8080")]
    listen: SocketAddr,
    /// Serve only these blocks (comma-separated ids): only their models are loaded, and a
    /// query whose best place hypothesis is another block is answered `outside_blocks`.
    #[arg(long, value_delimiter = ',', value_name = "IDS")]
    blocks: Option<Vec<usize>>,
    /// Localizations run at once (default: one per core).
    #[arg(long)]
    workers: Option<usize>,
    /// Requests admitted beyond the running ones; more get 503 at once (default: 2 × workers).
    #[arg(long)]
    queue: Option<usize>,
    /// Largest request body in bytes (413 beyond).
    #[arg(long, default_value_t = 16 << 20)]
    max_body_bytes: usize,
    /// Seconds from admission to answer (504 beyond).
    #[arg(long, default_value_t = 30.0)]
    timeout_s: f64,
    /// The localizer every request runs (as `localize --method`).
    #[arg(long, default_value_t = Method::DEFAULT)]
    method: Method,
}

/// Runs `matloc serve` until SIGINT or SIGTERM.
pub fn run(args: &ServeArgs) -> Result<()> {
    if !(args.timeout_s.is_finite() && args.timeout_s > 0.0) {
        bail!("--timeout-s must be a positive number of seconds");
    }
    let defaults = ServeConfig::default();
    let workers = args.workers.unwrap_or(defaults.workers);
    let config = ServeConfig {
        listen: args.listen,
        workers,
        queue: args.queue.unwrap_or(2 * workers),
        max_body_bytes: args.max_body_bytes,
        timeout: Duration::from_secs_f64(args.timeout_s),
        method: std::sync::Arc::new(args.method),
        ..defaults
    };
    if config.workers == 0 {
        bail!("--workers must be at least 1");
    }
    let map = LoadedMap::open_blocks(&args.map, args.blocks.as_deref())
        .with_context(|| format!("opening map {}", args.map.display()))?;
    tracing::info!(
        map = %args.map.display(),
        blocks = ?map.served_blocks(),
        "map loaded"
    );
    matloc_serve::run(Arc::new(map), config)?;
    tracing::info!("stopped");
    Ok(())
}
