//! A replica's view of the shard map (`mcapi serve --shard-map FILE
//! --replica NAME`): which shards it serves, and the answer for the others.
//! The session layer asks [`Placement::check`] before it looks a session up,
//! for both transports, and [`Placement::mint_shard`] when it creates one.
//!
//! Each shard is in one state (docs/cluster.md, "Shard states"):
//! - `Owned`: served here; new sessions are minted only in owned shards.
//! - `Frozen`: owned, but being handed over: refused with 503 and
//!   `Retry-After` (gRPC UNAVAILABLE) until the move ends. A freeze made by
//!   [`Placement::freeze`] holds a lease: once its deadline passes without
//!   a [`Placement::commit`], the shard is `Owned` again by itself, so a
//!   mover that died mid-move does not leave it refusing requests.
//! - `Importing`: being received from its owner: not served yet (421
//!   naming the owner of the map).
//! - `Foreign`: another replica's: 421 naming it (gRPC UNAVAILABLE).
//!
//! The states come from the map at start (owned or foreign); a shard move
//! (mcapi-server's `service::shards`, docs/cluster.md "How a shard moves") drives them
//! with [`Placement::set_state`] and [`Placement::set_owner`]. Every
//! request that changes a shard (create, observe, delete) holds a
//! [`ShardGuard`] while it runs, so a move that freezes the shard can wait
//! until none is in flight before it reads the shard's last changes.

use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use parking_lot::RwLock;

use thiserror::Error;

use crate::map::{ReplicaName, SHARDS, ShardMap, shard_key, shard_of_id};

/// A session whose shard belongs to another replica: a router with a stale
/// map sent the request here. Nothing was done; retrying through the
/// router succeeds once it follows the map.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error(
    "session `{id}` is in shard {shard}, owned by replica `{owner}` (shard map epoch {epoch}), not by this replica `{replica}`; retry through the router"
)]
pub struct WrongReplica {
    /// The session.
    pub id: String,
    /// Its shard's key (`s03a7`).
    pub shard: String,
    /// The replica that owns it.
    pub owner: String,
    /// This replica.
    pub replica: String,
    /// The epoch of this replica's map.
    pub epoch: u64,
}

/// A session whose shard is being moved to another replica: nothing was
/// done; retry after `retry_after_secs`.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error(
    "shard {shard} is being moved to another replica; nothing was done, retry in {retry_after_secs} s"
)]
pub struct ShardFrozen {
    /// The shard's key.
    pub shard: String,
    /// Seconds to wait (`Retry-After`).
    pub retry_after_secs: u64,
}

/// Why a request or a move step is refused here. The server turns each
/// into its service error of the same name, carrying the same refusal.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum PlacementError {
    /// No such session: its id has no shard, so no replica can hold it.
    #[error("session `{0}` not found")]
    NotFound(String),
    /// The session's shard belongs to another replica.
    #[error(transparent)]
    WrongReplica(WrongReplica),
    /// The session's shard is being moved to another replica.
    #[error(transparent)]
    ShardFrozen(ShardFrozen),
    /// A move step that does not fit this replica's map (a stale mover).
    #[error("{0}")]
    MoveConflict(String),
}

/// Seconds a client is told to wait (`Retry-After`) while a shard is frozen.
pub const FROZEN_RETRY_AFTER_SECS: u64 = 1;

/// One shard's state on this replica.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ShardState {
    /// Served here.
    Owned,
    /// Owned, being handed over: requests wait (503, `Retry-After`).
    Frozen,
    /// Being received: not served until the move ends.
    Importing,
    /// Owned by another replica.
    Foreign,
}

/// What this replica is and serves.
#[derive(Debug)]
pub struct Placement {
    replica: ReplicaName,
    inner: RwLock<Inner>,
    /// Requests changing each shard now ([`ShardGuard`]).
    in_flight: Vec<AtomicU32>,
    /// The next freeze's token. Starts from the clock, so a restarted
    /// replica does not hand out the tokens of its former life again.
    next_token: AtomicU64,
}

/// A freeze's lease: the shard is frozen until `until`, then served again
/// unless the move committed with `token` before.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Lease {
    /// What a commit must present: this freeze and no other.
    pub token: u64,
    /// When the shard is served again by itself.
    pub until: Instant,
    /// The lease's length as asked for.
    pub length: Duration,
}

impl Lease {
    /// Time left at `now` (zero once expired).
    pub fn left(&self, now: Instant) -> Duration {
        self.until.saturating_duration_since(now)
    }
}

/// A request changing a shard, counted while it lives (see
/// [`Placement::enter`]).
#[derive(Debug)]
pub struct ShardGuard {
    placement: Arc<Placement>,
    shard: u16,
}

impl ShardGuard {
    /// The shard.
    pub fn shard(&self) -> u16 {
        self.shard
    }
}

impl Drop for ShardGuard {
    fn drop(&mut self) {
        self.placement.in_flight[usize::from(self.shard) % SHARDS].fetch_sub(1, Ordering::AcqRel);
    }
}

#[derive(Debug)]
struct Inner {
    map: ShardMap,
    states: Vec<ShardState>,
    /// The lease of each frozen shard (`None`: frozen without a deadline,
    /// which only [`Placement::set_state`] does).
    leases: Vec<Option<Lease>>,
    /// The last lease that ran out on each shard: a late commit of it is
    /// told so precisely, whenever it comes.
    expired: Vec<Option<Lease>>,
}

impl Inner {
    /// A shard's state at `now`: a frozen shard whose lease has expired is
    /// owned, whether or not its timer has run yet. Every decision reads
    /// the state through this, so the deadline is exact.
    fn state_at(&self, shard: u16, now: Instant) -> ShardState {
        let i = usize::from(shard) % SHARDS;
        match (self.states[i], self.leases[i]) {
            (ShardState::Frozen, Some(lease)) if now >= lease.until => ShardState::Owned,
            (state, _) => state,
        }
    }

    /// Writes what [`Inner::state_at`] says back (an expired freeze is
    /// owned), so a write starts from the state in force.
    fn settle(&mut self, shard: u16, now: Instant) -> ShardState {
        let i = usize::from(shard) % SHARDS;
        let state = self.state_at(shard, now);
        if state != self.states[i] {
            self.states[i] = state;
            self.expired[i] = self.leases[i].take();
        }
        state
    }

    fn set(&mut self, shard: u16, state: ShardState) {
        let i = usize::from(shard) % SHARDS;
        self.states[i] = state;
        self.leases[i] = None;
    }
}

/// Why a commit is refused: the freeze it names is not in force.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum CommitRefused {
    /// The shard is not frozen here (its lease expired and it is served
    /// again, or it was thawed, or this replica restarted).
    #[error(
        "shard {shard} is {state} on replica `{replica}`, not frozen: {why}; nothing was committed, move it again"
    )]
    NotFrozen {
        /// The shard's key.
        shard: String,
        /// Its state here.
        state: &'static str,
        /// The replica.
        replica: String,
        /// What most likely happened.
        why: String,
    },
    /// Frozen, but by another freeze than the one named.
    #[error(
        "shard {shard} is frozen on replica `{replica}` by another freeze (token {found}, not {token}); nothing was committed"
    )]
    OtherFreeze {
        /// The shard's key.
        shard: String,
        /// The replica.
        replica: String,
        /// The token presented.
        token: u64,
        /// The token of the freeze in force.
        found: u64,
    },
}

/// A state's name, as the admin routes and the operator tool spell it.
pub fn state_name(s: ShardState) -> &'static str {
    match s {
        ShardState::Owned => "owned",
        ShardState::Frozen => "frozen",
        ShardState::Importing => "importing",
        ShardState::Foreign => "foreign",
    }
}

impl Placement {
    /// This replica's view of `map`. Refused if the map does not name the
    /// replica: a replica with no shard could serve nothing, and the cause
    /// is almost always a misspelt `--replica`.
    pub fn new(map: ShardMap, replica: ReplicaName) -> Result<Self, String> {
        Self::with_joining(map, replica, false)
    }

    /// [`Placement::new`]; with `joining`, a replica the map does not name
    /// yet is accepted, owning nothing until shards move to it (`mcapi
    /// cluster rebalance` starts new replicas so).
    pub fn with_joining(
        map: ShardMap,
        replica: ReplicaName,
        joining: bool,
    ) -> Result<Self, String> {
        if !joining && !map.has_replica(&replica) {
            let known: Vec<&str> = map.replicas().iter().map(ReplicaName::as_str).collect();
            return Err(format!(
                "replica `{replica}` owns no shard in the shard map (epoch {}); its replicas are: {}",
                map.epoch(),
                known.join(", ")
            ));
        }
        let states = (0..SHARDS as u16)
            .map(|s| {
                if *map.owner(s) == replica {
                    ShardState::Owned
                } else {
                    ShardState::Foreign
                }
            })
            .collect();
        let clock = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(1, |d| d.as_nanos() as u64);
        Ok(Self {
            replica,
            inner: RwLock::new(Inner {
                map,
                states,
                leases: vec![None; SHARDS],
                expired: vec![None; SHARDS],
            }),
            in_flight: (0..SHARDS).map(|_| AtomicU32::new(0)).collect(),
            next_token: AtomicU64::new(clock | 1),
        })
    }

    /// This replica's name.
    pub fn replica(&self) -> &ReplicaName {
        &self.replica
    }

    /// The epoch of the map in force.
    pub fn epoch(&self) -> u64 {
        self.inner.read().map.epoch()
    }

    /// Shards in the `Owned` state.
    pub fn owned_count(&self) -> usize {
        let inner = self.inner.read();
        let now = Instant::now();
        (0..SHARDS as u16)
            .filter(|&s| inner.state_at(s, now) == ShardState::Owned)
            .count()
    }

    /// A shard's state (a freeze whose lease expired is `Owned`).
    pub fn state(&self, shard: u16) -> ShardState {
        self.inner.read().state_at(shard, Instant::now())
    }

    /// Every shard's state and, when frozen, its lease, with the owner in
    /// this replica's map: what the operator's status shows.
    pub fn states(&self) -> Vec<(ShardState, Option<Lease>, ReplicaName)> {
        let inner = self.inner.read();
        let now = Instant::now();
        (0..SHARDS as u16)
            .map(|s| {
                let state = inner.state_at(s, now);
                let lease = if state == ShardState::Frozen {
                    inner.leases[usize::from(s)]
                } else {
                    None
                };
                (state, lease, inner.map.owner(s).clone())
            })
            .collect()
    }

    /// Sets a shard's state (a shard move drives this); a freeze set so
    /// has no lease.
    pub fn set_state(&self, shard: u16, state: ShardState) {
        self.inner.write().set(shard, state);
    }

    /// Sets a shard's state if it is `from` now; returns the state found.
    pub fn swap_state(&self, shard: u16, from: &[ShardState], to: ShardState) -> ShardState {
        let mut inner = self.inner.write();
        let now = inner.settle(shard, Instant::now());
        if from.contains(&now) {
            inner.set(shard, to);
        }
        now
    }

    /// Freezes an owned shard for `lease` (a frozen one: its lease starts
    /// again, with the same token, so a repeated call changes nothing
    /// else). Returns the lease, or the state found if the shard is
    /// neither owned nor frozen here.
    pub fn freeze(&self, shard: u16, lease: Duration) -> Result<Lease, ShardState> {
        let mut inner = self.inner.write();
        let now = Instant::now();
        let i = usize::from(shard) % SHARDS;
        let token = match (inner.settle(shard, now), inner.leases[i]) {
            (ShardState::Frozen, Some(held)) => held.token,
            (ShardState::Owned | ShardState::Frozen, _) => {
                self.next_token.fetch_add(2, Ordering::Relaxed)
            }
            (other, _) => return Err(other),
        };
        let held = Lease {
            token,
            until: now.checked_add(lease).unwrap_or(now),
            length: lease,
        };
        inner.states[i] = ShardState::Frozen;
        inner.leases[i] = Some(held);
        Ok(held)
    }

    /// The lease of a frozen shard, if it has one in force.
    pub fn lease(&self, shard: u16) -> Option<Lease> {
        let inner = self.inner.read();
        if inner.state_at(shard, Instant::now()) == ShardState::Frozen {
            inner.leases[usize::from(shard) % SHARDS]
        } else {
            None
        }
    }

    /// The lease's end (the timer a freeze starts): if the freeze of
    /// `token` is still there and past its deadline, the shard is owned
    /// again. Returns whether this call thawed it.
    pub fn expire(&self, shard: u16, token: u64) -> bool {
        let mut inner = self.inner.write();
        let i = usize::from(shard) % SHARDS;
        let ours = inner.states[i] == ShardState::Frozen
            && inner.leases[i].is_some_and(|l| l.token == token);
        ours && inner.settle(shard, Instant::now()) == ShardState::Owned
    }

    /// The commit point of a move on its source: the shard, frozen by the
    /// freeze of `token` whose lease has not expired, is `owner`'s from
    /// `epoch` on (`Foreign` here, 421 naming `owner`). Checked and done
    /// under the one lock that the lease's expiry also takes, so exactly
    /// one of the two happens: a move whose lease ran out cannot commit,
    /// and a committed shard is never served here again.
    pub fn commit(
        &self,
        shard: u16,
        token: u64,
        owner: &ReplicaName,
        epoch: u64,
    ) -> Result<(), PlacementError> {
        let mut inner = self.inner.write();
        let now = Instant::now();
        let i = usize::from(shard) % SHARDS;
        let state = inner.settle(shard, now);
        let lease = inner.leases[i].or(inner.expired[i]);
        match (state, lease) {
            (ShardState::Frozen, Some(l)) if l.token == token => {}
            (ShardState::Frozen, Some(l)) => {
                return Err(PlacementError::MoveConflict(
                    CommitRefused::OtherFreeze {
                        shard: shard_key(shard),
                        replica: self.replica.to_string(),
                        token,
                        found: l.token,
                    }
                    .to_string(),
                ));
            }
            (state, _) => {
                let why = match lease {
                    Some(l) if l.token == token && now >= l.until => format!(
                        "the lease of its freeze ({} ms) expired {} ms ago",
                        l.length.as_millis(),
                        now.saturating_duration_since(l.until).as_millis()
                    ),
                    _ if state == ShardState::Owned => {
                        "its freeze ended (its lease expired, it was thawed, or this replica restarted)"
                            .to_string()
                    }
                    _ => "it is not this replica's to give".to_string(),
                };
                return Err(PlacementError::MoveConflict(
                    CommitRefused::NotFrozen {
                        shard: shard_key(shard),
                        state: state_name(state),
                        replica: self.replica.to_string(),
                        why,
                    }
                    .to_string(),
                ));
            }
        }
        if owner == &self.replica {
            return Err(PlacementError::MoveConflict(format!(
                "shard {} cannot be committed to its own replica `{owner}`",
                shard_key(shard)
            )));
        }
        Self::set_owner_in(&mut inner, shard, owner, epoch, ShardState::Foreign)
    }

    /// Records a move's end: `shard` is `owner`'s from `epoch` on, which
    /// must be above the epoch in force (the highest epoch wins: a stale
    /// mover is refused), and gets `state` here.
    pub fn set_owner(
        &self,
        shard: u16,
        owner: &ReplicaName,
        epoch: u64,
        state: ShardState,
    ) -> Result<(), PlacementError> {
        let mut inner = self.inner.write();
        inner.settle(shard, Instant::now());
        Self::set_owner_in(&mut inner, shard, owner, epoch, state)
    }

    fn set_owner_in(
        inner: &mut Inner,
        shard: u16,
        owner: &ReplicaName,
        epoch: u64,
        state: ShardState,
    ) -> Result<(), PlacementError> {
        if epoch <= inner.map.epoch() {
            return Err(PlacementError::MoveConflict(format!(
                "epoch {epoch} is not above this replica's shard map epoch {}; another move came first (re-read the map and plan again)",
                inner.map.epoch()
            )));
        }
        let map = inner
            .map
            .with_owner(shard, owner, epoch)
            .map_err(|e| PlacementError::MoveConflict(e.to_string()))?;
        inner.map = map;
        inner.set(shard, state);
        Ok(())
    }

    /// Requests changing `shard` now.
    pub fn in_flight(&self, shard: u16) -> u32 {
        self.in_flight[usize::from(shard) % SHARDS].load(Ordering::Acquire)
    }

    /// [`Placement::check`], and if served here, a guard counting the
    /// request as changing the shard until it is dropped. Taken under the
    /// same lock a freeze takes, so a request either is counted before the
    /// freeze or refused after it.
    pub fn enter(self: &Arc<Self>, id: &str) -> Result<ShardGuard, PlacementError> {
        let inner = self.inner.read();
        self.check_in(&inner, id)?;
        let shard = shard_of_id(id).unwrap_or(0);
        self.in_flight[usize::from(shard)].fetch_add(1, Ordering::AcqRel);
        Ok(ShardGuard {
            placement: Arc::clone(self),
            shard,
        })
    }

    /// [`Placement::mint_shard`] with the guard of [`Placement::enter`].
    pub fn mint(self: &Arc<Self>, pick: u64) -> Option<ShardGuard> {
        let inner = self.inner.read();
        let shard = Self::mint_in(&inner, pick)?;
        self.in_flight[usize::from(shard)].fetch_add(1, Ordering::AcqRel);
        Some(ShardGuard {
            placement: Arc::clone(self),
            shard,
        })
    }

    /// The map in force.
    pub fn map(&self) -> ShardMap {
        self.inner.read().map.clone()
    }

    /// Whether a stored session of this id is served here (at start, the
    /// sessions of other shards stay in the store but are not loaded).
    pub fn holds(&self, id: &str) -> bool {
        shard_of_id(id)
            .is_some_and(|s| matches!(self.state(s), ShardState::Owned | ShardState::Frozen))
    }

    /// `Ok` if requests for session `id` are served here now; otherwise the
    /// refusal: [`PlacementError::WrongReplica`] naming the owner, or
    /// [`PlacementError::ShardFrozen`]. An id without a shard cannot exist on
    /// any replica: [`PlacementError::NotFound`].
    pub fn check(&self, id: &str) -> Result<(), PlacementError> {
        self.check_in(&self.inner.read(), id)
    }

    fn check_in(&self, inner: &Inner, id: &str) -> Result<(), PlacementError> {
        let Some(shard) = shard_of_id(id) else {
            return Err(PlacementError::NotFound(id.to_string()));
        };
        match inner.state_at(shard, Instant::now()) {
            ShardState::Owned => Ok(()),
            ShardState::Frozen => Err(PlacementError::ShardFrozen(ShardFrozen {
                shard: shard_key(shard),
                retry_after_secs: FROZEN_RETRY_AFTER_SECS,
            })),
            ShardState::Importing | ShardState::Foreign => {
                let owner = inner.map.owner(shard);
                // An importing shard's map owner may be this replica once
                // the map flips; until the move ends its data is elsewhere.
                Err(PlacementError::WrongReplica(WrongReplica {
                    id: id.to_string(),
                    shard: shard_key(shard),
                    owner: owner.to_string(),
                    replica: self.replica.to_string(),
                    epoch: inner.map.epoch(),
                }))
            }
        }
    }

    /// A shard for a new session: the `pick`-th owned shard (modulo their
    /// number), so a uniform `pick` spreads sessions evenly over them.
    /// `None` when no shard is owned (all frozen or handed over).
    pub fn mint_shard(&self, pick: u64) -> Option<u16> {
        Self::mint_in(&self.inner.read(), pick)
    }

    fn mint_in(inner: &Inner, pick: u64) -> Option<u16> {
        let now = Instant::now();
        let owned: Vec<u16> = (0..SHARDS as u16)
            .filter(|&s| inner.state_at(s, now) == ShardState::Owned)
            .collect();
        if owned.is_empty() {
            return None;
        }
        let i = usize::try_from(pick % owned.len() as u64).unwrap_or(0);
        owned.get(i).copied()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::{ordinal_names, plan};

    fn two() -> (ShardMap, Vec<ReplicaName>) {
        let names = ordinal_names("mcapi", 2).expect("names");
        (plan(&names, None).expect("plan").map, names)
    }

    #[test]
    fn owned_foreign_and_frozen_shards_answer_differently() {
        let (map, names) = two();
        let mine = map.shards_of(&names[0]);
        let theirs = map.shards_of(&names[1]);
        let p = Placement::new(map, names[0].clone()).expect("placement");
        assert_eq!(p.owned_count(), mine.len());
        let own_id = format!("{}.01JDX4", shard_key(mine[0]));
        let their_id = format!("{}.01JDX4", shard_key(theirs[0]));
        assert!(p.check(&own_id).is_ok());
        assert!(p.holds(&own_id));
        match p.check(&their_id) {
            Err(PlacementError::WrongReplica(WrongReplica {
                owner,
                replica,
                epoch,
                ..
            })) => {
                assert_eq!(owner, "mcapi-1");
                assert_eq!(replica, "mcapi-0");
                assert_eq!(epoch, 1);
            }
            other => panic!("expected WrongReplica, got {other:?}"),
        }
        assert!(!p.holds(&their_id));
        assert!(matches!(
            p.check("nonsense"),
            Err(PlacementError::NotFound(_))
        ));
        p.set_state(mine[0], ShardState::Frozen);
        assert!(matches!(
            p.check(&own_id),
            Err(PlacementError::ShardFrozen(ShardFrozen {
                retry_after_secs: 1,
                ..
            }))
        ));
        assert!(p.holds(&own_id), "a frozen shard's sessions stay loaded");
    }

    #[test]
    fn new_sessions_go_only_to_owned_shards() {
        let (map, names) = two();
        let p = Placement::new(map.clone(), names[1].clone()).expect("placement");
        let owned = map.shards_of(&names[1]);
        for pick in 0..5000u64 {
            let s = p
                .mint_shard(pick.wrapping_mul(0x9e37_79b9_7f4a_7c15))
                .expect("a shard");
            assert_eq!(map.owner(s), &names[1]);
        }
        p.set_state(owned[0], ShardState::Frozen);
        assert!((0..2000u64).all(|k| p.mint_shard(k) != Some(owned[0])));
        for s in owned {
            p.set_state(s, ShardState::Frozen);
        }
        assert_eq!(p.mint_shard(3), None);
    }

    #[test]
    fn a_freeze_ends_with_its_lease_and_a_late_commit_is_refused() {
        let (map, names) = two();
        let mine = map.shards_of(&names[0]);
        let (s, t) = (mine[0], mine[1]);
        let p = Placement::new(map, names[0].clone()).expect("placement");
        let id = format!("{}.01JDX4", shard_key(s));
        let lease = p.freeze(s, Duration::from_millis(40)).expect("owned");
        assert_eq!(p.state(s), ShardState::Frozen);
        assert!(matches!(p.check(&id), Err(PlacementError::ShardFrozen(_))));
        assert!(!p.expire(s, lease.token), "not before its deadline");
        let again = p.freeze(s, Duration::from_millis(40)).expect("renewed");
        assert_eq!(
            again.token, lease.token,
            "a repeated freeze keeps its token"
        );
        std::thread::sleep(Duration::from_millis(60));
        // Served again at the deadline, before any timer ran.
        assert_eq!(p.state(s), ShardState::Owned);
        assert!(p.check(&id).is_ok());
        assert!(p.mint_shard(0).is_some());
        let e = p
            .commit(s, lease.token, &names[1], 2)
            .expect_err("the lease expired");
        let PlacementError::MoveConflict(text) = e else {
            panic!("a move conflict")
        };
        assert!(
            text.contains("the lease of its freeze (40 ms) expired"),
            "{text}"
        );
        assert_eq!(p.epoch(), 1, "nothing committed");
        assert_eq!(p.state(s), ShardState::Owned);
        assert!(!p.expire(s, lease.token), "thawed already");

        // In time, with its own token: the shard is the new owner's.
        let lease = p.freeze(t, Duration::from_secs(30)).expect("owned");
        let e = p
            .commit(t, lease.token + 2, &names[1], 2)
            .expect_err("another token");
        assert!(e.to_string().contains("by another freeze"), "{e}");
        assert!(p.commit(t, lease.token, &names[0], 2).is_err(), "to itself");
        assert!(
            p.commit(t, lease.token, &names[1], 1).is_err(),
            "an old epoch"
        );
        p.commit(t, lease.token, &names[1], 2).expect("committed");
        assert_eq!(p.state(t), ShardState::Foreign);
        assert_eq!(p.epoch(), 2);
        assert!(!p.expire(t, lease.token), "a committed shard never thaws");
        assert!(
            p.commit(t, lease.token, &names[1], 3).is_err(),
            "committed once"
        );
        assert!(p.freeze(t, Duration::from_secs(1)).is_err(), "not owned");
    }

    #[test]
    fn a_replica_missing_from_the_map_is_refused() {
        let (map, _) = two();
        let e =
            Placement::new(map, ReplicaName::parse("mcapi-9").expect("name")).expect_err("refused");
        assert!(e.contains("mcapi-0, mcapi-1"), "{e}");
    }
}
