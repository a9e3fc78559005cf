//! # mcapi-shards
//!
//! The shard map of a cluster of replicas (docs/cluster.md), as plain data
//! that both the server and the operator tool use: the versioned map, shard
//! keys and replica names ([`map`]), proposing the next map by rendezvous
//! hashing ([`plan`]), a replica's view of the map that its session layer
//! consults on every call ([`placement`]), and the data a shard move
//! carries between replicas ([`moves`]).
//!
//! A leaf: it depends on no other mcapi crate. The server (mcapi-server)
//! turns a [`PlacementError`] into its service error; the operator tool
//! (mcapi-cluster) reads and writes maps and moves shards.

pub mod map;
pub mod moves;
pub mod placement;
pub mod plan;

pub use map::{MapError, ReplicaName, SHARDS, ShardMap, parse_shard, shard_key, shard_of_id};
pub use placement::{
    CommitRefused, Lease, Placement, PlacementError, ShardFrozen, ShardState, WrongReplica,
    state_name,
};
