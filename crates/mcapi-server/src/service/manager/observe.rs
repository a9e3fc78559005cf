//! Observations: priced, applied by the session, made durable before the
//! reply (lockstep and async); values and history.

use super::*;

impl SessionManager {
    /// Makes the next `n` calls of [`SessionManager::observe`] panic on the
    /// request's task before they touch a session, as a bug of the server
    /// would (for the tests of how a panicking request or stream ends; set
    /// only through this call, never by a request).
    #[doc(hidden)]
    pub fn panic_next_observations(&self, n: u32) {
        self.panic_observations.store(n, Ordering::Release);
    }

    pub(super) fn panic_if_asked(&self) {
        let asked = self
            .panic_observations
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| n.checked_sub(1))
            .is_ok();
        if asked {
            panic!("injected by a test: panic_next_observations");
        }
    }

    /// Applies observations in order and returns one reply each (docs/sessions.md,
    /// "Observing"). Lockstep sessions reply after their update
    /// on the tick pool; async sessions reply at once and queue an update.
    pub async fn observe(
        &self,
        caller: Caller,
        id: &str,
        batch: Vec<ObservationIn>,
    ) -> Result<Vec<StepOut>, ServiceError> {
        self.panic_if_asked();
        if batch.is_empty() {
            return Err(ServiceError::field("observations", "must not be empty"));
        }
        if batch.len() > self.limits.max_batch {
            return Err(ServiceError::LimitExceeded(format!(
                "`observations` has {} entries; the limit is {}",
                batch.len(),
                self.limits.max_batch
            )));
        }
        let _guard = self.enter_shard(id)?;
        // Loaded back if evicted; rolled back first if an earlier commit
        // failed.
        let session = not_failed(self.visible_session_async(caller, id).await?)?;
        self.limits.check_batch_cost(
            batch.len(),
            &cost::estimate(&session.model, &session.config),
        )?;
        // While the store cannot write, nothing is applied: the client gets
        // `storage_unavailable` at once and retries.
        self.store_writable()?;
        let result = self.observe_on(&session, batch).await;
        self.roll_back_if_uncommitted(&session, &result);
        result
    }

    /// After a commit of `session` failed, its observations are applied in
    /// memory but not durable, and the store refuses its writes from now
    /// on: it is rolled back to what is durable before it takes another
    /// observation. Rare, and a few milliseconds of reading: done on the
    /// caller's task.
    pub(super) fn roll_back_if_uncommitted<T>(
        &self,
        session: &SessionRef,
        result: &Result<T, ServiceError>,
    ) {
        if let Err(ServiceError::Storage(detail)) = result {
            tracing::warn!(session = %session.id, error = %detail, "reloading the session after a failed commit");
            if let Err(e) = self.reload(session) {
                tracing::error!(session = %session.id, error = %e, "reload failed; the session takes no observations until one succeeds");
            }
        }
    }

    /// Checks the estimated CPU time of one `InteractBatch` message: `n`
    /// observations for each of its sessions, together at most
    /// `--max-batch-ms`, as one `Observe` batch. Sessions the caller cannot
    /// see count nothing (their observations are refused anyway).
    pub fn check_message_cost<'a>(
        &self,
        caller: Caller,
        sessions: impl IntoIterator<Item = (&'a str, usize)>,
    ) -> Result<(), ServiceError> {
        let mut us = 0u64;
        for (id, n) in sessions {
            // Priced from the table: an evicted session is not loaded here.
            if let Ok(entry) = self.visible_entry(caller, id) {
                us = us.saturating_add(entry.cost().tick_us.saturating_mul(n as u64));
            }
        }
        if us / 1000 > self.limits.max_batch_ms {
            return Err(ServiceError::LimitExceeded(format!(
                "the message's observations cost an estimated {} ms in all; the limit per \
                 message is {} ms (--max-batch-ms): send fewer per message",
                us / 1000,
                self.limits.max_batch_ms
            )));
        }
        Ok(())
    }

    pub(super) async fn observe_on(
        &self,
        session: &SessionRef,
        batch: Vec<ObservationIn>,
    ) -> Result<Vec<StepOut>, ServiceError> {
        let n = batch.len() as u64;
        let out = match self.observe_inline(session, &batch, None) {
            Some(observed) => observed.durable().await?,
            None if session.mode == UpdateMode::Lockstep => {
                let (tx, rx) = oneshot::channel();
                self.pool.submit(Job::Observe {
                    session: Arc::clone(session),
                    batch,
                    reply: tx,
                })?;
                // The pool drains its queue before it stops, so a reply
                // that never comes means the job itself failed.
                rx.await
                    .map_err(|_| ServiceError::Internal("a tick job ended without a reply".into()))?
                    .durable()
                    .await?
            }
            None => {
                // Observing alone recomputes R for every pair and, with a
                // curiosity channel, learns each signal sample: beyond the
                // inline budget that runs on the blocking pool.
                let observing = Arc::clone(session);
                let observed =
                    tokio::task::spawn_blocking(move || observing.observe(&batch, false))
                        .await
                        .map_err(|e| {
                            ServiceError::Internal(format!("an observation task failed: {e}"))
                        })?;
                self.plan_after_observe(session, &observed, n);
                observed.durable().await?
            }
        };
        replays_stand(session, &out)?;
        // Replays count as observations: they are priced as such, too.
        tick::meters().observations.increment(n);
        Ok(out)
    }

    /// Applies `batch` to `session` on this thread if its update is cheap
    /// enough to run here (a hand-off to the pool would cost more than the
    /// update itself): a lockstep session whose plan fits the inline
    /// budget, observed and planned; an async session whose observing fits
    /// it, observed, then planned here or queued for the tick loop. `None`
    /// when it is not cheap: nothing was applied, and the caller hands it
    /// to the pool. Never waits for a commit (the [`Observed`] carries it),
    /// so a group step applies many members and then waits once; with
    /// `log_batch` (a group step's) the entries go into it, not to a commit
    /// of their own.
    pub(super) fn observe_inline(
        &self,
        session: &SessionRef,
        batch: &[ObservationIn],
        log_batch: Option<&Arc<Batch>>,
    ) -> Option<session::Observed> {
        let n = batch.len() as u64;
        match session.mode {
            UpdateMode::Lockstep => {
                if session.plan_cost_ns().saturating_mul(n) > self.inline_plan_ns {
                    return None;
                }
                let observed = session.observe_into(batch, true, log_batch);
                if let Some(took) = observed.timed {
                    tick::meters().tick_seconds.record(took.as_secs_f64());
                }
                if let Err(e @ ServiceError::Algo(mcapi_core::AlgoError::Numerical(_))) =
                    &observed.result
                {
                    tick::log_plan_error(session, e);
                }
                Some(observed)
            }
            UpdateMode::Async => {
                let observe_ns = session.observe_cost_ns().saturating_mul(n);
                if observe_ns > self.inline_plan_ns.max(50_000) {
                    return None;
                }
                let observed = session.observe_into(batch, false, log_batch);
                self.plan_after_observe(session, &observed, n);
                Some(observed)
            }
        }
    }

    /// An async session's policy update after it observed `n`
    /// observations: here if it fits the inline budget, else queued for
    /// the tick loop (once: a session already queued is not queued again).
    fn plan_after_observe(&self, session: &SessionRef, observed: &session::Observed, n: u64) {
        let inline = session.plan_cost_ns().saturating_mul(n) <= self.inline_plan_ns;
        if inline && observed.result.is_ok() {
            match session.plan_if_needed() {
                Ok(Some(took)) => tick::meters().tick_seconds.record(took.as_secs_f64()),
                Ok(None) => {}
                Err(e) => tick::log_plan_error(session, &e),
            }
        } else if session.try_enqueue()
            && let Err(e) = self.pool.submit(Job::Plan(Arc::clone(session)))
        {
            session.dequeued();
            tracing::warn!(session = %session.id, error = %e, "policy update not queued");
        }
    }

    /// Value tables of a session.
    #[tracing::instrument(level = "debug", skip(self))]
    pub fn values(
        &self,
        caller: Caller,
        id: &str,
        sel: ValueSelection,
    ) -> Result<Budgeted<Values>, ServiceError> {
        let session = self.session_for(caller, id)?;
        let bytes = sel.check_size(&session.model, self.limits.max_response_bytes)?;
        let permit = self.responses.reserve(budget::charge(bytes))?;
        Ok(Budgeted {
            value: values::tables(&session, sel),
            estimate: bytes,
            permit,
        })
    }

    /// The most recent `limit` ticks of a session's history, oldest first.
    pub fn history(
        &self,
        caller: Caller,
        id: &str,
        limit: Option<usize>,
    ) -> Result<Budgeted<Vec<HistoryEntry>>, ServiceError> {
        let session = self.session_for(caller, id)?;
        let limit = limit.unwrap_or(usize::MAX).min(session.config.history);
        // About 24 bytes per number: D, the stimulus, and the fixed fields.
        let entry = (2 * session.model.stimuli.len() + 12) * 24;
        let bytes = limit.saturating_mul(entry);
        if bytes > self.limits.max_response_bytes {
            return Err(ServiceError::LimitExceeded(format!(
                "{limit} history entries would take about {bytes} bytes; the limit of one response is {} (--max-response-bytes): ask for at most {} with `limit`",
                self.limits.max_response_bytes,
                self.limits.max_response_bytes / entry
            )));
        }
        let permit = self.responses.reserve(budget::charge(bytes))?;
        let value = session.history(limit);
        Ok(Budgeted {
            // The ring may hold fewer than `limit` entries.
            estimate: value.len().saturating_mul(entry),
            value,
            permit,
        })
    }
}

/// A replayed reply stands only if what it replays is still the session's
/// state: a commit of it that failed meanwhile rolls the observation back,
/// and the replies are then refused (`unavailable`, retry).
pub(super) fn replays_stand(session: &Session, out: &[StepOut]) -> Result<(), ServiceError> {
    if out.iter().any(|s| s.replayed) && !session.replays_stand() {
        return Err(ServiceError::Unavailable(format!(
            "session `{}` is being reloaded from its last durable state after a storage \
             failure; retry",
            session.id
        )));
    }
    Ok(())
}
