//! # mcapi-cluster
//!
//! The operator tool of a cluster of replicas (docs/cluster.md), behind
//! `mcapi cluster`: the command line ([`cli`]), HAProxy as the router
//! ([`haproxy`]), a supervised cluster on one machine ([`local`]), live
//! shard moves and rebalancing ([`mover`]) and the health probe
//! ([`probe`], also `mcapi healthcheck`'s).
//!
//! It works on the shard map of [`mcapi_shards`] and talks to the replicas
//! only as any client would: through their admin HTTP API, and by running
//! the `mcapi serve` binary. It does not depend on mcapi-server; its logging
//! ([`logging`]) is its own, and the signal that ends a supervised cluster
//! is the binary's, given to [`cli::run`].

pub mod cli;
pub mod files;
pub mod haproxy;
pub mod local;
pub mod logging;
pub mod mover;
pub mod probe;
