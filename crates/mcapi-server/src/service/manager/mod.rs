//! The session manager: the one entry point both transports call. It owns
//! the sessions, the tick pool and the store's durability settings, and
//! routes each call: create (built by [`super::setup`]), get, list, delete,
//! observe (applied by [`super::session`], made durable before the reply,
//! rolled back by a reload after a storage failure), values
//! ([`super::values`]) and history; [`super::recovery`] rebuilds the stored
//! sessions at start.

mod create;
pub use create::{AbandonOnDrop, Watch};
mod groups;
mod lifecycle;
mod lookup;
mod observe;
#[cfg(test)]
mod tests;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use parking_lot::{Mutex, RwLock};
use tokio::sync::oneshot;

use mcapi_store::{Batch, Store, Write};

use super::agent_config::{SessionConfig, UpdateMode};
use super::auth::{ApiKeys, Caller};
use super::budget::{self, Budgeted, ResponseBudget};
use super::cost;
use super::durable;
use super::error::{RecoveryError, ServiceError, StorageError};
use super::limits::{Limits, Usage};
use super::recovery::{self, RecoveryReport};
use super::session::{self, Durability, Session, SessionRef};
use super::setup::Setup;
use super::spec::ModelInput;
use super::table::{Entry, SessionTable};
use super::tick::{self, Job, TickPool};
use super::values::{self, ValueSelection};
use super::wire::{
    CreateSession, CuriosityInfo, HistoryEntry, ModelSummary, ObservationIn, SessionCost,
    SessionInfo, SessionPage, SessionStats, SessionSummary, StepOut, Values,
};
use mcapi_shards::Placement;
use mcapi_shards::placement::ShardGuard;

/// Number of virtual shards in session ids (fixed forever, docs/sessions.md).
pub const SHARDS: u64 = mcapi_shards::SHARDS as u64;

/// Default and maximum page size of `list`.
pub const DEFAULT_PAGE: usize = 100;
/// Largest page `list` returns.
pub const MAX_PAGE: usize = 1000;

/// Default of [`ManagerOptions::inline_plan`].
pub const DEFAULT_INLINE_PLAN: Duration = Duration::from_micros(20);

/// How a [`SessionManager`] runs.
#[derive(Debug, Clone)]
pub struct ManagerOptions {
    /// The limits in force.
    pub limits: Limits,
    /// Tick-loop worker threads.
    pub workers: usize,
    /// Policy updates measured to cost at most this much run on the
    /// requesting task instead of the tick pool: handing a 1 µs update to
    /// another thread costs several µs of wake-ups and context switches.
    /// Zero sends every update to the pool.
    pub inline_plan: Duration,
    /// The durable store, if any.
    pub store: Option<Arc<Store>>,
    /// Logged observations between snapshots of a session.
    pub snapshot_every: u64,
    /// API keys; none means no authentication.
    pub keys: ApiKeys,
    /// With a shard map (`--shard-map`, `--replica`): the shards this
    /// replica serves. `None`: a single node owning every shard.
    pub placement: Option<Arc<Placement>>,
    /// The admin key of the shard-move calls; none: they are refused.
    pub admin: ApiKeys,
    /// With a store: sessions inactive this long leave memory and are
    /// loaded back on their next request (docs/sessions.md, "Idle
    /// sessions"); `None` keeps every session in memory.
    pub evict_after: Option<Duration>,
}

/// Default of [`ManagerOptions::snapshot_every`].
pub const DEFAULT_SNAPSHOT_EVERY: u64 = 1000;

impl ManagerOptions {
    /// Defaults with these limits and workers: in memory, no keys.
    pub fn new(limits: Limits, workers: usize) -> Self {
        Self {
            limits,
            workers,
            inline_plan: DEFAULT_INLINE_PLAN,
            store: None,
            snapshot_every: DEFAULT_SNAPSHOT_EVERY,
            keys: ApiKeys::default(),
            placement: None,
            admin: ApiKeys::default(),
            evict_after: None,
        }
    }
}

/// Sessions examined per hold of the table's lock in an eviction pass.
const EVICT_CHUNK: usize = 1024;

/// The least a session must have been inactive to be evicted to make room
/// within its key's quota ([`SessionManager::make_room`]).
pub const PRESSURE_MIN_IDLE: Duration = Duration::from_secs(1);

/// The session manager: owns sessions, shared models and the tick pool.
pub struct SessionManager {
    sessions: RwLock<SessionTable>,
    /// The session groups (docs/groups.md); a group's members are in
    /// `sessions`. Taken after `sessions` when both are held.
    groups: RwLock<groups::GroupTable>,
    /// Builds sessions: shared planning models, seeds, bounded builds.
    setup: Arc<Setup>,
    limits: Limits,
    /// The memory of value and history responses in flight.
    responses: ResponseBudget,
    pool: TickPool,
    /// The tick threads' count (`--workers`, by default the CPUs this
    /// process may run on): how many parts a group step is cut into.
    workers: usize,
    inline_plan_ns: u64,
    durability: Option<Durability>,
    keys: ApiKeys,
    /// False while stored sessions are being recovered.
    ready: AtomicBool,
    /// Held while a session is reloaded after a storage failure.
    reloading: Mutex<()>,
    /// Held while sessions are evicted to make room within a key's quota
    /// ([`SessionManager::make_room`]).
    pressure: Mutex<()>,
    /// The shards served here, when clustered.
    placement: Option<Arc<Placement>>,
    /// The admin key of the shard-move calls.
    admin: ApiKeys,
    /// One shard move step at a time on this replica.
    pub(crate) moving: tokio::sync::Mutex<()>,
    /// How long a session stays in memory without activity (with a store).
    evict_after: Option<Duration>,
    /// Set by [`SessionManager::shutdown`]: the evictor stops.
    stopping: AtomicBool,
    /// Observations left to panic on ([`SessionManager::panic_next_observations`]).
    panic_observations: std::sync::atomic::AtomicU32,
}

impl SessionManager {
    /// A manager with `workers` tick threads and default options.
    pub fn new(limits: Limits, workers: usize) -> Result<Self, ServiceError> {
        Self::with_options(ManagerOptions::new(limits, workers))
    }

    /// A manager with these options.
    pub fn with_options(opts: ManagerOptions) -> Result<Self, ServiceError> {
        let ManagerOptions {
            limits,
            workers,
            inline_plan,
            store,
            snapshot_every,
            keys,
            placement,
            admin,
            evict_after,
        } = opts;
        let ready = AtomicBool::new(store.is_none());
        // Without a store an evicted session would be lost.
        let evict_after = evict_after.filter(|_| store.is_some());
        let durability = store.map(|store| Durability {
            store,
            snapshot_every: snapshot_every.max(1),
        });
        let pool = TickPool::start(workers, limits.queue)
            .map_err(|e| ServiceError::Internal(format!("starting tick workers: {e}")))?;
        Ok(Self {
            sessions: RwLock::new(SessionTable::default()),
            groups: RwLock::new(groups::GroupTable::new()),
            panic_observations: std::sync::atomic::AtomicU32::new(0),
            evict_after,
            setup: Arc::new(Setup::new(workers)),
            workers: workers.max(1),
            responses: ResponseBudget::new(limits.max_response_bytes_total),
            limits,
            pool,
            inline_plan_ns: u64::try_from(inline_plan.as_nanos()).unwrap_or(u64::MAX),
            durability,
            keys,
            ready,
            reloading: Mutex::new(()),
            pressure: Mutex::new(()),
            placement,
            admin,
            moving: tokio::sync::Mutex::new(()),
            stopping: AtomicBool::new(false),
        })
    }

    /// The shards this replica serves, when clustered (docs/cluster.md).
    pub fn placement(&self) -> Option<&Arc<Placement>> {
        self.placement.as_ref()
    }

    /// The limits in force.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// The memory of value and history responses in flight.
    pub fn responses(&self) -> &ResponseBudget {
        &self.responses
    }

    /// Basis builds of new sessions stopped before they finished: their
    /// request abandoned, or past `--max-build-ms`.
    pub fn builds_stopped(&self) -> u64 {
        self.setup.builds_stopped()
    }

    /// Number of sessions.
    pub fn len(&self) -> usize {
        self.sessions.read().len()
    }

    /// True when no session exists.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Jobs in the tick queue.
    pub fn queue_len(&self) -> usize {
        self.pool.queue_len()
    }

    /// The caller of a request with this `Authorization` header value;
    /// refused while stored sessions are still being recovered.
    pub fn authenticate(&self, authorization: Option<&str>) -> Result<Caller, ServiceError> {
        if !self.is_ready() {
            return Err(ServiceError::Unavailable(
                "the server is recovering its stored sessions; retry shortly".into(),
            ));
        }
        self.keys.authenticate(authorization)
    }

    /// Checks the admin key of a shard-move call (docs/cluster.md): 403
    /// when no admin key is configured or another key is presented.
    pub fn authenticate_admin(&self, authorization: Option<&str>) -> Result<(), ServiceError> {
        if !self.admin.enabled() {
            return Err(ServiceError::Forbidden(
                "admin calls are disabled: this server has no --admin-key (MCAPI_ADMIN_KEY)".into(),
            ));
        }
        match self.admin.authenticate(authorization) {
            Ok(_) => Ok(()),
            Err(e) => Err(ServiceError::Forbidden(format!("admin call refused: {e}"))),
        }
    }

    /// True once stored sessions are recovered (at once without a store).
    pub fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire)
    }

    /// Whether the server can serve its API fully (`/readyz`): `Err` with
    /// the reason while stored sessions are recovered, or while the store
    /// cannot write after a storage fault (it recovers by itself).
    pub fn readiness(&self) -> Result<(), String> {
        if !self.is_ready() {
            return Err("recovering the stored sessions".into());
        }
        let Some(d) = &self.durability else {
            return Ok(());
        };
        let health = d.store.health();
        metrics::gauge!("mcapi_store_healthy").set(if health.is_ok() { 1.0 } else { 0.0 });
        health.map_err(|why| {
            format!(
                "the session store {} cannot write after a storage fault ({why}); it is reopened automatically once the fault clears",
                d.store.path().display()
            )
        })
    }

    /// `Ok` unless the store is down after a storage fault: writes fail
    /// then at once, before anything is applied.
    fn store_writable(&self) -> Result<(), ServiceError> {
        match &self.durability {
            Some(d) => d.store.health().map_err(|why| {
                ServiceError::Storage(StorageError::Down {
                    path: d.store.path().to_path_buf(),
                    why,
                })
            }),
            None => Ok(()),
        }
    }

    /// The store and its settings, if any.
    pub(super) fn durability(&self) -> Option<&Durability> {
        self.durability.as_ref()
    }

    /// What builds sessions.
    pub(super) fn setup(&self) -> &Setup {
        &self.setup
    }

    /// Ids of the sessions in memory beginning with `prefix`.
    pub(super) fn ids_with_prefix(&self, prefix: &str) -> Vec<String> {
        self.sessions
            .read()
            .after(Some(prefix))
            .map(|(id, _)| id)
            .take_while(|id| id.starts_with(prefix))
            .cloned()
            .collect()
    }

    /// Serves these sessions (a shard moved here).
    pub(super) fn insert_sessions(&self, rebuilt: Vec<SessionRef>) {
        self.register_groups(rebuilt.iter().filter_map(|s| groups::GroupMember::of(s)));
        let mut sessions = self.sessions.write();
        for session in rebuilt {
            sessions.insert(session.id.clone(), session);
        }
        metrics::gauge!("mcapi_sessions").set(sessions.len() as f64);
    }

    /// Stops serving the sessions whose id begins with `prefix` (a shard
    /// moved away); their data is the caller's to delete. Returns how many.
    pub(super) fn remove_sessions(&self, prefix: &str) -> usize {
        let ids = self.ids_with_prefix(prefix);
        self.remove_groups(prefix);
        let mut sessions = self.sessions.write();
        for id in &ids {
            sessions.remove(id);
        }
        metrics::gauge!("mcapi_sessions").set(sessions.len() as f64);
        ids.len()
    }

    /// Clustered: refuses a session whose shard is not served here, else
    /// counts the request as changing its shard until the guard drops.
    fn enter_shard(&self, id: &str) -> Result<Option<ShardGuard>, ServiceError> {
        self.placement
            .as_ref()
            .map(|p| p.enter(id))
            .transpose()
            .map_err(ServiceError::from)
    }

    /// Runs a synchronous service call on the blocking pool, so no reader
    /// (value tables, history, listing) holds a session lock or copies a
    /// large table on an async runtime thread.
    pub async fn off_runtime<T, F>(self: &Arc<Self>, call: F) -> Result<T, ServiceError>
    where
        F: FnOnce(&SessionManager) -> Result<T, ServiceError> + Send + 'static,
        T: Send + 'static,
    {
        let manager = Arc::clone(self);
        tokio::task::spawn_blocking(move || call(&manager))
            .await
            .map_err(|e| ServiceError::Internal(format!("a blocking service call failed: {e}")))?
    }

    /// Stops the tick loop after draining its queue; with a store, writes
    /// a snapshot of every session changed since its last one and closes
    /// the store.
    pub fn shutdown(&self) {
        self.stopping.store(true, Ordering::Release);
        self.pool.shutdown();
        let Some(d) = &self.durability else {
            return;
        };
        // Evicted sessions are in the store already.
        let sessions: Vec<SessionRef> = self
            .sessions
            .read()
            .values()
            .filter_map(Entry::resident)
            .cloned()
            .collect();
        let commits: Vec<_> = sessions.iter().filter_map(|s| s.snapshot()).collect();
        let n = commits.len();
        let failed = commits
            .into_iter()
            .map(mcapi_store::Commit::wait_blocking)
            .filter(Result::is_err)
            .count();
        tracing::info!(snapshots = n, failed, "snapshots written at shutdown");
        d.store.close();
    }
}

/// `session` unless it is quarantined ([`Session::is_failed`]).
fn not_failed(session: SessionRef) -> Result<SessionRef, ServiceError> {
    if session.is_failed() {
        return Err(ServiceError::SessionFailed(session.id.clone()));
    }
    Ok(session)
}

fn info_of(session: &Session) -> SessionInfo {
    let st = session.state.lock();
    if let Some(c) = st.learner.continuous() {
        return SessionInfo {
            id: session.id.clone(),
            tick: c.tick(),
            drive: c.drive().vector().to_vec(),
            policy_version: c.policy_version(),
            next_seq: st.next_seq(),
            state: None,
            model: ModelSummary::clone(&session.model),
            agent: session.config.clone(),
            stats: SessionStats {
                lstdq_error: 0.0,
                lambda1_estimate: c.drive().lambda1_estimate(),
                condition_1_holds: c.drive().condition_holds(),
                constant_stimuli: Vec::new(),
                factorisation_reuses: 0,
                factorisations: 0,
                continuous: Some(c.stats().into()),
            },
            cost: cost::estimate(&session.model, &session.config),
            curiosity: None,
        };
    }
    let Some(agent) = st.learner.agent() else {
        unreachable!("a learner is discrete or continuous");
    };
    let stats = agent.planner().stats();
    SessionInfo {
        id: session.id.clone(),
        tick: agent.tick(),
        drive: agent.drive().vector().to_vec(),
        policy_version: agent.policy_version(),
        next_seq: st.next_seq(),
        state: agent.state(),
        model: ModelSummary::clone(&session.model),
        agent: session.config.clone(),
        stats: SessionStats {
            lstdq_error: agent.last_plan().lstdq_error,
            lambda1_estimate: agent.drive().lambda1_estimate(),
            condition_1_holds: agent.drive().condition_holds(),
            constant_stimuli: agent.stimulus().constant_columns(),
            factorisation_reuses: stats.reuses,
            factorisations: stats.factorisations,
            continuous: None,
        },
        cost: cost::estimate(&session.model, &session.config),
        curiosity: st.learner.curious().map(CuriosityInfo::of),
    }
}
