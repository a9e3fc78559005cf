//! When a failed part of the store (the log, the database) is tried again
//! after a storage fault: a doubling backoff between two bounds.

use std::time::{Duration, Instant};

/// First wait before repairing the log or reopening the database after a
/// storage fault; doubled after every failed attempt up to [`MAX_BACKOFF`],
/// reset by a success.
const MIN_BACKOFF: Duration = Duration::from_millis(50);
/// Longest wait between two repair or reopening attempts.
const MAX_BACKOFF: Duration = Duration::from_secs(1);

/// When a failed part of the store (the log, the database) is tried again:
/// [`MIN_BACKOFF`] after the first failure, twice as long after every
/// failed attempt up to [`MAX_BACKOFF`], back to the start once the part
/// has done its work again.
#[derive(Debug)]
pub(crate) struct Retry {
    /// When to try next, while the part is down.
    at: Option<Instant>,
    /// The wait after the next failed attempt.
    backoff: Duration,
}

impl Retry {
    pub(crate) fn new() -> Self {
        Self {
            at: None,
            backoff: MIN_BACKOFF,
        }
    }

    /// When the next attempt is due, while the part is down.
    pub(crate) fn at(&self) -> Option<Instant> {
        self.at
    }

    pub(crate) fn is_due(&self, now: Instant) -> bool {
        self.at.is_some_and(|at| now >= at)
    }

    pub(crate) fn is_scheduled(&self) -> bool {
        self.at.is_some()
    }

    /// The part went down: an attempt is scheduled unless one already is.
    pub(crate) fn went_down(&mut self) {
        if self.at.is_none() {
            self.attempt_failed();
        }
    }

    /// An attempt failed: the next one is scheduled; the wait until it.
    pub(crate) fn attempt_failed(&mut self) -> Duration {
        let wait = self.backoff;
        self.at = Some(Instant::now() + wait);
        self.backoff = (wait * 2).min(MAX_BACKOFF);
        wait
    }

    /// The part is up again (the backoff stays until [`Self::worked`]).
    pub(crate) fn cleared(&mut self) {
        self.at = None;
    }

    /// The part did its work: the next failure waits [`MIN_BACKOFF`].
    pub(crate) fn worked(&mut self) {
        self.backoff = MIN_BACKOFF;
    }
}
