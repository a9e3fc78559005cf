//! The operator tool's log: plain text on stderr at `info` (or `RUST_LOG`),
//! coloured on a terminal only, as `mcapi serve`'s text format.

use std::io::IsTerminal;

/// Starts logging to stderr; a second call keeps the first subscriber.
pub fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr)
        .try_init();
}
