//! Creating a session: checked against the limits and the caller's quota,
//! built by [`super::super::setup`] off the runtime, logged to the store
//! before it is installed in the table.

use std::sync::atomic::AtomicBool;

use super::super::setup::NewBuild;
use super::*;

/// Watches a creation's request: set when the request is abandoned (its
/// client went away or its time ran out), so that the build of its model
/// stops instead of running on for nobody. An adapter makes one per request
/// and keeps an [`AbandonOnDrop`] for it in the request's future.
#[derive(Debug, Clone, Default)]
pub struct Watch {
    abandoned: Arc<AtomicBool>,
}

impl Watch {
    /// A guard that marks this request abandoned when it is dropped: when
    /// the request's future is dropped before the creation returns, or
    /// after (harmless then).
    pub fn abandon_on_drop(&self) -> AbandonOnDrop {
        AbandonOnDrop(Arc::clone(&self.abandoned))
    }

    /// The flag a build checks.
    pub(super) fn flag(&self) -> &AtomicBool {
        &self.abandoned
    }

    /// Whether the request was abandoned.
    pub(super) fn is_abandoned(&self) -> bool {
        self.abandoned.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// See [`Watch::abandon_on_drop`].
#[derive(Debug)]
pub struct AbandonOnDrop(Arc<AtomicBool>);

impl Drop for AbandonOnDrop {
    fn drop(&mut self) {
        self.0.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// Passes of [`SessionManager::make_room`] one creation may ask for, when
/// concurrent creations of the same key keep taking the room made for it.
/// A creation is refused at its quota when a pass neither finds room nor
/// evicts a session (none of the key's is idle), or after this many
/// passes. With eight creations racing at a full quota, three passes that
/// also had to find room were measured too few.
pub(super) const ROOM_PASSES: usize = 16;

impl SessionManager {
    /// Creates a session. Synchronous and possibly slow (a PVF basis costs
    /// an eigendecomposition; with a store, the creation is committed before
    /// this returns): call it off the async runtime.
    pub fn create(&self, caller: Caller, req: CreateSession) -> Result<SessionInfo, ServiceError> {
        self.create_watched(caller, req, &Watch::default())
    }

    /// [`Self::create`] for a request that may be abandoned: its model's
    /// build stops once `watch` says so (see [`Watch`]).
    pub fn create_watched(
        &self,
        caller: Caller,
        req: CreateSession,
        watch: &Watch,
    ) -> Result<SessionInfo, ServiceError> {
        let CreateSession { model, agent } = req;
        if self.len() >= self.limits.max_sessions {
            return Err(ServiceError::TooManySessions(self.limits.max_sessions));
        }
        let model_text = self.durability.as_ref().map(|_| model.to_string());
        let input = ModelInput::parse(model)?;
        self.create_from(caller, input, &agent, model_text, watch)
    }

    /// Creates a session from a model already parsed (gRPC's typed `Model`,
    /// converted in `api::grpc::convert`); otherwise as [`Self::create`],
    /// with the same checks in the same order.
    pub fn create_parsed(
        &self,
        caller: Caller,
        input: ModelInput,
        agent: &SessionConfig,
        watch: &Watch,
    ) -> Result<SessionInfo, ServiceError> {
        if self.len() >= self.limits.max_sessions {
            return Err(ServiceError::TooManySessions(self.limits.max_sessions));
        }
        let model_text = match &self.durability {
            Some(_) => Some(input.to_json_text()?),
            None => None,
        };
        self.create_from(caller, input, agent, model_text, watch)
    }

    pub(super) fn create_from(
        &self,
        caller: Caller,
        input: ModelInput,
        agent: &SessionConfig,
        model_text: Option<String>,
        watch: &Watch,
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
        let admit = |cost: &SessionCost| self.admit_cost(&owner, cost);
        let new = NewBuild {
            admit: &admit,
            abandoned: Some(watch.flag()),
        };
        let (learner, summary, config) = self.setup.build_new(&input, agent, &self.limits, &new)?;
        let cost = cost::estimate(&summary, &config);
        self.admit_cost(&owner, &cost)?;
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
                group: None,
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
        // Checked again under the lock: concurrent creates see each other.
        // One that took the room this one was admitted to is made room for
        // again ([`ROOM_PASSES`] times at most: each pass leaves a tenth
        // free).
        let mut passes = 0;
        loop {
            let mut sessions = self.sessions.write();
            let refused = if sessions.len() >= self.limits.max_sessions {
                Some(ServiceError::TooManySessions(self.limits.max_sessions))
            } else {
                self.limits.check_cost(&cost, sessions.usage(&owner)).err()
            };
            let Some(e) = refused else {
                sessions.insert(id.clone(), Arc::clone(&session));
                metrics::gauge!("mcapi_sessions").set(sessions.len() as f64);
                break;
            };
            drop(sessions);
            if matches!(e, ServiceError::QuotaExceeded(_))
                && passes < ROOM_PASSES
                && self.room_or_progress(&owner, cost.bytes)
            {
                passes += 1;
                continue;
            }
            // Undo the stored record; the client sees the limit.
            if let Some(commit) = session.delete() {
                let _ = commit.wait_blocking();
            }
            return Err(e);
        }
        tracing::info!(session = %id, states = session.model.states, "session created");
        Ok(info_of(&session))
    }

    /// Checks a new session's estimated cost against the limits and its
    /// owner's quota, first evicting the owner's idle sessions when that
    /// makes it fit the quota of bytes ([`Self::make_room`]). Blocking.
    pub(super) fn admit_cost(
        &self,
        owner: &session::Owner,
        cost: &SessionCost,
    ) -> Result<(), ServiceError> {
        // The table's lock is not held past the check: making room takes
        // it to write. A concurrent creation may take the room made before
        // this one checks again: room is then made again ([`ROOM_PASSES`]
        // times at most, as when the session is inserted).
        let mut passes = 0;
        loop {
            let held = self.sessions.read().usage(owner);
            match self.limits.check_cost(cost, held) {
                Err(ServiceError::QuotaExceeded(_))
                    if passes < ROOM_PASSES
                        && cost.bytes <= self.limits.max_session_bytes
                        && self.room_or_progress(owner, cost.bytes) =>
                {
                    passes += 1;
                }
                other => return other,
            }
        }
    }

    /// Room for an evicted session to be loaded back: its owner is charged
    /// its full estimate again, so the owner's idle sessions make room if
    /// that goes over the quota ([`Self::make_room`]); when they cannot,
    /// the load is refused with `unavailable` (503) and the session stays
    /// in the store, unchanged. Blocking.
    pub(super) fn room_to_load(
        &self,
        id: &str,
        stub: &session::Evicted,
    ) -> Result<(), ServiceError> {
        let need = stub.cost.bytes.saturating_sub(stub.held);
        if self.make_room(&stub.owner, need) {
            return Ok(());
        }
        Err(ServiceError::Unavailable(format!(
            "session `{id}` is evicted to the store, and loading it back ({need} more bytes) would take its API key's sessions over their memory quota of {} bytes (--max-key-bytes), with no other session of the key idle for {} s to make room; retry later, or delete sessions",
            self.limits.max_key_bytes,
            PRESSURE_MIN_IDLE.as_secs()
        )))
    }

    /// Puts a session loaded back in place of its eviction `was`. Two
    /// requests may load the same session at once: both rebuilt it from
    /// the same stored state, the first to get here is served and the
    /// other's copy dropped. Gone meanwhile (deleted, its shard moved):
    /// `NotFound`.
    pub(super) fn install(
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
}
