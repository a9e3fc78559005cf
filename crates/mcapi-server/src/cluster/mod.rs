//! Scale-out over replicas (docs/cluster.md): the versioned shard map
//! ([`map`]), proposing the next one by rendezvous hashing ([`plan`]), a
//! replica's view of it that the session layer consults on every call
//! ([`placement`]), HAProxy as the router ([`haproxy`]), a supervised
//! cluster on one machine ([`local`]), the health probe ([`probe`]) and the
//! `mcapi cluster` command line ([`cli`]).

pub mod cli;
pub mod haproxy;
pub mod local;
pub mod map;
pub mod mover;
pub mod placement;
pub mod plan;
pub mod probe;

pub use map::{MapError, ReplicaName, ShardMap, shard_key, shard_of_id};
pub use placement::{Placement, ShardState};

#[cfg(test)]
mod move_tests;
#[cfg(test)]
mod service_tests;
