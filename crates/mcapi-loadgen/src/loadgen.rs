//! `mcapi-loadgen` (formerly `mcapi loadgen`): a load generator for a
//! running `mcapi serve`, over real sockets (the server's throughput,
//! latency and memory measurements of BENCHMARKS.md).
//!
//! Scenarios:
//!
//! - **rest**: for each number of hallway sessions (default 1, 100 and
//!   10,000) and each update mode, one virtual client per session drives its
//!   agent over `POST /v1/sessions/{id}/observations`: the first observation
//!   `{"state": 25}`, then the move the reply advised on a 50-state chain
//!   (left, right, stay), stimulus `[6, 0]` at state 10, `[0, 6]` at 40 and
//!   `[0, 0]` elsewhere. Each keep-alive HTTP/1.1 connection carries one
//!   request at a time; beyond `--max-connections` sessions the connections
//!   cycle over their share of the sessions, so at most that many requests
//!   are in flight. In the same run and with the same connections, `GET
//!   /healthz` is measured as the baseline. Then the observations go on
//!   open-loop at a fraction (`--paced-fraction`, default one half) of the
//!   measured peak rate: a pacing thread releases requests evenly spaced,
//!   and latency counts from the release (no coordinated omission).
//! - **grpc**: `Interact` over `--grpc-streams` bidirectional streams, one
//!   hallway session each, spread over `--grpc-connections` HTTP/2
//!   connections; one observation in flight per stream. Then, with
//!   `--grpc-batch` N > 1, as many sessions driven as vectorised worlds:
//!   `InteractBatch` streams of N sessions each, one message (N
//!   observations) in flight per stream.
//! - **memory**: the server's resident memory (`VmRSS`) with 10,000 and
//!   100,000 idle hallway sessions, after one observation each, and after
//!   deleting them (at once and `--settle-secs` later); it reports KiB per
//!   idle session and the RSS left after deleting them all. Needs the
//!   server's pid (`--server-pid`, or found in `/proc` when exactly one
//!   `mcapi serve` runs on this machine).
//!
//! Every closed-loop measurement runs for `--warmup-secs`, then counts the
//! requests completed during the next `--duration-secs`; latencies are exact
//! percentiles of every request of that window (nearest rank). Beside the
//! client's view, each REST row gives the server's own handler latency
//! (bucket bounds of its `/metrics` histogram over the window) and the CPU
//! used by the server, the load generator and everything else on the
//! machine during the window (`/proc`): the two share the machine's cores,
//! so neither number means much without the other. Results go to stdout as
//! Markdown tables (and, with `--json FILE`, to that file as one JSON
//! document, for scripts such as `benches/server.sh`); progress goes to
//! stderr.

use std::collections::HashSet;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail, ensure};
use clap::{Args, ValueEnum};
use http_body_util::{BodyExt, Full};
use hyper::body::Bytes;
use hyper::client::conn::http1::{self, SendRequest};
use hyper::header::{CONTENT_TYPE, HOST, HeaderValue};
use hyper::{Method, Request, StatusCode};
use hyper_util::rt::TokioIo;
use serde::Deserialize;
use serde_json::{Value, json};
use tokio::net::TcpStream;
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::{Channel, Endpoint};

use mcapi_proto as pb;
use mcapi_proto::SESSION_METADATA;
use mcapi_proto::agents_client::AgentsClient;

/// `mcapi-loadgen` options.
#[derive(Debug, Clone, Args)]
pub struct LoadgenArgs {
    /// Base URL of the server's REST port.
    #[arg(long, default_value = "http://127.0.0.1:8080")]
    pub http: String,
    /// Base URL of the server's gRPC port.
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
    fn as_str(self) -> &'static str {
        match self {
            Self::Async => "async",
            Self::Lockstep => "lockstep",
        }
    }

    fn to_pb(self) -> pb::UpdateMode {
        match self {
            Self::Async => pb::UpdateMode::Async,
            Self::Lockstep => pb::UpdateMode::Lockstep,
        }
    }
}

/// Runs the chosen scenarios against a running server and prints the results.
pub fn run(args: LoadgenArgs) -> Result<()> {
    ensure!(args.duration_secs > 0, "--duration-secs must be at least 1");
    ensure!(
        args.paced_fraction > 0.0 && args.paced_fraction <= 1.0,
        "--paced-fraction must be in (0, 1]"
    );
    ensure!(
        args.max_connections > 0 && args.create_connections > 0,
        "connection counts must be at least 1"
    );
    ensure!(
        args.grpc_streams > 0 && args.grpc_connections > 0,
        "--grpc-streams and --grpc-connections must be at least 1"
    );
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    if let Some(n) = args.threads {
        ensure!(n > 0, "--threads must be at least 1");
        builder.worker_threads(n);
    }
    builder.enable_all().build()?.block_on(run_scenarios(args))
}

async fn run_scenarios(args: LoadgenArgs) -> Result<()> {
    let http = HttpTarget::parse(&args.http)?;
    let server_pid = match args.server_pid {
        Some(pid) => Some(pid),
        None => find_server_pid()?,
    };
    let memory = matches!(args.scenario, Scenario::Memory | Scenario::All);
    if memory && server_pid.is_none() {
        bail!("the memory scenario needs the server's pid: pass --server-pid");
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!("# mcapi loadgen\n");
    println!(
        "REST {}, gRPC {}, server pid {}; {cores} cores shared by the server and the load \
         generator; {} s warm-up + {} s per measurement.\n",
        args.http,
        args.grpc,
        server_pid.map_or_else(|| "unknown".to_string(), |p| p.to_string()),
        args.warmup_secs,
        args.duration_secs
    );
    let mut report = serde_json::Map::new();
    report.insert("cores".into(), json!(cores));
    report.insert("warmup_secs".into(), json!(args.warmup_secs));
    report.insert("duration_secs".into(), json!(args.duration_secs));
    if matches!(args.scenario, Scenario::Rest | Scenario::All) {
        report.insert(
            "rest".into(),
            rest_scenario(&args, &http, server_pid).await?,
        );
    }
    if matches!(args.scenario, Scenario::Grpc | Scenario::All) {
        report.insert("grpc".into(), grpc_scenario(&args, server_pid).await?);
    }
    if let (true, Some(pid)) = (memory, server_pid) {
        report.insert("memory".into(), memory_scenario(&args, &http, pid).await?);
    }
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&Value::Object(report))?;
        std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

// ------------------------------------------------------------------ timing

/// A warm-up followed by a measurement window.
#[derive(Debug, Clone, Copy)]
struct Phase {
    start: Instant,
    measure_from: Instant,
    end: Instant,
}

impl Phase {
    fn new(args: &LoadgenArgs) -> Self {
        let start = Instant::now();
        let measure_from = start + Duration::from_secs(args.warmup_secs);
        Self {
            start,
            measure_from,
            end: measure_from + Duration::from_secs(args.duration_secs),
        }
    }

    fn window_secs(&self) -> f64 {
        (self.end - self.measure_from).as_secs_f64()
    }

    fn over(&self) -> bool {
        Instant::now() >= self.end
    }
}

/// What one worker saw during a phase.
#[derive(Debug, Default)]
struct Tally {
    /// Latencies (ns) of the successful requests completed in the window.
    latencies: Vec<u64>,
    /// Failed requests over the whole phase.
    errors: u64,
    first_error: Option<String>,
}

impl Tally {
    fn record(
        &mut self,
        phase: &Phase,
        issued: Instant,
        done: Instant,
        outcome: Result<(), String>,
    ) {
        match outcome {
            Ok(()) => {
                if done >= phase.measure_from && done <= phase.end {
                    self.latencies
                        .push(u64::try_from((done - issued).as_nanos()).unwrap_or(u64::MAX));
                }
            }
            Err(e) => {
                self.errors += 1;
                self.first_error.get_or_insert(e);
            }
        }
    }

    fn merge(&mut self, other: Self) {
        self.latencies.extend(other.latencies);
        self.errors += other.errors;
        if self.first_error.is_none() {
            self.first_error = other.first_error;
        }
    }

    fn summary(mut self, phase: &Phase) -> Summary {
        self.latencies.sort_unstable();
        let pct = |p: f64| -> Duration {
            if self.latencies.is_empty() {
                return Duration::ZERO;
            }
            // Nearest rank.
            let rank = (p * self.latencies.len() as f64).ceil() as usize;
            Duration::from_nanos(self.latencies[rank.clamp(1, self.latencies.len()) - 1])
        };
        Summary {
            rate: self.latencies.len() as f64 / phase.window_secs(),
            p50: pct(0.50),
            p99: pct(0.99),
            max: pct(1.0),
            errors: self.errors,
            first_error: self.first_error,
        }
    }
}

/// Throughput and latency of one measurement.
#[derive(Debug, Clone)]
struct Summary {
    /// Successful requests per second in the window.
    rate: f64,
    p50: Duration,
    p99: Duration,
    max: Duration,
    errors: u64,
    first_error: Option<String>,
}

impl Summary {
    /// The summary as JSON (latencies in µs).
    fn json(&self) -> Value {
        json!({
            "rate": self.rate,
            "p50_us": micros(self.p50),
            "p99_us": micros(self.p99),
            "max_us": micros(self.max),
            "errors": self.errors,
            "first_error": self.first_error,
        })
    }
}

fn micros(d: Duration) -> f64 {
    d.as_secs_f64() * 1e6
}

/// Clock ticks per second of `/proc` CPU times (`USER_HZ`, fixed at 100 on Linux).
const USER_HZ: f64 = 100.0;

/// CPU seconds a process has used (user + system), from `/proc/<pid>/stat`.
fn cpu_seconds(pid: &str) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name, which is in parentheses and may hold spaces.
    let rest = &stat[stat.rfind(')')? + 1..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime + stime) / USER_HZ)
}

/// Busy CPU seconds of the whole machine (all cores), from `/proc/stat`.
fn machine_busy_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let line = stat.lines().next()?.strip_prefix("cpu ")?;
    let ticks: Vec<f64> = line
        .split_whitespace()
        .filter_map(|f| f.parse().ok())
        .collect();
    // user nice system idle iowait irq softirq steal (guest time is in user).
    let busy: f64 = [0, 1, 2, 5, 6, 7]
        .iter()
        .filter_map(|&i| ticks.get(i))
        .sum();
    Some(busy / USER_HZ)
}

/// Cores kept busy over a window by the server, by the load generator and
/// by everything else on the machine (other processes, the hypervisor's
/// steal time): the machines are shared, so the last says how noisy a
/// measurement was.
#[derive(Debug, Clone, Copy, Default)]
struct CpuUse {
    server: Option<f64>,
    loadgen: Option<f64>,
    other: Option<f64>,
}

/// What was measured beside the client's own view over a window.
#[derive(Debug, Clone, Copy, Default)]
struct Window {
    cpu: CpuUse,
    /// Upper bounds of the server's own p50 and p99 of the route (handler
    /// time as its `/metrics` histogram buckets record it), in seconds.
    handler: Option<(f64, f64)>,
    /// Open loop: how late the pacing thread released requests (p99, max).
    pacer_lag: Option<(Duration, Duration)>,
}

impl Window {
    /// The window as JSON, with the server's CPU µs per request at `rate`.
    fn json(&self, rate: f64) -> Value {
        json!({
            "cpu_server": self.cpu.server,
            "cpu_loadgen": self.cpu.loadgen,
            "cpu_other": self.cpu.other,
            "server_cpu_us_per_request": server_us(self.cpu, rate),
            "handler_p50_s": self.handler.and_then(|h| finite(h.0)),
            "handler_p99_s": self.handler.and_then(|h| finite(h.1)),
            "pacer_lag_p99_us": self.pacer_lag.map(|l| micros(l.0)),
            "pacer_lag_max_us": self.pacer_lag.map(|l| micros(l.1)),
        })
    }
}

/// JSON has no infinity: a bound past the last bucket is `null`.
fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// Server CPU time per request, in µs.
fn server_us(cpu: CpuUse, rate: f64) -> Option<f64> {
    cpu.server
        .filter(|_| rate > 0.0)
        .map(|cores| cores / rate * 1e6)
}

/// Samples CPU time, and the server's latency histogram of `route` if
/// given, at the start and end of the window.
async fn measure_window(
    phase: Phase,
    server_pid: Option<u32>,
    route: Option<(&HttpTarget, &str)>,
) -> Window {
    let scrape = async || match route {
        Some((http, route)) => route_histogram(http, route).await.ok(),
        None => None,
    };
    tokio::time::sleep_until(phase.measure_from.into()).await;
    let (cpu_before, hist_before) = (cpu_now(server_pid), scrape().await);
    tokio::time::sleep_until(phase.end.into()).await;
    let (cpu_after, hist_after) = (cpu_now(server_pid), scrape().await);
    let handler = hist_before.zip(hist_after).and_then(|(a, b)| {
        Some((
            histogram_quantile(&a, &b, 0.50)?,
            histogram_quantile(&a, &b, 0.99)?,
        ))
    });
    Window {
        cpu: cpu_use(cpu_before, cpu_after, phase.window_secs()),
        handler,
        pacer_lag: None,
    }
}

/// CPU seconds of the server, this process and the machine.
fn cpu_now(server_pid: Option<u32>) -> [Option<f64>; 3] {
    [
        server_pid.and_then(|p| cpu_seconds(&p.to_string())),
        cpu_seconds("self"),
        machine_busy_seconds(),
    ]
}

fn cpu_use(before: [Option<f64>; 3], after: [Option<f64>; 3], secs: f64) -> CpuUse {
    let used = |i: usize| {
        before[i]
            .zip(after[i])
            .map(|(a, b): (f64, f64)| (b - a) / secs)
    };
    let (server, loadgen, machine) = (used(0), used(1), used(2));
    CpuUse {
        server,
        loadgen,
        other: machine
            .zip(loadgen)
            .map(|(m, l)| (m - l - server.unwrap_or(0.0)).max(0.0)),
    }
}

/// The server's request-duration histogram of one route (status 200, all
/// methods) from `/metrics`: cumulative count per bucket bound in seconds.
async fn route_histogram(http: &HttpTarget, route: &str) -> Result<Vec<(f64, f64)>> {
    let mut conn = HttpConn::connect(http).await?;
    let (status, body) = conn.send(Method::GET, "/metrics", None).await?;
    ensure!(status == StatusCode::OK, "/metrics: {status}");
    let text = String::from_utf8_lossy(&body);
    let route = format!("route=\"{route}\"");
    let mut buckets: Vec<(f64, f64)> = Vec::new();
    for line in text.lines() {
        let Some(rest) = line.strip_prefix("mcapi_http_request_duration_seconds_bucket{") else {
            continue;
        };
        let Some((labels, count)) = rest.rsplit_once("} ") else {
            continue;
        };
        if !labels.contains(&route) || !labels.contains("status=\"200\"") {
            continue;
        }
        let Some(le) = labels
            .split("le=\"")
            .nth(1)
            .and_then(|l| l.split('"').next())
        else {
            continue;
        };
        let le = if le == "+Inf" {
            f64::INFINITY
        } else {
            le.parse()?
        };
        let count: f64 = count.trim().parse()?;
        match buckets.iter_mut().find(|(b, _)| *b == le) {
            Some((_, c)) => *c += count,
            None => buckets.push((le, count)),
        }
    }
    buckets.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(buckets)
}

/// The bucket bound under which a fraction `q` of the requests counted
/// between two scrapes fell.
fn histogram_quantile(before: &[(f64, f64)], after: &[(f64, f64)], q: f64) -> Option<f64> {
    let delta = |le: f64, count: f64| {
        count
            - before
                .iter()
                .find(|(b, _)| *b == le)
                .map_or(0.0, |(_, c)| *c)
    };
    let total = after.last().map(|&(le, c)| delta(le, c))?;
    if total <= 0.0 {
        return None;
    }
    after
        .iter()
        .find(|&&(le, c)| delta(le, c) >= q * total)
        .map(|&(le, _)| le)
}

// -------------------------------------------------------------------- HTTP

/// Where the REST port is.
#[derive(Debug, Clone)]
struct HttpTarget {
    /// `host:port`, for connecting and for the `Host` header.
    authority: String,
}

impl HttpTarget {
    fn parse(url: &str) -> Result<Self> {
        if url.starts_with("https://") {
            bail!("--http: the load generator speaks plain HTTP only");
        }
        let rest = url.strip_prefix("http://").unwrap_or(url);
        let authority = rest.split('/').next().unwrap_or(rest);
        ensure!(!authority.is_empty(), "--http: no host in `{url}`");
        Ok(Self {
            authority: authority.to_string(),
        })
    }
}

type Connection = http1::Connection<TokioIo<TcpStream>, Full<Bytes>>;

/// One keep-alive HTTP/1.1 connection. The connection is driven by the task
/// that sends on it (no separate connection task), so a request costs no
/// cross-task hand-off in the client.
struct HttpConn {
    host: HeaderValue,
    sender: SendRequest<Full<Bytes>>,
    conn: Pin<Box<Connection>>,
}

/// Polls `fut` while driving the connection's I/O.
async fn driving<F: Future>(conn: &mut Pin<Box<Connection>>, fut: F) -> Result<F::Output> {
    tokio::select! {
        biased;
        out = fut => Ok(out),
        res = conn.as_mut() => match res {
            Ok(()) => Err(anyhow!("the server closed the connection")),
            Err(e) => Err(anyhow::Error::new(e).context("HTTP connection")),
        },
    }
}

impl HttpConn {
    async fn connect(target: &HttpTarget) -> Result<Self> {
        let stream = TcpStream::connect(&target.authority)
            .await
            .with_context(|| format!("connecting to {}", target.authority))?;
        stream.set_nodelay(true)?;
        let (sender, conn) = http1::handshake(TokioIo::new(stream)).await?;
        Ok(Self {
            host: HeaderValue::from_str(&target.authority)?,
            sender,
            conn: Box::pin(conn),
        })
    }

    /// Sends a request and reads the whole response.
    async fn send(
        &mut self,
        method: Method,
        path: &str,
        json: Option<String>,
    ) -> Result<(StatusCode, Bytes)> {
        let mut req = Request::builder()
            .method(method)
            .uri(path)
            .header(HOST, self.host.clone());
        if json.is_some() {
            req = req.header(CONTENT_TYPE, "application/json");
        }
        let req = req.body(Full::new(Bytes::from(json.unwrap_or_default())))?;
        driving(&mut self.conn, self.sender.ready()).await??;
        let resp = driving(&mut self.conn, self.sender.send_request(req)).await??;
        let status = resp.status();
        let body = driving(&mut self.conn, resp.into_body().collect())
            .await??
            .to_bytes();
        Ok((status, body))
    }
}

fn describe(status: StatusCode, body: &[u8]) -> String {
    let body = String::from_utf8_lossy(&body[..body.len().min(200)]);
    format!("{status}: {body}")
}

async fn connect_all(target: &HttpTarget, n: usize) -> Result<Vec<HttpConn>> {
    let mut conns = Vec::with_capacity(n);
    for _ in 0..n {
        conns.push(HttpConn::connect(target).await?);
    }
    Ok(conns)
}

// ---------------------------------------------------------------- hallway

/// The hallway as a client simulates it.
#[derive(Debug, Clone, Copy)]
struct Hallway {
    state: usize,
    started: bool,
}

impl Hallway {
    const STATES: usize = 50;
    const START: usize = 25;
    const FOOD: usize = 10;
    const REST: usize = 40;

    fn new() -> Self {
        Self {
            state: Self::START,
            started: false,
        }
    }

    /// The stimulus received on arrival in the current state.
    fn stimulus(&self) -> [f64; 2] {
        match self.state {
            Self::FOOD => [6.0, 0.0],
            Self::REST => [0.0, 6.0],
            _ => [0.0, 0.0],
        }
    }

    /// The next observation as JSON (no stimulus on the first).
    fn json(&self) -> String {
        if self.started {
            let [a, b] = self.stimulus();
            format!(r#"{{"state":{},"stimulus":[{a:?},{b:?}]}}"#, self.state)
        } else {
            format!(r#"{{"state":{}}}"#, self.state)
        }
    }

    /// The next observation as protobuf (no stimulus on the first).
    fn proto(&self) -> pb::Observation {
        pb::Observation {
            // Named by the stream's `x-mcapi-session` metadata instead.
            session_id: String::new(),
            state: self.state as u64,
            stimulus: self.started.then(|| pb::Stimulus {
                values: self.stimulus().to_vec(),
            }),
            action_taken: None,
            ..Default::default()
        }
    }

    /// Moves by the advised action: 0 left, 1 right, 2 stay.
    fn advance(&mut self, action: usize) {
        self.state = match action {
            0 => self.state.saturating_sub(1),
            1 => (self.state + 1).min(Self::STATES - 1),
            _ => self.state,
        };
        self.started = true;
    }
}

/// What a worker asks of its connection, request after request.
trait Workload: Send + 'static {
    /// The route as the server's metrics name it.
    const ROUTE: &'static str;
    /// The next request: method, path and JSON body.
    fn next(&mut self) -> (Method, &str, Option<String>);
    /// Takes the reply to the last request; an error message if it failed.
    fn reply(&mut self, status: StatusCode, body: &[u8]) -> Result<(), String>;
}

/// `GET /healthz`, the baseline.
struct Healthz;

impl Workload for Healthz {
    const ROUTE: &'static str = "/healthz";

    fn next(&mut self) -> (Method, &str, Option<String>) {
        (Method::GET, "/healthz", None)
    }

    fn reply(&mut self, status: StatusCode, body: &[u8]) -> Result<(), String> {
        if status == StatusCode::OK {
            Ok(())
        } else {
            Err(describe(status, body))
        }
    }
}

/// A connection's share of the sessions, observed in turn.
struct Observe {
    /// `(observation path, simulated world)` per session.
    sessions: Vec<(String, Hallway)>,
    cursor: usize,
}

#[derive(Deserialize)]
struct StepReply {
    action_index: usize,
}

impl Workload for Observe {
    const ROUTE: &'static str = "/v1/sessions/{id}/observations";

    fn next(&mut self) -> (Method, &str, Option<String>) {
        let (path, world) = &self.sessions[self.cursor];
        (Method::POST, path.as_str(), Some(world.json()))
    }

    fn reply(&mut self, status: StatusCode, body: &[u8]) -> Result<(), String> {
        let n = self.sessions.len();
        let (_, world) = &mut self.sessions[self.cursor];
        self.cursor = (self.cursor + 1) % n;
        if status != StatusCode::OK {
            // Not applied: the session sends the same observation next time.
            return Err(describe(status, body));
        }
        let step: StepReply = serde_json::from_slice(body).map_err(|e| format!("reply: {e}"))?;
        world.advance(step.action_index);
        Ok(())
    }
}

/// Runs one connection through a phase. Closed loop (`permits` is `None`):
/// the next request leaves as soon as the last reply is in. Open loop: each
/// request waits for a permit, stamped with its release time, and its
/// latency counts from that release, so time spent queued behind a slow
/// reply on this connection is included (no coordinated omission).
async fn http_worker<W: Workload>(
    mut conn: HttpConn,
    mut load: W,
    phase: Phase,
    mut permits: Option<mpsc::UnboundedReceiver<Instant>>,
) -> Result<(HttpConn, W, Tally)> {
    let mut tally = Tally::default();
    while !phase.over() {
        let issued = match &mut permits {
            None => Instant::now(),
            Some(rx) => match rx.recv().await {
                Some(t) => t,
                None => break,
            },
        };
        if phase.over() {
            break;
        }
        let (method, path, body) = load.next();
        let (status, bytes) = conn.send(method, path, body).await?;
        let done = Instant::now();
        tally.record(&phase, issued, done, load.reply(status, &bytes));
    }
    Ok((conn, load, tally))
}

/// Releases `rate` permits a second, evenly spaced, from the start of the
/// phase to its end, to the connections in turn (each gets `rate / n`, as
/// wrk2 does). A thread, because the runtime's timer has millisecond
/// granularity and the spacing is often shorter.
///
/// Returns how late the releases of the window were (p99, max): a mostly
/// sleeping thread released late means the machine itself stalled.
fn pace(txs: &[mpsc::UnboundedSender<Instant>], rate: f64, phase: Phase) -> (Duration, Duration) {
    let mut lateness = Tally::default();
    let mut k: u64 = 0;
    loop {
        let due = phase.start + Duration::from_secs_f64(k as f64 / rate);
        if due >= phase.end {
            break;
        }
        let now = Instant::now();
        if due > now {
            std::thread::sleep(due - now);
        }
        let released = Instant::now();
        lateness.record(&phase, due, released, Ok(()));
        let tx = &txs[(k % txs.len() as u64) as usize];
        if tx.send(released).is_err() {
            break;
        }
        k += 1;
    }
    let s = lateness.summary(&phase);
    (s.p99, s.max)
}

/// Runs every connection through one phase; returns them with the summary.
async fn run_http<W: Workload>(
    workers: Vec<(HttpConn, W)>,
    args: &LoadgenArgs,
    open_loop_rate: Option<f64>,
    (http, server_pid): (&HttpTarget, Option<u32>),
) -> Result<(Vec<(HttpConn, W)>, Summary, Window)> {
    let phase = Phase::new(args);
    let (mut permits, pacer) = match open_loop_rate {
        Some(rate) => {
            let (txs, rxs): (Vec<_>, Vec<_>) =
                workers.iter().map(|_| mpsc::unbounded_channel()).unzip();
            let pacer = std::thread::Builder::new()
                .name("loadgen-pacer".into())
                .spawn(move || pace(&txs, rate, phase))?;
            (rxs.into_iter().map(Some).collect(), Some(pacer))
        }
        None => (Vec::new(), None),
    };
    let mut set = JoinSet::new();
    for (i, (conn, load)) in workers.into_iter().enumerate() {
        let permits = permits.get_mut(i).and_then(Option::take);
        set.spawn(http_worker(conn, load, phase, permits));
    }
    let mut window = measure_window(phase, server_pid, Some((http, W::ROUTE))).await;
    let mut tally = Tally::default();
    let mut back = Vec::new();
    while let Some(joined) = set.join_next().await {
        let (conn, load, t) = joined??;
        tally.merge(t);
        back.push((conn, load));
    }
    if let Some(pacer) = pacer {
        let lag = pacer
            .join()
            .map_err(|_| anyhow!("the pacing thread panicked"))?;
        window.pacer_lag = Some(lag);
    }
    Ok((back, tally.summary(&phase), window))
}

#[derive(Deserialize)]
struct Created {
    id: String,
}

/// The longest wait between two attempts to create a session the server
/// refused with 503 (it limits concurrent creations).
const CREATE_RETRY_MAX: Duration = Duration::from_millis(2560);

/// Creates `n` hallway sessions (seed i for the i-th) over `conns`
/// connections; returns their ids in order.
async fn create_sessions(
    target: &HttpTarget,
    n: usize,
    first_seed: usize,
    mode: Option<Mode>,
    conns: usize,
) -> Result<Vec<String>> {
    let conns = conns.clamp(1, n.max(1));
    let mut set = JoinSet::new();
    for w in 0..conns {
        let target = target.clone();
        set.spawn(async move {
            let mut conn = HttpConn::connect(&target).await?;
            let mut ids = Vec::new();
            for i in (w..n).step_by(conns) {
                let seed = first_seed + i;
                let agent = match mode {
                    Some(m) => format!(r#"{{"seed":{seed},"update_mode":"{}"}}"#, m.as_str()),
                    None => format!(r#"{{"seed":{seed}}}"#),
                };
                let body = format!(r#"{{"model":{{"preset":"hallway"}},"agent":{agent}}}"#);
                // A server busy creating (503 "retry shortly") is waited for,
                // with backoff, up to about 5 s.
                let mut wait = Duration::from_millis(5);
                let (status, bytes) = loop {
                    let (status, bytes) = conn
                        .send(Method::POST, "/v1/sessions", Some(body.clone()))
                        .await?;
                    if status != StatusCode::SERVICE_UNAVAILABLE || wait > CREATE_RETRY_MAX {
                        break (status, bytes);
                    }
                    tokio::time::sleep(wait).await;
                    wait *= 2;
                };
                ensure!(
                    status == StatusCode::CREATED,
                    "creating a session: {}",
                    describe(status, &bytes)
                );
                let created: Created = serde_json::from_slice(&bytes)?;
                ids.push((i, created.id));
            }
            Ok::<_, anyhow::Error>(ids)
        });
    }
    let mut ids = vec![String::new(); n];
    while let Some(joined) = set.join_next().await {
        for (i, id) in joined?? {
            ids[i] = id;
        }
    }
    Ok(ids)
}

/// Sends `POST` (one first observation) or `DELETE` to every session.
async fn for_each_session(
    target: &HttpTarget,
    ids: &[String],
    method: Method,
    conns: usize,
) -> Result<()> {
    let ids: Arc<[String]> = ids.into();
    let conns = conns.clamp(1, ids.len().max(1));
    let mut set = JoinSet::new();
    for w in 0..conns {
        let (target, ids, method) = (target.clone(), Arc::clone(&ids), method.clone());
        set.spawn(async move {
            let mut conn = HttpConn::connect(&target).await?;
            for id in ids.iter().skip(w).step_by(conns) {
                let (status, bytes) = if method == Method::DELETE {
                    conn.send(Method::DELETE, &format!("/v1/sessions/{id}"), None)
                        .await?
                } else {
                    let path = format!("/v1/sessions/{id}/observations");
                    conn.send(method.clone(), &path, Some(Hallway::new().json()))
                        .await?
                };
                ensure!(
                    status.is_success(),
                    "{method} session {id}: {}",
                    describe(status, &bytes)
                );
            }
            Ok::<_, anyhow::Error>(())
        });
    }
    while let Some(joined) = set.join_next().await {
        joined??;
    }
    Ok(())
}

// -------------------------------------------------------------------- REST

/// One row of the REST tables.
struct RestRow {
    sessions: usize,
    mode: Mode,
    connections: usize,
    healthz: (Summary, Window),
    observe: (Summary, Window),
    /// The open-loop run: target rate and what it gave.
    paced: Option<(f64, Summary, Window)>,
}

async fn rest_scenario(args: &LoadgenArgs, http: &HttpTarget, pid: Option<u32>) -> Result<Value> {
    let mut rows = Vec::new();
    for &n in &args.sessions {
        ensure!(n > 0, "--sessions: counts must be at least 1");
        for &mode in &args.modes {
            let connections = n.min(args.max_connections);
            eprintln!(
                "rest: {n} {} sessions over {connections} connections",
                mode.as_str()
            );
            let ids = create_sessions(http, n, 0, Some(mode), args.create_connections).await?;

            // The baseline, on the same connections.
            let conns = connect_all(http, connections).await?;
            let workers = conns.into_iter().map(|c| (c, Healthz)).collect();
            let (workers, healthz, healthz_window) =
                run_http(workers, args, None, (http, pid)).await?;
            eprintln!("  /healthz {:.0} req/s", healthz.rate);

            // Connection w owns sessions w, w + connections, ...
            let workers: Vec<(HttpConn, Observe)> = workers
                .into_iter()
                .enumerate()
                .map(|(w, (conn, _))| {
                    let sessions = ids
                        .iter()
                        .skip(w)
                        .step_by(connections)
                        .map(|id| (format!("/v1/sessions/{id}/observations"), Hallway::new()))
                        .collect();
                    let load = Observe {
                        sessions,
                        cursor: 0,
                    };
                    (conn, load)
                })
                .collect();
            let (workers, observe, observe_window) =
                run_http(workers, args, None, (http, pid)).await?;
            eprintln!("  observe {:.0} req/s", observe.rate);

            let paced = if args.no_paced || observe.rate <= 0.0 {
                None
            } else {
                let rate = observe.rate * args.paced_fraction;
                let (_, summary, window) = run_http(workers, args, Some(rate), (http, pid)).await?;
                eprintln!(
                    "  observe at {rate:.0}/s: {:.0}/s, p99 {}",
                    summary.rate,
                    latency(summary.p99)
                );
                Some((rate, summary, window))
            };
            for_each_session(http, &ids, Method::DELETE, args.create_connections).await?;
            rows.push(RestRow {
                sessions: n,
                mode,
                connections,
                healthz: (healthz, healthz_window),
                observe: (observe, observe_window),
                paced,
            });
        }
    }
    print_rest(&rows, args);
    Ok(rows.iter().map(RestRow::json).collect())
}

impl RestRow {
    fn json(&self) -> Value {
        let ((h, hw), (o, ow)) = (&self.healthz, &self.observe);
        json!({
            "sessions": self.sessions,
            "mode": self.mode.as_str(),
            "connections": self.connections,
            "healthz": { "summary": h.json(), "window": hw.json(h.rate) },
            "observe": { "summary": o.json(), "window": ow.json(o.rate) },
            "observe_over_healthz": (h.rate > 0.0).then(|| o.rate / h.rate),
            "paced": self.paced.as_ref().map(|(target, s, w)| json!({
                "target_rate": target,
                "summary": s.json(),
                "window": w.json(s.rate),
            })),
        })
    }
}

fn print_rest(rows: &[RestRow], args: &LoadgenArgs) {
    println!("## REST: observe against GET /healthz (closed loop)\n");
    println!(
        "One keep-alive HTTP/1.1 connection per session up to {n} sessions; beyond that \
         {n} connections (= requests in flight) cycle over the sessions. Latencies are the \
         client's (p50 / p99 / max); \"handler\" is the bucket bound of the server's own \
         p50 / p99 from its /metrics histogram.\n",
        n = args.max_connections
    );
    println!(
        "| sessions | mode | conns | /healthz req/s | /healthz p50 / p99 | observe req/s | \
         observe / healthz | observe p50 / p99 / max | observe handler p50 / p99 | \
         server CPU µs/req: healthz / observe | CPU (observe): server / loadgen / other | \
         errors |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        let ((h, hw), (o, ow)) = (&r.healthz, &r.observe);
        println!(
            "| {} | {} | {} | {} | {} / {} | {} | {:.0}% | {} / {} / {} | {} | {} / {} | {} | {} |",
            thousands(r.sessions as f64),
            r.mode.as_str(),
            r.connections,
            thousands(h.rate),
            latency(h.p50),
            latency(h.p99),
            thousands(o.rate),
            100.0 * o.rate / h.rate.max(f64::MIN_POSITIVE),
            latency(o.p50),
            latency(o.p99),
            latency(o.max),
            handler(ow.handler),
            per_request(hw.cpu, h.rate),
            per_request(ow.cpu, o.rate),
            cores(ow.cpu),
            h.errors + o.errors,
        );
    }
    if rows.iter().any(|r| r.paced.is_some()) {
        println!(
            "\n## REST: observe at {:.0}% of the peak rate (open loop)\n",
            100.0 * args.paced_fraction
        );
        println!(
            "Requests are released by a pacing thread at a fixed rate ({:.0}% of the closed-loop \
             observe rate of the same row), evenly spaced and dealt to the connections above in \
             turn. Latency counts from the release, so time queued behind a slow reply on the \
             same connection is included. The pacer's lag is how late that thread itself \
             released requests: a mostly sleeping thread running late means the whole machine \
             stalled.\n",
            100.0 * args.paced_fraction
        );
        println!(
            "| sessions | mode | target req/s | achieved req/s | p50 | p99 | max | \
             handler p50 / p99 | pacer lag p99 / max | server CPU µs/req | \
             CPU: server / loadgen / other | errors |"
        );
        println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
        for r in rows {
            if let Some((target, s, w)) = &r.paced {
                println!(
                    "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                    thousands(r.sessions as f64),
                    r.mode.as_str(),
                    thousands(*target),
                    thousands(s.rate),
                    latency(s.p50),
                    latency(s.p99),
                    latency(s.max),
                    handler(w.handler),
                    w.pacer_lag.map_or_else(
                        || "—".to_string(),
                        |(p99, max)| format!("{} / {}", latency(p99), latency(max))
                    ),
                    per_request(w.cpu, s.rate),
                    cores(w.cpu),
                    s.errors
                );
            }
        }
    }
    for r in rows {
        let summaries = [&r.healthz.0, &r.observe.0]
            .into_iter()
            .chain(r.paced.as_ref().map(|(_, s, _)| s));
        for s in summaries {
            if let Some(e) = &s.first_error {
                println!(
                    "\nFirst error ({} {} sessions): {e}",
                    r.sessions,
                    r.mode.as_str()
                );
            }
        }
    }
    println!();
}

// -------------------------------------------------------------------- gRPC

/// One stream through a phase, one observation in flight.
async fn grpc_worker(mut client: AgentsClient<Channel>, id: String, phase: Phase) -> Result<Tally> {
    let (tx, rx) = mpsc::channel(1);
    let mut request = tonic::Request::new(ReceiverStream::new(rx));
    request.metadata_mut().insert(SESSION_METADATA, id.parse()?);
    let mut steps = client.interact(request).await?.into_inner();
    let mut world = Hallway::new();
    let mut tally = Tally::default();
    while !phase.over() {
        let issued = Instant::now();
        tx.send(world.proto())
            .await
            .map_err(|_| anyhow!("the Interact stream closed"))?;
        let step = steps
            .message()
            .await?
            .ok_or_else(|| anyhow!("the server ended the Interact stream"))?;
        let done = Instant::now();
        world.advance(step.action_index as usize);
        tally.record(&phase, issued, done, Ok(()));
    }
    drop(tx);
    while steps.message().await?.is_some() {}
    Ok(tally)
}

/// One `InteractBatch` stream through a phase: its sessions as a vectorised
/// world, one message (an observation per session) in flight.
async fn grpc_batch_worker(
    mut client: AgentsClient<Channel>,
    ids: Vec<String>,
    phase: Phase,
) -> Result<Tally> {
    let (tx, rx) = mpsc::channel(1);
    let mut steps = client
        .interact_batch(ReceiverStream::new(rx))
        .await?
        .into_inner();
    let mut worlds: Vec<Hallway> = ids.iter().map(|_| Hallway::new()).collect();
    let mut tally = Tally::default();
    while !phase.over() {
        let observations = ids
            .iter()
            .zip(&worlds)
            .map(|(id, world)| pb::Observation {
                session_id: id.clone(),
                ..world.proto()
            })
            .collect();
        let issued = Instant::now();
        tx.send(pb::ObservationBatch { observations })
            .await
            .map_err(|_| anyhow!("the InteractBatch stream closed"))?;
        let reply = steps
            .message()
            .await?
            .ok_or_else(|| anyhow!("the server ended the InteractBatch stream"))?;
        let done = Instant::now();
        ensure!(
            reply.results.len() == worlds.len(),
            "{} results for {} observations",
            reply.results.len(),
            worlds.len()
        );
        for (world, result) in worlds.iter_mut().zip(reply.results) {
            match result.outcome {
                Some(pb::step_result::Outcome::Step(step)) => {
                    world.advance(step.action_index as usize);
                    tally.record(&phase, issued, done, Ok(()));
                }
                Some(pb::step_result::Outcome::Error(e)) => {
                    tally.record(
                        &phase,
                        issued,
                        done,
                        Err(format!("{}: {}", e.code, e.message)),
                    );
                }
                None => bail!("a result with neither a step nor an error"),
            }
        }
    }
    drop(tx);
    while steps.message().await?.is_some() {}
    Ok(tally)
}

/// `n` hallway sessions in `mode`, seeded 0..n.
async fn create_grpc_sessions(
    admin: &mut AgentsClient<Channel>,
    n: usize,
    mode: Mode,
) -> Result<Vec<String>> {
    let mut ids = Vec::with_capacity(n);
    for i in 0..n {
        let info = admin
            .create_session(pb::CreateSessionRequest {
                model: Some(pb::Model::preset("hallway")),
                agent: Some(pb::SessionConfig {
                    seed: Some(i as u64),
                    update_mode: mode.to_pb().into(),
                    ..Default::default()
                }),
                ..Default::default()
            })
            .await?
            .into_inner();
        ids.push(info.id);
    }
    Ok(ids)
}

/// One row of the gRPC table.
struct GrpcRow {
    mode: Mode,
    method: &'static str,
    streams: usize,
    batch: usize,
    summary: Summary,
    cpu: CpuUse,
}

async fn grpc_scenario(args: &LoadgenArgs, pid: Option<u32>) -> Result<Value> {
    let endpoint = Endpoint::from_shared(args.grpc.clone())?.tcp_nodelay(true);
    let mut channels = Vec::with_capacity(args.grpc_connections);
    for _ in 0..args.grpc_connections {
        channels.push(
            endpoint
                .connect()
                .await
                .with_context(|| format!("connecting to {}", args.grpc))?,
        );
    }
    let mut admin = AgentsClient::new(channels[0].clone());
    let batch = usize::from(args.grpc_batch);
    let mut rows = Vec::new();
    for &mode in &args.modes {
        eprintln!(
            "grpc: Interact, {} {} streams over {} connections",
            args.grpc_streams,
            mode.as_str(),
            args.grpc_connections
        );
        let ids = create_grpc_sessions(&mut admin, args.grpc_streams, mode).await?;
        let phase = Phase::new(args);
        let mut set = JoinSet::new();
        for (i, id) in ids.iter().enumerate() {
            let client = AgentsClient::new(channels[i % channels.len()].clone());
            set.spawn(grpc_worker(client, id.clone(), phase));
        }
        rows.push(grpc_row(mode, "Interact", args.grpc_streams, 1, set, phase, pid).await?);
        delete_grpc_sessions(&mut admin, ids).await?;
        if batch <= 1 {
            continue;
        }
        let streams = args.grpc_streams.div_ceil(batch);
        eprintln!(
            "grpc: InteractBatch, {} {} sessions in {streams} streams of up to {batch}",
            args.grpc_streams,
            mode.as_str(),
        );
        let ids = create_grpc_sessions(&mut admin, args.grpc_streams, mode).await?;
        let phase = Phase::new(args);
        let mut set = JoinSet::new();
        for (i, chunk) in ids.chunks(batch).enumerate() {
            let client = AgentsClient::new(channels[i % channels.len()].clone());
            set.spawn(grpc_batch_worker(client, chunk.to_vec(), phase));
        }
        rows.push(grpc_row(mode, "InteractBatch", streams, batch, set, phase, pid).await?);
        delete_grpc_sessions(&mut admin, ids).await?;
    }
    println!("## gRPC: Interact and InteractBatch (closed loop)\n");
    println!(
        "{} hallway sessions over {} HTTP/2 connections: `Interact` with one stream per \
         session, `InteractBatch` with streams of up to {batch} sessions (one observation \
         each per message); each stream waits for its reply before sending again.\n",
        args.grpc_streams, args.grpc_connections
    );
    println!(
        "| mode | method | streams × batch | observations/s | p50 / p99 / max | \
         server CPU µs/obs | CPU: server / loadgen / other |"
    );
    println!("|---|---|---|---|---|---|---|");
    let mut out = Vec::with_capacity(rows.len());
    for r in rows {
        let (s, cpu) = (&r.summary, r.cpu);
        out.push(json!({
            "mode": r.mode.as_str(),
            "method": r.method,
            "streams": r.streams,
            "batch": r.batch,
            "connections": args.grpc_connections,
            "summary": s.json(),
            "cpu_server": cpu.server,
            "cpu_loadgen": cpu.loadgen,
            "cpu_other": cpu.other,
            "server_cpu_us_per_observation": server_us(cpu, s.rate),
        }));
        println!(
            "| {} | {} | {} × {} | {} | {} / {} / {} | {} | {} |",
            r.mode.as_str(),
            r.method,
            r.streams,
            r.batch,
            thousands(s.rate),
            latency(s.p50),
            latency(s.p99),
            latency(s.max),
            per_request(cpu, s.rate),
            cores(cpu),
        );
    }
    println!();
    Ok(Value::Array(out))
}

/// Waits for a phase's workers and measures it.
async fn grpc_row(
    mode: Mode,
    method: &'static str,
    streams: usize,
    batch: usize,
    mut set: JoinSet<Result<Tally>>,
    phase: Phase,
    pid: Option<u32>,
) -> Result<GrpcRow> {
    let cpu = measure_window(phase, pid, None).await.cpu;
    let mut tally = Tally::default();
    while let Some(joined) = set.join_next().await {
        tally.merge(joined??);
    }
    let summary = tally.summary(&phase);
    eprintln!("  {:.0} observations/s", summary.rate);
    if let Some(e) = &summary.first_error {
        bail!(
            "{method}: {} observations failed, the first: {e}",
            summary.errors
        );
    }
    Ok(GrpcRow {
        mode,
        method,
        streams,
        batch,
        summary,
        cpu,
    })
}

async fn delete_grpc_sessions(admin: &mut AgentsClient<Channel>, ids: Vec<String>) -> Result<()> {
    for id in ids {
        admin
            .delete_session(pb::DeleteSessionRequest { session_id: id })
            .await?;
    }
    Ok(())
}

// ------------------------------------------------------------------ memory

/// `VmRSS` and `VmHWM` of a process, in bytes.
fn memory_of(pid: u32) -> Result<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .with_context(|| format!("reading /proc/{pid}/status"))?;
    let field = |name: &str| -> Result<u64> {
        let line = status
            .lines()
            .find(|l| l.starts_with(name))
            .ok_or_else(|| anyhow!("no {name} in /proc/{pid}/status"))?;
        let kib: u64 = line
            .trim_start_matches(name)
            .trim()
            .trim_end_matches("kB")
            .trim()
            .parse()?;
        Ok(kib * 1024)
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?))
}

async fn memory_scenario(args: &LoadgenArgs, http: &HttpTarget, pid: u32) -> Result<Value> {
    let mut levels = args.memory_sessions.clone();
    levels.sort_unstable();
    levels.dedup();
    ensure!(
        levels.last().is_some_and(|&n| n > 0),
        "--memory-sessions: give at least one count above 0"
    );
    let (baseline, _) = memory_of(pid)?;
    let mut rows = vec![("before".to_string(), 0usize, baseline, None)];
    let mut ids: Vec<String> = Vec::new();
    let started = Instant::now();
    let wait = Duration::from_secs(args.evicted_wait_secs);
    for &level in &levels {
        let more = level.saturating_sub(ids.len());
        eprintln!("memory: creating {more} sessions (total {level})");
        ids.extend(create_sessions(http, more, ids.len(), None, args.create_connections).await?);
        let state = match wait_evicted(http, ids.len(), wait).await? {
            Some(n) => format!("idle, {} evicted", thousands(n as f64)),
            None => "idle".into(),
        };
        let (rss, _) = memory_of(pid)?;
        rows.push((state, ids.len(), rss, None));
    }
    let create_rate = ids.len() as f64 / started.elapsed().as_secs_f64();
    let idle_rss = rows.last().map_or(baseline, |r| r.2);
    eprintln!("memory: one observation per session");
    let t = Instant::now();
    for_each_session(http, &ids, Method::POST, args.create_connections).await?;
    let observe_rate = ids.len() as f64 / t.elapsed().as_secs_f64();
    let (observed_rss, hwm) = memory_of(pid)?;
    rows.push((
        "one observation each".into(),
        ids.len(),
        observed_rss,
        Some(hwm),
    ));
    let mut evicted_again = None;
    if let Some(n) = wait_evicted(http, ids.len(), wait).await? {
        let (rss, hwm) = memory_of(pid)?;
        rows.push((
            format!("observed, then {} evicted", thousands(n as f64)),
            ids.len(),
            rss,
            Some(hwm),
        ));
        evicted_again = Some(rss);
    }
    eprintln!("memory: deleting {} sessions", ids.len());
    for_each_session(http, &ids, Method::DELETE, args.create_connections).await?;
    let (deleted_rss, hwm) = memory_of(pid)?;
    rows.push(("all deleted".into(), 0, deleted_rss, Some(hwm)));
    tokio::time::sleep(Duration::from_secs(args.settle_secs)).await;
    let (settled_rss, hwm) = memory_of(pid)?;
    rows.push((
        format!("all deleted, {} s later", args.settle_secs),
        0,
        settled_rss,
        Some(hwm),
    ));

    let n = ids.len();
    let kib = |rss: u64| rss.saturating_sub(baseline) as f64 / n as f64 / 1024.0;
    // How much of what the sessions took the server gave back.
    let taken = observed_rss.max(idle_rss).saturating_sub(baseline);
    let returned = |rss: u64| {
        (taken > 0).then(|| observed_rss.max(idle_rss).saturating_sub(rss) as f64 / taken as f64)
    };
    println!("## Memory: server VmRSS with idle hallway sessions\n");
    println!(
        "Sessions created over {} connections ({} sessions/s), then one first observation \
         each ({} observations/s), then deleted. Per session: (RSS - RSS before) / sessions.\n",
        args.create_connections,
        thousands(create_rate),
        thousands(observe_rate)
    );
    println!("| sessions | state | VmRSS | per session | VmHWM (peak) |");
    println!("|---|---|---|---|---|");
    for (state, n, rss, hwm) in &rows {
        let per = if *n > 0 {
            format!(
                "{:.1} KiB",
                (rss.saturating_sub(baseline)) as f64 / *n as f64 / 1024.0
            )
        } else {
            "—".into()
        };
        println!(
            "| {} | {state} | {} | {per} | {} |",
            thousands(*n as f64),
            mib(*rss),
            hwm.map_or_else(|| "—".to_string(), mib)
        );
    }
    let pct = |r: Option<f64>| r.map_or_else(|| "—".to_string(), |r| format!("{:.0}%", 100.0 * r));
    println!(
        "\n**{:.2} KiB per idle session** ({} sessions; {:.2} KiB after one observation each). \
         **RSS after deleting them all: {}** ({} over the fresh server's {}; {} of what the \
         sessions took returned at once, {} after {} s).\n",
        kib(idle_rss),
        thousands(n as f64),
        kib(observed_rss),
        mib(settled_rss),
        mib(settled_rss.saturating_sub(baseline)),
        mib(baseline),
        pct(returned(deleted_rss)),
        pct(returned(settled_rss)),
        args.settle_secs,
    );
    Ok(json!({
        "sessions": n,
        "baseline_rss_bytes": baseline,
        "idle_rss_bytes": idle_rss,
        "observed_rss_bytes": observed_rss,
        "deleted_rss_bytes": deleted_rss,
        "settled_rss_bytes": settled_rss,
        "settle_secs": args.settle_secs,
        "peak_rss_bytes": hwm,
        "kib_per_idle_session": kib(idle_rss),
        "kib_per_observed_session": kib(observed_rss),
        "kib_per_observed_evicted_session": evicted_again.map(kib),
        "returned_at_once": returned(deleted_rss),
        "returned_after_settle": returned(settled_rss),
        "create_rate": create_rate,
        "observe_rate": observe_rate,
        "levels": rows.iter().map(|(state, n, rss, hwm)| json!({
            "state": state, "sessions": n, "rss_bytes": rss, "hwm_bytes": hwm,
        })).collect::<Vec<_>>(),
    }))
}

/// With `wait` > 0: waits until the server's `mcapi_sessions_evicted`
/// reaches `n` or `wait` has passed, and returns the count last read.
async fn wait_evicted(http: &HttpTarget, n: usize, wait: Duration) -> Result<Option<usize>> {
    if wait.is_zero() {
        return Ok(None);
    }
    let until = Instant::now() + wait;
    eprintln!(
        "memory: waiting up to {} s for the server to evict {n} sessions",
        wait.as_secs()
    );
    loop {
        let mut conn = HttpConn::connect(http).await?;
        let (status, body) = conn.send(Method::GET, "/metrics", None).await?;
        ensure!(status == StatusCode::OK, "/metrics: {status}");
        let evicted = String::from_utf8_lossy(&body)
            .lines()
            .find_map(|l| l.strip_prefix("mcapi_sessions_evicted "))
            .and_then(|v| v.trim().parse::<f64>().ok())
            .unwrap_or(0.0) as usize;
        if evicted >= n || Instant::now() >= until {
            return Ok(Some(evicted));
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// The pid of the one `mcapi serve` process on this machine, if there is one.
fn find_server_pid() -> Result<Option<u32>> {
    let me = std::process::id();
    let mut found = HashSet::new();
    for entry in std::fs::read_dir("/proc")?.flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<u32>().ok())
        else {
            continue;
        };
        let Ok(cmdline) = std::fs::read(entry.path().join("cmdline")) else {
            continue;
        };
        let mut argv = cmdline.split(|&b| b == 0).map(String::from_utf8_lossy);
        let is_mcapi = argv
            .next()
            .is_some_and(|a| a.rsplit('/').next().is_some_and(|f| f.starts_with("mcapi")));
        if pid != me && is_mcapi && argv.any(|a| a == "serve") {
            found.insert(pid);
        }
    }
    match found.len() {
        0 => Ok(None),
        1 => Ok(found.into_iter().next()),
        _ => bail!("several `mcapi serve` processes ({found:?}): pass --server-pid"),
    }
}

// -------------------------------------------------------------- formatting

fn thousands(x: f64) -> String {
    let digits = format!("{:.0}", x.max(0.0));
    let mut out = String::with_capacity(digits.len() + digits.len() / 3);
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i) % 3 == 0 {
            out.push(',');
        }
        out.push(c);
    }
    out
}

fn latency(d: Duration) -> String {
    let us = d.as_secs_f64() * 1e6;
    if us < 10_000.0 {
        format!("{us:.0} µs")
    } else {
        format!("{:.1} ms", us / 1000.0)
    }
}

/// `server / loadgen / other` in cores.
fn cores(c: CpuUse) -> String {
    let one = |c: Option<f64>| c.map_or_else(|| "—".to_string(), |c| format!("{c:.2}"));
    format!("{} / {} / {}", one(c.server), one(c.loadgen), one(c.other))
}

/// Server CPU time per request, in µs.
fn per_request(cpu: CpuUse, rate: f64) -> String {
    server_us(cpu, rate).map_or_else(|| "—".to_string(), |us| format!("{us:.1}"))
}

/// `≤ p50 / ≤ p99` from histogram bucket bounds.
fn handler(h: Option<(f64, f64)>) -> String {
    let bound = |secs: f64| {
        if secs.is_finite() {
            format!("≤ {}", latency(Duration::from_secs_f64(secs)))
        } else {
            "> 5 s".to_string()
        }
    };
    h.map_or_else(
        || "—".to_string(),
        |(p50, p99)| format!("{} / {}", bound(p50), bound(p99)),
    )
}

fn mib(bytes: u64) -> String {
    format!("{:.0} MiB", bytes as f64 / (1024.0 * 1024.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hallway_moves_and_stimuli() {
        let mut w = Hallway::new();
        assert_eq!(w.json(), r#"{"state":25}"#);
        for _ in 0..15 {
            w.advance(0);
        }
        assert_eq!(w.state, 10);
        assert_eq!(w.json(), r#"{"state":10,"stimulus":[6.0,0.0]}"#);
        w.advance(2);
        assert_eq!(w.state, 10);
        for _ in 0..100 {
            w.advance(1);
        }
        assert_eq!(w.state, 49);
        assert_eq!(w.proto().stimulus.map(|s| s.values), Some(vec![0.0, 0.0]));
    }

    #[test]
    fn percentiles_are_nearest_rank() {
        let start = Instant::now();
        let phase = Phase {
            start,
            measure_from: start,
            end: start + Duration::from_secs(1),
        };
        let tally = Tally {
            latencies: (1..=100).rev().map(|i| i * 1000).collect(),
            ..Tally::default()
        };
        let s = tally.summary(&phase);
        assert_eq!(s.p50, Duration::from_micros(50));
        assert_eq!(s.p99, Duration::from_micros(99));
        assert_eq!(s.max, Duration::from_micros(100));
        assert!((s.rate - 100.0).abs() < 1e-9);
    }

    #[test]
    fn quantiles_of_a_scraped_histogram() {
        let before = [(0.001, 10.0), (0.01, 10.0), (f64::INFINITY, 10.0)];
        let after = [(0.001, 60.0), (0.01, 109.0), (f64::INFINITY, 110.0)];
        // 100 new requests: 50 under 1 ms, 49 more under 10 ms, one slower.
        assert_eq!(histogram_quantile(&before, &after, 0.5), Some(0.001));
        assert_eq!(histogram_quantile(&before, &after, 0.99), Some(0.01));
        assert_eq!(
            histogram_quantile(&before, &after, 1.0),
            Some(f64::INFINITY)
        );
        assert_eq!(histogram_quantile(&after, &after, 0.5), None);
        assert_eq!(handler(Some((0.001, 0.01))), "≤ 1000 µs / ≤ 10.0 ms");
    }

    #[test]
    fn formatting() {
        assert_eq!(thousands(1_234_567.4), "1,234,567");
        assert_eq!(thousands(999.0), "999");
        assert_eq!(latency(Duration::from_micros(1500)), "1500 µs");
        assert_eq!(latency(Duration::from_millis(25)), "25.0 ms");
        assert_eq!(
            HttpTarget::parse("http://127.0.0.1:8080/")
                .map(|t| t.authority)
                .ok(),
            Some("127.0.0.1:8080".to_string())
        );
    }
}
