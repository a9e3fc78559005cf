//! The session manager: the one entry point both transports call. It owns
//! the sessions, the tick pool and the store's durability settings, and
//! routes each call: create (built by [`super::setup`]), get, list, delete,
//! observe (applied by [`super::session`], made durable before the reply,
//! rolled back by a reload after a storage failure), values
//! ([`super::values`]) and history; [`super::recovery`] rebuilds the stored
//! sessions at start.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use parking_lot::{Mutex, RwLock};
use tokio::sync::oneshot;

use mcapi_store::{Store, Write};

use super::agent_config::{SessionConfig, UpdateMode};
use super::auth::{ApiKeys, Caller};
use super::cost;
use super::durable;
use super::error::{RecoveryError, ServiceError, StorageError};
use super::limits::Limits;
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

/// The session manager: owns sessions, shared models and the tick pool.
pub struct SessionManager {
    sessions: RwLock<SessionTable>,
    /// Builds sessions: shared planning models, seeds, bounded builds.
    setup: Arc<Setup>,
    limits: Limits,
    pool: TickPool,
    inline_plan_ns: u64,
    durability: Option<Durability>,
    keys: ApiKeys,
    /// False while stored sessions are being recovered.
    ready: AtomicBool,
    /// Held while a session is reloaded after a storage failure.
    reloading: Mutex<()>,
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
            evict_after,
            setup: Arc::new(Setup::new(workers)),
            limits,
            pool,
            inline_plan_ns: u64::try_from(inline_plan.as_nanos()).unwrap_or(u64::MAX),
            durability,
            keys,
            ready,
            reloading: Mutex::new(()),
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

    /// Creates a session. Synchronous and possibly slow (a PVF basis costs
    /// an eigendecomposition; with a store, the creation is committed before
    /// this returns): call it off the async runtime.
    pub fn create(&self, caller: Caller, req: CreateSession) -> Result<SessionInfo, ServiceError> {
        let CreateSession { model, agent } = req;
        if self.len() >= self.limits.max_sessions {
            return Err(ServiceError::TooManySessions(self.limits.max_sessions));
        }
        let model_text = self.durability.as_ref().map(|_| model.to_string());
        let input = ModelInput::parse(model)?;
        self.create_from(caller, input, &agent, model_text)
    }

    /// Creates a session from a model already parsed (gRPC's typed `Model`,
    /// converted in `api::grpc::convert`); otherwise as [`Self::create`],
    /// with the same checks in the same order.
    pub fn create_parsed(
        &self,
        caller: Caller,
        input: ModelInput,
        agent: &SessionConfig,
    ) -> Result<SessionInfo, ServiceError> {
        if self.len() >= self.limits.max_sessions {
            return Err(ServiceError::TooManySessions(self.limits.max_sessions));
        }
        let model_text = match &self.durability {
            Some(_) => Some(input.to_json_text()?),
            None => None,
        };
        self.create_from(caller, input, agent, model_text)
    }

    fn create_from(
        &self,
        caller: Caller,
        input: ModelInput,
        agent: &SessionConfig,
        model_text: Option<String>,
    ) -> Result<SessionInfo, ServiceError> {
        let owner = caller.owner();
        // Refused early when the key's quota of sessions is used up.
        self.limits.check_cost(
            &SessionCost {
                bytes: 0,
                tick_us: 0,
            },
            self.sessions.read().usage(&owner),
        )?;
        let (learner, summary, config) = self.setup.build(&input, agent, &self.limits)?;
        let cost = cost::estimate(&summary, &config);
        self.limits
            .check_cost(&cost, self.sessions.read().usage(&owner))?;
        // Held until the session is in the table: a move freezing the
        // shard waits for it (docs/cluster.md, "How a shard moves").
        let (shard, _guard) = match &self.placement {
            // Only in a shard owned here, so a create is never misdirected.
            Some(p) => {
                let guard = p.mint(self.setup.fresh_u64()).ok_or_else(|| {
                    ServiceError::Unavailable(format!(
                        "replica `{}` owns no shard open for new sessions right now; retry (the router sends creates to every replica in turn)",
                        p.replica()
                    ))
                })?;
                (guard.shard(), Some(guard))
            }
            None => ((self.setup.fresh_u64() % SHARDS) as u16, None),
        };
        let id = format!("s{shard:04x}.{}", ulid::Ulid::new());
        if let (Some(d), Some(model)) = (&self.durability, model_text) {
            let record = durable::SessionRecord {
                model,
                config: config.clone(),
                owner: caller.owner(),
            };
            let bytes = serde_json::to_vec(&record)
                .map_err(|e| ServiceError::Internal(format!("encoding a session record: {e}")))?;
            d.store
                .submit(vec![mcapi_store::Write::Session {
                    id: Arc::from(id.as_str()),
                    record: bytes,
                }])
                .wait_blocking()
                .map_err(ServiceError::from)?;
        }
        let session = Arc::new(Session::resume(
            id.clone(),
            learner,
            summary,
            config,
            self.durability.clone(),
            session::Resumed {
                owner: caller.owner(),
                // What a rebuild from its record gives, until it observes.
                pristine: true,
                ..session::Resumed::default()
            },
        ));
        {
            let mut sessions = self.sessions.write();
            // Checked again under the lock: concurrent creates see each other.
            let refused = if sessions.len() >= self.limits.max_sessions {
                Some(ServiceError::TooManySessions(self.limits.max_sessions))
            } else {
                self.limits.check_cost(&cost, sessions.usage(&owner)).err()
            };
            if let Some(e) = refused {
                drop(sessions);
                // Undo the stored record; the client sees the limit.
                if let Some(commit) = session.delete() {
                    let _ = commit.wait_blocking();
                }
                return Err(e);
            }
            sessions.insert(id.clone(), Arc::clone(&session));
            metrics::gauge!("mcapi_sessions").set(sessions.len() as f64);
        }
        tracing::info!(session = %id, states = session.model.states, "session created");
        Ok(info_of(&session))
    }

    /// The session with this id, whoever owns it, loaded back if it was
    /// evicted (blocking then: call off the async runtime).
    pub fn session(&self, id: &str) -> Result<SessionRef, ServiceError> {
        let entry = self.entry(id)?;
        self.loaded(id, entry)
    }

    /// The table's entry for `id`.
    fn entry(&self, id: &str) -> Result<Entry, ServiceError> {
        self.sessions
            .read()
            .get(id)
            .cloned()
            .ok_or_else(|| ServiceError::NotFound(id.to_string()))
    }

    /// The session with this id if it is in memory (never loads).
    fn resident(&self, id: &str) -> Option<SessionRef> {
        self.sessions
            .read()
            .get(id)
            .and_then(Entry::resident)
            .cloned()
    }

    /// The session of `entry`, loaded back if it is evicted (blocking).
    fn loaded(&self, id: &str, entry: Entry) -> Result<SessionRef, ServiceError> {
        match entry {
            Entry::Resident(s) => Ok(s),
            Entry::Evicted(stub) => {
                let d = self.evicted_store(id)?;
                let fresh = recovery::load(&self.setup, &self.limits, d, id, stub.lsn)?;
                let was = Entry::Evicted(stub);
                self.install(id, &was, fresh)
            }
        }
    }

    /// [`Self::loaded`] for the async paths: an evicted session is loaded
    /// back on the blocking pool.
    async fn loaded_async(&self, id: &str, entry: Entry) -> Result<SessionRef, ServiceError> {
        match entry {
            Entry::Resident(s) => Ok(s),
            Entry::Evicted(stub) => {
                let d = self.evicted_store(id)?.clone();
                let (setup, limits, owned, lsn) = (
                    Arc::clone(&self.setup),
                    self.limits.clone(),
                    id.to_string(),
                    stub.lsn,
                );
                let was = Entry::Evicted(stub);
                let fresh = tokio::task::spawn_blocking(move || {
                    recovery::load(&setup, &limits, &d, &owned, lsn)
                })
                .await
                .map_err(|e| {
                    ServiceError::Internal(format!("loading a session back failed: {e}"))
                })??;
                self.install(id, &was, fresh)
            }
        }
    }

    fn evicted_store(&self, id: &str) -> Result<&Durability, ServiceError> {
        self.durability.as_ref().ok_or_else(|| {
            ServiceError::Internal(format!("session `{id}` is evicted but there is no store"))
        })
    }

    /// Puts a session loaded back in place of its eviction `was`. Two
    /// requests may load the same session at once: both rebuilt it from
    /// the same stored state, the first to get here is served and the
    /// other's copy dropped. Gone meanwhile (deleted, its shard moved):
    /// `NotFound`.
    fn install(
        &self,
        id: &str,
        was: &Entry,
        fresh: SessionRef,
    ) -> Result<SessionRef, ServiceError> {
        if let Entry::Evicted(stub) = was {
            fresh.set_last_observed_ns(stub.last_observed_ns);
        }
        let mut sessions = self.sessions.write();
        if sessions.swap(id, was, Entry::Resident(Arc::clone(&fresh))) {
            metrics::gauge!("mcapi_sessions_evicted").set(sessions.evicted() as f64);
            drop(sessions);
            metrics::counter!("mcapi_session_loads_total").increment(1);
            return Ok(fresh);
        }
        match sessions.get(id) {
            Some(Entry::Resident(s)) => Ok(Arc::clone(s)),
            _ => Err(ServiceError::NotFound(id.to_string())),
        }
    }

    /// The session with this id if `caller` may see it; another key's
    /// session is `NotFound`, exactly like a missing one. A quarantined
    /// session is [`ServiceError::SessionFailed`] (see [`Session::is_failed`]).
    /// A session whose commit failed is first rolled back to its durable
    /// state (reloaded, see [`SessionManager::visible_session`]).
    pub fn session_for(&self, caller: Caller, id: &str) -> Result<SessionRef, ServiceError> {
        not_failed(self.visible_session(caller, id)?)
    }

    /// [`SessionManager::session_for`], quarantined sessions included (for
    /// `delete`). A session whose commit failed is first rolled back to its
    /// durable state (reloaded), so nothing that was not made durable is
    /// ever served; while that cannot be done, `Storage`. An evicted
    /// session is loaded back (blocking: call off the async runtime).
    ///
    /// Clustered, a session whose shard is not served here is refused
    /// before it is looked up ([`Placement::check`]): 421 naming the owner,
    /// or 503 while the shard moves; both transports come through here.
    pub fn visible_session(&self, caller: Caller, id: &str) -> Result<SessionRef, ServiceError> {
        let entry = self.visible_entry(caller, id)?;
        let session = self.loaded(id, entry)?;
        self.rolled_back(id, session)
    }

    /// [`Self::visible_session`] for the async paths (an evicted session
    /// is loaded back on the blocking pool).
    async fn visible_session_async(
        &self,
        caller: Caller,
        id: &str,
    ) -> Result<SessionRef, ServiceError> {
        let entry = self.visible_entry(caller, id)?;
        let session = self.loaded_async(id, entry).await?;
        self.rolled_back(id, session)
    }

    /// The entry of a session served here that `caller` may see.
    fn visible_entry(&self, caller: Caller, id: &str) -> Result<Entry, ServiceError> {
        if let Some(p) = &self.placement {
            p.check(id)?;
        }
        let entry = self.entry(id)?;
        if !caller.may_see(entry.owner().as_ref()) {
            return Err(ServiceError::NotFound(id.to_string()));
        }
        Ok(entry)
    }

    /// `session`, first rolled back to its durable state if a commit of it
    /// failed.
    fn rolled_back(&self, id: &str, session: SessionRef) -> Result<SessionRef, ServiceError> {
        if !session.is_stale() {
            return Ok(session);
        }
        self.reload(&session).map_err(|e| StorageError::Rollback {
            id: id.to_string(),
            source: Box::new(e),
        })?;
        self.session(id)
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

    /// Details of a session.
    #[tracing::instrument(level = "debug", skip(self))]
    pub fn get(&self, caller: Caller, id: &str) -> Result<SessionInfo, ServiceError> {
        Ok(info_of(&*self.session_for(caller, id)?))
    }

    /// Up to `limit` sessions with ids after `after`, in id order.
    pub fn list(
        &self,
        caller: Caller,
        after: Option<&str>,
        limit: Option<usize>,
    ) -> Result<SessionPage, ServiceError> {
        let limit = limit.unwrap_or(DEFAULT_PAGE);
        if limit == 0 || limit > MAX_PAGE {
            return Err(ServiceError::field(
                "limit",
                format!("must be between 1 and {MAX_PAGE}"),
            ));
        }
        let sessions = self.sessions.read();
        let page: Vec<(String, Entry)> = sessions
            .after(after)
            .filter(|(_, e)| caller.may_see(e.owner().as_ref()))
            .take(limit + 1)
            .map(|(id, e)| (id.clone(), e.clone()))
            .collect();
        drop(sessions);
        let next = (page.len() > limit).then(|| page[limit - 1].0.clone());
        let ms = |d: std::time::Duration| u64::try_from(d.as_millis()).unwrap_or(u64::MAX);
        let sessions = page
            .into_iter()
            .take(limit)
            .map(|(id, entry)| match entry {
                Entry::Resident(s) => SessionSummary {
                    id,
                    tick: s.state.lock().learner.agent().tick(),
                    states: s.model.states,
                    update_mode: s.mode,
                    idle_ms: s.idle().map(ms),
                },
                // Listed from the table, not loaded.
                Entry::Evicted(e) => SessionSummary {
                    id,
                    tick: e.tick,
                    states: e.states,
                    update_mode: e.mode,
                    idle_ms: session::idle_since(e.last_observed_ns).map(ms),
                },
            })
            .collect();
        Ok(SessionPage { sessions, next })
    }

    /// Deletes a session and, with a store, its stored data. The deletion is
    /// committed before anything is removed: if the commit fails, the
    /// session stays and is served as before (the client gets
    /// `storage_unavailable` and may retry); once it returns `Ok`, the
    /// session is gone, restarts included.
    #[tracing::instrument(level = "debug", skip(self))]
    pub async fn delete(&self, caller: Caller, id: &str) -> Result<(), ServiceError> {
        let _guard = self.enter_shard(id)?;
        let session = self.visible_session_async(caller, id).await?;
        self.store_writable()?;
        let result = match session.begin_delete()? {
            Some(commit) => commit.wait().await.map_err(ServiceError::from),
            None => Ok(()),
        };
        // A reload during the commit may have replaced the session in the
        // map; the delete ends on both.
        let current = self.resident(id).filter(|s| !Arc::ptr_eq(s, &session));
        if let Err(e) = result {
            session.end_delete(false);
            if let Some(s) = current {
                s.end_delete(false);
            }
            tracing::warn!(session = %id, error = %e, "session not deleted: its deletion was not committed");
            return Err(e);
        }
        {
            let mut sessions = self.sessions.write();
            sessions.remove(id);
            metrics::gauge!("mcapi_sessions").set(sessions.len() as f64);
        }
        session.end_delete(true);
        if let Some(s) = current {
            s.end_delete(true);
        }
        tracing::info!(session = %id, "session deleted");
        Ok(())
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
        if let Err(ServiceError::Storage(detail)) = &result {
            // The observations are applied in memory but not durable, and
            // the store refuses the session's writes from now on: roll it
            // back to what is durable before it takes another observation.
            // Rare, and a few milliseconds of reading: done on this task.
            tracing::warn!(session = %id, error = %detail, "reloading the session after a failed commit");
            if let Err(e) = self.reload(&session) {
                tracing::error!(session = %id, error = %e, "reload failed; the session takes no observations until one succeeds");
            }
        }
        result
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

    async fn observe_on(
        &self,
        session: &SessionRef,
        batch: Vec<ObservationIn>,
    ) -> Result<Vec<StepOut>, ServiceError> {
        let session = Arc::clone(session);
        let n = batch.len() as u64;
        // Updates measured to be cheap run here: a hand-off to the pool
        // would cost more than the update itself.
        let inline = session.plan_cost_ns().saturating_mul(n) <= self.inline_plan_ns;
        let out = match session.mode {
            UpdateMode::Lockstep if inline => {
                let started = Instant::now();
                let observed = session.observe(&batch, true);
                tick::meters()
                    .tick_seconds
                    .record(started.elapsed().as_secs_f64());
                if let Err(e @ ServiceError::Algo(mcapi_core::AlgoError::Numerical(_))) =
                    &observed.result
                {
                    tick::log_plan_error(&session, e);
                }
                observed.durable().await?
            }
            UpdateMode::Lockstep => {
                let (tx, rx) = oneshot::channel();
                self.pool.submit(Job::Observe {
                    session,
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
            UpdateMode::Async => {
                // Observing alone recomputes R for every pair and, with a
                // curiosity channel, learns each signal sample: beyond the
                // inline budget that runs on the blocking pool.
                let observe_ns = cost::observe_us(&session.model, &session.config)
                    .saturating_mul(1000)
                    .saturating_mul(n);
                let observed = if observe_ns <= self.inline_plan_ns.max(50_000) {
                    session.observe(&batch, false)
                } else {
                    let session = Arc::clone(&session);
                    tokio::task::spawn_blocking(move || session.observe(&batch, false))
                        .await
                        .map_err(|e| {
                            ServiceError::Internal(format!("an observation task failed: {e}"))
                        })?
                };
                if inline && observed.result.is_ok() {
                    let started = Instant::now();
                    match session.plan_if_needed() {
                        Ok(true) => tick::meters()
                            .tick_seconds
                            .record(started.elapsed().as_secs_f64()),
                        Ok(false) => {}
                        Err(e) => tick::log_plan_error(&session, &e),
                    }
                } else if session.try_enqueue()
                    && let Err(e) = self.pool.submit(Job::Plan(Arc::clone(&session)))
                {
                    session.dequeued();
                    tracing::warn!(session = %session.id, error = %e, "policy update not queued");
                }
                observed.durable().await?
            }
        };
        tick::meters().observations.increment(n);
        Ok(out)
    }

    /// Value tables of a session.
    #[tracing::instrument(level = "debug", skip(self))]
    pub fn values(
        &self,
        caller: Caller,
        id: &str,
        sel: ValueSelection,
    ) -> Result<Values, ServiceError> {
        let session = self.session_for(caller, id)?;
        sel.check_size(&session.model, self.limits.max_response_bytes)?;
        Ok(values::tables(&session, sel))
    }

    /// The most recent `limit` ticks of a session's history, oldest first.
    pub fn history(
        &self,
        caller: Caller,
        id: &str,
        limit: Option<usize>,
    ) -> Result<Vec<HistoryEntry>, ServiceError> {
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
        Ok(session.history(limit))
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
    let agent = st.learner.agent();
    let stats = agent.planner().stats();
    SessionInfo {
        id: session.id.clone(),
        tick: agent.tick(),
        drive: agent.drive().vector().to_vec(),
        policy_version: agent.policy_version(),
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
        },
        cost: cost::estimate(&session.model, &session.config),
        curiosity: st.learner.curious().map(CuriosityInfo::of),
    }
}

impl SessionManager {
    /// Loads every stored session ([`recovery::recover_all`]) and marks the
    /// manager ready when done. A session whose records do not decode or
    /// replay is skipped (logged, counted, listed in the report, its data
    /// left in the store); a store that cannot be read fails the recovery.
    pub fn recover(&self) -> Result<RecoveryReport, ServiceError> {
        let Some(d) = &self.durability else {
            self.ready.store(true, Ordering::Release);
            return Ok(RecoveryReport::default());
        };
        let placement = self.placement.as_deref();
        // With eviction, recovered sessions stay in the store until their
        // first request: a store of a million sessions starts without
        // needing them all in memory at once.
        // A rebuilt session is pristine: it goes unless an update is due.
        let keep = |session: SessionRef| match self.evict_after {
            Some(_) => session
                .still_evictable(cost::estimate(&session.model, &session.config))
                .map_or(Entry::Resident(session), |stub| {
                    Entry::Evicted(Arc::new(stub))
                }),
            None => Entry::Resident(session),
        };
        let (rebuilt, report) =
            recovery::recover_all(&self.setup, &self.limits, d, placement, keep)?;
        if report.not_owned > 0 {
            tracing::warn!(
                sessions = report.not_owned,
                store = %d.store.path().display(),
                "stored sessions of shards this replica does not own are kept in the store, not served"
            );
        }
        let mut sessions = self.sessions.write();
        for (id, entry) in rebuilt {
            sessions.insert_entry(id, entry);
        }
        metrics::gauge!("mcapi_sessions").set(sessions.len() as f64);
        metrics::gauge!("mcapi_sessions_evicted").set(sessions.evicted() as f64);
        drop(sessions);
        if report.skipped > 0 {
            tracing::warn!(
                skipped = report.skipped,
                ids = ?report.skipped_ids,
                store = %d.store.path().display(),
                "stored sessions skipped at recovery"
            );
        }
        // Logged before the server reports ready, so whoever sees it ready
        // finds the line in the log.
        if report.sessions > 0 {
            tracing::info!(
                sessions = report.sessions,
                replayed = report.replayed,
                seconds = report.seconds,
                evicted = self.evicted_len(),
                "sessions recovered"
            );
        }
        self.ready.store(true, Ordering::Release);
        Ok(report)
    }

    /// Replaces a session whose commit failed by a fresh recovery of its
    /// durable state (snapshot and log, as at start, [`recovery::rebuild`]),
    /// then lets the store accept its writes again
    /// ([`mcapi_store::Write::Resume`]). The old session is marked stale
    /// first, so nothing is applied to it while this runs. A no-op if the
    /// session was deleted or already replaced.
    pub fn reload(&self, session: &SessionRef) -> Result<(), RecoveryError> {
        let Some(d) = &self.durability else {
            return Ok(());
        };
        session.mark_stale();
        let _one_at_a_time = self.reloading.lock();
        let current = |sessions: &SessionTable| {
            sessions
                .get(&session.id)
                .and_then(Entry::resident)
                .is_some_and(|s| Arc::ptr_eq(s, session))
        };
        if !current(&self.sessions.read()) {
            return Ok(());
        }
        let stored = d
            .store
            .session(&session.id)?
            .ok_or_else(|| RecoveryError::Missing(session.id.clone()))?;
        let (fresh, replayed) = recovery::rebuild(&self.setup, &self.limits, d, stored)?;
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

    /// Number of sessions evicted to the store (docs/sessions.md, "Idle
    /// sessions").
    pub fn evicted_len(&self) -> usize {
        self.sessions.read().evicted()
    }

    /// Starts the evictor: a thread that, four times per `evict_after`
    /// (at most once a minute, at least every 10 ms), evicts the sessions
    /// inactive that long ([`Self::evict_idle`]), so a session leaves
    /// between `evict_after` and 1.25 `evict_after` after its last
    /// observation; a pass over a million resident sessions touches each
    /// once. Nothing without a store or `evict_after`. It stops with
    /// [`Self::shutdown`] or when the manager is dropped.
    pub fn start_evictor(self: &Arc<Self>) -> std::io::Result<()> {
        let Some(after) = self.evict_after else {
            return Ok(());
        };
        let period = (after / 4).clamp(Duration::from_millis(10), Duration::from_secs(60));
        let manager = Arc::downgrade(self);
        std::thread::Builder::new()
            .name("mcapi-evict".into())
            .spawn(move || {
                loop {
                    std::thread::sleep(period);
                    let Some(m) = manager.upgrade() else { break };
                    if m.stopping.load(Ordering::Acquire) {
                        break;
                    }
                    if m.is_ready() {
                        m.evict_idle(after);
                    }
                }
            })
            .map(drop)
    }

    /// One eviction pass: every resident session inactive for at least
    /// `idle` whose state the store rebuilds bit for bit leaves memory,
    /// after a snapshot if it changed since it was built
    /// ([`Session::prepare_eviction`]); the table keeps a stub of it
    /// ([`super::table::Evicted`]) and its next request loads it back.
    /// A session in use (a request or a tick job holds it), with a policy
    /// update pending, being deleted or rolled back stays. The table is
    /// read a chunk at a time and written once per chunk, so requests are
    /// not held up by a pass over a million sessions. Returns how many
    /// left. Blocking.
    pub fn evict_idle(&self, idle: Duration) -> usize {
        if self.durability.is_none() {
            return 0;
        }
        let mut after: Option<String> = None;
        let mut evicted = 0;
        loop {
            let (candidates, last) = {
                let sessions = self.sessions.read();
                let mut candidates = Vec::new();
                let mut last = None;
                for (id, entry) in sessions.after(after.as_deref()).take(EVICT_CHUNK) {
                    last = Some(id);
                    if let Entry::Resident(s) = entry
                        && Arc::strong_count(s) == 1
                        && s.inactive() >= idle
                    {
                        candidates.push(Arc::clone(s));
                    }
                }
                (candidates, last.cloned())
            };
            let prepared: Vec<_> = candidates
                .into_iter()
                .filter_map(|s| s.prepare_eviction().map(|commit| (s, commit)))
                .collect();
            let mut ready = Vec::with_capacity(prepared.len());
            for (s, commit) in prepared {
                match commit.map(mcapi_store::Commit::wait_blocking).transpose() {
                    Ok(_) => ready.push(s),
                    Err(e) => {
                        s.not_pristine();
                        tracing::warn!(session = %s.id, error = %e, "session kept in memory: its eviction snapshot was not committed");
                    }
                }
            }
            if !ready.is_empty() {
                let mut sessions = self.sessions.write();
                for s in &ready {
                    // Held by the table and `ready` only: no request or
                    // job has it, and none can take it while the lock is
                    // held.
                    if Arc::strong_count(s) != 2 {
                        continue;
                    }
                    let Some(stub) = s.still_evictable(cost::estimate(&s.model, &s.config)) else {
                        continue;
                    };
                    let was = Entry::Resident(Arc::clone(s));
                    if sessions.swap(&s.id, &was, Entry::Evicted(Arc::new(stub))) {
                        evicted += 1;
                    }
                }
                metrics::gauge!("mcapi_sessions_evicted").set(sessions.evicted() as f64);
                drop(sessions);
                // The sessions are freed here, outside the lock.
                drop(ready);
            }
            match last {
                Some(id) => after = Some(id),
                None => break,
            }
        }
        if evicted > 0 {
            metrics::counter!("mcapi_session_evictions_total").increment(evicted as u64);
            tracing::debug!(sessions = evicted, "idle sessions evicted to the store");
        }
        evicted
    }
}
