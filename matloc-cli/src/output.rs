//! Command results on stdout. A reader that closes the pipe early (`matloc dataset info D |
//! head -1`) ends the command quietly with success, as `cat` or `grep` would; any other write
//! error (e.g. a full disk) is an error that says stdout could not be written.

use std::io::{ErrorKind, Write};

/// The reader of stdout went away: the command stops, successfully and without a message.
#[derive(Debug, thiserror::Error)]
#[error("stdout was closed by its reader")]
pub struct StdoutClosed;

/// Writes formatted text to stdout and flushes it.
pub fn write(args: std::fmt::Arguments<'_>) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    match out.write_fmt(args).and_then(|()| out.flush()) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == ErrorKind::BrokenPipe => Err(StdoutClosed.into()),
        Err(e) => Err(anyhow::Error::new(e).context("writing to stdout")),
    }
}

/// `err` and its causes joined by `: ` (as `{:#}` prints them), a cause whose text the message
/// before it already ends with left out ([`matloc_pipeline::query::error_chain`]).
pub fn error_chain(err: &anyhow::Error) -> String {
    matloc_pipeline::query::error_chain(err.as_ref())
}

/// Whether `err` (anywhere in its chain) is a closed stdout.
pub fn is_closed_stdout(err: &anyhow::Error) -> bool {
    err.chain().any(|e| {
        e.is::<StdoutClosed>()
            || e.downcast_ref::<std::io::Error>()
                .is_some_and(|io| io.kind() == ErrorKind::BrokenPipe)
    })
}

/// `println!` that returns `anyhow::Result<()>` instead of panicking on a closed or full stdout.
macro_rules! outln {
    () => {
        $crate::output::write(format_args!("\n"))
    };
    ($($arg:tt)*) => {
        $crate::output::write(format_args!("{}\n", format_args!($($arg)*)))
    };
}

/// `print!` that returns `anyhow::Result<()>` instead of panicking on a closed or full stdout.
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::output::write(format_args!($($arg)*))
    };
}

/// Writes a line to stderr, dropping it when stderr cannot take it (closed, or a full
/// device): the exit status still tells the caller, where `eprintln!` would panic.
pub fn write_err(args: std::fmt::Arguments<'_>) {
    use std::io::Write as _;
    let _ = writeln!(std::io::stderr().lock(), "{args}");
}

/// `eprintln!` that never panics (see [`write_err`]).
macro_rules! errln {
    ($($arg:tt)*) => {
        $crate::output::write_err(format_args!($($arg)*))
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cause_already_in_the_message_is_not_repeated() {
        #[derive(Debug, thiserror::Error)]
        #[error("I/O error on /m/x: {source}")]
        struct Wrapped {
            source: std::io::Error,
        }
        let io = std::io::Error::other("No space left on device");
        let err = anyhow::Error::new(Wrapped { source: io }).context("writing the map");
        assert_eq!(
            super::error_chain(&err),
            "writing the map: I/O error on /m/x: No space left on device"
        );
        let plain = anyhow::anyhow!("inner").context("outer");
        assert_eq!(super::error_chain(&plain), "outer: inner");
    }

    #[test]
    fn a_broken_pipe_anywhere_in_the_chain_is_a_closed_stdout() {
        let e: anyhow::Error = StdoutClosed.into();
        assert!(is_closed_stdout(&e.context("printing the table")));
        let io = std::io::Error::from(ErrorKind::BrokenPipe);
        assert!(is_closed_stdout(&anyhow::Error::new(io)));
        let full = std::io::Error::from(ErrorKind::StorageFull);
        assert!(!is_closed_stdout(&anyhow::Error::new(full)));
    }
}
