//! Latency statistics: a measurement's [`Phase`] (a warm-up, then the
//! window that counts), what the workers saw during it ([`Tally`]), and its
//! throughput and exact nearest-rank percentiles ([`Summary`]).

use std::time::{Duration, Instant};

use serde_json::{Value, json};

use crate::args::LoadgenArgs;

/// A warm-up followed by a measurement window.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Phase {
    pub(crate) start: Instant,
    pub(crate) measure_from: Instant,
    pub(crate) end: Instant,
}

impl Phase {
    pub(crate) fn new(args: &LoadgenArgs) -> Self {
        let start = Instant::now();
        let measure_from = start + Duration::from_secs(args.warmup_secs);
        Self {
            start,
            measure_from,
            end: measure_from + Duration::from_secs(args.duration_secs),
        }
    }

    pub(crate) fn window_secs(&self) -> f64 {
        (self.end - self.measure_from).as_secs_f64()
    }

    pub(crate) fn over(&self) -> bool {
        Instant::now() >= self.end
    }
}

/// What one worker saw during a phase.
#[derive(Debug, Default)]
pub(crate) struct Tally {
    /// Latencies (ns) of the successful requests completed in the window.
    latencies: Vec<u64>,
    /// Failed requests over the whole phase.
    errors: u64,
    first_error: Option<String>,
}

impl Tally {
    pub(crate) fn record(
        &mut self,
        phase: &Phase,
        issued: Instant,
        done: Instant,
        outcome: Result<(), String>,
    ) {
        match outcome {
            Ok(()) => {
                if done >= phase.measure_from && done <= phase.end {
                    self.latencies
                        .push(u64::try_from((done - issued).as_nanos()).unwrap_or(u64::MAX));
                }
            }
            Err(e) => {
                self.errors += 1;
                self.first_error.get_or_insert(e);
            }
        }
    }

    pub(crate) fn merge(&mut self, other: Self) {
        self.latencies.extend(other.latencies);
        self.errors += other.errors;
        if self.first_error.is_none() {
            self.first_error = other.first_error;
        }
    }

    pub(crate) fn summary(mut self, phase: &Phase) -> Summary {
        self.latencies.sort_unstable();
        let pct = |p: f64| -> Duration {
            if self.latencies.is_empty() {
                return Duration::ZERO;
            }
            // Nearest rank.
            let rank = (p * self.latencies.len() as f64).ceil() as usize;
            Duration::from_nanos(self.latencies[rank.clamp(1, self.latencies.len()) - 1])
        };
        Summary {
            rate: self.latencies.len() as f64 / phase.window_secs(),
            p50: pct(0.50),
            p99: pct(0.99),
            max: pct(1.0),
            errors: self.errors,
            first_error: self.first_error,
        }
    }
}

/// Throughput and latency of one measurement.
#[derive(Debug, Clone)]
pub(crate) struct Summary {
    /// Successful requests per second in the window.
    pub(crate) rate: f64,
    pub(crate) p50: Duration,
    pub(crate) p99: Duration,
    pub(crate) max: Duration,
    pub(crate) errors: u64,
    pub(crate) first_error: Option<String>,
}

impl Summary {
    /// The summary as JSON (latencies in µs).
    pub(crate) fn json(&self) -> Value {
        json!({
            "rate": self.rate,
            "p50_us": micros(self.p50),
            "p99_us": micros(self.p99),
            "max_us": micros(self.max),
            "errors": self.errors,
            "first_error": self.first_error,
        })
    }
}

pub(crate) fn micros(d: Duration) -> f64 {
    d.as_secs_f64() * 1e6
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_are_nearest_rank() {
        let start = Instant::now();
        let phase = Phase {
            start,
            measure_from: start,
            end: start + Duration::from_secs(1),
        };
        let tally = Tally {
            latencies: (1..=100).rev().map(|i| i * 1000).collect(),
            ..Tally::default()
        };
        let s = tally.summary(&phase);
        assert_eq!(s.p50, Duration::from_micros(50));
        assert_eq!(s.p99, Duration::from_micros(99));
        assert_eq!(s.max, Duration::from_micros(100));
        assert!((s.rate - 100.0).abs() < 1e-9);
    }
}
