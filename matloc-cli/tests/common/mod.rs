//! Helpers shared by the CLI integration tests.

use std::process::{Command, Output};

/// Runs the `matloc` binary with `args` (progress bars off).
pub fn matloc(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_matloc"))
        .args(args)
        .arg("--quiet")
        .output()
        .expect("binary runs")
}

/// stdout and stderr of a run, for assertion messages.
pub fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}
