//! The memory of large responses, bounded in total: value tables and
//! history are estimated before they are built (each under
//! `--max-response-bytes`), and every response holds its estimate from a
//! shared budget (`--max-response-bytes-total`) until it is sent. A
//! response that does not fit while others hold the budget is refused at
//! once with 503 `responses_busy` and `Retry-After`, as a full creation
//! queue is, instead of taking the server's memory with it.

use std::sync::Arc;

use tokio::sync::{OwnedSemaphorePermit, Semaphore, TryAcquireError};

use super::error::ServiceError;

/// The budget is kept in KiB, so any byte total fits a semaphore's count
/// and one permit count fits the `u32` it is taken in.
const UNIT: usize = 1024;

/// Seconds a refused caller is told to wait before it asks again.
pub const RETRY_AFTER_SECS: u64 = 1;

/// The budget shared by every response of one server.
#[derive(Debug, Clone)]
pub struct ResponseBudget {
    units: Arc<Semaphore>,
    total: usize,
}

/// A response's share of the budget, given back when it is dropped.
#[derive(Debug)]
pub struct ResponsePermit {
    _units: OwnedSemaphorePermit,
}

/// A value built under the budget, with the permit its response holds
/// until it is sent.
#[derive(Debug)]
pub struct Budgeted<T> {
    /// The value.
    pub value: T,
    /// Its estimated size once encoded (JSON), in bytes.
    pub estimate: usize,
    /// Dropped when the response is sent (REST: after its last chunk is
    /// taken by the connection; gRPC: when the message is handed to the
    /// transport).
    pub permit: ResponsePermit,
}

/// What a response of `estimate` bytes takes from the budget: its tables
/// and their encoding exist together while it is encoded, and the tables
/// take about a third of the JSON's bytes (8-byte numbers against about
/// 24 characters) plus their vectors' headers; twice the estimate covers
/// both (measured, BENCHMARKS.md §5).
pub fn charge(estimate: usize) -> usize {
    estimate.saturating_mul(2)
}

impl ResponseBudget {
    /// A budget of `total` bytes.
    pub fn new(total: usize) -> Self {
        let units = (total / UNIT).clamp(1, Semaphore::MAX_PERMITS);
        Self {
            units: Arc::new(Semaphore::new(units)),
            total,
        }
    }

    /// Takes `bytes` (rounded up to the next KiB, at least one) from the
    /// budget, or refuses with [`ServiceError::ResponsesBusy`] when the
    /// responses in flight hold too much of it for this one now.
    pub fn reserve(&self, bytes: usize) -> Result<ResponsePermit, ServiceError> {
        let wanted = bytes.div_ceil(UNIT).max(1);
        // A single response never needs more than the whole budget (the
        // configuration keeps the budget at least one maximal response).
        let units = u32::try_from(wanted.min(self.units_total())).unwrap_or(u32::MAX);
        match Arc::clone(&self.units).try_acquire_many_owned(units) {
            Ok(units) => Ok(ResponsePermit { _units: units }),
            Err(TryAcquireError::NoPermits) => Err(ServiceError::ResponsesBusy(format!(
                "responses in flight hold the server's response memory (--max-response-bytes-total, {} bytes); this one needs about {bytes} bytes: retry after {RETRY_AFTER_SECS} s, or ask for less (fewer tables, a smaller history `limit`)",
                self.total
            ))),
            Err(TryAcquireError::Closed) => {
                Err(ServiceError::Unavailable("the server is stopping".into()))
            }
        }
    }

    /// Bytes held by responses in flight now.
    pub fn held_bytes(&self) -> usize {
        (self.units_total() - self.units.available_permits()) * UNIT
    }

    fn units_total(&self) -> usize {
        (self.total / UNIT).clamp(1, Semaphore::MAX_PERMITS)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn responses_share_the_budget_and_give_it_back_when_dropped() {
        let budget = ResponseBudget::new(10 * UNIT);
        let a = budget.reserve(6 * UNIT).expect("fits");
        assert_eq!(budget.held_bytes(), 6 * UNIT);
        let refused = budget.reserve(5 * UNIT).expect_err("6 + 5 > 10");
        assert!(
            matches!(refused, ServiceError::ResponsesBusy(_)),
            "{refused}"
        );
        let b = budget
            .reserve(4 * UNIT - 1)
            .expect("rounded up to 4 KiB: fits");
        assert_eq!(budget.held_bytes(), 10 * UNIT);
        drop(a);
        drop(b);
        assert_eq!(budget.held_bytes(), 0);
        // Tiny responses take one unit; an absurd estimate takes the whole
        // budget rather than overflowing the count.
        let tiny = budget.reserve(0).expect("one unit");
        assert_eq!(budget.held_bytes(), UNIT);
        drop(tiny);
        let all = budget.reserve(usize::MAX).expect("the whole budget");
        assert_eq!(budget.held_bytes(), 10 * UNIT);
        drop(all);
    }
}
