//! A replica's view of the shard map (`mcapi serve --shard-map FILE
//! --replica NAME`): which shards it serves, and the answer for the others.
//! The session layer asks [`Placement::check`] before it looks a session up,
//! for both transports, and [`Placement::mint_shard`] when it creates one.
//!
//! Each shard is in one state (docs/cluster.md, "Shard states"):
//! - `Owned`: served here; new sessions are minted only in owned shards.
//! - `Frozen`: owned, but being handed over: refused with 503 and
//!   `Retry-After` (gRPC UNAVAILABLE) until the move ends.
//! - `Importing`: being received from its owner: not served yet (421
//!   naming the owner of the map).
//! - `Foreign`: another replica's: 421 naming it (gRPC UNAVAILABLE).
//!
//! This round reads the states from the map at start (owned or foreign);
//! [`Placement::set_state`] is the hook the shard moves will drive.

use parking_lot::RwLock;

use super::map::{ReplicaName, SHARDS, ShardMap, shard_key, shard_of_id};
use crate::service::ServiceError;

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
}

#[derive(Debug)]
struct Inner {
    map: ShardMap,
    states: Vec<ShardState>,
}

impl Placement {
    /// This replica's view of `map`. Refused if the map does not name the
    /// replica: a replica with no shard could serve nothing, and the cause
    /// is almost always a misspelt `--replica`.
    pub fn new(map: ShardMap, replica: ReplicaName) -> Result<Self, String> {
        if !map.has_replica(&replica) {
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
        Ok(Self {
            replica,
            inner: RwLock::new(Inner { map, states }),
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
        self.inner
            .read()
            .states
            .iter()
            .filter(|s| **s == ShardState::Owned)
            .count()
    }

    /// A shard's state.
    pub fn state(&self, shard: u16) -> ShardState {
        self.inner.read().states[usize::from(shard) % SHARDS]
    }

    /// Sets a shard's state (the shard moves of a later round drive this).
    pub fn set_state(&self, shard: u16, state: ShardState) {
        self.inner.write().states[usize::from(shard) % SHARDS] = state;
    }

    /// Whether a stored session of this id is served here (at start, the
    /// sessions of other shards stay in the store but are not loaded).
    pub fn holds(&self, id: &str) -> bool {
        shard_of_id(id)
            .is_some_and(|s| matches!(self.state(s), ShardState::Owned | ShardState::Frozen))
    }

    /// `Ok` if requests for session `id` are served here now; otherwise the
    /// refusal: [`ServiceError::WrongReplica`] naming the owner, or
    /// [`ServiceError::ShardFrozen`]. An id without a shard cannot exist on
    /// any replica: [`ServiceError::NotFound`].
    pub fn check(&self, id: &str) -> Result<(), ServiceError> {
        let Some(shard) = shard_of_id(id) else {
            return Err(ServiceError::NotFound(id.to_string()));
        };
        let inner = self.inner.read();
        match inner.states[usize::from(shard)] {
            ShardState::Owned => Ok(()),
            ShardState::Frozen => Err(ServiceError::ShardFrozen {
                shard: shard_key(shard),
                retry_after_secs: FROZEN_RETRY_AFTER_SECS,
            }),
            ShardState::Importing | ShardState::Foreign => {
                let owner = inner.map.owner(shard);
                // An importing shard's map owner may be this replica once
                // the map flips; until the move ends its data is elsewhere.
                Err(ServiceError::WrongReplica {
                    id: id.to_string(),
                    shard: shard_key(shard),
                    owner: owner.to_string(),
                    replica: self.replica.to_string(),
                    epoch: inner.map.epoch(),
                })
            }
        }
    }

    /// A shard for a new session: the `pick`-th owned shard (modulo their
    /// number), so a uniform `pick` spreads sessions evenly over them.
    /// `None` when no shard is owned (all frozen or handed over).
    pub fn mint_shard(&self, pick: u64) -> Option<u16> {
        let inner = self.inner.read();
        let owned: Vec<u16> = (0..SHARDS as u16)
            .filter(|&s| inner.states[usize::from(s)] == ShardState::Owned)
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
    use crate::cluster::plan::{ordinal_names, plan};

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
            Err(ServiceError::WrongReplica {
                owner,
                replica,
                epoch,
                ..
            }) => {
                assert_eq!(owner, "mcapi-1");
                assert_eq!(replica, "mcapi-0");
                assert_eq!(epoch, 1);
            }
            other => panic!("expected WrongReplica, got {other:?}"),
        }
        assert!(!p.holds(&their_id));
        assert!(matches!(
            p.check("nonsense"),
            Err(ServiceError::NotFound(_))
        ));
        p.set_state(mine[0], ShardState::Frozen);
        assert!(matches!(
            p.check(&own_id),
            Err(ServiceError::ShardFrozen {
                retry_after_secs: 1,
                ..
            })
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
    fn a_replica_missing_from_the_map_is_refused() {
        let (map, _) = two();
        let e =
            Placement::new(map, ReplicaName::parse("mcapi-9").expect("name")).expect_err("refused");
        assert!(e.contains("mcapi-0, mcapi-1"), "{e}");
    }
}
