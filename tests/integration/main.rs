//! The `mcapi` binary's integration tests, in one test binary: the tests
//! that start `mcapi serve`, `mcapi experiment` or `mcapi cluster` as child
//! processes (crashes, restarts, the cluster, connections, the CLI), and
//! the modules that do so for some of their tests. One link of the whole
//! server instead of one per file, which is most of what a cold `make test`
//! spends compiling. Each module is one subject (`cargo test --test
//! integration crash::` runs one). The tests of the server library in
//! process live with it, in `crates/mcapi-server/tests/`.

#[path = "../common/mod.rs"]
mod common;

mod cluster;
mod connections;
mod continuous_experiments;
mod crash;
mod curious_sessions;
mod dashboard;
mod durability;
mod experiments;
mod full_disk;
mod hostile;
mod learned;
mod serve;
