//! A session's life beyond its requests: deletion, recovery of the stored
//! sessions at start, reload after a storage failure, and eviction of idle
//! sessions to the store.

use super::*;

impl SessionManager {
    /// Deletes a session and, with a store, its stored data. The deletion is
    /// committed before anything is removed: if the commit fails, the
    /// session stays and is served as before (the client gets
    /// `storage_unavailable` and may retry); once it returns `Ok`, the
    /// session is gone, restarts included.
    #[tracing::instrument(level = "debug", skip(self))]
    pub async fn delete(&self, caller: Caller, id: &str) -> Result<(), ServiceError> {
        let _guard = self.enter_shard(id)?;
        // An evicted session is loaded to be deleted whatever its key's
        // quota: a delete is how a key makes room.
        let session = self.visible_session_loaded(caller, id, false).await?;
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
        let keep_entry = |session: SessionRef| match self.evict_after {
            Some(_) => session
                .still_evictable(cost::estimate(&session.model, &session.config))
                .map_or(Entry::Resident(session), |stub| {
                    Entry::Evicted(Arc::new(stub))
                }),
            None => Entry::Resident(session),
        };
        // Each member's record names its group: the groups are rebuilt
        // from them.
        let members = Mutex::new(Vec::new());
        let keep = |session: SessionRef| {
            if let Some(member) = groups::GroupMember::of(&session) {
                members.lock().push(member);
            }
            keep_entry(session)
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
        self.register_groups(members.into_inner());
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
            evicted += self.evict(candidates);
            match last {
                Some(id) => after = Some(id),
                None => break,
            }
        }
        if evicted > 0 {
            tracing::debug!(sessions = evicted, "idle sessions evicted to the store");
        }
        evicted
    }

    /// Evicts `candidates` that may still go: each is prepared (a snapshot
    /// committed if it changed since it was built), then swapped for its
    /// stub under one write of the table. Returns how many left. Blocking.
    fn evict(&self, candidates: Vec<SessionRef>) -> usize {
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
        if ready.is_empty() {
            return 0;
        }
        let mut evicted = 0;
        let mut sessions = self.sessions.write();
        for s in &ready {
            // Held by the table and `ready` only: no request or job has
            // it, and none can take it while the lock is held.
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
        // A group remembers its members by weak references, which would
        // keep each evicted session's struct allocated until the group
        // steps again.
        let groups = self.groups.read();
        for tag in ready.iter().filter_map(|s| s.group.as_ref()) {
            if let Some(group) = groups.get(&tag.group) {
                group.resolved.forget(tag.index as usize);
            }
        }
        drop(groups);
        // The sessions are freed here, outside the lock.
        drop(ready);
        metrics::counter!("mcapi_session_evictions_total").increment(evicted as u64);
        evicted
    }

    /// Makes room for `need` more bytes of `owner`'s within its quota
    /// (`--max-key-bytes`) by evicting its least recently active sessions,
    /// when sessions may be evicted at all (a store and `--evict-idle-secs`;
    /// docs/limits.md, "Memory pressure"). Only sessions inactive for at
    /// least [`PRESSURE_MIN_IDLE`] go, so that sessions in use are not
    /// thrown out and loaded back in turn; enough go to leave a tenth of the
    /// quota free besides `need`, so that a run of creations does not pay
    /// a pass each. True if `need` then fits. One pass at a time; blocking.
    pub(super) fn make_room(&self, owner: &session::Owner, need: u64) -> bool {
        self.room_pass(owner, need).fits
    }

    /// [`Self::make_room`] for a caller that checks the quota again and
    /// retries (a bounded number of times) when a concurrent creation took
    /// the room: true when `need` fits now, or when this pass evicted
    /// sessions (so a retry may find room). A pass that evicts nothing
    /// and finds no room ends the retries.
    pub(super) fn room_or_progress(&self, owner: &session::Owner, need: u64) -> bool {
        let pass = self.room_pass(owner, need);
        pass.fits || pass.evicted > 0
    }

    /// One pass of [`Self::make_room`].
    fn room_pass(&self, owner: &session::Owner, need: u64) -> RoomPass {
        let quota = self.limits.max_key_bytes;
        let fits = |m: &Self| m.sessions.read().usage(owner).bytes.saturating_add(need) <= quota;
        let done = |fits| RoomPass { fits, evicted: 0 };
        if fits(self) {
            return done(true);
        }
        if self.evict_after.is_none() || need > quota {
            return done(false);
        }
        let _one_pass = self.pressure.lock();
        if fits(self) {
            return done(true);
        }
        let target = (quota - need).saturating_sub(quota / 10);
        // The owner's evictable sessions, least recently active first.
        let mut idle: Vec<(Duration, u64, SessionRef)> = Vec::new();
        let held = {
            let sessions = self.sessions.read();
            for entry in sessions.values() {
                if let Entry::Resident(s) = entry
                    && s.owner == *owner
                    && Arc::strong_count(s) == 1
                {
                    let inactive = s.inactive();
                    if inactive >= PRESSURE_MIN_IDLE {
                        let freed = entry
                            .charge()
                            .saturating_sub(session::Evicted::held_bytes(&s.id));
                        idle.push((inactive, freed, Arc::clone(s)));
                    }
                }
            }
            sessions.usage(owner).bytes
        };
        idle.sort_by_key(|e| std::cmp::Reverse(e.0));
        let mut to_free = held.saturating_sub(target);
        let mut chosen = Vec::new();
        for (_, freed, s) in idle {
            if to_free == 0 {
                break;
            }
            to_free = to_free.saturating_sub(freed);
            chosen.push(s);
        }
        let mut evicted = 0;
        while !chosen.is_empty() {
            let rest = chosen.split_off(chosen.len().min(EVICT_CHUNK));
            evicted += self.evict(std::mem::replace(&mut chosen, rest));
        }
        metrics::counter!("mcapi_pressure_evictions_total").increment(evicted as u64);
        tracing::debug!(
            sessions = evicted,
            "sessions evicted to make room within a key's quota"
        );
        RoomPass {
            fits: fits(self),
            evicted,
        }
    }
}

/// What one pass of [`SessionManager::make_room`] did.
struct RoomPass {
    /// The bytes asked for fit the quota when the pass ended.
    fits: bool,
    /// Sessions it evicted.
    evicted: usize,
}
