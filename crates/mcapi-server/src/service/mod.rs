//! The one session layer both transports call (DESIGN.md, "Layers"): create,
//! get, list, delete, observe, values and history of hosted agents, the
//! limits, and the tick loop that runs policy updates off the request path.

pub mod auth;
pub mod cost;
pub mod durable;
pub mod error;
pub mod limits;
mod recovery;
pub mod session;
pub mod spec;
pub mod table;
pub mod tick;

#[cfg(test)]
mod fault_tests;

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use parking_lot::{Mutex, RwLock};
use serde::{Deserialize, Serialize};
use tokio::sync::oneshot;

use crate::store::Store;
use mcapi_core::{Agent, Basis, CuriousAgent, PlanningModel};

pub use auth::{ApiKeys, Caller};
pub use cost::SessionCost;
pub use error::ServiceError;
pub use limits::{Limits, Usage};
pub use recovery::RecoveryReport;
pub use session::{
    Durability, HistoryEntry, Learner, ObservationIn, Session, SessionRef, StepOut, TickCuriosity,
};
pub use spec::{
    BasisSummary, CreateSession, CuriosityConfig, EffectiveConfig, ModelInput, ModelSummary,
    SessionConfig, UpdateMode,
};
use table::SessionTable;
use tick::{Job, TickPool};

/// Number of virtual shards in session ids (fixed forever, DESIGN.md).
pub const SHARDS: u64 = 1024;

/// Default and maximum page size of `list`.
pub const DEFAULT_PAGE: usize = 100;
/// Largest page `list` returns.
pub const MAX_PAGE: usize = 1000;

/// A session as `get` returns it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionInfo {
    /// `s<shard>.<ULID>`.
    pub id: String,
    /// Ticks so far.
    pub tick: u64,
    /// The drive D.
    pub drive: Vec<f64>,
    /// Policy updates applied.
    pub policy_version: u64,
    /// The agent's current state, once it has observed one.
    pub state: Option<usize>,
    /// The model.
    pub model: ModelSummary,
    /// Effective configuration.
    pub agent: EffectiveConfig,
    /// Statistics of the learner.
    pub stats: SessionStats,
    /// The session's estimated memory and per-observation CPU time, as
    /// checked against the server's budgets when it was created.
    pub cost: SessionCost,
    /// The curiosity channel, for a session with one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curiosity: Option<CuriosityInfo>,
}

/// The state of a session's curiosity channel (ALGORITHM.md §7).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CuriosityInfo {
    /// Signal samples received.
    pub samples: u64,
    /// The active module's estimation error ε.
    pub epsilon: f64,
    /// The source the active module learns, once bound.
    pub active_source: Option<usize>,
    /// Samples the active module learned from.
    pub active_samples: u64,
    /// Every known source is explained by a frozen module: condition (3)
    /// holds and D\[curiosity\] is held at 0.
    pub all_explained: bool,
    /// The module library, in freezing order.
    pub modules: Vec<FrozenModuleInfo>,
}

/// One frozen module of the library.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct FrozenModuleInfo {
    /// The source it learned.
    pub source: usize,
    /// The session's tick when it froze.
    pub frozen_tick: u64,
    /// Samples it learned from before freezing.
    pub learned_samples: u64,
}

impl CuriosityInfo {
    fn of(agent: &CuriousAgent) -> Self {
        let channel = agent.channel();
        let active = channel.active();
        Self {
            samples: channel.samples(),
            epsilon: channel.epsilon(),
            active_source: active.source(),
            active_samples: active.learned_samples(),
            all_explained: channel.all_explained(),
            modules: channel
                .library()
                .iter()
                .zip(agent.frozen_ticks())
                .map(|(m, &tick)| FrozenModuleInfo {
                    source: m.source(),
                    frozen_tick: tick,
                    learned_samples: m.learned_samples(),
                })
                .collect(),
        }
    }
}

/// Learner statistics of a session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionStats {
    /// ‖Q_t − Q_{t+1}‖ of the last policy update.
    pub lstdq_error: f64,
    /// Running estimate of λ₁ of E[Λξ ξᵀΛ] (condition (1)).
    pub lambda1_estimate: f64,
    /// Whether η λ₁ < 0.5 holds for the estimate.
    pub condition_1_holds: bool,
    /// Stimulus dimensions whose column of Ξ is constant (condition (3)).
    pub constant_stimuli: Vec<usize>,
    /// Policy updates that reused the factorisation.
    pub factorisation_reuses: u64,
    /// Full factorisations of A.
    pub factorisations: u64,
}

/// One line of `list`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionSummary {
    /// Session id.
    pub id: String,
    /// Ticks so far.
    pub tick: u64,
    /// Number of states of its model.
    pub states: usize,
    /// Update mode.
    pub update_mode: UpdateMode,
    /// Milliseconds since its last applied observation; absent if it had
    /// none since the server started.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub idle_ms: Option<u64>,
}

/// A page of sessions, ordered by id.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionPage {
    /// The sessions.
    pub sessions: Vec<SessionSummary>,
    /// Pass as `after` for the next page; absent on the last page.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub next: Option<String>,
}

/// Which value tables to return.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ValueSelection {
    /// V(s).
    pub v: bool,
    /// Q(s, a).
    pub q: bool,
    /// Greedy action per state.
    pub policy: bool,
    /// R(s, a).
    pub r: bool,
    /// Ξ(s, a).
    pub xi: bool,
}

impl ValueSelection {
    /// Parses `v,q,policy,r,xi` (any subset); empty means `v,policy`.
    pub fn parse(include: Option<&str>) -> Result<Self, ServiceError> {
        let Some(include) = include.filter(|s| !s.trim().is_empty()) else {
            return Ok(Self {
                v: true,
                policy: true,
                ..Self::default()
            });
        };
        let mut sel = Self::default();
        for part in include.split(',').map(str::trim) {
            match part {
                "v" => sel.v = true,
                "q" => sel.q = true,
                "policy" => sel.policy = true,
                "r" => sel.r = true,
                "xi" => sel.xi = true,
                "all" => {
                    sel = Self {
                        v: true,
                        q: true,
                        policy: true,
                        r: true,
                        xi: true,
                    }
                }
                other => {
                    return Err(ServiceError::field(
                        "include",
                        format!("unknown table `{other}` (choose from v, q, policy, r, xi, all)"),
                    ));
                }
            }
        }
        Ok(sel)
    }
}

/// Value tables of a session; per-pair tables are `[state][action]`, null
/// where the action is unavailable.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Values {
    /// Ticks so far.
    pub tick: u64,
    /// Policy updates applied.
    pub policy_version: u64,
    /// V(s) = Q(s, π(s)).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub v: Option<Vec<f64>>,
    /// Q(s, a).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub q: Option<Vec<Vec<Option<f64>>>>,
    /// Greedy action name per state.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub policy: Option<Vec<String>>,
    /// R(s, a) = |Ξ Λ D| as of the last update.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub r: Option<Vec<Vec<Option<f64>>>>,
    /// Ξ(s, a), one vector per pair.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub xi: Option<Vec<Vec<Option<Vec<f64>>>>>,
    /// The curiosity channel (ε, module library), for a session with one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curiosity: Option<CuriosityInfo>,
}

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
        }
    }
}

/// The session manager: owns sessions, shared models and the tick pool.
pub struct SessionManager {
    sessions: RwLock<SessionTable>,
    models: Mutex<HashMap<String, (Weak<PlanningModel>, Built)>>,
    limits: Limits,
    pool: TickPool,
    seed_counter: AtomicU64,
    inline_plan_ns: u64,
    durability: Option<Durability>,
    keys: ApiKeys,
    /// False while stored sessions are being recovered.
    ready: AtomicBool,
    /// Held while a session is reloaded after a storage failure.
    reloading: Mutex<()>,
    /// Bounds the planning models being built at once (a PVF basis costs an
    /// eigendecomposition).
    builds: BuildSlots,
}

/// A counting semaphore for model builds: at most `slots` at once, and at
/// most `queue` more waiting; beyond that a create is refused with 503
/// instead of piling up blocking threads.
struct BuildSlots {
    state: Mutex<(usize, usize)>,
    freed: parking_lot::Condvar,
    slots: usize,
    queue: usize,
}

struct BuildSlot<'a>(&'a BuildSlots);

impl BuildSlots {
    fn new(slots: usize) -> Self {
        Self {
            state: Mutex::new((0, 0)),
            freed: parking_lot::Condvar::new(),
            slots: slots.max(1),
            queue: 8 * slots.max(1),
        }
    }

    /// Waits for a slot (blocking: call off the async runtime).
    fn acquire(&self) -> Result<BuildSlot<'_>, ServiceError> {
        let mut st = self.state.lock();
        if st.0 >= self.slots {
            if st.1 >= self.queue {
                return Err(ServiceError::Unavailable(format!(
                    "{} sessions are being created and {} more wait; retry shortly",
                    st.0, st.1
                )));
            }
            st.1 += 1;
            while st.0 >= self.slots {
                self.freed.wait(&mut st);
            }
            st.1 -= 1;
        }
        st.0 += 1;
        Ok(BuildSlot(self))
    }
}

impl Drop for BuildSlot<'_> {
    fn drop(&mut self) {
        self.0.state.lock().0 -= 1;
        self.0.freed.notify_one();
    }
}

/// What the model summaries of sessions sharing a planning model take from
/// its one build: the basis chosen and the grid layout.
#[derive(Debug, Clone)]
struct Built {
    basis: BasisSummary,
    layout: Option<spec::GridLayout>,
}

/// SplitMix64, for seeds and shards.
fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
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
        } = opts;
        let ready = AtomicBool::new(store.is_none());
        let durability = store.map(|store| Durability {
            store,
            snapshot_every: snapshot_every.max(1),
        });
        let pool = TickPool::start(workers, limits.queue)
            .map_err(|e| ServiceError::Internal(format!("starting tick workers: {e}")))?;
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        Ok(Self {
            sessions: RwLock::new(SessionTable::default()),
            models: Mutex::new(HashMap::new()),
            limits,
            pool,
            seed_counter: AtomicU64::new(splitmix(now ^ u64::from(std::process::id()))),
            inline_plan_ns: u64::try_from(inline_plan.as_nanos()).unwrap_or(u64::MAX),
            durability,
            keys,
            ready,
            reloading: Mutex::new(()),
            builds: BuildSlots::new(workers),
        })
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

    fn fresh_u64(&self) -> u64 {
        splitmix(
            self.seed_counter
                .fetch_add(0x9E37_79B9_7F4A_7C15, Ordering::Relaxed),
        )
    }

    /// The shared planning model for `input`, built once per distinct model,
    /// with what a session's model summary takes from its build.
    fn planning_model(
        &self,
        input: &ModelInput,
        curious: bool,
        limits: &Limits,
    ) -> Result<(Arc<PlanningModel>, Built), ServiceError> {
        let key = format!("{}:curious={curious}", input.cache_key());
        if let Some((weak, built)) = self.models.lock().get(&key)
            && let Some(ctx) = weak.upgrade()
        {
            return Ok((ctx, built.clone()));
        }
        // Built outside the lock (PVFs cost an eigendecomposition), a few at
        // a time.
        let _slot = self.builds.acquire()?;
        let (model, basis_spec) = input.build(limits, curious)?;
        let basis = Basis::build(&basis_spec, &model)?;
        let built = Built {
            basis: BasisSummary::of(&basis_spec),
            layout: input.layout(),
        };
        let ctx = Arc::new(PlanningModel::new(model, basis));
        let mut models = self.models.lock();
        models.retain(|_, (w, _)| w.strong_count() > 0);
        if let Some((weak, existing_built)) = models.get(&key)
            && let Some(existing) = weak.upgrade()
        {
            return Ok((existing, existing_built.clone()));
        }
        models.insert(key, (Arc::downgrade(&ctx), built.clone()));
        Ok((ctx, built))
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
                ServiceError::Storage(format!(
                    "the store {} cannot write after a storage fault ({why}); it is reopened automatically once the fault clears",
                    d.store.path().display()
                ))
            }),
            None => Ok(()),
        }
    }

    /// Builds the agent of a session (fresh, or the base of a recovery).
    fn build(
        &self,
        input: &ModelInput,
        agent: &SessionConfig,
        limits: &Limits,
    ) -> Result<(Learner, ModelSummary, EffectiveConfig), ServiceError> {
        limits.check_config(agent)?;
        let (ctx, built) = self.planning_model(input, agent.curiosity.is_some(), limits)?;
        let model = ctx.model();
        let history = agent.history.unwrap_or(spec::DEFAULT_HISTORY);
        let params = agent.params().check(model.n_stimuli(), self.fresh_u64())?;
        let config = EffectiveConfig {
            eta: params.eta,
            gamma: params.gamma,
            priorities: params.priorities.clone(),
            stimulus_rate: params.stimulus_rate,
            optimistic_sd: params.optimistic_sd,
            ridge: params.ridge,
            epsilon: params.epsilon,
            seed: params.seed,
            update_mode: agent.update_mode.unwrap_or_default(),
            history,
            curiosity: agent.curiosity.clone(),
        };
        let summary = ModelSummary {
            states: model.states(),
            actions: model.actions().to_vec(),
            stimuli: model.stimuli().to_vec(),
            pairs: model.n_pairs(),
            transitions: model.n_transitions(),
            deterministic: model.is_deterministic(),
            basis: built.basis,
            features: ctx.n_features(),
            layout: built.layout,
        };
        let learner = match &agent.curiosity {
            None => Learner::Plain(Agent::new(ctx, params)),
            Some(c) => {
                let checked = c
                    .params
                    .check()
                    .map_err(|e| prefix("agent.curiosity.params", e))?;
                Learner::Curious(Box::new(
                    CuriousAgent::new(ctx, params, checked, c.signal_dim)
                        .map_err(|e| prefix("agent.curiosity", e))?,
                ))
            }
        };
        Ok((learner, summary, config))
    }

    /// Creates a session. Synchronous and possibly slow (a PVF basis costs
    /// an eigendecomposition; with a store, the creation is committed before
    /// this returns): call it off the async runtime.
    pub fn create(&self, caller: Caller, req: CreateSession) -> Result<SessionInfo, ServiceError> {
        if self.len() >= self.limits.max_sessions {
            return Err(ServiceError::TooManySessions(self.limits.max_sessions));
        }
        let model_text = self.durability.as_ref().map(|_| req.model.to_string());
        let input = ModelInput::parse(req.model)?;
        let owner = caller.owner();
        // Refused early when the key's quota of sessions is used up.
        self.limits.check_cost(
            &SessionCost {
                bytes: 0,
                tick_us: 0,
            },
            self.sessions.read().usage(&owner),
        )?;
        let (learner, summary, config) = self.build(&input, &req.agent, &self.limits)?;
        let cost = cost::estimate(&summary, &config);
        self.limits
            .check_cost(&cost, self.sessions.read().usage(&owner))?;
        let id = format!("s{:04x}.{}", self.fresh_u64() % SHARDS, ulid::Ulid::new());
        if let (Some(d), Some(model)) = (&self.durability, model_text) {
            let record = durable::SessionRecord {
                model,
                config: config.clone(),
                owner: caller.owner(),
            };
            let bytes = serde_json::to_vec(&record)
                .map_err(|e| ServiceError::Internal(format!("encoding a session record: {e}")))?;
            d.store
                .submit(vec![crate::store::Write::Session {
                    id: Arc::from(id.as_str()),
                    record: bytes,
                }])
                .wait_blocking()
                .map_err(|e| ServiceError::Storage(e.to_string()))?;
        }
        let session = Arc::new(Session::resume(
            id.clone(),
            learner,
            summary,
            config,
            self.durability.clone(),
            session::Resumed {
                owner: caller.owner(),
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

    /// The session with this id, whoever owns it (for tests and tools).
    pub fn session(&self, id: &str) -> Result<SessionRef, ServiceError> {
        self.sessions
            .read()
            .get(id)
            .cloned()
            .ok_or_else(|| ServiceError::NotFound(id.to_string()))
    }

    /// The session with this id if `caller` may see it; another key's
    /// session is `NotFound`, exactly like a missing one. A quarantined
    /// session is [`ServiceError::SessionFailed`] (see [`Session::is_failed`]).
    /// A session whose commit failed is first rolled back to its durable
    /// state (reloaded, see [`SessionManager::visible_session`]).
    pub fn session_for(&self, caller: Caller, id: &str) -> Result<SessionRef, ServiceError> {
        let session = self.visible_session(caller, id)?;
        if session.is_failed() {
            return Err(ServiceError::SessionFailed(id.to_string()));
        }
        Ok(session)
    }

    /// [`SessionManager::session_for`], quarantined sessions included (for
    /// `delete`). A session whose commit failed is first rolled back to its
    /// durable state (reloaded), so nothing that was not made durable is
    /// ever served; while that cannot be done, `Storage`.
    pub fn visible_session(&self, caller: Caller, id: &str) -> Result<SessionRef, ServiceError> {
        let session = self.session(id)?;
        if !caller.may_see(session.owner.as_ref()) {
            return Err(ServiceError::NotFound(id.to_string()));
        }
        if !session.is_stale() {
            return Ok(session);
        }
        self.reload(&session).map_err(|e| {
            ServiceError::Storage(format!(
                "session `{id}` cannot be rolled back to its durable state after a storage failure ({e})"
            ))
        })?;
        self.session(id)
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
        let page: Vec<SessionRef> = sessions
            .after(after)
            .filter(|(_, s)| caller.may_see(s.owner.as_ref()))
            .take(limit + 1)
            .map(|(_, s)| Arc::clone(s))
            .collect();
        drop(sessions);
        let next = (page.len() > limit).then(|| page[limit - 1].id.clone());
        let sessions = page
            .iter()
            .take(limit)
            .map(|s| SessionSummary {
                id: s.id.clone(),
                tick: s.state.lock().learner.agent().tick(),
                states: s.model.states,
                update_mode: s.mode,
                idle_ms: s
                    .idle()
                    .map(|d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX)),
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
        let session = self.visible_session(caller, id)?;
        self.store_writable()?;
        let result = match session.begin_delete()? {
            Some(commit) => commit
                .wait()
                .await
                .map_err(|e| ServiceError::Storage(e.to_string())),
            None => Ok(()),
        };
        // A reload during the commit may have replaced the session in the
        // map; the delete ends on both.
        let current = self.session(id).ok().filter(|s| !Arc::ptr_eq(s, &session));
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

    /// Applies observations in order and returns one reply each (DESIGN.md,
    /// "Observation protocol"). Lockstep sessions reply after their update
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
        // Rolled back first if an earlier commit failed.
        let session = self.session_for(caller, id)?;
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
                metrics::histogram!("mcapi_tick_seconds").record(started.elapsed().as_secs_f64());
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
                        Ok(true) => metrics::histogram!("mcapi_tick_seconds")
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
        metrics::counter!("mcapi_observations_total").increment(n);
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
        self.check_values_size(&session, sel)?;
        let st = session.state.lock();
        let agent = st.learner.agent();
        let model = agent.planning_model().model();
        let per_pair = |f: &dyn Fn(usize) -> f64| -> Vec<Vec<Option<f64>>> {
            (0..model.states())
                .map(|s| {
                    (0..model.n_actions())
                        .map(|a| model.pair(s, a).map(f))
                        .collect()
                })
                .collect()
        };
        let planner = agent.planner();
        Ok(Values {
            tick: agent.tick(),
            policy_version: agent.policy_version(),
            v: sel
                .v
                .then(|| (0..model.states()).map(|s| planner.value(s)).collect()),
            q: sel.q.then(|| per_pair(&|p| planner.q()[p])),
            policy: sel.policy.then(|| {
                (0..model.states())
                    .map(|s| model.actions()[agent.greedy_action(s)].clone())
                    .collect()
            }),
            r: sel.r.then(|| per_pair(&|p| agent.rewards()[p])),
            xi: sel.xi.then(|| {
                (0..model.states())
                    .map(|s| {
                        (0..model.n_actions())
                            .map(|a| model.pair(s, a).map(|p| agent.stimulus().row(p).to_vec()))
                            .collect()
                    })
                    .collect()
            }),
            curiosity: st.learner.curious().map(CuriosityInfo::of),
        })
    }

    /// Refuses value tables whose JSON would exceed
    /// [`Limits::max_response_bytes`], before anything is built (about 24
    /// bytes per number, and per name for `policy`).
    fn check_values_size(
        &self,
        session: &Session,
        sel: ValueSelection,
    ) -> Result<(), ServiceError> {
        let m = &session.model;
        let cells = m.states.saturating_mul(m.actions.len());
        let longest = m.actions.iter().map(String::len).max().unwrap_or(0);
        let mut bytes = 0usize;
        if sel.v {
            bytes = bytes.saturating_add(m.states.saturating_mul(24));
        }
        if sel.policy {
            bytes = bytes.saturating_add(m.states.saturating_mul(longest + 4));
        }
        for table in [sel.q, sel.r] {
            if table {
                bytes = bytes.saturating_add(cells.saturating_mul(24));
            }
        }
        if sel.xi {
            bytes = bytes.saturating_add(cells.saturating_mul(m.stimuli.len() * 24 + 4));
        }
        if bytes > self.limits.max_response_bytes {
            return Err(ServiceError::LimitExceeded(format!(
                "the value tables asked for (`include`) would take about {bytes} bytes; the limit of one response is {} (--max-response-bytes): ask for fewer tables",
                self.limits.max_response_bytes
            )));
        }
        Ok(())
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
        self.pool.shutdown();
        let Some(d) = &self.durability else {
            return;
        };
        let sessions: Vec<SessionRef> = self.sessions.read().values().cloned().collect();
        let commits: Vec<_> = sessions.iter().filter_map(|s| s.snapshot()).collect();
        let n = commits.len();
        let failed = commits
            .into_iter()
            .map(crate::store::Commit::wait_blocking)
            .filter(Result::is_err)
            .count();
        tracing::info!(snapshots = n, failed, "snapshots written at shutdown");
        d.store.close();
    }
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
        model: session.model.clone(),
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

/// An algorithm error about a field of `agent.curiosity`, with its path:
/// `invalid parameter `agent.curiosity.params`: `gain` must be ...`.
fn prefix(field: &'static str, e: mcapi_core::AlgoError) -> ServiceError {
    match e {
        mcapi_core::AlgoError::InvalidParameter { name, reason } => {
            mcapi_core::AlgoError::InvalidParameter {
                name: field,
                reason: format!("`{name}` {reason}"),
            }
            .into()
        }
        e => ServiceError::field(field, e),
    }
}
