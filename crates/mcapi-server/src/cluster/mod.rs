//! Scale-out over replicas (docs/cluster.md): the versioned shard map
//! ([`map`]), proposing the next one by rendezvous hashing ([`plan`]), a
//! replica's view of it that the session layer consults on every call
//! ([`placement`]), HAProxy as the router ([`haproxy`]) and the
//! `mcapi cluster` command line ([`cli`]).

pub mod cli;
pub mod haproxy;
pub mod map;
pub mod placement;
pub mod plan;

pub use map::{MapError, ReplicaName, ShardMap, shard_key, shard_of_id};
pub use placement::{Placement, ShardState};

#[cfg(test)]
mod service_tests;
