//! Proposing a shard map (`mcapi cluster plan`, docs/cluster.md): rendezvous
//! (highest random weight) hashing ranks the replicas for each shard, and
//! a capacity of ⌈1024 / N⌉ shards per replica keeps the spread even.
//!
//! From an earlier map, every shard stays where it is unless its owner is
//! gone or holds more than its capacity; an owner over capacity gives up
//! the shards it ranks lowest, and each shard given up goes to the
//! highest-ranked replica with room. So going from N to N+1 replicas moves
//! the old replicas' excess only: ⌊1024 / (N+1)⌋ or so shards, all of them
//! to the new replica, which is the least any even spread can move.
//!
//! The weight of (shard, replica) is the first 8 bytes of SHA-256 over a
//! fixed prefix, the shard and the replica's name: deterministic across
//! machines, versions and runs.

use sha2::{Digest, Sha256};

use crate::map::{MapError, ReplicaName, SHARDS, ShardMap};

/// The rendezvous weight of a replica for a shard.
pub fn weight(shard: u16, replica: &ReplicaName) -> u64 {
    let mut h = Sha256::new();
    h.update(b"mcapi-shard-v1\0");
    h.update(shard.to_be_bytes());
    h.update(replica.as_str().as_bytes());
    let digest = h.finalize();
    let mut first = [0u8; 8];
    first.copy_from_slice(&digest[..8]);
    u64::from_be_bytes(first)
}

/// A proposed map and how it differs from the one it came from.
#[derive(Debug, Clone)]
pub struct Plan {
    /// The proposed map.
    pub map: ShardMap,
    /// Shards whose owner changed (all of them without an earlier map).
    pub moved: Vec<Move>,
}

/// One shard changing owner.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Move {
    /// The shard.
    pub shard: u16,
    /// Its owner in the earlier map.
    pub from: ReplicaName,
    /// Its owner in the proposed one.
    pub to: ReplicaName,
}

/// Proposes a map over `replicas` (distinct names; 1 to 1024 of them),
/// starting from `from` if given; the epoch is one past `from`'s, else 1.
pub fn plan(replicas: &[ReplicaName], from: Option<&ShardMap>) -> Result<Plan, MapError> {
    let mut names: Vec<ReplicaName> = replicas.to_vec();
    names.sort();
    names.dedup();
    if names.is_empty() || names.len() != replicas.len() {
        return Err(MapError::Syntax {
            line: 0,
            reason: "a plan needs at least one replica, each named once".into(),
        });
    }
    if names.len() > crate::map::MAX_REPLICAS {
        return Err(MapError::TooManyReplicas {
            max: crate::map::MAX_REPLICAS,
        });
    }
    let n = names.len();
    let capacity = SHARDS.div_ceil(n);
    // Replica indices ranked by weight, best first, per shard.
    let ranked: Vec<Vec<usize>> = (0..SHARDS as u16)
        .map(|s| {
            let mut r: Vec<(u64, usize)> = names
                .iter()
                .enumerate()
                .map(|(i, name)| (weight(s, name), i))
                .collect();
            r.sort_unstable_by(|a, b| b.cmp(a));
            r.into_iter().map(|(_, i)| i).collect()
        })
        .collect();
    // Start: the earlier owner if still there, else the top-ranked replica.
    let mut owner: Vec<Option<usize>> = (0..SHARDS)
        .map(|s| match from {
            Some(m) => names.binary_search(m.owner(s as u16)).ok(),
            None => Some(ranked[s][0]),
        })
        .collect();
    // Owners over capacity give up the shards they rank lowest.
    for (r, name) in names.iter().enumerate() {
        let mut held: Vec<(u64, usize)> = (0..SHARDS)
            .filter(|&s| owner[s] == Some(r))
            .map(|s| (weight(s as u16, name), s))
            .collect();
        if held.len() <= capacity {
            continue;
        }
        held.sort_unstable();
        let excess = held.len() - capacity;
        for &(_, s) in &held[..excess] {
            owner[s] = None;
        }
    }
    // Each shard without an owner goes to its best-ranked replica with room.
    let mut load = vec![0usize; n];
    for o in owner.iter().flatten() {
        load[*o] += 1;
    }
    for s in 0..SHARDS {
        if owner[s].is_some() {
            continue;
        }
        // The capacities sum to at least 1024: some replica has room.
        let to = ranked[s]
            .iter()
            .copied()
            .find(|&r| load[r] < capacity)
            .unwrap_or(ranked[s][0]);
        load[to] += 1;
        owner[s] = Some(to);
    }
    let owners: Vec<ReplicaName> = owner
        .iter()
        .map(|o| names[o.unwrap_or(0)].clone())
        .collect();
    let epoch = from.map_or(1, |m| m.epoch().saturating_add(1));
    let map = ShardMap::from_owners(epoch, &owners)?;
    let moved = match from {
        Some(old) => (0..SHARDS as u16)
            .filter(|&s| old.owner(s) != map.owner(s))
            .map(|s| Move {
                shard: s,
                from: old.owner(s).clone(),
                to: map.owner(s).clone(),
            })
            .collect(),
        None => Vec::new(),
    };
    Ok(Plan { map, moved })
}

/// `prefix-0` .. `prefix-(n-1)`, the names of a Kubernetes StatefulSet's pods.
pub fn ordinal_names(prefix: &str, n: usize) -> Result<Vec<ReplicaName>, String> {
    (0..n)
        .map(|i| ReplicaName::parse(&format!("{prefix}-{i}")))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(n: usize) -> Vec<ReplicaName> {
        ordinal_names("mcapi", n).expect("names")
    }

    #[test]
    fn weights_are_fixed() {
        // Pinned (computed independently: the first 8 bytes, big-endian, of
        // SHA-256 over b"mcapi-shard-v1\0", the shard as u16 BE and the
        // name): a change of the hash would move shards between versions.
        assert_eq!(weight(0, &names(1)[0]), 0x6e49_f601_ffb5_6d68);
        assert_eq!(weight(0x3a7, &names(3)[2]), 0xc424_3bb3_5cc7_9f1a);
        assert_ne!(weight(1, &names(1)[0]), weight(0, &names(1)[0]));
        let again = plan(&names(3), None).expect("plan");
        assert_eq!(plan(&names(3), None).expect("plan").map, again.map);
    }

    #[test]
    fn a_fresh_plan_is_even() {
        for n in [1, 2, 3, 4, 7, 64] {
            let p = plan(&names(n), None).expect("plan");
            assert_eq!(p.map.epoch(), 1);
            let counts: Vec<usize> = p.map.counts().iter().map(|(_, c)| *c).collect();
            assert_eq!(counts.len(), n);
            assert_eq!(counts.iter().sum::<usize>(), SHARDS);
            let cap = SHARDS.div_ceil(n);
            assert!(counts.iter().all(|&c| c <= cap), "{n}: {counts:?}");
            assert!(
                counts.iter().all(|&c| c + n >= cap),
                "{n}: {counts:?} (cap {cap})"
            );
        }
    }

    #[test]
    fn adding_a_replica_moves_about_one_in_n_plus_one_all_to_it() {
        for n in 1..=8 {
            let old = plan(&names(n), None).expect("plan").map;
            let p = plan(&names(n + 1), Some(&old)).expect("plan");
            assert_eq!(p.map.epoch(), 2);
            let new = &names(n + 1)[n];
            let ideal = SHARDS as f64 / (n + 1) as f64;
            let moved = p.moved.len() as f64;
            assert!(
                (moved - ideal).abs() <= 0.02 * SHARDS as f64,
                "{n}->{}: {moved} moved, ideal {ideal:.1}",
                n + 1
            );
            assert!(
                p.moved.iter().all(|m| &m.to == new),
                "{n}: not all to {new}"
            );
            // No move among the old replicas.
            assert!(p.moved.iter().all(|m| &m.from != new));
        }
    }

    #[test]
    fn removing_a_replica_moves_only_its_shards() {
        let old = plan(&names(4), None).expect("plan").map;
        let three = names(3);
        let p = plan(&three, Some(&old)).expect("plan");
        let gone = &names(4)[3];
        assert_eq!(p.moved.len(), old.shards_of(gone).len());
        assert!(p.moved.iter().all(|m| &m.from == gone));
        assert!(!p.map.has_replica(gone));
    }

    #[test]
    fn an_even_map_plans_to_itself() {
        let old = plan(&names(5), None).expect("plan").map;
        let p = plan(&names(5), Some(&old)).expect("plan");
        assert!(p.moved.is_empty());
        assert_eq!(p.map.owners(), old.owners());
        assert_eq!(p.map.epoch(), old.epoch() + 1);
    }

    #[test]
    fn bad_replica_sets_are_refused() {
        assert!(plan(&[], None).is_err());
        let twice = vec![names(1)[0].clone(), names(1)[0].clone()];
        assert!(plan(&twice, None).is_err());
        assert!(ordinal_names("Bad", 2).is_err());
    }
}
