//! The server's integration tests, in one test binary: one link of the
//! whole server instead of one per file, which is most of what a cold
//! `make test` spends compiling. Each module is one subject (`cargo test
//! --test integration crash::` runs one). `tests/fuzz/` and
//! `tests/grpc_model.rs` stay binaries of their own: they measure their
//! own process's resident memory, which other tests would disturb here.

#[path = "../common/mod.rs"]
mod common;

mod cluster;
mod connections;
mod continuous_experiments;
mod crash;
mod curious_sessions;
mod dashboard;
mod durability;
mod eviction;
mod experiments;
mod full_disk;
mod grpc;
mod hostile;
mod learned;
mod openapi;
mod parity;
mod rest;
mod serve;
mod shard_move;
