//! Rebuilding sessions from the store (docs/sessions.md, "Durability and recovery"): at start
//! ([`recover_all`], called by `SessionManager::recover`) and after a failed
//! commit ([`rebuild`], called by `SessionManager::reload`, the rollback to
//! what is durable).
//!
//! A stored session that cannot be rebuilt (a record, snapshot or log entry
//! that does not decode or does not replay) is skipped, not fatal: it is
//! logged with its id and the reason, counted in [`RecoveryReport`] and in
//! `mcapi_recovery_skipped_total`, and its data is left in the store
//! untouched for an operator to inspect. A store that cannot be read at all
//! still fails the start. The errors are typed all the way: the store's
//! [`StoreError`], this session's damage ([`RecordError`]), and the
//! service's [`StorageError`] that carries either to a client.

use std::collections::VecDeque;
use std::sync::Arc;

use mcapi_core::continuous::{ContinuousAgent, ContinuousObservation, ContinuousState};
use mcapi_core::{Agent, CuriousAgent};
use mcapi_shards::Placement;
use mcapi_store::{StoreError, StoredSession};

use super::agent_config::{EffectiveConfig, SessionConfig, UpdateMode};
use super::durable::{self, LearnerSnapshot, LogEntry};
use super::error::{RecordError, RecoveryError, ServiceError, StorageError};
use super::history::{RingTick, push_tick};
use super::learner::Learner;
use super::limits::Limits;
use super::session::{self, Durability, Session, SessionRef};
use super::setup::Setup;
use super::spec::ModelInput;
use super::table::Entry;

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
    /// Clustered: stored sessions of shards this replica does not own,
    /// left in the store untouched and not loaded (a shard move will need
    /// them; docs/cluster.md, "Recovery").
    pub not_owned: u64,
    /// Wall time.
    pub seconds: f64,
}

/// One step of reading a session's log: the store failed, or this entry
/// is bad. A malformed chunk is this session's damage, not the store's.
enum LogRead {
    Store(StoreError),
    Record(RecordError),
}

impl From<StoreError> for LogRead {
    fn from(e: StoreError) -> Self {
        match e {
            e @ StoreError::Corrupt { .. } => Self::Record(RecordError::Corrupt(e)),
            e => Self::Store(e),
        }
    }
}

/// A rebuilt session and the log entries replayed.
pub(super) type Rebuilt = Result<(SessionRef, u64), RecoveryError>;

/// Loads every stored session: snapshot, then the log after it, then one
/// policy update; sessions are rebuilt in parallel. A session whose records
/// do not decode or replay is skipped (logged, counted, listed in the
/// report, its data left in the store); a store that cannot be read fails
/// the recovery.
///
/// `keep` decides how each rebuilt session enters the table, as it is
/// rebuilt (resident, or evicted at once so a large store never needs all
/// its sessions in memory together).
pub(super) fn recover_all(
    setup: &Setup,
    limits: &Limits,
    d: &Durability,
    placement: Option<&Placement>,
    keep: impl Fn(SessionRef) -> Entry + Sync + Send,
) -> Result<(Vec<(String, Entry)>, RecoveryReport), ServiceError> {
    use rayon::prelude::*;
    let started = std::time::Instant::now();
    let mut stored = d.store.sessions()?;
    let before = stored.len();
    if let Some(p) = placement {
        stored.retain(|s| p.holds(&s.id));
    }
    let not_owned = (before - stored.len()) as u64;
    let recovered: Vec<(String, Result<_, RecoveryError>)> = stored
        .into_par_iter()
        .map(|s| {
            let id = s.id.clone();
            let rebuilt = rebuild(setup, limits, d, s);
            (id, rebuilt.map(|(session, n)| (keep(session), n)))
        })
        .collect();
    let mut report = RecoveryReport {
        not_owned,
        ..RecoveryReport::default()
    };
    let mut rebuilt = Vec::with_capacity(recovered.len());
    for (id, r) in recovered {
        match r {
            Ok((entry, replayed)) => {
                report.sessions += 1;
                report.replayed += replayed;
                rebuilt.push((id, entry));
            }
            Err(RecoveryError::Store(source)) => {
                return Err(StorageError::Recovery {
                    path: d.store.path().to_path_buf(),
                    id,
                    source,
                }
                .into());
            }
            Err(reason) => {
                tracing::error!(
                    session = %id,
                    %reason,
                    "a stored session cannot be recovered and is skipped; its data is left in the store untouched"
                );
                metrics::counter!("mcapi_recovery_skipped_total").increment(1);
                report.skipped += 1;
                report.skipped_ids.push(id);
            }
        }
    }
    report.seconds = started.elapsed().as_secs_f64();
    Ok((rebuilt, report))
}

/// Rebuilds one stored session.
pub(super) fn rebuild(
    setup: &Setup,
    limits: &Limits,
    d: &Durability,
    stored: StoredSession,
) -> Rebuilt {
    let id = stored.id;
    let bad = |source: RecordError| RecoveryError::Records {
        id: id.clone(),
        source,
    };
    let record: durable::SessionRecord =
        serde_json::from_slice(&stored.record).map_err(|e| bad(RecordError::Record(e)))?;
    let model: serde_json::Value =
        serde_json::from_str(&record.model).map_err(|e| bad(RecordError::Model(e)))?;
    let setup_failed = |e: ServiceError| bad(RecordError::Setup(Box::new(e)));
    let input = ModelInput::parse(model).map_err(setup_failed)?;
    let agent_cfg = SessionConfig::from(&record.config);
    // Limits are for new sessions: one created under looser limits is
    // recovered anyway (and said so), not refused with the whole store.
    let built = match setup.build(&input, &agent_cfg, limits) {
        Err(ServiceError::LimitExceeded(why)) => {
            tracing::warn!(session = %id, limit = %why, "a stored session exceeds the current limits; recovered anyway");
            setup.build(&input, &agent_cfg, &Limits::unlimited())
        }
        built => built,
    };
    let (mut learner, summary, config) = built.map_err(setup_failed)?;
    let mut history = VecDeque::new();
    let mut after = None;
    if let Some((seq, bytes)) = &stored.snapshot {
        let snap = durable::decode_snapshot(bytes, "its snapshot").map_err(|e| bad(e.into()))?;
        let mut snap = snap;
        let known = match &snap.learner {
            LearnerSnapshot::Learned(l) => l.history_known.clone(),
            _ => Vec::new(),
        };
        let observations = snap
            .learner
            .history_observations_mut()
            .map(std::mem::take)
            .unwrap_or_default();
        learner = restore(&learner, snap.learner).map_err(&bad)?;
        history = snap
            .history
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let tick = RingTick::from(t).with_known_fraction(known.get(i).copied().flatten());
                match observations.get(i).and_then(Option::as_deref) {
                    Some(x) => tick.with_observation(x),
                    None => tick,
                }
            })
            .collect();
        after = Some(*seq);
    }
    let mut next_seq = after.map_or(0, |s| s + 1);
    let mut replayed = 0u64;
    let read = d.store.for_each_entry(&id, after, |seq, bytes| {
        if seq != next_seq {
            return Err(LogRead::Record(RecordError::Gap {
                expected: next_seq,
                found: seq,
            }));
        }
        let entry = durable::decode_entry(bytes, &format!("log entry {seq}"))
            .map_err(|e| LogRead::Record(e.into()))?;
        replay(&mut learner, &mut history, &config, &entry).map_err(|e| {
            LogRead::Record(RecordError::Replay {
                seq,
                source: Box::new(e),
            })
        })?;
        next_seq += 1;
        replayed += 1;
        Ok(())
    });
    match read {
        Ok(()) => {}
        Err(LogRead::Record(why)) => return Err(bad(why)),
        Err(LogRead::Store(e)) => return Err(RecoveryError::Store(e)),
    }
    let mut planned_since_log = false;
    if learner.needs_plan() {
        match learner.plan() {
            // A continuous world's next entry records this update, so a
            // later replay makes it too.
            Ok(()) => planned_since_log = learner.continuous().is_some(),
            // As live after the same failed update: the session keeps its
            // last policy and plans again at its next observation.
            Err(e) => {
                tracing::warn!(session = %id, error = %e, "the recovered session's policy update failed; it keeps its last policy");
            }
        }
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
            group: record.group,
            history,
            seq: next_seq,
            since_snapshot,
            pristine: true,
            last_observed_ns: 0,
            planned_since_log,
        },
    );
    Ok((Arc::new(session), replayed))
}

/// Loads an evicted session back (docs/sessions.md, "Idle sessions"): the
/// same rebuild as at start, so a session whose state was pristine when it
/// left comes back bit for bit. Blocking: a store read and a model build.
pub(super) fn load(
    setup: &Setup,
    limits: &Limits,
    d: &Durability,
    id: &str,
    lsn: u64,
) -> Result<SessionRef, ServiceError> {
    let started = std::time::Instant::now();
    let failed = |source: RecoveryError| StorageError::Load {
        id: id.to_string(),
        source: Box::new(source),
    };
    let stored = d
        .store
        .session_since(id, lsn)
        .map_err(|e| failed(e.into()))?
        .ok_or_else(|| failed(RecoveryError::Missing(id.to_string())))?;
    let (session, _) = rebuild(setup, limits, d, stored).map_err(failed)?;
    metrics::histogram!("mcapi_session_load_seconds").record(started.elapsed().as_secs_f64());
    Ok(session)
}

/// Applies one logged observation to a recovering learner and its history
/// ring: Ξ, visits, D, the curiosity channel and the tick change exactly as
/// they did live. A continuous world's agent (docs/algorithm.md §9) also
/// plans where it did live (after each observation in lockstep, where the
/// entry says the tick loop did in async mode) and chooses its action
/// again, which must be the logged one.
pub fn replay(
    learner: &mut Learner,
    history: &mut VecDeque<RingTick>,
    config: &EffectiveConfig,
    entry: &LogEntry,
) -> Result<(), ServiceError> {
    let history_cap = config.history;
    if let Some(x) = &entry.observation {
        if entry.planned_before {
            learner.plan()?;
        }
        let out = learner.observe_continuous(&ContinuousObservation {
            observation: x,
            stimulus: entry.stimulus.as_deref(),
            action_taken: entry.taken.map(|a| a as usize),
        })?;
        if config.update_mode == UpdateMode::Lockstep && learner.needs_plan() {
            learner.plan()?;
        }
        learner.set_advised_action(entry.advised as usize)?;
        let tick = RingTick::new(
            out.tick,
            0,
            entry.advised as usize,
            learner.drive().vector(),
            entry.stimulus.as_deref(),
            None,
            out.reward,
            entry.lstdq_error,
            None,
            None,
        )
        .with_reply(entry.policy_version, entry.digest)
        .with_observation(x);
        push_ring(history, history_cap, tick, entry);
        return Ok(());
    }
    let obs = mcapi_core::Observation {
        state: entry.state as usize,
        stimulus: entry.stimulus.as_deref(),
        action_taken: entry.taken.map(|a| a as usize),
    };
    let signal = entry
        .signal
        .as_ref()
        .map(|(source, x)| (*source as usize, x.as_slice()));
    let out = learner.observe(&obs, signal)?;
    learner.set_advised_action(entry.advised as usize)?;
    let tick = RingTick::new(
        out.tick,
        obs.state,
        entry.advised as usize,
        learner.drive().vector(),
        entry.stimulus.as_deref(),
        out.xi_cur.filter(|_| entry.stimulus.is_some()),
        out.reward,
        entry.lstdq_error,
        out.curiosity,
        learner.known_fraction(),
    )
    .with_reply(entry.policy_version, entry.digest);
    push_ring(history, history_cap, tick, entry);
    learner.resume_policy_version(entry.policy_version);
    Ok(())
}

/// Pushes a replayed observation's ring entry as the live path did: the
/// first observation (no stimulus) as the entry seq 0 is replayed from.
fn push_ring(history: &mut VecDeque<RingTick>, cap: usize, tick: RingTick, entry: &LogEntry) {
    let tick = if entry.stimulus.is_none() {
        tick.as_first()
    } else {
        tick
    };
    push_tick(history, cap, tick);
}

/// A recovered learner: `base` (built from the session record) resumed from
/// a snapshot of the same kind.
fn restore(base: &Learner, snap: LearnerSnapshot) -> Result<Learner, RecordError> {
    // docs/algorithm.md §9.7: the agent whole, on the record's model.
    if let Some(c) = base.continuous() {
        let state = match snap {
            LearnerSnapshot::Continuous(s) => ContinuousState::from(s.agent),
            LearnerSnapshot::ContinuousGrid(s) => ContinuousState::from(s.agent),
            _ => {
                return Err(RecordError::Mismatch(
                    "its snapshot is of a numbered world's agent, its record a continuous world",
                ));
            }
        };
        return ContinuousAgent::restore(c.model().clone(), c.params().clone(), state)
            .map(|a| Learner::Continuous(Box::new(a)))
            .map_err(RecordError::Restore);
    }
    let Some(agent) = base.agent() else {
        return Err(RecordError::Mismatch(
            "its record is of neither a numbered nor a continuous world",
        ));
    };
    let ctx = Arc::clone(agent.planning_model());
    let params = agent.params().clone();
    let learned = agent.learned().map(|l| l.params());
    match (snap, base.curious()) {
        (LearnerSnapshot::Plain(_), None) if learned.is_some() => Err(RecordError::Mismatch(
            "its snapshot has no learned transitions, its record learns them",
        )),
        (LearnerSnapshot::Plain(s), None) => Agent::restore(ctx, params, s)
            .map(Learner::Plain)
            .map_err(RecordError::Restore),
        // docs/algorithm.md §8: P̂ is rebuilt from the counts.
        (LearnerSnapshot::Learned(s), None) => match learned {
            Some(l) => Agent::restore_learned(ctx, params, l, s.agent)
                .map(Learner::Plain)
                .map_err(RecordError::Restore),
            None => Err(RecordError::Mismatch(
                "its snapshot has learned transitions, its record posted ones",
            )),
        },
        (LearnerSnapshot::Learned(_), Some(_)) => Err(RecordError::Mismatch(
            "its snapshot has learned transitions, its record a curiosity channel",
        )),
        (LearnerSnapshot::Curious(s), Some(c)) => {
            let channel = c.channel();
            CuriousAgent::restore(ctx, params, channel.params(), channel.signal_dim(), *s)
                .map(|a| Learner::Curious(Box::new(a)))
                .map_err(RecordError::Restore)
        }
        (LearnerSnapshot::Plain(_), Some(_)) => Err(RecordError::Mismatch(
            "its snapshot has no curiosity channel, its record one",
        )),
        (LearnerSnapshot::Curious(_), None) => Err(RecordError::Mismatch(
            "its snapshot has a curiosity channel, its record none",
        )),
        (LearnerSnapshot::Continuous(_) | LearnerSnapshot::ContinuousGrid(_), _) => {
            Err(RecordError::Mismatch(
                "its snapshot is of a continuous world's agent, its record a numbered world",
            ))
        }
    }
}
