//! Logging and metrics set-up, and the panic hook.

use std::collections::HashSet;
use std::io::IsTerminal;
use std::sync::OnceLock;

use parking_lot::Mutex;

use metrics_exporter_prometheus::{PrometheusBuilder, PrometheusHandle};

use clap::ValueEnum;
use serde::Serialize;

/// Log output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line.
    Json,
}

/// Installs the global tracing subscriber (stderr; `RUST_LOG` overrides `default_level`).
pub fn init_logging(format: LogFormat, default_level: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level));
    // Colours only on a terminal: a log file or a pipe gets plain text.
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr);
    // A second initialisation (tests) keeps the first subscriber.
    let _ = match format {
        LogFormat::Json => builder.json().try_init(),
        LogFormat::Text => builder.try_init(),
    };
}

/// Latency buckets in seconds, 50 µs to 5 s.
const BUCKETS: [f64; 14] = [
    5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 5e-2, 0.1, 0.5, 1.0, 5.0,
];

/// The process-wide Prometheus recorder (installed once; later calls share it).
pub fn prometheus() -> Option<PrometheusHandle> {
    static HANDLE: OnceLock<Option<PrometheusHandle>> = OnceLock::new();
    HANDLE
        .get_or_init(|| {
            let builder = PrometheusBuilder::new().set_buckets(&BUCKETS).ok()?;
            match builder.install_recorder() {
                Ok(handle) => Some(handle),
                Err(e) => {
                    tracing::error!(error = %e, "metrics recorder not installed");
                    None
                }
            }
        })
        .clone()
}

/// The places in the code that have panicked, each logged once.
#[derive(Debug, Default)]
pub struct PanicSites(Mutex<HashSet<String>>);

impl PanicSites {
    /// Records a panic at `site`; true the first time.
    pub fn first(&self, site: &str) -> bool {
        let mut seen = self.0.lock();
        !seen.contains(site) && seen.insert(site.to_owned())
    }
}

/// Installs the process's panic hook in place of the default one (which
/// writes every panic to stderr, so a request that panics on every call
/// would write one per request): every panic counts in
/// `mcapi_panics_total{site}` (its `file:line`), and only the first at each
/// site is logged, at error level, with its message and a backtrace. What
/// the request gets is the caller's business (500 / INTERNAL
/// `internal_panic`, docs/errors.md).
pub fn install_panic_hook() {
    static SITES: OnceLock<PanicSites> = OnceLock::new();
    std::panic::set_hook(Box::new(|info| {
        let site = info.location().map_or_else(
            || "unknown".to_owned(),
            |l| format!("{}:{}", l.file(), l.line()),
        );
        metrics::counter!("mcapi_panics_total", "site" => site.clone()).increment(1);
        if SITES.get_or_init(PanicSites::default).first(&site) {
            let payload = info.payload();
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_owned())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            let backtrace = std::backtrace::Backtrace::force_capture();
            tracing::error!(
                %site,
                panic = %message,
                %backtrace,
                "a panic, logged once for its place in the code (mcapi_panics_total counts each)"
            );
        }
    }));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_panic_site_is_logged_once() {
        let sites = PanicSites::default();
        assert!(sites.first("src/a.rs:1"));
        assert!(
            !sites.first("src/a.rs:1"),
            "the second panic there only counts"
        );
        assert!(sites.first("src/a.rs:2"));
    }
}
