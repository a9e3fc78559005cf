//! One hosted agent: the core `Agent` behind a brief lock, its history ring
//! and the synchronous operations the tick loop and handlers call.

use std::collections::VecDeque;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Weak};
use std::time::Duration;

use parking_lot::Mutex;

use mcapi_core::continuous::ContinuousObservation;
use mcapi_core::spec::ActionRef;
use mcapi_core::{AlgoError, Observation};
use mcapi_store::{Batch, Commit, LogId, Outcome, Store, Write};

use super::agent_config::{EffectiveConfig, UpdateMode};
use super::cost;
use super::durable::{LearnerSnapshotRef, LogEntryRef, SnapshotRecordRef, TickRecord, encode};
use super::error::{ServiceError, StorageError};
use super::history::{self, RingTick};
use super::learner::Learner;
use super::membership::GroupTag;
use super::wire::{HistoryEntry, ModelSummary, ObservationIn, SessionCost, StepOut};

/// Mutable state of a session, behind its lock.
#[derive(Debug)]
pub struct SessionState {
    /// The learner.
    pub learner: Learner,
    history: VecDeque<RingTick>,
    /// Sequence number of the next log entry.
    seq: u64,
    /// Log entries since the last snapshot.
    since_snapshot: u64,
    /// A group member's index and its group's size, which spread the
    /// members' snapshots ([`SessionState::snapshot_due`]) and the
    /// doublings of their history rings (`history::group_ring_first`).
    group_slot: Option<(u32, u32)>,
    /// Set by `delete`: the session takes no more observations.
    deleted: bool,
    /// Set while a delete's commit is in flight: no observation or
    /// snapshot is queued after the delete; cleared if the commit fails.
    deleting: bool,
    /// Policy updates to fail on purpose (tests of the failure path).
    fail_plans: u32,
    /// For a model whose transitions the agent learns: the most (pair,
    /// successor) entries it may store (`LearnedSummary::max_transitions`).
    learned_cap: Option<usize>,
    /// A continuous world's session: the tick loop ran a policy update
    /// since the last logged observation (the next entry says so, so a
    /// replay plans where the live session did).
    planned_since_log: bool,
    /// The batch holding this session's newest log entry, while it may not
    /// have been sent: sent first by whatever writes next to the session,
    /// so the session's writes reach the store in order (`Batch`'s docs).
    batch: Weak<Batch>,
}

/// Where a session's observations are made durable.
#[derive(Debug, Clone)]
pub struct Durability {
    /// The store.
    pub store: Arc<Store>,
    /// A snapshot is written after this many logged observations.
    pub snapshot_every: u64,
}

/// What `Session::observe` did: the replies (or the error that stopped the
/// batch) and, with a store, the commit that makes the applied observations
/// durable. Await the commit before replying, error or not.
#[derive(Debug)]
pub struct Observed {
    /// One reply per observation, or the error that stopped the batch.
    pub result: Result<Vec<StepOut>, ServiceError>,
    /// Resolves once the applied observations are durable (for a batch of
    /// replays only: once everything queued before them is).
    pub commit: Option<Commit>,
    /// Every observation was a replay: the commit awaited carries none of
    /// this session's writes, so its failure is not this session's.
    pub replay_only: bool,
    /// Logged into a batch ([`Session::observe_into`]): the positions of
    /// its writes there, durable once the batch's parts holding them are
    /// committed ([`Observed::durable_in`]).
    pub batched: Option<Range<usize>>,
    /// How long the observations with their policy updates took, if they
    /// planned and were timed ([`TIME_ONE_PLAN_IN`]).
    pub timed: Option<Duration>,
}

impl Observed {
    /// A refusal before anything was applied.
    fn refused(e: ServiceError) -> Self {
        Self {
            result: Err(e),
            commit: None,
            replay_only: false,
            batched: None,
            timed: None,
        }
    }

    /// [`Self::durable`] for observations logged into a batch, once the
    /// batch's parts are committed: the outcome of the parts that hold its
    /// writes.
    pub async fn durable_in(self, outcome: &Outcome) -> Result<Vec<StepOut>, ServiceError> {
        if let Some(positions) = &self.batched {
            outcome.of(positions.clone())?;
        }
        self.durable().await
    }

    /// Whether there is a commit of its own to wait for
    /// ([`Self::durable`]); a group step's members have none (their writes
    /// are in its batch), nor has anything on a store that keeps nothing.
    pub fn waits(&self) -> bool {
        self.commit.is_some()
    }

    /// [`Self::durable_in`] for one that does not [`Self::waits`], without
    /// a future: the replies, or the error of their part of `outcome`.
    pub fn settled_in(self, outcome: &Outcome) -> Result<Vec<StepOut>, ServiceError> {
        debug_assert!(
            !self.waits(),
            "settled_in on a reply with a commit to wait for"
        );
        if let Some(positions) = &self.batched {
            outcome.of(positions.clone())?;
        }
        self.result
    }

    /// Waits for durability, then hands back the replies.
    pub async fn durable(self) -> Result<Vec<StepOut>, ServiceError> {
        if let Some(commit) = self.commit {
            match commit.wait().await {
                Ok(()) => {}
                // Nothing of this session was in the failed commit: the
                // replies stand, but whether the observations they replay
                // are durable is not known yet.
                Err(e) if self.replay_only => {
                    return Err(ServiceError::Unavailable(format!(
                        "the store could not confirm that the replayed observations are durable \
                         ({e}); retry"
                    )));
                }
                Err(e) => return Err(e.into()),
            }
        }
        self.result
    }
}

/// A hosted session. Immutable parts live outside the lock.
#[derive(Debug)]
pub struct Session {
    /// The session id.
    pub id: String,
    /// The id as the store's writes carry it, with its log key (made
    /// once, not per write).
    store_id: LogId,
    /// Lockstep or async.
    pub mode: UpdateMode,
    /// Model summary, shared by every session of the same model.
    pub model: Arc<ModelSummary>,
    /// Effective configuration.
    pub config: EffectiveConfig,
    /// SHA-256 of the API key that created it, if keys were in force.
    pub owner: Option<[u8; 32]>,
    /// The group it was created in, if any (docs/groups.md).
    pub group: Option<GroupTag>,
    /// Mutable state.
    pub state: Mutex<SessionState>,
    durability: Option<Durability>,
    /// True while a plan job for this session waits in the tick queue.
    pub queued: AtomicBool,
    /// Set after a failed commit (under the state lock, and read under it
    /// where observations are applied): the state is ahead of what is
    /// durable, so it takes no more observations and is replaced by a
    /// reload. Read without the lock on the request path.
    stale: AtomicBool,
    /// Moving average of one policy update's cost in nanoseconds;
    /// `u64::MAX` until the first update is measured.
    plan_cost_ns: AtomicU64,
    /// Policy updates applied since this session came into memory (the
    /// first [`TIME_ALL_PLANS_UNTIL`] are all timed).
    plans_here: AtomicU64,
    /// The estimated cost of one observation without its policy update
    /// ([`cost::observe_us`]), in nanoseconds: the model and configuration
    /// it depends on never change, so it is worked out once.
    observe_ns: u64,
    /// [`clock_ns`] at the last applied observation; 0 if none since the
    /// server started.
    last_observed_ns: AtomicU64,
    /// [`clock_ns`] when this session came into memory (created, loaded
    /// back or recovered).
    resident_since_ns: AtomicU64,
    /// True while the state is exactly what rebuilding the session from
    /// the store gives (created or rebuilt, and unchanged since; or just
    /// snapshotted by an eviction): it can then leave memory and come back
    /// without a bit changing. Cleared, under the state lock, by every
    /// observation and policy update.
    pristine: AtomicBool,
    history_cap: usize,
    /// Set when an update panicked (a bug, not a client's mistake): the
    /// state may be half-updated, so the session is quarantined and answers
    /// [`ServiceError::SessionFailed`] until it is deleted.
    failed: AtomicBool,
    /// Test hook: the next update of this kind panics (see [`Update`]).
    #[cfg(test)]
    pub(crate) panic_next: std::sync::atomic::AtomicU8,
}

/// One policy update in this many of a session's is timed, for the moving
/// average of its cost ([`Session::plan_cost_ns`]) and for
/// `mcapi_tick_seconds`: the two clock reads and the histogram's sample
/// were about 4% of the server's samples in a group step of hallway
/// members, whose update costs about a microsecond (BENCHMARKS.md §14).
/// A session's cost depends on its model and configuration, which do not
/// change, so a sample follows it as well.
pub const TIME_ONE_PLAN_IN: u64 = 16;

/// A session's first updates in memory are all timed: its first estimate
/// comes from an update with nothing in cache, which the moving average
/// forgets a quarter at a time.
pub const TIME_ALL_PLANS_UNTIL: u64 = 32;

/// Nanoseconds since the process's first call, plus one (never 0).
///
/// This is read once per observation and the timing of policy updates
/// twice per timed update, so they read `quanta`'s (the CPU's time-stamp
/// counter where it is invariant, the system's monotonic clock otherwise):
/// about 10 ns a read here against 25 for `std::time::Instant::now`.
fn clock_ns() -> u64 {
    static EPOCH: std::sync::OnceLock<quanta::Instant> = std::sync::OnceLock::new();
    let epoch = EPOCH.get_or_init(quanta::Instant::now);
    u64::try_from(epoch.elapsed().as_nanos())
        .unwrap_or(u64::MAX - 1)
        .saturating_add(1)
}

/// Time since [`clock_ns`] read `at`; `None` for 0 (never).
pub(super) fn idle_since(at: u64) -> Option<std::time::Duration> {
    match at {
        0 => None,
        at => Some(std::time::Duration::from_nanos(
            clock_ns().saturating_sub(at),
        )),
    }
}

impl Session {
    /// Hints the CPU to load what this session's next observation touches:
    /// its agent's tables and the slot of the history ring its tick goes
    /// to ([`mcapi_core::prefetch`]). A caller stepping many sessions in
    /// turn (a group step) calls it on the next session before stepping
    /// this one. Skipped while another thread holds the state; changes
    /// nothing.
    pub fn prefetch(&self) {
        if let Some(st) = self.state.try_lock() {
            st.learner.prefetch();
            let slot = if st.history.len() >= self.history_cap {
                st.history.front()
            } else {
                st.history.back()
            };
            if let Some(tick) = slot {
                mcapi_core::prefetch::value(tick);
            }
        }
    }

    /// Wraps a fresh learner.
    pub fn new(
        id: String,
        learner: Learner,
        model: Arc<ModelSummary>,
        config: EffectiveConfig,
    ) -> Self {
        Self::resume(id, learner, model, config, None, Resumed::default())
    }

    /// Wraps a learner with its owner, store and recovered log position.
    pub fn resume(
        id: String,
        learner: Learner,
        model: Arc<ModelSummary>,
        config: EffectiveConfig,
        durability: Option<Durability>,
        resumed: Resumed,
    ) -> Self {
        let learned_cap = model.learned.as_ref().map(|l| l.max_transitions);
        let observe_ns = cost::observe_us(&model, &config).saturating_mul(1000);
        let group_slot = resumed.group.as_ref().map(|t| (t.index, t.size));
        // A session without a store has nowhere to be rebuilt from.
        let resumed = Resumed {
            pristine: resumed.pristine && durability.is_some(),
            ..resumed
        };
        Self {
            store_id: LogId::new(Arc::from(id.as_str())),
            id,
            mode: config.update_mode,
            history_cap: config.history,
            model,
            config,
            owner: resumed.owner,
            group: resumed.group,
            durability,
            state: Mutex::new(SessionState {
                learner,
                history: resumed.history,
                seq: resumed.seq,
                since_snapshot: resumed.since_snapshot,
                group_slot,
                deleted: false,
                deleting: false,
                fail_plans: 0,
                learned_cap,
                planned_since_log: resumed.planned_since_log,
                batch: Weak::new(),
            }),
            queued: AtomicBool::new(false),
            stale: AtomicBool::new(false),
            plan_cost_ns: AtomicU64::new(u64::MAX),
            plans_here: AtomicU64::new(0),
            observe_ns,
            last_observed_ns: AtomicU64::new(resumed.last_observed_ns),
            resident_since_ns: AtomicU64::new(clock_ns()),
            pristine: AtomicBool::new(resumed.pristine),
            failed: AtomicBool::new(false),
            #[cfg(test)]
            panic_next: std::sync::atomic::AtomicU8::new(0),
        }
    }

    /// Carries the idle time of the session this one replaces (an
    /// evicted session loaded back keeps its `idle_ms`).
    pub(super) fn set_last_observed_ns(&self, ns: u64) {
        self.last_observed_ns.store(ns, Ordering::Relaxed);
    }

    /// Whether an update of this session panicked (it is quarantined).
    pub fn is_failed(&self) -> bool {
        self.failed.load(Ordering::Acquire)
    }

    /// Runs `update` on the locked state, catching a panic: the session is
    /// then quarantined ([`Session::is_failed`]) and the caller gets
    /// [`ServiceError::SessionFailed`] instead of a dead worker or a
    /// half-updated state served to the next request.
    fn guarded<T>(
        &self,
        st: &mut SessionState,
        kind: Update,
        update: impl FnOnce(&mut SessionState) -> Result<T, ServiceError>,
    ) -> Result<T, ServiceError> {
        #[cfg(test)]
        let inject = self
            .panic_next
            .compare_exchange(kind as u8, 0, Ordering::AcqRel, Ordering::Acquire)
            .is_ok();
        #[cfg(not(test))]
        let _ = kind;
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            #[cfg(test)]
            if inject {
                panic!("injected by a test");
            }
            update(st)
        }));
        outcome.unwrap_or_else(|panic| {
            self.failed.store(true, Ordering::Release);
            let what = panic
                .downcast_ref::<&str>()
                .map(|s| (*s).to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            tracing::error!(session = %self.id, panic = %what, "an update panicked; the session is quarantined");
            metrics::counter!("mcapi_session_panics_total").increment(1);
            Err(ServiceError::SessionFailed(self.id.clone()))
        })
    }

    /// Time since the last applied observation; `None` if none since the
    /// server started.
    pub fn idle(&self) -> Option<std::time::Duration> {
        idle_since(self.last_observed_ns.load(Ordering::Relaxed))
    }

    /// The estimated cost of one observation without its policy update,
    /// in nanoseconds.
    pub fn observe_cost_ns(&self) -> u64 {
        self.observe_ns
    }

    /// The measured cost of one policy update (a moving average over recent
    /// updates), or `u64::MAX` before the first.
    pub fn plan_cost_ns(&self) -> u64 {
        self.plan_cost_ns.load(Ordering::Relaxed)
    }

    fn record_plan_cost(&self, took: Duration, updates: usize) {
        if updates == 0 {
            return;
        }
        let x = u64::try_from(took.as_nanos() / updates as u128).unwrap_or(u64::MAX - 1);
        let old = self.plan_cost_ns.load(Ordering::Relaxed);
        let new = if old == u64::MAX {
            x
        } else {
            (old.saturating_mul(3).saturating_add(x)) / 4
        };
        self.plan_cost_ns
            .store(new.min(u64::MAX - 1), Ordering::Relaxed);
    }

    /// Applies observations in order. With `plan` (lockstep) each is followed
    /// by exactly one LSTDQ update, as `Agent::step`; without (async) the
    /// reply uses the current policy and planning is left to the tick loop.
    ///
    /// On an error at observation i, the i earlier ones stay applied and the
    /// message says so.
    ///
    /// With a store, the applied observations are queued for the next group
    /// commit while the lock is held, so the log keeps their order.
    pub fn observe(&self, batch: &[ObservationIn], plan: bool) -> Observed {
        self.observe_into(batch, plan, None)
    }

    /// [`Self::observe`], logging into `log_batch` if given (a group
    /// step's, sent once its members are applied) instead of queuing a
    /// commit of its own: the result's [`Observed::batched`] says where.
    pub fn observe_into(
        &self,
        batch: &[ObservationIn],
        plan: bool,
        log_batch: Option<&Arc<Batch>>,
    ) -> Observed {
        let mut st = self.state.lock();
        if st.deleted {
            return Observed::refused(ServiceError::NotFound(self.id.clone()));
        }
        if self.is_failed() {
            return Observed::refused(ServiceError::SessionFailed(self.id.clone()));
        }
        if self.stale.load(Ordering::Acquire) {
            return Observed::refused(ServiceError::Unavailable(format!(
                "session `{}` is being reloaded from its last durable state after a storage failure; retry",
                self.id
            )));
        }
        if st.deleting {
            return Observed::refused(ServiceError::Unavailable(format!(
                "session `{}` is being deleted; retry",
                self.id
            )));
        }
        // Observations already applied (by `seq`) are answered from the
        // history ring and not applied again; a refused seq refuses the
        // whole batch before anything is applied.
        let mut out = match st.replays(batch) {
            Ok(replies) => replies,
            Err(e) => return Observed::refused(e),
        };
        let start = out.len();
        if start == batch.len() {
            // Replays only: nothing changes. The replies are sent once what
            // they replay is durable: everything queued before them is,
            // once a commit queued after it returns.
            return Observed {
                result: Ok(out),
                commit: self
                    .durability
                    .as_ref()
                    .map(|d| st.submit(&d.store, Vec::new())),
                replay_only: true,
                batched: None,
                timed: None,
            };
        }
        self.pristine.store(false, Ordering::Release);
        // Timed only when it plans (the cost of a plan is what is learned),
        // and then only now and then.
        let started =
            (plan && self.times_plan(&st, batch.len() - start)).then(quanta::Instant::now);
        out.reserve(batch.len() - start);
        let mut log = Vec::new();
        let log_to = self.durability.as_ref().map(|_| &mut log);
        // The observations applied before a panic stay applied and logged:
        // the log then holds a consistent prefix, which a restart recovers.
        let cap = self.history_cap;
        let result = self.guarded(&mut st, Update::Observe, |st| {
            st.apply_all(batch, start, plan, cap, &mut out, log_to)
        });
        if out.len() > start {
            self.last_observed_ns.store(clock_ns(), Ordering::Relaxed);
        }
        let (commit, batched) = match &self.durability {
            Some(d) if !log.is_empty() => match log_batch {
                Some(b) => (None, Some(st.log_into(&self.store_id, d, log, b))),
                None => (Some(st.log(self.store_id.id(), d, log)), None),
            },
            _ => (None, None),
        };
        drop(st);
        let timed = started.map(|started| started.elapsed());
        if let Some(took) = timed {
            self.record_plan_cost(took, out.len() - start);
        }
        Observed {
            result: result.map(|()| out),
            commit,
            replay_only: false,
            batched,
            timed,
        }
    }

    /// Whether replies replayed from this session still stand once their
    /// wait for durability is over: no commit of it failed meanwhile (the
    /// observations they replay would be rolled back).
    pub fn replays_stand(&self) -> bool {
        !self.is_stale()
            && self
                .durability
                .as_ref()
                .is_none_or(|d| !d.store.is_broken(&self.id))
    }

    /// The `seq` the next observation takes (docs/sessions.md, "Delivery
    /// guarantees").
    pub fn next_seq(&self) -> u64 {
        self.state.lock().next_seq()
    }

    /// Marks the session stale after a failed commit: no observation is
    /// applied to it any more (the manager replaces it by a reload).
    pub fn mark_stale(&self) {
        // Under the lock: an observation being applied finishes first. Its
        // entry, if in a batch not sent yet, is sent now: it reaches the
        // store before the reload's `Resume`, so it is refused as the
        // session's later writes are until then.
        let mut st = self.state.lock();
        if let Some(batch) = std::mem::take(&mut st.batch).upgrade() {
            batch.send();
        }
        self.stale.store(true, Ordering::Release);
    }

    /// Whether a failed commit made this session stale.
    pub fn is_stale(&self) -> bool {
        self.stale.load(Ordering::Acquire)
    }

    /// Marks the session deleted (no observation is applied after this) and
    /// deletes its stored data; the commit resolves once that is durable.
    pub fn delete(&self) -> Option<Commit> {
        let mut st = self.state.lock();
        st.deleted = true;
        self.durability.as_ref().map(|d| {
            st.submit(
                &d.store,
                vec![Write::Delete {
                    id: Arc::clone(self.store_id.id()),
                }],
            )
        })
    }

    /// Starts deleting the session: queues the deletion of its stored data
    /// and, until [`Self::end_delete`], refuses observations (nothing is
    /// queued after the delete). Nothing is removed yet: if the commit
    /// fails, the session goes on as before. `None` without a store.
    pub fn begin_delete(&self) -> Result<Option<Commit>, ServiceError> {
        let mut st = self.state.lock();
        if st.deleted {
            return Err(ServiceError::NotFound(self.id.clone()));
        }
        if self.is_stale() {
            return Err(StorageError::RollingBack(self.id.clone()).into());
        }
        if st.deleting {
            return Err(ServiceError::Unavailable(format!(
                "session `{}` is already being deleted; retry",
                self.id
            )));
        }
        st.deleting = true;
        Ok(self.durability.as_ref().map(|d| {
            st.submit(
                &d.store,
                vec![Write::Delete {
                    id: Arc::clone(self.store_id.id()),
                }],
            )
        }))
    }

    /// Ends a delete: `deleted` once its commit is durable (the session
    /// takes nothing more), otherwise the session is served again.
    pub fn end_delete(&self, deleted: bool) {
        let mut st = self.state.lock();
        st.deleting = false;
        st.deleted |= deleted;
    }

    /// Whether a delete of this session is in flight.
    pub fn is_deleting(&self) -> bool {
        self.state.lock().deleting
    }

    /// Marks a reloaded session as being deleted, as the session it
    /// replaces was (the delete in flight ends on it).
    pub(super) fn inherit_deleting(&self) {
        self.state.lock().deleting = true;
    }

    /// Makes the next `n` policy updates of observations fail with
    /// `AlgoError::Numerical` after the observation was applied, as a
    /// numerical breakdown of the planner would (for tests of that path;
    /// no request reaches it).
    #[doc(hidden)]
    pub fn fail_next_plans(&self, n: u32) {
        self.state.lock().fail_plans = n;
    }

    /// Writes a snapshot now (at clean shutdown), unless nothing changed
    /// since the last one.
    pub fn snapshot(&self) -> Option<Commit> {
        let d = self.durability.as_ref()?;
        let mut st = self.state.lock();
        if self.in_flux(&st) || st.since_snapshot == 0 {
            return None;
        }
        match st.snapshot_write(&self.id) {
            Ok(w) => Some(st.submit(&d.store, vec![w])),
            Err(e) => {
                tracing::error!(session = %self.id, error = %e, "snapshot not written");
                None
            }
        }
    }

    /// One policy update if the reward changed since the last one (the tick
    /// loop's work for async sessions): how long it took if it was timed
    /// ([`TIME_ONE_PLAN_IN`]), `None` if it was not or none was needed.
    pub fn plan_if_needed(&self) -> Result<Option<Duration>, ServiceError> {
        let mut st = self.state.lock();
        if self.is_failed() || !st.learner.needs_plan() {
            return Ok(None);
        }
        self.pristine.store(false, Ordering::Release);
        let started = self.times_plan(&st, 1).then(quanta::Instant::now);
        self.guarded(&mut st, Update::Plan, |st| {
            st.learner.plan()?;
            st.planned_since_log = true;
            Ok(())
        })?;
        drop(st);
        let took = started.map(|started| started.elapsed());
        if let Some(took) = took {
            self.record_plan_cost(took, 1);
        }
        Ok(took)
    }

    /// Whether the next `updates` policy updates are timed: several at
    /// once always; one alone always among the first
    /// [`TIME_ALL_PLANS_UNTIL`] since the session came into memory (so
    /// that an estimate from a cold first update is corrected as soon as
    /// before), else one in [`TIME_ONE_PLAN_IN`] (by the policy version).
    fn times_plan(&self, st: &SessionState, updates: usize) -> bool {
        // Under the state's lock (`st`): a plain read and write suffice.
        let here = self.plans_here.load(Ordering::Relaxed);
        self.plans_here
            .store(here.saturating_add(updates as u64), Ordering::Relaxed);
        updates > 1
            || here < TIME_ALL_PLANS_UNTIL
            || st.learner.policy_version() % TIME_ONE_PLAN_IN == 0
    }

    /// Deleted, being deleted, rolled back or quarantined: its state is
    /// not one to write down.
    fn in_flux(&self, st: &SessionState) -> bool {
        st.deleted || st.deleting || self.is_stale() || self.is_failed()
    }

    /// [`Self::in_flux`], or a policy update is queued or due: it stays in
    /// memory.
    fn kept_in_memory(&self, st: &SessionState) -> bool {
        self.in_flux(st) || self.queued.load(Ordering::Acquire) || st.learner.needs_plan()
    }

    /// Time since this session was last active: its last applied
    /// observation, or its coming into memory if that was later.
    pub fn inactive(&self) -> std::time::Duration {
        let last = self
            .last_observed_ns
            .load(Ordering::Relaxed)
            .max(self.resident_since_ns.load(Ordering::Relaxed));
        std::time::Duration::from_nanos(clock_ns().saturating_sub(last))
    }

    /// Readies the session to leave memory (docs/sessions.md, "Idle
    /// sessions"): `Some(None)` if it can go as it is (its state is what
    /// the store rebuilds), `Some(Some(commit))` once a snapshot of it is
    /// committed (its planner restores exactly, [`Learner::restores_exactly`]),
    /// `None` if it must stay: a delete, a rollback or a policy update is
    /// pending, it is quarantined, or a snapshot would not restore it bit
    /// for bit. [`Session::still_evictable`] is checked again at the swap.
    pub fn prepare_eviction(&self) -> Option<Option<Commit>> {
        let d = self.durability.as_ref()?;
        let mut st = self.state.lock();
        if self.kept_in_memory(&st) {
            return None;
        }
        if self.pristine.load(Ordering::Acquire) {
            return Some(None);
        }
        if !st.learner.restores_exactly() || st.seq == 0 {
            return None;
        }
        match st.snapshot_write(&self.id) {
            Ok(w) => {
                self.pristine.store(true, Ordering::Release);
                Some(Some(st.submit(&d.store, vec![w])))
            }
            Err(e) => {
                tracing::error!(session = %self.id, error = %e, "snapshot for eviction not written");
                None
            }
        }
    }

    /// After a failed eviction snapshot: the store does not hold this
    /// state, so it may not leave memory as it is.
    pub fn not_pristine(&self) {
        self.pristine.store(false, Ordering::Release);
    }

    /// What the table keeps of this session once evicted, if it may still
    /// go: nothing changed it since [`Session::prepare_eviction`] and
    /// nothing is pending. Call with no other holder of the session (the
    /// table's write lock held and only the table and the caller holding
    /// it), so nothing can change it until it is replaced.
    pub fn still_evictable(&self, cost: SessionCost) -> Option<Evicted> {
        let lsn = self.durability.as_ref()?.store.committed();
        let st = self.state.try_lock()?;
        if self.kept_in_memory(&st) || !self.pristine.load(Ordering::Acquire) {
            return None;
        }
        Some(Evicted {
            owner: self.owner,
            cost,
            held: Evicted::held_bytes(&self.id),
            tick: st.learner.tick(),
            states: self.model.states,
            mode: self.mode,
            last_observed_ns: self.last_observed_ns.load(Ordering::Relaxed),
            lsn,
        })
    }

    /// Marks the session queued; true if it was not already.
    pub fn try_enqueue(&self) -> bool {
        !self.queued.swap(true, Ordering::AcqRel)
    }

    /// Clears the queued mark (before planning, so newer rewards re-queue).
    pub fn dequeued(&self) {
        self.queued.store(false, Ordering::Release);
    }

    /// The most recent `limit` history entries, oldest first (ticks only:
    /// the entry of the first observation, kept for replays, is none).
    pub fn history(&self, limit: usize) -> Vec<HistoryEntry> {
        let st = self.state.lock();
        let ticks = st.history.iter().filter(|t| !t.is_first());
        let first = usize::from(st.history.front().is_some_and(RingTick::is_first));
        let skip = (st.history.len() - first).saturating_sub(limit);
        ticks.skip(skip).map(RingTick::entry).collect()
    }
}

/// What a recovered session resumes from.
#[derive(Debug, Default)]
pub struct Resumed {
    /// Its state is exactly what rebuilding it from the store gives (a
    /// session just created or rebuilt; ignored without a store).
    pub pristine: bool,
    /// [`Evicted::last_observed_ns`] of a session loaded back; 0 otherwise.
    pub last_observed_ns: u64,
    /// Owner digest.
    pub owner: Option<[u8; 32]>,
    /// Its group, from its creation record.
    pub group: Option<GroupTag>,
    /// History ring, oldest first.
    pub history: VecDeque<RingTick>,
    /// Sequence number of the next log entry.
    pub seq: u64,
    /// Log entries since the last snapshot.
    pub since_snapshot: u64,
    /// A continuous world's session: a policy update ran after the last
    /// logged observation ([`SessionState`]'s flag of the same name).
    pub planned_since_log: bool,
}

impl SessionState {
    /// The `seq` of the next observation: how many were applied (the
    /// first observation, which carries no stimulus, has tick 0 and every
    /// later one is a tick).
    pub fn next_seq(&self) -> u64 {
        match self.learner.advised_action() {
            Some(_) => self.learner.tick().saturating_add(1),
            None => 0,
        }
    }

    /// Checks the seqs of `batch` (docs/sessions.md, "Delivery
    /// guarantees") and returns the recorded replies of its observations
    /// already applied: a prefix of the batch, as a batch's seqs are
    /// consecutive. Every refusal comes before anything is applied.
    fn replays(&self, batch: &[ObservationIn]) -> Result<Vec<StepOut>, ServiceError> {
        let Some(first) = batch.first().and_then(|o| o.seq) else {
            if let Some(i) = batch.iter().position(|o| o.seq.is_some()) {
                return Err(ServiceError::field(
                    &format!("observations[{i}].seq"),
                    "is given, but `observations[0].seq` is not: in a batch, every observation \
                     carries a seq or none does",
                ));
            }
            return Ok(Vec::new());
        };
        for (i, obs) in batch.iter().enumerate().skip(1) {
            let want = first.checked_add(i as u64);
            if obs.seq != want {
                let want = want.map_or_else(|| "beyond 2^64 - 1".to_owned(), |w| w.to_string());
                let got = obs
                    .seq
                    .map_or_else(|| "missing".to_owned(), |s| s.to_string());
                return Err(ServiceError::field(
                    &format!("observations[{i}].seq"),
                    format!(
                        "is {got}, expected {want}: the seqs of a batch are consecutive, from \
                         `observations[0].seq` ({first})"
                    ),
                ));
            }
        }
        let next = self.next_seq();
        if first > next {
            return Err(ServiceError::SeqGap {
                expected: next,
                got: first,
            });
        }
        let replayed = usize::try_from(next - first).map_or(batch.len(), |n| n.min(batch.len()));
        if replayed == 0 {
            return Ok(Vec::new());
        }
        // The window: the ring's replayable entries, which hold consecutive
        // seqs (entries restored from a record before sequence numbers sit
        // in front of them and cannot be replayed).
        let oldest = self
            .history
            .iter()
            .find(|t| t.reply().is_some())
            .map_or(next, RingTick::seq);
        let front = self.history.front().map_or(next, RingTick::seq);
        let actions = self.learner.actions();
        let mut out = Vec::with_capacity(replayed);
        for (obs, seq) in batch[..replayed].iter().zip(first..) {
            let entry = usize::try_from(seq.wrapping_sub(front))
                .ok()
                .filter(|_| seq >= oldest)
                .and_then(|i| self.history.get(i))
                .filter(|t| t.seq() == seq);
            let Some(step) = entry.and_then(|t| t.replay(actions)) else {
                return Err(ServiceError::SeqExpired { oldest, got: seq });
            };
            if entry.is_some_and(|t| !t.matches(history::digest(obs))) {
                return Err(ServiceError::SeqConflict(seq));
            }
            out.push(step);
        }
        Ok(out)
    }

    /// A snapshot of the session.
    fn snapshot_write(&mut self, id: &str) -> Result<Write, ServiceError> {
        let mut learner = self.learner.snapshot();
        if let LearnerSnapshotRef::Learned(l) = &mut learner {
            l.history_known = self.history.iter().map(RingTick::known_fraction).collect();
        }
        if let Some(observations) = learner.history_observations_mut() {
            *observations = self
                .history
                .iter()
                .map(|t| t.observation().map(<[f64]>::to_vec))
                .collect();
        }
        let record = SnapshotRecordRef {
            learner,
            history: self.history.iter().map(TickRecord::from).collect(),
        };
        self.since_snapshot = 0;
        Ok(Write::Snapshot {
            id: Arc::from(id),
            seq: self.seq.saturating_sub(1),
            snapshot: encode(&record)?,
        })
    }

    /// Queues writes of this session for commit, after the batch holding
    /// its newest log entry if that was not sent yet (so they commit after
    /// it). Every write of a session goes through here or [`Self::log_into`].
    fn submit(&mut self, store: &Store, writes: Vec<Write>) -> Commit {
        if let Some(batch) = std::mem::take(&mut self.batch).upgrade() {
            batch.send();
        }
        store.submit(writes)
    }

    /// [`snapshot_due`] for the entries just logged.
    fn snapshot_due(&self, logged: u64, every: u64) -> bool {
        snapshot_due(
            self.since_snapshot,
            self.seq,
            logged,
            every,
            self.group_slot,
        )
    }

    /// Queues log entries, encoded (and a snapshot when one is due), for
    /// commit.
    fn log(&mut self, id: &Arc<str>, d: &Durability, entries: Vec<LogEntryRef<'_>>) -> Commit {
        let mut writes = Vec::with_capacity(entries.len() + 1);
        let logged = entries.len() as u64;
        for entry in entries {
            match entry.encode() {
                Ok(bytes) => writes.push(Write::Append {
                    id: Arc::clone(id),
                    seq: self.seq,
                    entry: bytes,
                }),
                Err(e) => tracing::error!(session = %id, error = %e, "log entry not encoded"),
            }
            self.seq += 1;
            self.since_snapshot += 1;
        }
        if self.snapshot_due(logged, d.snapshot_every) {
            match self.snapshot_write(id) {
                Ok(w) => writes.push(w),
                Err(e) => tracing::error!(session = %id, error = %e, "snapshot not written"),
            }
        }
        self.submit(&d.store, writes)
    }

    /// [`Self::log`] into `batch`: each entry encoded into the batch's
    /// buffer, nothing queued for commit until the batch is sent. Returns
    /// the positions of the writes in the batch.
    fn log_into(
        &mut self,
        id: &LogId,
        d: &Durability,
        entries: Vec<LogEntryRef<'_>>,
        batch: &Arc<Batch>,
    ) -> Range<usize> {
        if !std::ptr::eq(self.batch.as_ptr(), Arc::as_ptr(batch)) {
            // An earlier batch still unsent holds an earlier entry.
            if let Some(earlier) = std::mem::take(&mut self.batch).upgrade() {
                earlier.send();
            }
            self.batch = Arc::downgrade(batch);
        }
        let mut positions: Option<Range<usize>> = None;
        let logged = entries.len() as u64;
        let mut added = |p: usize| {
            let r = positions.get_or_insert(p..p);
            r.end = p + 1;
        };
        for entry in entries {
            match batch.append(id, self.seq, |out| entry.encode_into(out)) {
                Ok(p) => added(p),
                Err(e) => tracing::error!(session = %id.id(), error = %e, "log entry not encoded"),
            }
            self.seq += 1;
            self.since_snapshot += 1;
        }
        if self.snapshot_due(logged, d.snapshot_every) {
            match self.snapshot_write(id.id()) {
                Ok(w) => added(batch.push(w)),
                Err(e) => tracing::error!(session = %id.id(), error = %e, "snapshot not written"),
            }
        }
        positions.unwrap_or(0..0)
    }

    /// Applies `batch[start..]` (those before `start` were replays).
    fn apply_all<'a>(
        &mut self,
        batch: &'a [ObservationIn],
        start: usize,
        plan: bool,
        history_cap: usize,
        out: &mut Vec<StepOut>,
        mut log: Option<&mut Vec<LogEntryRef<'a>>>,
    ) -> Result<(), ServiceError> {
        for (i, obs) in batch.iter().enumerate().skip(start) {
            // The action whose pair this observation updates, resolved now.
            let advised_before = self.learner.advised_action();
            let planned_before = std::mem::take(&mut self.planned_since_log);
            let digest = history::digest(obs);
            match self.apply(obs, digest, plan, history_cap) {
                Ok(Applied {
                    step,
                    taken,
                    plan_failed,
                }) => {
                    if let Some(log) = log.as_deref_mut() {
                        log.push(LogEntryRef {
                            state: obs.state.unwrap_or(0) as u32,
                            observation: obs.observation.as_deref(),
                            planned_before,
                            stimulus: obs.stimulus.as_deref(),
                            taken: obs
                                .stimulus
                                .as_ref()
                                .and(taken.or(advised_before))
                                .map(|a| a as u32),
                            advised: step.action_index as u32,
                            lstdq_error: self.learner.lstdq_error(),
                            policy_version: step.policy_version,
                            signal: obs
                                .signal
                                .as_deref()
                                .map(|x| (obs.signal_source.unwrap_or(0) as u32, x)),
                            digest,
                        });
                    }
                    if let Some(e) = plan_failed {
                        // The observation is applied (Ξ, D, the tick) and
                        // logged above, so memory and log agree; the reply
                        // is the planner's error.
                        return Err(e.into());
                    }
                    out.push(step);
                }
                Err(e) if batch.len() == 1 => {
                    self.planned_since_log |= planned_before;
                    return Err(e);
                }
                Err(e) => {
                    self.planned_since_log |= planned_before;
                    return Err(match e {
                        ServiceError::Algo(AlgoError::Numerical(_)) | ServiceError::Internal(_) => {
                            e
                        }
                        e => ServiceError::BadRequest(format!(
                            "`observations[{i}]`: {e} (the {i} observations before it were applied)"
                        )),
                    });
                }
            }
        }
        Ok(())
    }

    /// Applies one observation. An error means nothing was applied; a
    /// failed policy update after the observation was applied is
    /// [`Applied::plan_failed`], so the caller logs the observation.
    fn apply(
        &mut self,
        obs: &ObservationIn,
        digest: u64,
        plan: bool,
        history_cap: usize,
    ) -> Result<Applied, ServiceError> {
        let actions = self.learner.actions();
        let action_taken = match &obs.action_taken {
            None => None,
            Some(ActionRef::Index(a)) => Some(*a),
            Some(ActionRef::Name(name)) => {
                Some(actions.iter().position(|a| a == name).ok_or_else(|| {
                    ServiceError::field(
                        "action_taken",
                        format!("unknown action `{name}` (actions: {})", actions.join(", ")),
                    )
                })?)
            }
        };
        if obs.signal_source.is_some() && obs.signal.is_none() {
            return Err(ServiceError::field(
                "signal_source",
                "is given without a `signal`",
            ));
        }
        let observed = match (obs.state, obs.observation.as_deref()) {
            (Some(state), None) => {
                let observation = Observation {
                    state,
                    stimulus: obs.stimulus.as_deref(),
                    action_taken,
                };
                let signal = obs
                    .signal
                    .as_deref()
                    .map(|x| (obs.signal_source.unwrap_or(0), x));
                if let Some(cap) = self.learned_cap {
                    self.learner.check_learned_room(&observation, cap)?;
                }
                self.learner.observe(&observation, signal)?
            }
            (None, Some(x)) => {
                if obs.signal.is_some() {
                    return Err(ServiceError::field(
                        "signal",
                        "this session has no curiosity channel (a continuous world takes none)",
                    ));
                }
                self.learner.observe_continuous(&ContinuousObservation {
                    observation: x,
                    stimulus: obs.stimulus.as_deref(),
                    action_taken,
                })?
            }
            (Some(_), Some(_)) => {
                return Err(ServiceError::field(
                    "observation",
                    "give `state` (a model with numbered states) or `observation` (a continuous world), not both",
                ));
            }
            (None, None) => {
                let (field, what) = match self.learner.continuous() {
                    Some(c) => (
                        "observation",
                        format!(
                            "is missing: this session's model is continuous, so each observation carries `observation`, a vector of {} numbers",
                            c.model().dim()
                        ),
                    ),
                    None => (
                        "state",
                        "is missing: each observation carries the `state` the agent is in"
                            .to_owned(),
                    ),
                };
                return Err(ServiceError::field(field, what));
            }
        };
        // Algorithm 1 lines 8-10, as `Agent::step`: act even if planning
        // failed, so the agent stays consistent.
        let planned = (plan && self.learner.needs_plan()).then(|| {
            if self.fail_plans > 0 {
                self.fail_plans -= 1;
                return Err(AlgoError::Numerical(
                    "injected policy update failure".into(),
                ));
            }
            self.learner.plan()
        });
        let action = self
            .learner
            .act()
            .ok_or_else(|| ServiceError::Internal("no state after an observation".into()))?;
        let plan_failed = planned.and_then(Result::err);
        let learner = &self.learner;
        let drive = learner.drive().vector().to_vec();
        // Every applied observation enters the ring with its whole reply,
        // the first one (no stimulus, no tick) too: the ring is the window
        // of replays (docs/sessions.md, "Delivery guarantees").
        let first = obs.stimulus.is_none();
        let tick = RingTick::new(
            observed.tick,
            obs.state.unwrap_or(0),
            action,
            &drive,
            obs.stimulus.as_deref(),
            observed.xi_cur.filter(|_| !first),
            observed.reward,
            learner.lstdq_error(),
            observed.curiosity,
            learner.known_fraction(),
        )
        .with_reply(learner.policy_version(), digest);
        let tick = match &obs.observation {
            Some(x) => tick.with_observation(x),
            None => tick,
        };
        let tick = if first { tick.as_first() } else { tick };
        let first = self.group_slot.map_or(history::RING_FIRST, |(i, n)| {
            history::group_ring_first(i, n)
        });
        history::push_tick_from(&mut self.history, history_cap, first, tick);
        Ok(Applied {
            step: StepOut {
                tick: observed.tick,
                action: learner.actions()[action].clone(),
                action_index: action,
                drive,
                reward: observed.reward,
                policy_version: learner.policy_version(),
                curiosity: observed.curiosity,
                replayed: false,
            },
            taken: action_taken,
            plan_failed,
        })
    }
}

/// Whether a snapshot is due after `logged` entries were just logged, the
/// last of them `seq − 1`, `since` of them since the last snapshot: once
/// `every` entries were logged since the last one. A group member's (`slot`:
/// its index and its group's size) also comes when its sequence numbers
/// cross the next multiple of `every` shifted by its phase, index × every /
/// size. Members stepped together would otherwise all reach `every` at the
/// same step and write their snapshots in one burst (10,000 hallway
/// members: about a second in which the step waits); their phases spread
/// them over `every` steps. The phase is derived from the member's record,
/// so a recovered member keeps it. A member never holds more entries after
/// its snapshot than a lone session would; a snapshot taken off its phase
/// (at an eviction) may be followed by the phase's one soon after.
fn snapshot_due(since: u64, seq: u64, logged: u64, every: u64, slot: Option<(u32, u32)>) -> bool {
    if since >= every {
        return true;
    }
    let Some((index, size)) = slot else {
        return false;
    };
    let phase = u128::from(super::membership::spread(index, size, every));
    let every = u128::from(every.max(1));
    let before = u128::from(seq.saturating_sub(logged));
    (before + phase) / every != (u128::from(seq) + phase) / every
}

/// One applied observation.
struct Applied {
    /// The reply.
    step: StepOut,
    /// The action the client reported taking, if any.
    taken: Option<usize>,
    /// The policy update after it failed (the observation stays applied).
    plan_failed: Option<AlgoError>,
}

/// A shared handle.
pub type SessionRef = Arc<Session>;

/// The two ways a session's state changes, for [`Session::guarded`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub(crate) enum Update {
    /// Observations applied (and, in lockstep, their plans).
    Observe = 1,
    /// An async-mode policy update.
    Plan = 2,
}

/// Who holds a session: the SHA-256 of its API key, or `None` without keys.
pub type Owner = Option<[u8; 32]>;

/// What the table keeps of an evicted session: enough to list it, charge
/// its owner and price a message without loading it (about 200 bytes with
/// its id and table slot, against kilobytes for the session).
#[derive(Debug)]
pub struct Evicted {
    /// Its owner.
    pub owner: Owner,
    /// Its estimated cost once loaded back (what its owner is charged
    /// while it is resident).
    pub cost: SessionCost,
    /// What its owner is charged while it is evicted: what it holds in
    /// memory ([`Evicted::held_bytes`]).
    pub held: u64,
    /// Ticks so far.
    pub tick: u64,
    /// States of its model.
    pub states: usize,
    /// Lockstep or async.
    pub mode: UpdateMode,
    /// The session clock at its last applied observation (0: none since
    /// the server started), carried into the session loaded back.
    pub last_observed_ns: u64,
    /// Every write of the session is in the store's frames up to this one
    /// ([`mcapi_store::Store::committed`] when it left memory).
    pub lsn: u64,
}

impl Evicted {
    /// What session `id` holds in memory once evicted, this stub included
    /// ([`cost::evicted_bytes`]).
    pub fn held_bytes(id: &str) -> u64 {
        cost::evicted_bytes(std::mem::size_of::<Self>(), id)
    }
}

#[cfg(test)]
mod tests {
    use super::snapshot_due;

    /// Logs `steps` steps of `per_step` entries each for a session starting
    /// at sequence number `seq`, `since` entries after its last snapshot;
    /// returns the sequence numbers after which it snapshotted and the
    /// most entries it held between two snapshots.
    fn run(
        slot: Option<(u32, u32)>,
        every: u64,
        mut seq: u64,
        mut since: u64,
        steps: u64,
        per_step: u64,
    ) -> (Vec<u64>, u64) {
        let (mut at, mut most) = (Vec::new(), since);
        for _ in 0..steps {
            seq += per_step;
            since += per_step;
            most = most.max(since);
            if snapshot_due(since, seq, per_step, every, slot) {
                at.push(seq);
                since = 0;
            }
        }
        (at, most)
    }

    #[test]
    fn a_lone_session_snapshots_every_n_entries() {
        let (at, most) = run(None, 100, 0, 0, 350, 1);
        assert_eq!(at, vec![100, 200, 300]);
        assert_eq!(most, 100);
        // After a snapshot taken elsewhere (an eviction at seq 130), the
        // next comes `every` entries later.
        let (at, _) = run(None, 100, 130, 0, 150, 1);
        assert_eq!(at, vec![230]);
    }

    #[test]
    fn group_members_spread_their_snapshots_over_n_steps() {
        let (size, every, steps) = (1000u32, 100u64, 1000u64);
        let mut per_step = vec![0u32; steps as usize + 1];
        for index in 0..size {
            let (at, most) = run(Some((index, size)), every, 0, 0, steps, 1);
            assert!(most <= every, "member {index} held {most} entries");
            assert!(
                (10..=11).contains(&at.len()),
                "member {index}: {} snapshots in {steps} steps",
                at.len()
            );
            for seq in at {
                per_step[seq as usize] += 1;
            }
        }
        // Without phases all 1000 would snapshot at steps 100, 200, ...
        let busiest = per_step.iter().max().copied().unwrap_or(0);
        assert_eq!(busiest, size / every as u32, "{per_step:?}");
        // Member 0's phase is 0: it snapshots as a lone session does.
        assert_eq!(run(Some((0, size)), every, 0, 0, 250, 1).0, vec![100, 200]);
    }

    #[test]
    fn batches_and_off_phase_snapshots_keep_the_bound() {
        // Batches of 7 cross the member's phase (index 3 of 4: 75) between
        // two calls; the crossing counts.
        let (at, most) = run(Some((3, 4)), 100, 0, 0, 100, 7);
        assert_eq!(at.first(), Some(&28));
        assert!(most <= 100 + 6, "{most}");
        // An eviction's snapshot at seq 60 of a member of phase 50: the
        // next comes at the phase (150), not 100 entries after seq 60.
        let (at, most) = run(Some((1, 2)), 100, 60, 0, 200, 1);
        assert_eq!(at, vec![150, 250]);
        assert!(most <= 100);
        // Absurd settings: an interval of 1 snapshots every entry; the
        // largest interval and index do not overflow.
        assert_eq!(run(Some((5, 9)), 1, 0, 0, 3, 1).0, vec![1, 2, 3]);
        assert!(!snapshot_due(
            0,
            u64::MAX,
            1,
            u64::MAX,
            Some((u32::MAX - 1, u32::MAX))
        ));
    }
}
