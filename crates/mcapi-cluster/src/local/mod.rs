//! `mcapi cluster local`: a whole cluster on one machine in one command, as
//! `cockroach demo` does (docs/cluster.md, "A local cluster"). It plans a
//! shard map (or reuses the data directory's), writes the router's files,
//! starts N `mcapi serve` replicas of this very executable on free loopback
//! ports and HAProxy (from PATH) in front of them, waits until all are
//! ready, then supervises: a process that exits is started again after a
//! backoff ([`Backoff`]), and SIGTERM or Ctrl-C stops everything in order
//! (the replicas drain on SIGTERM, then the router stops).
//!
//! The data directory:
//!
//! ```text
//! shards.map            the shard map (kept across runs: sessions survive)
//! replicas/<name>/      each replica's store (--data-dir)
//! router/haproxy.cfg    written on every start (the replicas' ports change)
//! router/shards.map     HAProxy's map file; router/admin.sock the Runtime API
//! logs/<name>.log       each process's stderr, appended across restarts
//! cluster.json          while running: pids, ports, restarts (State)
//! admin.key             the replicas' admin key (shard moves), mode 0600
//! rebalance.json        a request of `mcapi cluster rebalance` (then SIGHUP)
//! move.lock             held by a running `mcapi cluster move` / `rebalance`
//! ```
//!
//! `mcapi cluster rebalance --replicas N` writes `rebalance.json` and sends
//! the supervisor SIGHUP: it starts the missing replicas (`--joining`: they
//! own nothing yet), adds them to the running HAProxy through its Runtime
//! API (their backends were declared, empty, from the start: HAProxy 2.6
//! cannot add a backend at run time), writes the router's configuration
//! with them, and records `replicas` in `cluster.json`; the rebalance then
//! moves shards to them live ([`crate::mover`]). HAProxy is never
//! restarted for it: a restart cut the requests in flight.
//!
//! Children run in their own process group, so a terminal's Ctrl-C reaches
//! only the supervisor, which stops them in order; on Linux each child also
//! gets SIGTERM if the supervisor dies without stopping them.
//!
//! Files, one idea each: the flags and the entry point (here), the state
//! file (`state.rs`), the supervised processes and their backoff
//! (`process.rs`), the checks and files before a start (`setup.rs`), the
//! supervisor (`supervisor.rs`) and the network namespaces a process may
//! run in (`netns.rs`, `--netns`).

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use setup::prepare;
use supervisor::supervise;

mod netns;
mod process;
mod setup;
mod state;
mod supervisor;

pub use process::Backoff;
pub use state::{ProcessState, State};

/// The most replicas `cluster local` starts on one machine.
pub const MAX_LOCAL_REPLICAS: usize = 64;
/// The replicas when neither `--replicas` nor an existing map says.
pub const DEFAULT_REPLICAS: usize = 3;
/// The shard map's file in the data directory.
pub const MAP_FILE: &str = "shards.map";
/// The state file in the data directory, present while the cluster runs.
pub const STATE_FILE: &str = "cluster.json";
/// The replicas' admin key in the data directory.
pub const ADMIN_KEY_FILE: &str = "admin.key";
/// A rebalance's request to the supervisor in the data directory.
pub const REQUEST_FILE: &str = "rebalance.json";
/// The router's name among the supervised processes (and its log's).
const ROUTER: &str = "haproxy";
/// `serve` flags that `cluster local` sets itself for each replica.
const MANAGED_FLAGS: [&str; 5] = ["--http", "--grpc", "--data-dir", "--shard-map", "--replica"];
/// A Unix socket's path must fit `sockaddr_un.sun_path` (108 bytes with its NUL).
const MAX_SOCKET_PATH: usize = 107;

/// How a running router takes new replicas.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum RouterUpdate {
    /// Servers added through the Runtime API: HAProxy keeps running.
    Runtime,
    /// HAProxy in master-worker mode, reloaded (SIGUSR2): a new worker
    /// takes the listening sockets over and the old one finishes what it
    /// has, but closes its clients' idle connections.
    Reload,
    /// HAProxy stopped and started again, as `cluster local` once did:
    /// every connection is cut, and connections are refused until it
    /// listens again. Kept to show what the Runtime API avoids.
    Restart,
}

/// `mcapi cluster local`.
#[derive(Debug, Args)]
pub struct LocalArgs {
    /// Replicas, 1 to 64 (default: those of the data directory's map, else 3).
    #[arg(long, value_parser = clap::value_parser!(u16).range(1..=MAX_LOCAL_REPLICAS as i64))]
    pub replicas: Option<u16>,
    /// The router's REST address.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub http: SocketAddr,
    /// The router's gRPC address (h2c).
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub grpc: SocketAddr,
    /// The cluster's directory: shard map, stores, router files, logs (created if missing).
    #[arg(long, default_value = "./cluster")]
    pub data_dir: PathBuf,
    /// The `haproxy` executable (default: from PATH, then /usr/sbin).
    #[arg(long)]
    pub haproxy: Option<PathBuf>,
    /// Seconds to wait for every replica and the router to be ready (1 to 600).
    #[arg(long, default_value_t = 120, value_parser = clap::value_parser!(u64).range(1..=600))]
    pub ready_timeout_secs: u64,
    /// Seconds a replica may take to drain after SIGTERM before SIGKILL (1 to 300).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..=300))]
    pub drain_timeout_secs: u64,
    /// How the router learns of the replicas `rebalance` adds or removes:
    /// `runtime` (the Runtime API, HAProxy keeps running), `reload` (a
    /// master-worker reload) or `restart`. Only for measuring them against each other
    /// (docs/cluster.md gives the numbers).
    #[arg(long, hide = true, value_enum, default_value_t = RouterUpdate::Runtime)]
    pub router_update: RouterUpdate,
    /// Run a process in a network namespace that exists (`ip netns exec
    /// NETNS`, as root), to test network partitions: `NAME=NETNS@IP` runs
    /// replica NAME there, listening on IP (an address of that namespace)
    /// instead of 127.0.0.1; `haproxy=NETNS` runs the router there, on
    /// --http and --grpc (then not checked free from here). Repeat per
    /// process. This supervisor, the mover and clients must reach every
    /// address given.
    #[arg(long, value_name = "NAME=NETNS[@IP]")]
    pub netns: Vec<String>,
    /// Extra `mcapi serve` flags for every replica, after `--` (e.g. `-- --workers 2`).
    #[arg(last = true)]
    pub serve_args: Vec<String>,
}

/// Runs `mcapi cluster local` until the future that `stop` makes resolves (the
/// binary's SIGTERM or Ctrl-C). `stop` is called inside the cluster's
/// runtime, before any replica starts, so that no early signal is lost.
pub fn run<S, F>(args: &LocalArgs, stop: S) -> Result<()>
where
    S: FnOnce() -> F,
    F: Future<Output = ()> + Send,
{
    crate::logging::init_logging();
    let setup = prepare(args)?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async { supervise(setup, stop()).await })
}

#[cfg(test)]
mod tests;
