//! # mcapi-server
//!
//! Hosts motivated reinforcement-learning agents (MCA-PI, Kompella,
//! Kazerounian, Schmidhuber, SAB 2014, implemented in [`mcapi_core`]) as
//! sessions, over REST (axum) and gRPC (tonic).
//!
//! Modules, from the bottom up (docs/architecture.md, "The layers"):
//! - [`service`]: the session layer both transports call (sessions, tick
//!   loop, limits, recovery), over the durable store ([`mcapi_store`], or
//!   memory); on a replica of a cluster it asks the shard map's placement
//!   ([`mcapi_shards`]) first.
//! - [`api`]: thin transport adapters over [`service`], with one error
//!   mapping.
//! - [`generated`]: the files written from the parameter tables (the
//!   docs' tables, the Python client's options) and the checks that keep
//!   the proto and the OpenAPI document in step with them.
//! - [`config`], [`telemetry`], [`server`]: `mcapi serve`'s one config
//!   struct, logging and metrics, and the start-up that binds both ports.

pub mod api;
pub mod config;
pub mod generated;
pub mod server;
pub mod service;
pub mod telemetry;

#[cfg(test)]
mod placement_tests;
