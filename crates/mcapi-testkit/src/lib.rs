//! The helpers the integration tests share: mcapi-server's own tests
//! (`crates/mcapi-server/tests/`, the server in process) and the root
//! package's tests of the `mcapi` binary (`tests/integration/`). A
//! dev-dependency only (`crates/mcapi-core/tests/closure.rs` checks that no
//! crate depends on it otherwise), one module per idea:
//!
//! - [`in_process`]: the full server in this process;
//! - [`closing`]: how long a server takes to close a connection;
//! - [`ports`]: free loopback ports;
//! - [`process`]: signals to a child process, its JSON log;
//! - [`rest`]: REST calls with an API key;
//! - [`grpc`]: gRPC calls with an API key;
//! - [`hallway`]: the simulated hallway client and its observations;
//! - [`reply`]: one acknowledged observation and what its reply said;
//! - [`floats`]: exact float comparisons;
//! - [`replay`]: the exact in-memory replay a recovered session is compared with;
//! - [`session_check`]: a served session checked against that replay.
//!
//! Starting the `mcapi` binary itself is not here: only the root package's
//! tests know its path (`env!("CARGO_BIN_EXE_mcapi")`), so that helper is
//! theirs (`tests/common/server.rs`).
//!
//! Everything is re-exported at the root, so call sites name
//! `mcapi_testkit::xyz` (or `common::xyz` in the root tests).
//!
//! mcapi-server dev-depends on this crate, which depends on mcapi-server:
//! Cargo allows that cycle for dev-dependencies, and an integration test
//! links one mcapi-server, so the types the helpers take and return are the
//! test's own. mcapi-server's unit tests do not use it (there the crate
//! under test is a second build of mcapi-server, whose types differ).

pub mod closing;
pub mod floats;
pub mod grpc;
pub mod hallway;
pub mod in_process;
pub mod ports;
pub mod process;
pub mod replay;
pub mod reply;
pub mod rest;
pub mod session_check;

pub use closing::*;
pub use floats::*;
pub use grpc::*;
pub use hallway::*;
pub use in_process::*;
pub use ports::*;
pub use process::*;
pub use replay::*;
pub use reply::*;
pub use rest::*;
pub use session_check::*;
