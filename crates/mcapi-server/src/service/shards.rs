//! A replica's side of a live shard move (docs/cluster.md, "How a shard
//! moves"). The mover (`mcapi cluster move`, mcapi-cluster's `mover`)
//! calls these through the admin routes (`api::admin`), in order:
//!
//! 1. source [`SessionManager::export_shard`] with no manifest: the
//!    snapshot, every stored session of the shard, read from the store in
//!    one transaction while the shard is still served;
//! 2. target [`SessionManager::import_shard`] (`begin`): the shard becomes
//!    `Importing` there, stale leftovers of it are deleted, and what was
//!    received is committed to the target's store before the call returns;
//! 3. source [`SessionManager::freeze_shard`]: requests for the shard get
//!    503 `shard_moving` from now on, and the call returns once no request
//!    that changes the shard is still running. The freeze holds a lease
//!    (`lease_ms`, [`DEFAULT_FREEZE_LEASE`]): if the move has not committed
//!    when it runs out, the source serves the shard again by itself, so a
//!    mover that died does not leave it refusing requests;
//! 4. source [`SessionManager::export_shard`] with the manifest of step 1:
//!    the delta (new sessions, log tails, sessions replaced by a newer
//!    snapshot, deleted ids); target [`SessionManager::import_shard`];
//! 5. the commit point: source [`SessionManager::commit_shard`] gives the
//!    shard to the target at epoch + 1, only if the freeze's lease is
//!    still running (else 409 `move_conflict`: the source serves the shard
//!    again and the move must start over); then the mover writes the new
//!    map (epoch + 1);
//! 6. target [`SessionManager::activate_shard`]: the shard's sessions are
//!    rebuilt from the target's store and served (`Owned`) at the new epoch;
//! 7. the router's map is flipped; source [`SessionManager::release_shard`]:
//!    `Foreign` at the new epoch (421 naming the target), the sessions
//!    leave its memory and its store.
//!
//! Before step 5 a failure is undone with [`SessionManager::thaw_shard`]
//! on the source (served again) and [`SessionManager::abort_import`] on the
//! target (its copy deleted). Every step checks the shard's state first and
//! answers 409 `move_conflict` when it does not fit.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::error::{RecoveryError, ServiceError};
use super::manager::SessionManager;
use super::recovery;
pub use mcapi_shards::moves::{Manifest, MovedSession, ShardData, ShardStatus};
pub use mcapi_shards::moves::{ReplicaShards, ShardLine};
use mcapi_shards::{Placement, ReplicaName, SHARDS, ShardState, shard_key, state_name};
use mcapi_store::{StoredSession, Write};

/// Longest wait for the requests changing a shard to end once it is frozen.
pub const FREEZE_DRAIN: Duration = Duration::from_secs(10);

/// A freeze's lease when the mover names none: a move's freeze lasts
/// milliseconds (the delta and two admin calls), so 30 s is ample for a
/// slow disk, and a dead mover's shard refuses requests for 30 s at most.
pub const DEFAULT_FREEZE_LEASE: Duration = Duration::from_secs(30);
/// The shortest lease (ms): below this, the delta's own round trips could
/// not fit, and every move would fail.
pub const MIN_FREEZE_LEASE_MS: u64 = 100;
/// The longest lease (ms): a shard left frozen longer by a dead mover is
/// an outage, not a move.
pub const MAX_FREEZE_LEASE_MS: u64 = 600_000;

/// A lease asked for in milliseconds, checked against its bounds.
pub fn freeze_lease(ms: Option<u64>) -> Result<Duration, ServiceError> {
    match ms {
        None => Ok(DEFAULT_FREEZE_LEASE),
        Some(ms) if (MIN_FREEZE_LEASE_MS..=MAX_FREEZE_LEASE_MS).contains(&ms) => {
            Ok(Duration::from_millis(ms))
        }
        Some(ms) => Err(ServiceError::field(
            "lease_ms",
            format!(
                "must be between {MIN_FREEZE_LEASE_MS} and {MAX_FREEZE_LEASE_MS} (10 minutes), not {ms}"
            ),
        )),
    }
}

/// Most log entries one session may bring in a move (a session's log
/// between snapshots is `--snapshot-every` long, at most a few thousand).
pub const MAX_MOVE_ENTRIES: usize = 1 << 20;

/// Parses a shard key from a path (`s03a7`).
pub fn parse_shard(key: &str) -> Result<u16, ServiceError> {
    mcapi_shards::parse_shard(key).map_err(|e| ServiceError::field("shard", e))
}

impl SessionManager {
    fn move_parts(&self) -> Result<(&Arc<Placement>, &super::session::Durability), ServiceError> {
        let p = self.placement().ok_or_else(|| {
            ServiceError::MoveConflict(
                "this server is not a replica of a cluster (no --shard-map); it has no shards to move"
                    .into(),
            )
        })?;
        let d = self.durability().ok_or_else(|| {
            ServiceError::MoveConflict(
                "this replica keeps no store (no --data-dir); its shards cannot move".into(),
            )
        })?;
        Ok((p, d))
    }

    fn expect_state(
        &self,
        p: &Placement,
        shard: u16,
        want: &[ShardState],
        step: &str,
    ) -> Result<ShardState, ServiceError> {
        let now = p.state(shard);
        if want.contains(&now) {
            return Ok(now);
        }
        let names: Vec<&str> = want.iter().map(|s| state_name(*s)).collect();
        Err(ServiceError::MoveConflict(format!(
            "{step}: shard {} is {} on replica `{}`, not {}",
            shard_key(shard),
            state_name(now),
            p.replica(),
            names.join(" or ")
        )))
    }

    /// The status of a shard here.
    pub fn shard_status(&self, shard: u16) -> Result<ShardStatus, ServiceError> {
        let (p, _) = self.move_parts()?;
        let map = p.map();
        let prefix = format!("{}.", shard_key(shard));
        Ok(ShardStatus {
            shard: shard_key(shard),
            state: state_name(p.state(shard)).into(),
            owner: map.owner(shard).to_string(),
            replica: p.replica().to_string(),
            epoch: map.epoch(),
            sessions: self.ids_with_prefix(&prefix).len(),
            boot: boot_id(),
            lease_ms: p.lease(shard).map(|l| ms(l.left(Instant::now()))),
            freeze_token: p.lease(shard).map(|l| l.token),
        })
    }

    /// Every shard here at once: state, owner in this replica's map,
    /// sessions in memory and a freeze's lease left (`mcapi cluster
    /// status`). One pass over the sessions, not one per shard.
    pub fn all_shards(&self) -> Result<ReplicaShards, ServiceError> {
        let (p, _) = self.move_parts()?;
        let mut counts = vec![0usize; SHARDS];
        for id in self.ids_with_prefix("s") {
            if let Some(s) = mcapi_shards::shard_of_id(&id) {
                counts[usize::from(s)] += 1;
            }
        }
        let now = Instant::now();
        let shards = p
            .states()
            .into_iter()
            .zip(counts)
            .map(|((state, lease, owner), sessions)| ShardLine {
                state: state_name(state).into(),
                owner: owner.to_string(),
                sessions,
                lease_ms: lease.map(|l| ms(l.left(now))),
            })
            .collect();
        Ok(ReplicaShards {
            replica: p.replica().to_string(),
            epoch: p.epoch(),
            boot: boot_id(),
            shards,
        })
    }

    /// Steps 1 and 4: the shard's stored sessions, whole when `manifest`
    /// is `None`; else only what changed since it.
    pub fn export_shard(
        &self,
        shard: u16,
        manifest: Option<&Manifest>,
    ) -> Result<ShardData, ServiceError> {
        let (p, d) = self.move_parts()?;
        self.expect_state(p, shard, &[ShardState::Owned, ShardState::Frozen], "export")?;
        let started = Instant::now();
        let stored = d
            .store
            .sessions_with_prefix(&format!("{}.", shard_key(shard)))?;
        let known: HashMap<&str, Option<u64>> = manifest
            .map(|m| m.sessions.iter().map(|(id, s)| (id.as_str(), *s)).collect())
            .unwrap_or_default();
        let mut data = ShardData::default();
        let mut present = std::collections::HashSet::new();
        for s in stored {
            present.insert(s.id.clone());
            let full = |s: mcapi_store::ExportedSession| MovedSession::Full {
                id: s.id,
                record: s.record,
                snapshot: s.snapshot,
                entries: s.entries,
            };
            match (manifest, known.get(s.id.as_str())) {
                (Some(_), Some(&held)) => {
                    let last = s
                        .entries
                        .last()
                        .map(|(q, _)| *q)
                        .or(s.snapshot.as_ref().map(|(q, _)| *q));
                    if last == held {
                        continue;
                    }
                    let snap = s.snapshot.as_ref().map(|(q, _)| *q);
                    // A tail is enough while the log still holds every
                    // entry after what the target has.
                    let tail_ok = match (held, snap) {
                        (_, None) => true,
                        (Some(h), Some(q)) => q <= h,
                        (None, Some(_)) => false,
                    };
                    if tail_ok {
                        let entries = s
                            .entries
                            .into_iter()
                            .filter(|(q, _)| held.is_none_or(|h| *q > h))
                            .collect();
                        data.sessions.push(MovedSession::Tail { id: s.id, entries });
                    } else {
                        data.sessions.push(full(s));
                    }
                }
                _ => data.sessions.push(full(s)),
            }
        }
        if let Some(m) = manifest {
            data.deleted = m
                .sessions
                .iter()
                .filter(|(id, _)| !present.contains(id))
                .map(|(id, _)| id.clone())
                .collect();
        }
        tracing::info!(
            shard = %shard_key(shard),
            sessions = data.sessions.len(),
            deleted = data.deleted.len(),
            delta = manifest.is_some(),
            ms = started.elapsed().as_millis() as u64,
            "shard exported"
        );
        Ok(data)
    }

    /// Step 3: freezes an owned shard for `lease` and waits until no
    /// request changing it runs ([`FREEZE_DRAIN`] at most, and never past
    /// the lease; then it is served again and the step fails with 503).
    /// Frozen already: its lease starts again. When the lease runs out
    /// before [`SessionManager::commit_shard`], the shard is served here
    /// again: exactly at the deadline for every request (the state is read
    /// against the clock), and a timer logs it and settles the state.
    pub async fn freeze_shard(
        &self,
        shard: u16,
        lease: Duration,
    ) -> Result<ShardStatus, ServiceError> {
        let (p, _) = self.move_parts()?;
        let held = match p.freeze(shard, lease) {
            Ok(held) => held,
            Err(_) => {
                self.expect_state(p, shard, &[ShardState::Owned], "freeze")?;
                return Err(ServiceError::MoveConflict(format!(
                    "freeze: shard {} changed state during the call; retry",
                    shard_key(shard)
                )));
            }
        };
        let started = Instant::now();
        let drain_until = started + FREEZE_DRAIN.min(lease);
        while p.in_flight(shard) > 0 {
            if Instant::now() >= drain_until {
                p.swap_state(shard, &[ShardState::Frozen], ShardState::Owned);
                return Err(ServiceError::Unavailable(format!(
                    "shard {}: requests still running {} ms after the freeze; the shard is served again, retry the move",
                    shard_key(shard),
                    started.elapsed().as_millis()
                )));
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        let timer = Arc::clone(p);
        tokio::spawn(async move {
            tokio::time::sleep_until(tokio::time::Instant::from_std(held.until)).await;
            if timer.expire(shard, held.token) {
                tracing::warn!(
                    shard = %shard_key(shard),
                    lease_ms = ms(held.length),
                    "the freeze's lease expired before its move committed: the shard is served here again"
                );
            }
        });
        tracing::info!(shard = %shard_key(shard), drained_us = started.elapsed().as_micros() as u64, lease_ms = ms(lease), "shard frozen");
        self.shard_status(shard)
    }

    /// Step 5 on the source, the commit point: the shard, frozen by the
    /// freeze of `token` whose lease is still running, is `owner`'s from
    /// `epoch` on; it answers 421 naming `owner` here from now on, and its
    /// sessions stay in memory and store until [`SessionManager::release_shard`].
    /// Refused (409) once the lease has expired, whatever the mover
    /// believes: the source may have served writes since, which the target
    /// does not have, so the move must start over.
    pub fn commit_shard(
        &self,
        shard: u16,
        token: u64,
        owner: &ReplicaName,
        epoch: u64,
    ) -> Result<ShardStatus, ServiceError> {
        let (p, _) = self.move_parts()?;
        p.commit(shard, token, owner, epoch)?;
        tracing::info!(shard = %shard_key(shard), %owner, epoch, "shard committed to its new owner: answered with 421 here from now on");
        self.shard_status(shard)
    }

    /// Undoes a freeze: the shard is served here again.
    pub fn thaw_shard(&self, shard: u16) -> Result<ShardStatus, ServiceError> {
        let (p, _) = self.move_parts()?;
        let found = p.swap_state(shard, &[ShardState::Frozen], ShardState::Owned);
        self.expect_state(p, shard, &[ShardState::Owned], "thaw")
            .inspect_err(|_| {
                tracing::warn!(shard = %shard_key(shard), found = state_name(found), "thaw refused");
            })?;
        tracing::info!(shard = %shard_key(shard), "shard thawed: served here again");
        self.shard_status(shard)
    }

    /// Steps 2 and 4 on the target: applies `data` to the store and waits
    /// for its commit. `begin` starts an import: the shard must be foreign
    /// here, and what the store holds of it (a failed earlier move's
    /// leftovers) is deleted first. On error nothing is committed and a
    /// beginning import leaves the shard in the state it found it in.
    pub async fn import_shard(
        &self,
        shard: u16,
        data: ShardData,
        begin: bool,
    ) -> Result<usize, ServiceError> {
        let (p, _) = self.move_parts()?;
        let before = p.state(shard);
        let result = self.import_inner(shard, data, begin).await;
        if begin && result.is_err() && before != ShardState::Importing {
            let found = p.swap_state(shard, &[ShardState::Importing], before);
            if found == ShardState::Importing {
                tracing::warn!(shard = %shard_key(shard), state = state_name(before), "import failed: the shard is back in its state before it");
            }
        }
        result
    }

    async fn import_inner(
        &self,
        shard: u16,
        data: ShardData,
        begin: bool,
    ) -> Result<usize, ServiceError> {
        let (p, d) = self.move_parts()?;
        let prefix = format!("{}.", shard_key(shard));
        self.check_import(shard, &prefix, &data)?;
        let mut writes = Vec::new();
        if begin {
            self.expect_state(
                p,
                shard,
                &[ShardState::Foreign, ShardState::Importing],
                "import",
            )?;
            p.set_state(shard, ShardState::Importing);
            writes.extend(stored_deletes(&d.store, shard, "import").await?);
        } else {
            self.expect_state(p, shard, &[ShardState::Importing], "import")?;
        }
        let n = data.sessions.len();
        for id in data.deleted {
            writes.push(Write::Delete {
                id: Arc::from(id.as_str()),
            });
        }
        for s in data.sessions {
            match s {
                MovedSession::Full {
                    id,
                    record,
                    snapshot,
                    entries,
                } => {
                    let id: Arc<str> = Arc::from(id.as_str());
                    writes.push(Write::Delete {
                        id: Arc::clone(&id),
                    });
                    writes.push(Write::Session {
                        id: Arc::clone(&id),
                        record,
                    });
                    if let Some((seq, snapshot)) = snapshot {
                        writes.push(Write::Snapshot {
                            id: Arc::clone(&id),
                            seq,
                            snapshot,
                        });
                    }
                    for (seq, entry) in entries {
                        writes.push(Write::Append {
                            id: Arc::clone(&id),
                            seq,
                            entry,
                        });
                    }
                }
                MovedSession::Tail { id, entries } => {
                    let id: Arc<str> = Arc::from(id.as_str());
                    for (seq, entry) in entries {
                        writes.push(Write::Append {
                            id: Arc::clone(&id),
                            seq,
                            entry,
                        });
                    }
                }
            }
        }
        if !writes.is_empty() {
            d.store.submit(writes).wait().await?;
        }
        tracing::info!(shard = %shard_key(shard), sessions = n, begin, "shard data imported and durable");
        Ok(n)
    }

    /// Bounds and shape of received data: ids of this shard, at most the
    /// session limit, entries in increasing order and bounded.
    fn check_import(&self, shard: u16, prefix: &str, data: &ShardData) -> Result<(), ServiceError> {
        let max = self.limits().max_sessions;
        if data.sessions.len() > max || data.deleted.len() > max {
            return Err(ServiceError::LimitExceeded(format!(
                "shard {} brings {} sessions and {} deletions; this replica holds at most {max} sessions",
                shard_key(shard),
                data.sessions.len(),
                data.deleted.len()
            )));
        }
        let ids = data
            .sessions
            .iter()
            .map(MovedSession::id)
            .chain(data.deleted.iter().map(String::as_str));
        for id in ids {
            if !id.starts_with(prefix) || id.len() > 64 {
                return Err(ServiceError::field(
                    "sessions",
                    format!(
                        "session id `{}` is not of shard {}",
                        id.escape_debug(),
                        shard_key(shard)
                    ),
                ));
            }
        }
        for s in &data.sessions {
            let (entries, after) = match s {
                MovedSession::Full {
                    snapshot, entries, ..
                } => (entries, snapshot.as_ref().map(|(q, _)| *q)),
                MovedSession::Tail { entries, .. } => (entries, None),
            };
            if entries.len() > MAX_MOVE_ENTRIES {
                return Err(ServiceError::LimitExceeded(format!(
                    "session `{}` brings {} log entries; at most {MAX_MOVE_ENTRIES} are accepted",
                    s.id(),
                    entries.len()
                )));
            }
            let mut prev = after;
            for (q, _) in entries {
                if prev.is_some_and(|p| *q <= p) {
                    return Err(ServiceError::field(
                        "sessions",
                        format!("session `{}`: log entry {q} is out of order", s.id()),
                    ));
                }
                prev = Some(*q);
            }
        }
        Ok(())
    }

    /// Undoes an import: the target's copy is deleted, the shard foreign.
    pub async fn abort_import(&self, shard: u16) -> Result<usize, ServiceError> {
        let (p, d) = self.move_parts()?;
        self.expect_state(
            p,
            shard,
            &[ShardState::Importing, ShardState::Foreign],
            "abort",
        )?;
        p.set_state(shard, ShardState::Foreign);
        let writes = stored_deletes(&d.store, shard, "abort").await?;
        let n = writes.len();
        if !writes.is_empty() {
            d.store.submit(writes).wait().await?;
        }
        tracing::warn!(shard = %shard_key(shard), sessions = n, "shard import aborted; its copy deleted");
        Ok(n)
    }

    /// Step 6 on the target: rebuilds the shard's sessions from the store
    /// and serves them, owned at `epoch`. Blocking (replays the logs).
    pub fn activate_shard(&self, shard: u16, epoch: u64) -> Result<usize, ServiceError> {
        let (p, d) = self.move_parts()?;
        self.expect_state(p, shard, &[ShardState::Importing], "activate")?;
        if epoch <= p.epoch() {
            return Err(ServiceError::MoveConflict(format!(
                "activate: epoch {epoch} is not above this replica's shard map epoch {}",
                p.epoch()
            )));
        }
        let started = Instant::now();
        let stored = d
            .store
            .sessions_with_prefix(&format!("{}.", shard_key(shard)))?;
        if self.len().saturating_add(stored.len()) > self.limits().max_sessions {
            return Err(ServiceError::TooManySessions(self.limits().max_sessions));
        }
        let mut rebuilt = Vec::with_capacity(stored.len());
        for s in stored {
            let id = s.id.clone();
            let one = StoredSession {
                id: s.id,
                record: s.record,
                snapshot: s.snapshot,
            };
            match recovery::rebuild(self.setup(), self.limits(), d, one) {
                Ok((session, _)) => rebuilt.push(session),
                Err(RecoveryError::Store(e)) => return Err(e.into()),
                Err(e) => {
                    return Err(ServiceError::Internal(format!(
                        "activating shard {}: session `{id}` does not rebuild: {e}",
                        shard_key(shard)
                    )));
                }
            }
        }
        let n = rebuilt.len();
        self.insert_sessions(rebuilt);
        p.set_owner(shard, p.replica(), epoch, ShardState::Owned)?;
        tracing::info!(shard = %shard_key(shard), sessions = n, epoch, ms = started.elapsed().as_millis() as u64, "shard activated: served here");
        Ok(n)
    }

    /// Step 7 on the source: the shard is `owner`'s from `epoch` on; its
    /// sessions leave this replica's memory and store.
    pub async fn release_shard(
        &self,
        shard: u16,
        owner: &ReplicaName,
        epoch: u64,
    ) -> Result<usize, ServiceError> {
        let (p, d) = self.move_parts()?;
        self.expect_state(
            p,
            shard,
            &[ShardState::Frozen, ShardState::Foreign],
            "release",
        )?;
        if owner == p.replica() {
            return Err(ServiceError::field(
                "owner",
                "a shard cannot be released to its own replica",
            ));
        }
        if p.state(shard) == ShardState::Frozen {
            p.set_owner(shard, owner, epoch, ShardState::Foreign)?;
        }
        let prefix = format!("{}.", shard_key(shard));
        let removed = self.remove_sessions(&prefix);
        let writes = stored_deletes(&d.store, shard, "release").await?;
        let n = writes.len();
        if !writes.is_empty() {
            d.store.submit(writes).wait().await?;
        }
        tracing::info!(shard = %shard_key(shard), %owner, epoch, in_memory = removed, deleted = n, "shard released to its new owner; its data deleted here");
        Ok(n)
    }
}

fn ms(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

/// A number drawn once per process (what [`ShardStatus::boot`] reports).
pub fn boot_id() -> u64 {
    use std::sync::OnceLock;
    static BOOT: OnceLock<u64> = OnceLock::new();
    *BOOT.get_or_init(|| {
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        t ^ (u64::from(std::process::id()) << 32)
    })
}

/// A delete of every session of `shard` in `store`, read off the runtime
/// (what an import's first part, an abort and a release remove).
async fn stored_deletes(
    store: &Arc<mcapi_store::Store>,
    shard: u16,
    step: &str,
) -> Result<Vec<Write>, ServiceError> {
    let prefix = format!("{}.", shard_key(shard));
    let store = Arc::clone(store);
    let stored = tokio::task::spawn_blocking(move || store.sessions_with_prefix(&prefix))
        .await
        .map_err(|e| ServiceError::Internal(format!("the {step} task failed: {e}")))??;
    Ok(stored
        .into_iter()
        .map(|s| Write::Delete {
            id: Arc::from(s.id.as_str()),
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_manifest_follows_full_sessions_tails_and_deletions() {
        let before = Manifest {
            sessions: vec![("s0001.a".into(), Some(4)), ("s0001.b".into(), None)],
        };
        let data = ShardData {
            sessions: vec![
                MovedSession::Tail {
                    id: "s0001.a".into(),
                    entries: vec![(5, vec![1]), (6, vec![2])],
                },
                MovedSession::Full {
                    id: "s0001.c".into(),
                    record: vec![],
                    snapshot: Some((9, vec![])),
                    entries: vec![],
                },
            ],
            deleted: vec!["s0001.b".into()],
        };
        assert_eq!(
            data.manifest(&before).sessions,
            vec![
                ("s0001.a".to_string(), Some(6)),
                ("s0001.c".to_string(), Some(9))
            ]
        );
        assert_eq!(parse_shard("s03ff").ok(), Some(1023));
        assert!(parse_shard("s0400").is_err());
        assert!(parse_shard("s00012").is_err());
        assert!(parse_shard("S0001").is_err());
    }

    #[test]
    fn a_lease_is_bounded_with_a_precise_message() {
        assert_eq!(freeze_lease(None).ok(), Some(DEFAULT_FREEZE_LEASE));
        assert_eq!(
            freeze_lease(Some(100)).ok(),
            Some(Duration::from_millis(100))
        );
        assert!(freeze_lease(Some(MAX_FREEZE_LEASE_MS)).is_ok());
        for bad in [0, 99, MAX_FREEZE_LEASE_MS + 1, u64::MAX] {
            let e = freeze_lease(Some(bad)).expect_err("out of bounds");
            let text = e.to_string();
            assert!(
                text.contains("lease_ms") && text.contains(&format!("not {bad}")),
                "{text}"
            );
        }
    }
}
