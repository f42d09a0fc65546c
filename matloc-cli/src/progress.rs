//! Progress bars shared by every long-running command.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// A bar with count, rate and ETA; hidden when stderr is not a terminal or `quiet` is set, so
/// logs and CI output stay clean.
pub fn bar(total: u64, message: &str, quiet: bool) -> ProgressBar {
    let pb = ProgressBar::new(total);
    if quiet {
        pb.set_draw_target(ProgressDrawTarget::hidden());
    }
    pb.set_style(
        ProgressStyle::with_template(
            "{msg:>12} [{elapsed_precise}] {wide_bar} {pos}/{len} ({per_sec}, ETA {eta})",
        )
        .expect("static template is valid"),
    );
    pb.set_message(message.to_string());
    pb
}
