//! Rebuilding sessions from the store (DESIGN.md, "Durability"): at start
//! ([`SessionManager::recover`]) and after a failed commit
//! ([`SessionManager::reload`], the rollback to what is durable).
//!
//! A stored session that cannot be rebuilt (a record, snapshot or log entry
//! that does not decode or does not replay) is skipped, not fatal: it is
//! logged with its id and the reason, counted in [`RecoveryReport`] and in
//! `mcapi_recovery_skipped_total`, and its data is left in the store
//! untouched for an operator to inspect. A store that cannot be read at all
//! still fails the start.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::Ordering;

use crate::store::{StoreError, StoredSession, Write};
use mcapi_core::{Agent, CuriousAgent};

use super::session::{self, Durability, Learner, Session, SessionRef};
use super::spec::{ModelInput, SessionConfig};
use super::table::SessionTable;
use super::{Limits, ServiceError, SessionManager, durable};

/// What `recover` did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RecoveryReport {
    /// Sessions recovered.
    pub sessions: u64,
    /// Log entries replayed.
    pub replayed: u64,
    /// Stored sessions that could not be rebuilt and were skipped (their
    /// data stays in the store).
    pub skipped: u64,
    /// The ids of the skipped sessions.
    pub skipped_ids: Vec<String>,
    /// Wall time.
    pub seconds: f64,
}

/// Why a stored session could not be rebuilt.
#[derive(Debug)]
pub(super) enum Unrecoverable {
    /// The store could not be read: nothing says the session is bad.
    Store(StoreError),
    /// Its records do not decode or replay.
    Records(String),
}

/// A rebuilt session and the log entries replayed, or why not.
type Rebuilt = Result<(SessionRef, u64), Unrecoverable>;

impl std::fmt::Display for Unrecoverable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Store(e) => write!(f, "{e}"),
            Self::Records(why) => f.write_str(why),
        }
    }
}

impl SessionManager {
    /// Loads every stored session: snapshot, then the log after it, then
    /// one policy update; sessions are rebuilt in parallel. Marks the
    /// manager ready when done. A session whose records do not decode or
    /// replay is skipped (logged, counted, listed in the report, its data
    /// left in the store); a store that cannot be read fails the recovery.
    pub fn recover(&self) -> Result<RecoveryReport, ServiceError> {
        use rayon::prelude::*;
        let Some(d) = &self.durability else {
            self.ready.store(true, Ordering::Release);
            return Ok(RecoveryReport::default());
        };
        let started = std::time::Instant::now();
        let stored = d
            .store
            .sessions()
            .map_err(|e| ServiceError::Storage(e.to_string()))?;
        let recovered: Vec<(String, Rebuilt)> = stored
            .into_par_iter()
            .map(|s| (s.id.clone(), self.recover_one(d, s)))
            .collect();
        let mut report = RecoveryReport::default();
        let mut rebuilt = Vec::with_capacity(recovered.len());
        for (id, r) in recovered {
            match r {
                Ok((session, replayed)) => {
                    report.sessions += 1;
                    report.replayed += replayed;
                    rebuilt.push(session);
                }
                Err(Unrecoverable::Records(reason)) => {
                    tracing::error!(
                        session = %id,
                        %reason,
                        "a stored session cannot be recovered and is skipped; its data is left in the store untouched"
                    );
                    metrics::counter!("mcapi_recovery_skipped_total").increment(1);
                    report.skipped += 1;
                    report.skipped_ids.push(id);
                }
                Err(Unrecoverable::Store(e)) => {
                    return Err(ServiceError::Storage(format!(
                        "reading the store {} to recover session `{id}`: {e}",
                        d.store.path().display()
                    )));
                }
            }
        }
        let mut sessions = self.sessions.write();
        for session in rebuilt {
            sessions.insert(session.id.clone(), session);
        }
        metrics::gauge!("mcapi_sessions").set(sessions.len() as f64);
        drop(sessions);
        report.seconds = started.elapsed().as_secs_f64();
        if report.skipped > 0 {
            tracing::warn!(
                skipped = report.skipped,
                ids = ?report.skipped_ids,
                store = %d.store.path().display(),
                "stored sessions skipped at recovery"
            );
        }
        self.ready.store(true, Ordering::Release);
        Ok(report)
    }

    /// Rebuilds one stored session.
    pub(super) fn recover_one(&self, d: &Durability, stored: StoredSession) -> Rebuilt {
        let id = stored.id;
        let ctx = |e: String| Unrecoverable::Records(format!("session `{id}`: {e}"));
        let record: durable::SessionRecord = serde_json::from_slice(&stored.record)
            .map_err(|e| ctx(format!("its record does not decode: {e}")))?;
        let model: serde_json::Value = serde_json::from_str(&record.model)
            .map_err(|e| ctx(format!("its model does not decode: {e}")))?;
        let input = ModelInput::parse(model).map_err(|e| ctx(e.to_string()))?;
        let c = &record.config;
        let agent_cfg = SessionConfig {
            eta: Some(c.eta),
            gamma: Some(c.gamma),
            priorities: Some(c.priorities.clone()),
            stimulus_rate: Some(c.stimulus_rate),
            optimistic_sd: Some(c.optimistic_sd),
            ridge: Some(c.ridge),
            epsilon: Some(c.epsilon),
            seed: Some(c.seed),
            update_mode: Some(c.update_mode),
            history: Some(c.history),
            curiosity: c.curiosity.clone(),
        };
        // Limits are for new sessions: one created under looser limits is
        // recovered anyway (and said so), not refused with the whole store.
        let built = match self.build(&input, &agent_cfg, &self.limits) {
            Err(ServiceError::LimitExceeded(why)) => {
                tracing::warn!(session = %id, limit = %why, "a stored session exceeds the current limits; recovered anyway");
                self.build(&input, &agent_cfg, &Limits::unlimited())
            }
            built => built,
        };
        let (mut learner, summary, config) = built.map_err(|e| ctx(e.to_string()))?;
        let mut history = VecDeque::new();
        let mut after = None;
        if let Some((seq, bytes)) = &stored.snapshot {
            let snap = durable::decode_snapshot(bytes, "its snapshot").map_err(&ctx)?;
            learner = restore(&learner, snap.learner).map_err(&ctx)?;
            history = snap.history.iter().map(session::RingTick::from).collect();
            after = Some(*seq);
        }
        let mut next_seq = after.map_or(0, |s| s + 1);
        let mut replayed = 0u64;
        // A bad entry stops the read; what was wrong is kept here.
        let mut bad: Option<String> = None;
        let read = d.store.for_each_entry(&id, after, |seq, bytes| {
            let step = (|| {
                if seq != next_seq {
                    return Err(format!("log entry {next_seq} is missing (found {seq})"));
                }
                let entry = durable::decode_entry(bytes, &format!("log entry {seq}"))?;
                durable::replay(&mut learner, &mut history, config.history, &entry)
                    .map_err(|e| format!("log entry {seq}: {e}"))
            })();
            match step {
                Ok(()) => {
                    next_seq += 1;
                    replayed += 1;
                    Ok(())
                }
                Err(why) => {
                    let e = StoreError::Failed(why.clone());
                    bad = Some(why);
                    Err(e)
                }
            }
        });
        match (read, bad) {
            (Ok(()), _) => {}
            (Err(_), Some(why)) => return Err(ctx(why)),
            // A malformed chunk is this session's damage, not the store's.
            (Err(e @ StoreError::Corrupt { .. }), None) => return Err(ctx(e.to_string())),
            (Err(e), None) => return Err(Unrecoverable::Store(e)),
        }
        if learner.needs_plan()
            && let Err(e) = learner.plan()
        {
            // As live after the same failed update: the session keeps its
            // last policy and plans again at its next observation.
            tracing::warn!(session = %id, error = %e, "the recovered session's policy update failed; it keeps its last policy");
        }
        let since_snapshot = next_seq - after.map_or(0, |s| s + 1);
        let session = Session::resume(
            id.clone(),
            learner,
            summary,
            config,
            Some(d.clone()),
            session::Resumed {
                owner: record.owner,
                history,
                seq: next_seq,
                since_snapshot,
            },
        );
        Ok((Arc::new(session), replayed))
    }

    /// Replaces a session whose commit failed by a fresh recovery of its
    /// durable state (snapshot and log, as at start), then lets the store
    /// accept its writes again ([`crate::store::Write::Resume`]). The old
    /// session is marked stale first, so nothing is applied to it while
    /// this runs. A no-op if the session was deleted or already replaced.
    pub fn reload(&self, session: &SessionRef) -> Result<(), String> {
        let Some(d) = &self.durability else {
            return Ok(());
        };
        session.mark_stale();
        let _one_at_a_time = self.reloading.lock();
        let current = |sessions: &SessionTable| {
            sessions
                .get(&session.id)
                .is_some_and(|s| Arc::ptr_eq(s, session))
        };
        if !current(&self.sessions.read()) {
            return Ok(());
        }
        let stored = d
            .store
            .session(&session.id)
            .map_err(|e| e.to_string())?
            .ok_or_else(|| format!("session `{}` is not in the store", session.id))?;
        let (fresh, replayed) = self.recover_one(d, stored).map_err(|e| e.to_string())?;
        // Queued before the fresh session can submit anything, so the
        // store readmits exactly the writes that continue the durable state.
        drop(d.store.submit(vec![Write::Resume {
            id: Arc::from(session.id.as_str()),
        }]));
        let mut sessions = self.sessions.write();
        if current(&sessions) {
            // A delete in flight on the old session goes on with the new
            // one: it takes no observation until the delete ends.
            if session.is_deleting() {
                fresh.inherit_deleting();
            }
            sessions.insert(session.id.clone(), fresh);
        }
        drop(sessions);
        tracing::info!(session = %session.id, replayed, "session reloaded from its durable state");
        Ok(())
    }
}

/// A recovered learner: `base` (built from the session record) resumed from
/// a snapshot of the same kind.
fn restore(base: &Learner, snap: durable::LearnerSnapshot) -> Result<Learner, String> {
    let ctx = Arc::clone(base.agent().planning_model());
    let params = base.agent().params().clone();
    match (snap, base.curious()) {
        (durable::LearnerSnapshot::Plain(s), None) => Agent::restore(ctx, params, s)
            .map(Learner::Plain)
            .map_err(|e| e.to_string()),
        (durable::LearnerSnapshot::Curious(s), Some(c)) => {
            let channel = c.channel();
            CuriousAgent::restore(ctx, params, channel.params(), channel.signal_dim(), *s)
                .map(|a| Learner::Curious(Box::new(a)))
                .map_err(|e| e.to_string())
        }
        (durable::LearnerSnapshot::Plain(_), Some(_)) => {
            Err("its snapshot has no curiosity channel, its record one".into())
        }
        (durable::LearnerSnapshot::Curious(_), None) => {
            Err("its snapshot has a curiosity channel, its record none".into())
        }
    }
}
