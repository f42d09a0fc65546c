//! Log output through `tracing`: stderr (level from `-v`, `RUST_LOG`, or whether stderr is a
//! terminal) and optionally a log file, so a long build run under a batch scheduler shows its
//! progress in a file.

use std::fs::OpenOptions;
use std::io::IsTerminal;
use std::path::Path;

use anyhow::{Context, Result};
use tracing_subscriber::filter::{EnvFilter, LevelFilter};
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::{Layer, fmt};

/// The stderr level for `-v` given `count` times: a terminal shows warnings (its progress
/// bars show progress), anything else (a pipe, a batch job's log) shows info.
fn stderr_level(count: u8, terminal: bool) -> LevelFilter {
    match count {
        0 if terminal => LevelFilter::WARN,
        0 | 1 => LevelFilter::INFO,
        2 => LevelFilter::DEBUG,
        _ => LevelFilter::TRACE,
    }
}

/// The filter of one output: `RUST_LOG` when set, else `level` for everything.
fn filter(level: LevelFilter) -> EnvFilter {
    EnvFilter::builder()
        .with_default_directive(level.into())
        .from_env_lossy()
}

/// Installs the global subscriber.
pub fn init(verbose: u8, log_file: Option<&Path>) -> Result<()> {
    let terminal = std::io::stderr().is_terminal();
    let stderr = fmt::layer()
        .with_writer(std::io::stderr)
        .with_ansi(terminal)
        .with_target(false)
        .with_filter(filter(stderr_level(verbose, terminal)));
    let file = match log_file {
        Some(path) => {
            let f = OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)
                .with_context(|| format!("opening the log file {}", path.display()))?;
            let level = stderr_level(verbose.max(1), false);
            Some(
                fmt::layer()
                    .with_writer(std::sync::Mutex::new(f))
                    .with_ansi(false)
                    .with_filter(filter(level)),
            )
        }
        None => None,
    };
    tracing_subscriber::registry()
        .with(stderr)
        .with(file)
        .try_init()
        .context("installing the logger")?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn verbosity_levels() {
        assert_eq!(stderr_level(0, true), LevelFilter::WARN);
        assert_eq!(stderr_level(0, false), LevelFilter::INFO);
        assert_eq!(stderr_level(1, true), LevelFilter::INFO);
        assert_eq!(stderr_level(2, true), LevelFilter::DEBUG);
        assert_eq!(stderr_level(5, false), LevelFilter::TRACE);
    }
}
