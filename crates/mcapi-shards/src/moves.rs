//! The plain data of a live shard move as the admin API sends it (postcard
//! on the wire, docs/cluster.md "How a shard moves"): the sessions of a
//! shard ([`ShardData`]), what a mover already holds of it ([`Manifest`])
//! and a shard's state on a replica ([`ShardStatus`]). The replicas
//! (mcapi-server's `service::shards`) produce and apply them; the operator
//! tool (mcapi-cluster's mover) carries them between replicas.

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

/// One session in a move.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub enum MovedSession {
    /// The whole session: replaces whatever the target has of it.
    Full {
        /// Session id.
        id: String,
        /// The creation record.
        record: Vec<u8>,
        /// The newest snapshot and the sequence number it covers.
        snapshot: Option<(u64, Vec<u8>)>,
        /// The log after the snapshot.
        entries: Vec<(u64, Vec<u8>)>,
    },
    /// Log entries after those the target has.
    Tail {
        /// Session id.
        id: String,
        /// The new entries, in order.
        entries: Vec<(u64, Vec<u8>)>,
    },
}

impl MovedSession {
    /// Its id.
    pub fn id(&self) -> &str {
        match self {
            Self::Full { id, .. } | Self::Tail { id, .. } => id,
        }
    }

    /// The last sequence number the target holds once this is applied
    /// (`None`: a session without observations), given what it held.
    pub fn last_seq(&self, before: Option<u64>) -> Option<u64> {
        match self {
            Self::Full {
                snapshot, entries, ..
            } => entries
                .last()
                .map(|(s, _)| *s)
                .or(snapshot.as_ref().map(|(s, _)| *s)),
            Self::Tail { entries, .. } => entries.last().map(|(s, _)| *s).or(before),
        }
    }
}

/// A shard's data as one move step sends it (postcard on the wire).
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct ShardData {
    /// Sessions, whole or their tails.
    pub sessions: Vec<MovedSession>,
    /// Sessions deleted since the manifest (a delta only).
    pub deleted: Vec<String>,
}

/// What the mover already holds of a shard: each session id and the last
/// sequence number received (postcard on the wire).
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct Manifest {
    /// `(id, last sequence number)`, at most one entry per id.
    pub sessions: Vec<(String, Option<u64>)>,
}

impl ShardData {
    /// The manifest after applying this to `before`.
    pub fn manifest(&self, before: &Manifest) -> Manifest {
        let mut held: HashMap<&str, Option<u64>> = before
            .sessions
            .iter()
            .map(|(id, s)| (id.as_str(), *s))
            .collect();
        for s in &self.sessions {
            let prev = held.get(s.id()).copied().flatten();
            held.insert(s.id(), s.last_seq(prev));
        }
        for id in &self.deleted {
            held.remove(id.as_str());
        }
        let mut sessions: Vec<(String, Option<u64>)> = held
            .into_iter()
            .map(|(id, s)| (id.to_string(), s))
            .collect();
        sessions.sort();
        Manifest { sessions }
    }
}

/// A shard's state as the admin status call reports it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ShardStatus {
    /// The shard's key.
    pub shard: String,
    /// `owned`, `frozen`, `importing` or `foreign`.
    pub state: String,
    /// Its owner in this replica's map.
    pub owner: String,
    /// This replica.
    pub replica: String,
    /// The epoch of this replica's map.
    pub epoch: u64,
    /// Sessions of the shard served here.
    pub sessions: usize,
    /// A number drawn when this process started: a mover sees a restart.
    pub boot: u64,
    /// A frozen shard's lease left, in milliseconds: it is served here
    /// again after that unless its move commits first.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lease_ms: Option<u64>,
    /// A frozen shard's freeze token, which the move's commit presents.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub freeze_token: Option<u64>,
}

/// Every shard of one replica at once (`GET /admin/shards`): what
/// `mcapi cluster status` compares with the map file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ReplicaShards {
    /// The replica.
    pub replica: String,
    /// The epoch of its map.
    pub epoch: u64,
    /// [`ShardStatus::boot`].
    pub boot: u64,
    /// Shard by shard, `s0000` first.
    pub shards: Vec<ShardLine>,
}

/// One shard in [`ReplicaShards`].
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ShardLine {
    /// `owned`, `frozen`, `importing` or `foreign`.
    pub state: String,
    /// Its owner in the replica's map.
    pub owner: String,
    /// Sessions of it in the replica's memory.
    pub sessions: usize,
    /// A frozen shard's lease left, in milliseconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lease_ms: Option<u64>,
}
