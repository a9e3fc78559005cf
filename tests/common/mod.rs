//! The helpers of the root package's tests (`tests/integration/`):
//! [`server`] starts, kills and stops the real `mcapi serve` binary, which
//! only this package's tests can name (Cargo sets
//! `CARGO_BIN_EXE_mcapi` for them alone). Every other helper is shared with
//! mcapi-server's own tests and lives in the mcapi-testkit crate
//! (`crates/mcapi-testkit/`), re-exported here, so call sites name
//! `common::xyz`.

pub mod server;

pub use mcapi_testkit::*;
pub use server::*;
