//! Finding a session: by id, for a caller (other keys' sessions are not
//! found), loaded back when evicted, reloaded after a storage failure;
//! `get` and `list`.

use super::*;

impl SessionManager {
    /// The session with this id, whoever owns it, loaded back if it was
    /// evicted (blocking then: call off the async runtime).
    pub fn session(&self, id: &str) -> Result<SessionRef, ServiceError> {
        let entry = self.entry(id)?;
        self.loaded(id, entry)
    }

    /// The table's entry for `id`.
    pub(super) fn entry(&self, id: &str) -> Result<Entry, ServiceError> {
        self.sessions
            .read()
            .get(id)
            .cloned()
            .ok_or_else(|| ServiceError::NotFound(id.to_string()))
    }

    /// The session with this id if it is in memory (never loads).
    pub(super) fn resident(&self, id: &str) -> Option<SessionRef> {
        self.sessions
            .read()
            .get(id)
            .and_then(Entry::resident)
            .cloned()
    }

    /// The session of `entry`, loaded back if it is evicted (blocking).
    pub(super) fn loaded(&self, id: &str, entry: Entry) -> Result<SessionRef, ServiceError> {
        match entry {
            Entry::Resident(s) => Ok(s),
            Entry::Evicted(stub) => {
                let d = self.evicted_store(id)?;
                self.room_to_load(id, &stub)?;
                let fresh = recovery::load(&self.setup, &self.limits, d, id, stub.lsn)?;
                let was = Entry::Evicted(stub);
                self.install(id, &was, fresh)
            }
        }
    }

    /// [`Self::loaded`] for the async paths: an evicted session is loaded
    /// back on the blocking pool.
    /// `room`: whether the load must fit its key's quota ([`Self::room_to_load`]);
    /// not for a delete, which only loads the session to end it.
    pub(super) async fn loaded_async(
        &self,
        id: &str,
        entry: Entry,
        room: bool,
    ) -> Result<SessionRef, ServiceError> {
        match entry {
            Entry::Resident(s) => Ok(s),
            Entry::Evicted(stub) => {
                let d = self.evicted_store(id)?.clone();
                // Making room may commit eviction snapshots: off the
                // runtime's own work (the server's runtime has several
                // threads; a single-threaded one, in tests, waits inline).
                if room {
                    match tokio::runtime::Handle::try_current().map(|h| h.runtime_flavor()) {
                        Ok(tokio::runtime::RuntimeFlavor::MultiThread) => {
                            tokio::task::block_in_place(|| self.room_to_load(id, &stub))?;
                        }
                        _ => self.room_to_load(id, &stub)?,
                    }
                }
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

    pub(super) fn evicted_store(&self, id: &str) -> Result<&Durability, ServiceError> {
        self.durability.as_ref().ok_or_else(|| {
            ServiceError::Internal(format!("session `{id}` is evicted but there is no store"))
        })
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
    pub(super) async fn visible_session_async(
        &self,
        caller: Caller,
        id: &str,
    ) -> Result<SessionRef, ServiceError> {
        self.visible_session_loaded(caller, id, true).await
    }

    /// [`Self::visible_session_async`]; `room` as [`Self::loaded_async`]
    /// takes it.
    pub(super) async fn visible_session_loaded(
        &self,
        caller: Caller,
        id: &str,
        room: bool,
    ) -> Result<SessionRef, ServiceError> {
        let entry = self.visible_entry(caller, id)?;
        let session = self.loaded_async(id, entry, room).await?;
        self.rolled_back(id, session)
    }

    /// The entry of a session served here that `caller` may see.
    pub(super) fn visible_entry(&self, caller: Caller, id: &str) -> Result<Entry, ServiceError> {
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
    pub(super) fn rolled_back(
        &self,
        id: &str,
        session: SessionRef,
    ) -> Result<SessionRef, ServiceError> {
        if !session.is_stale() {
            return Ok(session);
        }
        self.reload(&session).map_err(|e| StorageError::Rollback {
            id: id.to_string(),
            source: Box::new(e),
        })?;
        self.session(id)
    }

    /// What `caller`'s key holds now: its sessions, and the bytes they are
    /// charged against `--max-key-bytes` (each resident one its estimate,
    /// each evicted one its stub).
    pub fn usage(&self, caller: Caller) -> Usage {
        self.sessions.read().usage(&caller.owner())
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
                    tick: s.state.lock().learner.tick(),
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
}
