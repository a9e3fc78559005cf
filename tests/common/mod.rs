//! Shared helpers of the tests that run the real `mcapi` binary
//! (`tests/integration/crash.rs`, `tests/integration/durability/`) or the full server in-process
//! (`tests/integration/parity.rs`, `tests/grpc_model.rs`), one module per idea:
//!
//! - [`in_process`]: the full server in this process;
//! - [`ports`]: free loopback ports;
//! - [`server`]: starting, killing and stopping the `mcapi serve` binary;
//! - [`process`]: signals to a child process, its JSON log;
//! - [`rest`]: REST calls with an API key;
//! - [`grpc`]: gRPC calls with an API key;
//! - [`hallway`]: the simulated hallway client and its observations;
//! - [`reply`]: one acknowledged observation and what its reply said;
//! - [`floats`]: exact float comparisons;
//! - [`replay`]: the exact in-memory replay a recovered session is compared with;
//! - [`session_check`]: a served session checked against that replay.
//!
//! Everything is re-exported here, so call sites name `common::xyz`.

// Each test binary uses a different part of these modules.
#![allow(dead_code, unused_imports)]

pub mod floats;
pub mod grpc;
pub mod hallway;
pub mod in_process;
pub mod ports;
pub mod process;
pub mod replay;
pub mod reply;
pub mod rest;
pub mod server;
pub mod session_check;

pub use floats::*;
pub use grpc::*;
pub use hallway::*;
pub use in_process::*;
pub use ports::*;
pub use process::*;
pub use replay::*;
pub use reply::*;
pub use rest::*;
pub use server::*;
pub use session_check::*;
