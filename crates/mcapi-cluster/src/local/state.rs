//! The state file of a running `mcapi cluster local` (`cluster.json`):
//! what runs where, for people, the mover and tests.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// The state file: what runs where, for people and tests (`cluster.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct State {
    /// The supervisor's pid.
    pub supervisor: u32,
    /// The router's REST address.
    pub http: String,
    /// The router's gRPC address.
    pub grpc: String,
    /// HAProxy's Runtime API socket.
    pub admin_socket: PathBuf,
    /// The shard map's epoch.
    pub epoch: u64,
    /// Replicas running behind the router.
    #[serde(default)]
    pub replicas: usize,
    /// The replicas, then the router.
    pub processes: Vec<ProcessState>,
}

/// One supervised process in [`State`].
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ProcessState {
    /// A replica's name, or `haproxy`.
    pub name: String,
    /// Its pid; none while it waits to be started again.
    pub pid: Option<u32>,
    /// A replica's REST address.
    pub http: Option<String>,
    /// A replica's gRPC address.
    pub grpc: Option<String>,
    /// Times it was started again.
    pub restarts: u64,
    /// Its log.
    pub log: PathBuf,
}
