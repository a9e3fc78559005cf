//! What is measured over a window beside the client's own view: the cores
//! the server, the load generator and everything else kept busy (from
//! `/proc`), the server's own handler latency (from its `/metrics`) and,
//! in open loop, the pacing thread's lag.

use std::time::Duration;

use serde_json::{Value, json};

use crate::http::HttpTarget;
use crate::proc::{CpuUse, cpu_now, cpu_use};
use crate::prometheus::{histogram_quantile, route_histogram};
use crate::stats::{Phase, micros};

/// What was measured beside the client's own view over a window.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Window {
    pub(crate) cpu: CpuUse,
    /// Upper bounds of the server's own p50 and p99 of the route (handler
    /// time as its `/metrics` histogram buckets record it), in seconds.
    pub(crate) handler: Option<(f64, f64)>,
    /// Open loop: how late the pacing thread released requests (p99, max).
    pub(crate) pacer_lag: Option<(Duration, Duration)>,
}

impl Window {
    /// The window as JSON, with the server's CPU µs per request at `rate`.
    pub(crate) fn json(&self, rate: f64) -> Value {
        json!({
            "cpu_server": self.cpu.server,
            "cpu_loadgen": self.cpu.loadgen,
            "cpu_other": self.cpu.other,
            "server_cpu_us_per_request": server_us(self.cpu, rate),
            "handler_p50_s": self.handler.and_then(|h| finite(h.0)),
            "handler_p99_s": self.handler.and_then(|h| finite(h.1)),
            "pacer_lag_p99_us": self.pacer_lag.map(|l| micros(l.0)),
            "pacer_lag_max_us": self.pacer_lag.map(|l| micros(l.1)),
        })
    }
}

/// JSON has no infinity: a bound past the last bucket is `null`.
fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// Server CPU time per request, in µs.
pub(crate) fn server_us(cpu: CpuUse, rate: f64) -> Option<f64> {
    cpu.server
        .filter(|_| rate > 0.0)
        .map(|cores| cores / rate * 1e6)
}

/// Samples CPU time, and the server's latency histogram of `route` if
/// given, at the start and end of the window.
pub(crate) async fn measure_window(
    phase: Phase,
    server_pid: Option<u32>,
    route: Option<(&HttpTarget, &str)>,
) -> Window {
    let scrape = async || match route {
        Some((http, route)) => route_histogram(http, route).await.ok(),
        None => None,
    };
    tokio::time::sleep_until(phase.measure_from.into()).await;
    let (cpu_before, hist_before) = (cpu_now(server_pid), scrape().await);
    tokio::time::sleep_until(phase.end.into()).await;
    let (cpu_after, hist_after) = (cpu_now(server_pid), scrape().await);
    let handler = hist_before.zip(hist_after).and_then(|(a, b)| {
        Some((
            histogram_quantile(&a, &b, 0.50)?,
            histogram_quantile(&a, &b, 0.99)?,
        ))
    });
    Window {
        cpu: cpu_use(cpu_before, cpu_after, phase.window_secs()),
        handler,
        pacer_lag: None,
    }
}
