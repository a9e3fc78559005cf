//! The command line: `mcapi-loadgen`'s options ([`LoadgenArgs`]), the
//! scenarios it can run ([`Scenario`]) and the update modes of the sessions
//! it drives ([`Mode`]).

use clap::{Args, ValueEnum};

use mcapi_proto as pb;

/// `mcapi-loadgen` options.
#[derive(Debug, Clone, Args)]
pub struct LoadgenArgs {
    /// Base URL of the server's REST port.
    #[arg(long, default_value = "http://127.0.0.1:8080")]
    pub http: String,
    /// Base URL of the server's gRPC port, or `unix:PATH` for its Unix
    /// socket (`mcapi serve --grpc-socket PATH`).
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    pub grpc: String,
    /// What to measure.
    #[arg(long, value_enum, default_value = "all")]
    pub scenario: Scenario,
    /// Length of each measurement window, in seconds.
    #[arg(long, default_value_t = 10)]
    pub duration_secs: u64,
    /// Warm-up before each measurement window, in seconds.
    #[arg(long, default_value_t = 2)]
    pub warmup_secs: u64,
    /// Numbers of concurrent hallway sessions of the REST scenario.
    #[arg(long, value_delimiter = ',', default_value = "1,100,10000")]
    pub sessions: Vec<usize>,
    /// Update modes of the REST and gRPC scenarios.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "async,lockstep"
    )]
    pub modes: Vec<Mode>,
    /// Most HTTP connections (= requests in flight) of the REST scenario.
    #[arg(long, default_value_t = 256)]
    pub max_connections: usize,
    /// Connections used to create and delete sessions.
    #[arg(long, default_value_t = 16)]
    pub create_connections: usize,
    /// Skip the open-loop run at a fraction of the peak rate.
    #[arg(long)]
    pub no_paced: bool,
    /// The REST scenario's observations carry `seq` (exactly-once
    /// delivery), to measure what it costs against the same run without.
    #[arg(long)]
    pub seq: bool,
    /// The open-loop run's rate as a fraction of the closed-loop peak.
    #[arg(long, default_value_t = 0.5)]
    pub paced_fraction: f64,
    /// Concurrent `Interact` streams of the gRPC scenario.
    #[arg(long, default_value_t = 64)]
    pub grpc_streams: usize,
    /// HTTP/2 connections the gRPC streams are spread over.
    #[arg(long, default_value_t = 1)]
    pub grpc_connections: usize,
    /// Sessions per `InteractBatch` stream in the gRPC scenario's batched
    /// run (1: no batched run).
    #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u16).range(1..=10_000))]
    pub grpc_batch: u16,
    /// Session counts at which the memory scenario reads the server's RSS.
    #[arg(long, value_delimiter = ',', default_value = "10000,100000")]
    pub memory_sessions: Vec<usize>,
    /// Pid of the server (for RSS and CPU); default: the one `mcapi serve`
    /// process found in /proc.
    #[arg(long)]
    pub server_pid: Option<u32>,
    /// Worker threads of the load generator's runtime (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Also write the results as one JSON document to this file (for
    /// scripts: `benches/server.sh`).
    #[arg(long)]
    pub json: Option<std::path::PathBuf>,
    /// The memory scenario reads RSS again this long after the last delete
    /// (an allocator may give memory back to the system with a delay).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u64).range(0..=600))]
    pub settle_secs: u64,
    /// The memory scenario waits up to this long, after creating the
    /// sessions and again after observing them, for a server started with
    /// a short `--evict-idle-secs` to evict them all (its
    /// `mcapi_sessions_evicted`) before it reads RSS; 0: no wait.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=3600))]
    pub evicted_wait_secs: u64,
}

/// Which measurements to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Scenario {
    /// REST observe against `/healthz`, peak and half-peak rate.
    Rest,
    /// gRPC `Interact` throughput.
    Grpc,
    /// Server RSS with many idle sessions.
    Memory,
    /// All three, in this order.
    All,
}

/// A session's update mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Mode {
    /// Reply at once; the tick loop plans in the background.
    Async,
    /// Reply after the observation's LSTDQ update.
    Lockstep,
}

impl Mode {
    pub(crate) fn as_str(self) -> &'static str {
        match self {
            Self::Async => "async",
            Self::Lockstep => "lockstep",
        }
    }

    pub(crate) fn to_pb(self) -> pb::UpdateMode {
        match self {
            Self::Async => pb::UpdateMode::Async,
            Self::Lockstep => pb::UpdateMode::Lockstep,
        }
    }
}
