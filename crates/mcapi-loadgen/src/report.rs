//! The cells of the Markdown report: counts with thousands separators,
//! latencies in µs or ms, CPU as cores and as server µs per request, the
//! server's handler latency as bucket bounds, and memory in MiB. Each
//! scenario prints its own tables with them (and returns its part of the
//! JSON document).

use std::time::Duration;

use crate::proc::CpuUse;
use crate::window::server_us;

pub(crate) fn thousands(x: f64) -> String {
    let digits = format!("{:.0}", x.max(0.0));
    let mut out = String::with_capacity(digits.len() + digits.len() / 3);
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i) % 3 == 0 {
            out.push(',');
        }
        out.push(c);
    }
    out
}

pub(crate) fn latency(d: Duration) -> String {
    let us = d.as_secs_f64() * 1e6;
    if us < 10_000.0 {
        format!("{us:.0} µs")
    } else {
        format!("{:.1} ms", us / 1000.0)
    }
}

/// `server / loadgen / other` in cores.
pub(crate) fn cores(c: CpuUse) -> String {
    let one = |c: Option<f64>| c.map_or_else(|| "—".to_string(), |c| format!("{c:.2}"));
    format!("{} / {} / {}", one(c.server), one(c.loadgen), one(c.other))
}

/// Server CPU time per request, in µs.
pub(crate) fn per_request(cpu: CpuUse, rate: f64) -> String {
    server_us(cpu, rate).map_or_else(|| "—".to_string(), |us| format!("{us:.1}"))
}

/// `≤ p50 / ≤ p99` from histogram bucket bounds.
pub(crate) fn handler(h: Option<(f64, f64)>) -> String {
    let bound = |secs: f64| {
        if secs.is_finite() {
            format!("≤ {}", latency(Duration::from_secs_f64(secs)))
        } else {
            "> 5 s".to_string()
        }
    };
    h.map_or_else(
        || "—".to_string(),
        |(p50, p99)| format!("{} / {}", bound(p50), bound(p99)),
    )
}

pub(crate) fn mib(bytes: u64) -> String {
    format!("{:.0} MiB", bytes as f64 / (1024.0 * 1024.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formatting() {
        assert_eq!(thousands(1_234_567.4), "1,234,567");
        assert_eq!(thousands(999.0), "999");
        assert_eq!(latency(Duration::from_micros(1500)), "1500 µs");
        assert_eq!(latency(Duration::from_millis(25)), "25.0 ms");
        assert_eq!(handler(Some((0.001, 0.01))), "≤ 1000 µs / ≤ 10.0 ms");
    }
}
