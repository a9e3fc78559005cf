//! The server's one configuration struct: CLI flags with `MCAPI_*`
//! environment overrides and defaults, validated before any port opens.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{Args, ValueEnum};
use serde::Serialize;

use crate::api::conn::ConnLimits;
use crate::service::{ApiKeys, Limits, ManagerOptions};
pub use crate::telemetry::LogFormat;
use mcapi_shards::{Placement, ReplicaName, ShardMap};

/// Where sessions are kept.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
pub enum StoreKind {
    /// The embedded store (redb) in `--data-dir`: sessions survive restarts
    /// and crashes.
    Redb,
    /// In memory only: sessions are lost when the server stops.
    Memory,
}

/// `mcapi serve` options.
#[derive(Debug, Clone, Args, Serialize)]
pub struct ServeConfig {
    /// REST listen address.
    #[arg(
        help_heading = "Network",
        long,
        env = "MCAPI_HTTP",
        default_value = "127.0.0.1:8080"
    )]
    pub http: SocketAddr,
    /// gRPC listen address.
    #[arg(
        help_heading = "Network",
        long,
        env = "MCAPI_GRPC",
        default_value = "127.0.0.1:50051"
    )]
    pub grpc: SocketAddr,
    /// gRPC on a Unix domain socket at this path as well, for clients on
    /// the same host (no TCP stack between them and the server). Created
    /// at start (a stale socket left by a crash is replaced; anything else
    /// at the path stops the start) and removed at stop.
    #[arg(help_heading = "Network", long, env = "MCAPI_GRPC_SOCKET")]
    pub grpc_socket: Option<PathBuf>,
    /// Data directory of the embedded store (created if missing).
    #[arg(
        help_heading = "Storage",
        long,
        env = "MCAPI_DATA_DIR",
        default_value = "./mcapi-data"
    )]
    pub data_dir: PathBuf,
    /// Session store: `redb` (durable, in --data-dir) or `memory`.
    #[arg(
        help_heading = "Storage",
        long,
        env = "MCAPI_STORE",
        value_enum,
        default_value = "redb"
    )]
    pub store: StoreKind,
    /// When an observation is acknowledged: `sync` after its log frame is
    /// on disk (fdatasync; survives a power cut), `os` after it reaches the
    /// kernel (survives kill -9 of the process, not a power cut; synced in
    /// the background every 5 ms).
    #[arg(
        help_heading = "Storage",
        long,
        env = "MCAPI_DURABILITY",
        value_enum,
        default_value = "sync"
    )]
    pub durability: mcapi_store::Durability,
    /// Ceiling of the durable store's page cache, in MiB (1 to 65536).
    #[arg(help_heading = "Storage", long, env = "MCAPI_STORE_CACHE_MIB", default_value_t = (mcapi_store::DEFAULT_CACHE_BYTES >> 20) as u64)]
    pub store_cache_mib: u64,
    /// With the durable store: a session inactive (no observation) for
    /// this many seconds leaves memory, after a snapshot, and is loaded
    /// back from the store by its next request, bit for bit as it was;
    /// sessions whose planner cannot be restored exactly (a PVF or learned
    /// model once it has observed) stay in memory. 0 keeps every session
    /// in memory. At most 2592000 (30 days). Refused with `--store memory`.
    /// [default: 300 with the durable store]
    #[arg(help_heading = "Storage", long, env = "MCAPI_EVICT_IDLE_SECS")]
    pub evict_idle_secs: Option<u64>,
    /// Most logged observations between two snapshots of a session (the
    /// log before a snapshot is trimmed); a group's members spread theirs
    /// over that many steps.
    #[arg(help_heading = "Storage", long, env = "MCAPI_SNAPSHOT_EVERY", default_value_t = crate::service::DEFAULT_SNAPSHOT_EVERY)]
    pub snapshot_every: u64,
    /// API key clients must send as `Authorization: Bearer <key>`; repeat
    /// for several keys (env: comma-separated). Each key sees only the
    /// sessions it created. Without keys, no authentication.
    #[arg(
        help_heading = "Access",
        long = "api-key",
        env = "MCAPI_API_KEYS",
        value_delimiter = ',',
        hide_env_values = true
    )]
    #[serde(skip)]
    pub api_keys: Vec<String>,
    /// Tick-loop worker threads (default: number of cores); also the number
    /// of parts a group step is cut into.
    #[arg(help_heading = "Runtime", long, env = "MCAPI_WORKERS")]
    pub workers: Option<usize>,
    /// Policy updates measured to cost at most this many microseconds run
    /// on the requesting task instead of the tick pool (0: always the pool).
    #[arg(
        help_heading = "Runtime",
        long,
        env = "MCAPI_INLINE_PLAN_US",
        default_value_t = 20
    )]
    pub inline_plan_us: u64,
    /// Log format.
    #[arg(
        help_heading = "Runtime",
        long,
        env = "MCAPI_LOG_FORMAT",
        value_enum,
        default_value = "text"
    )]
    pub log_format: LogFormat,
    /// Maximum number of sessions.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_SESSIONS", default_value_t = Limits::default().max_sessions)]
    pub max_sessions: usize,
    /// Maximum states x actions of a model.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_PAIRS", default_value_t = Limits::default().max_pairs)]
    pub max_pairs: usize,
    /// Maximum transitions of a model.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_TRANSITIONS", default_value_t = Limits::default().max_transitions)]
    pub max_transitions: usize,
    /// Maximum features of a basis (k x actions).
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_FEATURES", default_value_t = Limits::default().max_features)]
    pub max_features: usize,
    /// Maximum stimulus dimensions.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_STIMULI", default_value_t = Limits::default().max_stimuli)]
    pub max_stimuli: usize,
    /// Maximum request body in bytes.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_BODY_BYTES", default_value_t = Limits::default().max_body_bytes)]
    pub max_body_bytes: usize,
    /// Maximum observations in one batch.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_BATCH", default_value_t = Limits::default().max_batch)]
    pub max_batch: usize,
    /// Maximum members of one session group.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_GROUP_MEMBERS", default_value_t = Limits::default().max_group_members)]
    pub max_group_members: usize,
    /// Buffered messages per gRPC stream.
    #[arg(help_heading = "Connections", long, env = "MCAPI_STREAM_BUFFER", default_value_t = Limits::default().stream_buffer)]
    pub stream_buffer: usize,
    /// Maximum history ticks a session keeps (`agent.history`).
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_HISTORY", default_value_t = Limits::default().max_history)]
    pub max_history: usize,
    /// Maximum states of a model with a proto_value basis (its
    /// eigendecomposition is O(|S|³): the default keeps one build under a
    /// second on one core).
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_PVF_STATES", default_value_t = Limits::default().max_pvf_states)]
    pub max_pvf_states: usize,
    /// Maximum bytes of a name (action, stimulus, state, preset, grid mark).
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_NAME_BYTES", default_value_t = Limits::default().max_name_bytes)]
    pub max_name_bytes: usize,
    /// Maximum curiosity `tau` and `lag`.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_CURIOSITY_WINDOW", default_value_t = Limits::default().max_curiosity_window)]
    pub max_curiosity_window: usize,
    /// Maximum curiosity `max_centres`.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_ROC_CENTRES", default_value_t = Limits::default().max_roc_centres)]
    pub max_roc_centres: usize,
    /// Maximum curiosity `max_sources`.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_SIGNAL_SOURCES", default_value_t = Limits::default().max_signal_sources)]
    pub max_signal_sources: usize,
    /// Maximum estimated memory of one session, in bytes.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_SESSION_BYTES", default_value_t = Limits::default().max_session_bytes)]
    pub max_session_bytes: u64,
    /// Maximum estimated CPU time of one observation, in microseconds.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_TICK_US", default_value_t = Limits::default().max_tick_us)]
    pub max_tick_us: u64,
    /// Maximum estimated CPU time of one batch of observations, in ms.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_BATCH_MS", default_value_t = Limits::default().max_batch_ms)]
    pub max_batch_ms: u64,
    /// Maximum time one basis build (proto-value functions) may take when a
    /// session is created, in ms: estimated before it starts, enforced
    /// while it runs.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_BUILD_MS", default_value_t = Limits::default().max_build_ms)]
    pub max_build_ms: u64,
    /// Sessions one API key (without keys: all clients) may hold.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_KEY_SESSIONS", default_value_t = Limits::default().max_key_sessions)]
    pub max_key_sessions: usize,
    /// Estimated bytes of all sessions of one API key (without keys: of all
    /// sessions).
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_KEY_BYTES", default_value_t = Limits::default().max_key_bytes)]
    pub max_key_bytes: u64,
    /// Maximum bytes of one response of value tables.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_RESPONSE_BYTES", default_value_t = Limits::default().max_response_bytes)]
    pub max_response_bytes: usize,
    /// Maximum bytes of all value-table and history responses in flight
    /// together (at least --max-response-bytes); a response that does not
    /// fit gets 503 `responses_busy` with Retry-After.
    #[arg(help_heading = "Limits", long, env = "MCAPI_MAX_RESPONSE_BYTES_TOTAL", default_value_t = Limits::default().max_response_bytes_total)]
    pub max_response_bytes_total: usize,

    // Connection limits
    /// Open connections per port (REST and gRPC each); further clients wait
    /// in the listen backlog until one closes.
    #[arg(help_heading = "Connections", long, env = "MCAPI_MAX_CONNECTIONS", default_value_t = ConnLimits::default().max_connections)]
    pub max_connections: usize,
    /// A client must send a complete request head within this many ms of
    /// connecting or of its previous response (REST; also the idle limit of
    /// a kept-alive connection), and the HTTP/2 preface within it (gRPC).
    #[arg(help_heading = "Connections", long, env = "MCAPI_HEADER_READ_TIMEOUT_MS", default_value_t = ConnLimits::default().header_read_timeout_ms)]
    pub header_read_timeout_ms: u64,
    /// A request (body read included; not an open event or gRPC stream)
    /// must be answered within this many ms, or it gets 503 / DEADLINE_EXCEEDED
    /// `request_timeout`; a REST response write blocked this long (the
    /// client stopped reading) closes the connection.
    #[arg(help_heading = "Connections", long, env = "MCAPI_REQUEST_TIMEOUT_MS", default_value_t = ConnLimits::default().request_timeout_ms)]
    pub request_timeout_ms: u64,
    /// Concurrent event streams (REST `/events`) plus gRPC `Watch` streams
    /// per API key (per client IP address without keys); beyond it 429
    /// `too_many_streams` / RESOURCE_EXHAUSTED.
    #[arg(help_heading = "Connections", long, env = "MCAPI_MAX_STREAMS_PER_KEY", default_value_t = ConnLimits::default().max_streams_per_key)]
    pub max_streams_per_key: usize,
    /// Concurrent HTTP/2 streams (calls) per gRPC connection.
    #[arg(help_heading = "Connections", long, env = "MCAPI_HTTP2_MAX_STREAMS", default_value_t = ConnLimits::default().http2_max_streams)]
    pub http2_max_streams: u32,
    /// HTTP/2 keep-alive: a gRPC connection is pinged after this many ms
    /// without traffic, and closed if the ping is not answered within
    /// --http2-keepalive-timeout-ms.
    #[arg(help_heading = "Connections", long, env = "MCAPI_HTTP2_KEEPALIVE_MS", default_value_t = ConnLimits::default().http2_keepalive_ms)]
    pub http2_keepalive_ms: u64,
    /// See --http2-keepalive-ms.
    #[arg(help_heading = "Connections", long, env = "MCAPI_HTTP2_KEEPALIVE_TIMEOUT_MS", default_value_t = ConnLimits::default().http2_keepalive_timeout_ms)]
    pub http2_keepalive_timeout_ms: u64,
    /// TCP keep-alive probes start after this many seconds of silence on a
    /// connection (both ports), so dead peers are noticed.
    #[arg(help_heading = "Connections", long, env = "MCAPI_TCP_KEEPALIVE_SECS", default_value_t = ConnLimits::default().tcp_keepalive_secs)]
    pub tcp_keepalive_secs: u64,

    // Cluster (docs/cluster.md)
    /// Shard map file (`mcapi cluster plan`): run as one replica of a
    /// cluster, serving only the shards the map gives --replica. Needs
    /// --replica; without both, a single node owning every shard.
    #[arg(
        help_heading = "Cluster",
        long,
        env = "MCAPI_SHARD_MAP",
        requires = "replica"
    )]
    pub shard_map: Option<PathBuf>,
    /// This replica's name in the shard map (e.g. `mcapi-0`). Needs --shard-map.
    #[arg(
        help_heading = "Cluster",
        long,
        env = "MCAPI_REPLICA",
        requires = "shard_map"
    )]
    pub replica: Option<String>,
    /// Start as a replica the shard map does not name yet, owning nothing
    /// until shards move to it (`mcapi cluster rebalance` does so).
    #[arg(
        help_heading = "Cluster",
        long,
        env = "MCAPI_JOINING",
        requires = "replica"
    )]
    #[serde(skip)]
    pub joining: bool,
    /// The key of the admin calls that move shards (`/admin/shards/...`,
    /// docs/cluster.md), sent as `Authorization: Bearer <key>`; at least 16
    /// characters. Without it the admin calls answer 403.
    #[arg(
        help_heading = "Cluster",
        long,
        env = "MCAPI_ADMIN_KEY",
        hide_env_values = true
    )]
    #[serde(skip)]
    pub admin_key: Option<String>,
}

/// Longest `--grpc-socket` path, in bytes: a Unix socket's address holds
/// 108 bytes with the terminating NUL (Linux's `sun_path`).
pub const MAX_SOCKET_PATH_BYTES: usize = 107;

/// `--grpc-socket` names a path a socket can be bound at.
fn check_socket_path(path: &std::path::Path) -> Result<(), String> {
    let len = path.as_os_str().len();
    if len == 0 {
        return Err("--grpc-socket is empty".into());
    }
    if len > MAX_SOCKET_PATH_BYTES {
        return Err(format!(
            "--grpc-socket must be at most {MAX_SOCKET_PATH_BYTES} bytes (the limit of a Unix socket's path), not {len}; use a shorter path"
        ));
    }
    if path.file_name().is_none() || path.as_os_str().as_encoded_bytes().ends_with(b"/") {
        return Err(format!(
            "--grpc-socket {} names a directory, not a file",
            path.display()
        ));
    }
    Ok(())
}

/// Default of `--evict-idle-secs` with the durable store.
pub const DEFAULT_EVICT_IDLE_SECS: u64 = 300;
/// Largest `--evict-idle-secs`.
pub const MAX_EVICT_IDLE_SECS: u64 = 30 * 24 * 3600;

impl ServeConfig {
    /// The worker count in force.
    pub fn worker_count(&self) -> usize {
        self.workers
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(2, |n| n.get()))
    }

    /// The limits in force.
    pub fn limits(&self) -> Limits {
        Limits {
            max_sessions: self.max_sessions,
            max_pairs: self.max_pairs,
            max_transitions: self.max_transitions,
            max_features: self.max_features,
            max_stimuli: self.max_stimuli,
            max_body_bytes: self.max_body_bytes,
            max_batch: self.max_batch,
            max_group_members: self.max_group_members,
            stream_buffer: self.stream_buffer,
            max_history: self.max_history,
            max_pvf_states: self.max_pvf_states,
            max_name_bytes: self.max_name_bytes,
            max_curiosity_window: self.max_curiosity_window,
            max_roc_centres: self.max_roc_centres,
            max_signal_sources: self.max_signal_sources,
            max_session_bytes: self.max_session_bytes,
            max_tick_us: self.max_tick_us,
            max_batch_ms: self.max_batch_ms,
            max_build_ms: self.max_build_ms,
            max_key_sessions: self.max_key_sessions,
            max_key_bytes: self.max_key_bytes,
            max_response_bytes: self.max_response_bytes,
            max_response_bytes_total: self.max_response_bytes_total,
            ..Limits::default()
        }
    }

    /// The connection limits in force.
    pub fn conn_limits(&self) -> ConnLimits {
        ConnLimits {
            max_connections: self.max_connections,
            header_read_timeout_ms: self.header_read_timeout_ms,
            request_timeout_ms: self.request_timeout_ms,
            max_streams_per_key: self.max_streams_per_key,
            http2_max_streams: self.http2_max_streams,
            http2_keepalive_ms: self.http2_keepalive_ms,
            http2_keepalive_timeout_ms: self.http2_keepalive_timeout_ms,
            tcp_keepalive_secs: self.tcp_keepalive_secs,
        }
    }

    /// The replica's view of the shard map when clustered (`--shard-map`
    /// and `--replica`), read and checked; `None` for a single node.
    pub fn placement(&self) -> Result<Option<Placement>, String> {
        match (&self.shard_map, &self.replica) {
            (None, None) => Ok(None),
            (Some(path), Some(name)) => {
                let replica = ReplicaName::parse(name)
                    .map_err(|e| format!("--replica / MCAPI_REPLICA: {e}"))?;
                let map = ShardMap::read(path).map_err(|e| {
                    format!("--shard-map / MCAPI_SHARD_MAP {}: {e}", path.display())
                })?;
                Placement::with_joining(map, replica, self.joining)
                    .map(Some)
                    .map_err(|e| format!("--replica / MCAPI_REPLICA: {e}"))
            }
            (Some(_), None) => Err("--shard-map needs --replica (MCAPI_REPLICA) too".into()),
            (None, Some(_)) => Err("--replica needs --shard-map (MCAPI_SHARD_MAP) too".into()),
        }
    }

    /// The session manager's options.
    pub fn manager_options(&self) -> ManagerOptions {
        ManagerOptions {
            inline_plan: Duration::from_micros(self.inline_plan_us),
            snapshot_every: self.snapshot_every,
            keys: ApiKeys::new(&self.api_keys),
            admin: ApiKeys::new(self.admin_key.as_deref()),
            evict_after: self.evict_after(),
            ..ManagerOptions::new(self.limits(), self.worker_count())
        }
    }

    /// The store's page cache ceiling in bytes.
    pub fn store_cache_bytes(&self) -> usize {
        usize::try_from(self.store_cache_mib.clamp(1, 65536) << 20).unwrap_or(usize::MAX)
    }

    /// How long a session stays in memory without activity: `None` with
    /// the memory store or `--evict-idle-secs 0`.
    pub fn evict_after(&self) -> Option<Duration> {
        match (self.store, self.evict_idle_secs) {
            (StoreKind::Memory, _) | (_, Some(0)) => None,
            (StoreKind::Redb, secs) => {
                Some(Duration::from_secs(secs.unwrap_or(DEFAULT_EVICT_IDLE_SECS)))
            }
        }
    }

    /// Checks the configuration before anything binds.
    pub fn validate(&self) -> Result<(), String> {
        if !(1..=65536).contains(&self.store_cache_mib) {
            return Err(format!(
                "--store-cache-mib must be between 1 and 65536, not {}",
                self.store_cache_mib
            ));
        }
        match self.evict_idle_secs {
            Some(secs) if secs > MAX_EVICT_IDLE_SECS => {
                return Err(format!(
                    "--evict-idle-secs must be at most {MAX_EVICT_IDLE_SECS} (30 days), not {secs}; 0 keeps every session in memory"
                ));
            }
            Some(secs) if secs > 0 && self.store == StoreKind::Memory => {
                return Err(
                    "--evict-idle-secs needs the durable store: with --store memory an evicted session would be lost (use 0, or leave it out)".into(),
                );
            }
            _ => {}
        }
        if self.http == self.grpc && self.http.port() != 0 {
            return Err(format!("--http and --grpc both use {}", self.http));
        }
        if let Some(path) = &self.grpc_socket {
            check_socket_path(path)?;
        }
        let workers = self.worker_count();
        if self.snapshot_every == 0 {
            return Err("--snapshot-every must be at least 1".into());
        }
        if self.api_keys.iter().any(|k| k.trim().is_empty()) {
            return Err("--api-key / MCAPI_API_KEYS: a key is empty".into());
        }
        if let Some(k) = self.api_keys.iter().find(|k| k.trim().len() < 16) {
            return Err(format!(
                "--api-key / MCAPI_API_KEYS: keys must have at least 16 characters (one has {})",
                k.trim().len()
            ));
        }
        if let Some(k) = &self.admin_key
            && k.trim().len() < 16
        {
            return Err(format!(
                "--admin-key / MCAPI_ADMIN_KEY must have at least 16 characters (it has {})",
                k.trim().len()
            ));
        }
        if self.inline_plan_us > 10_000 {
            return Err(format!(
                "--inline-plan-us must be at most 10000 (10 ms), not {}; longer updates belong on the tick pool",
                self.inline_plan_us
            ));
        }
        if workers == 0 || workers > 1024 {
            return Err(format!(
                "--workers must be between 1 and 1024, not {workers}"
            ));
        }
        let positive = [
            ("--max-sessions", self.max_sessions),
            ("--max-pairs", self.max_pairs),
            ("--max-transitions", self.max_transitions),
            ("--max-features", self.max_features),
            ("--max-stimuli", self.max_stimuli),
            ("--max-body-bytes", self.max_body_bytes),
            ("--max-batch", self.max_batch),
            ("--max-group-members", self.max_group_members),
            ("--stream-buffer", self.stream_buffer),
            ("--max-pvf-states", self.max_pvf_states),
            ("--max-name-bytes", self.max_name_bytes),
            ("--max-curiosity-window", self.max_curiosity_window),
            ("--max-roc-centres", self.max_roc_centres),
            ("--max-signal-sources", self.max_signal_sources),
            ("--max-key-sessions", self.max_key_sessions),
            ("--max-response-bytes", self.max_response_bytes),
        ];
        for (flag, value) in positive {
            if value == 0 {
                return Err(format!("{flag} must be at least 1"));
            }
        }
        for (flag, value) in [
            ("--max-session-bytes", self.max_session_bytes),
            ("--max-tick-us", self.max_tick_us),
            ("--max-batch-ms", self.max_batch_ms),
            ("--max-build-ms", self.max_build_ms),
            ("--max-key-bytes", self.max_key_bytes),
        ] {
            if value == 0 {
                return Err(format!("{flag} must be at least 1"));
            }
        }
        if self.max_response_bytes_total < self.max_response_bytes {
            return Err(format!(
                "--max-response-bytes-total ({}) must be at least --max-response-bytes ({}): a response of the largest size would never fit",
                self.max_response_bytes_total, self.max_response_bytes
            ));
        }
        if self.max_roc_centres < 2 {
            return Err("--max-roc-centres must be at least 2 (ROC merges a pair)".into());
        }
        self.placement()?;
        self.conn_limits().validate()
    }
}

#[cfg(test)]
mod tests {
    use clap::Args;

    use super::*;
    use crate::api::schemas::agent::limit_of;
    use crate::service::agent_config::session_options;
    use mcapi_core::params::{CURIOSITY_PARAMS, Kind, Max};

    /// Every server limit the parameter tables name is a flag of `mcapi
    /// serve` that the OpenAPI document reads ([`limit_of`]).
    #[test]
    fn every_limit_of_the_tables_is_a_flag_of_serve() {
        let command = ServeConfig::augment_args(clap::Command::new("serve"));
        let limits = Limits::default();
        for p in session_options().chain(CURIOSITY_PARAMS.iter()) {
            if let Kind::Integer {
                max: Max::Limit { flag, .. },
                ..
            } = p.kind
            {
                assert!(limit_of(&limits, flag).is_some(), "{flag} is not read");
                let long = flag.trim_start_matches("--");
                assert!(
                    command.get_arguments().any(|a| a.get_long() == Some(long)),
                    "{flag} is not a flag of serve"
                );
            }
        }
    }
}
