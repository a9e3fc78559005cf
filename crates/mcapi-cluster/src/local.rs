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
//! own nothing yet), writes the router's configuration with them and starts
//! HAProxy again (clients reconnect), and records `replicas` in
//! `cluster.json`; the rebalance then moves shards to them live
//! ([`crate::mover`]).
//!
//! Children run in their own process group, so a terminal's Ctrl-C reaches
//! only the supervisor, which stops them in order; on Linux each child also
//! gets SIGTERM if the supervisor dies without stopping them.

use std::ffi::OsString;
use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use serde::{Deserialize, Serialize};

use mcapi_shards::plan::{self, ordinal_names};
use mcapi_shards::{ReplicaName, ShardMap};

use crate::cli::{write_atomic, write_router};
use crate::haproxy::{Backend, RouterSpec, find_haproxy};
use crate::probe::http_ok;

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
    /// Extra `mcapi serve` flags for every replica, after `--` (e.g. `-- --workers 2`).
    #[arg(last = true)]
    pub serve_args: Vec<String>,
}

/// When to start again a process that exited. Pure: the tests drive it with
/// made-up durations.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Backoff {
    /// The wait after a first exit.
    pub first: Duration,
    /// The longest wait.
    pub max: Duration,
    /// A process that ran this long before exiting starts a new streak.
    pub steady: Duration,
}

impl Backoff {
    /// 250 ms, doubling to 30 s; a minute up resets it.
    pub const DEFAULT: Self = Self {
        first: Duration::from_millis(250),
        max: Duration::from_secs(30),
        steady: Duration::from_secs(60),
    };

    /// A process that ran for `ran` exited, after `streak` quick exits in a
    /// row: the wait before starting it again and the new streak.
    pub fn after_exit(&self, ran: Duration, streak: u32) -> (Duration, u32) {
        let streak = if ran >= self.steady {
            1
        } else {
            streak.saturating_add(1)
        };
        let doublings = streak.saturating_sub(1).min(20);
        let wait = self.first.saturating_mul(1 << doublings).min(self.max);
        (wait, streak)
    }
}

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

/// What a look at a supervised process found worth logging.
#[derive(Debug)]
enum Event {
    Exited {
        status: ExitStatus,
        ran: Duration,
        wait: Duration,
    },
    Restarted {
        pid: u32,
    },
    SpawnFailed {
        error: String,
        wait: Duration,
    },
}

enum Run {
    Up { child: Child, since: Instant },
    Waiting { until: Instant },
    Stopped,
}

/// One supervised process: how to start it and where it stands.
struct Process {
    name: String,
    program: PathBuf,
    args: Vec<OsString>,
    /// Environment variables set for it (a replica's admin key).
    env: Vec<(String, String)>,
    log: PathBuf,
    /// A replica's (REST, gRPC) ports.
    ports: Option<(u16, u16)>,
    /// What answers 200 once it is ready.
    ready_url: String,
    run: Run,
    streak: u32,
    restarts: u64,
}

impl Process {
    fn pid(&self) -> Option<u32> {
        match &self.run {
            Run::Up { child, .. } => Some(child.id()),
            _ => None,
        }
    }

    fn spawn(&mut self) -> Result<u32> {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)
            .with_context(|| format!("opening {}", self.log.display()))?;
        let mut cmd = Command::new(&self.program);
        cmd.args(&self.args)
            .envs(self.env.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::from(log));
        detach(&mut cmd);
        let child = cmd
            .spawn()
            .with_context(|| format!("starting {}", self.program.display()))?;
        let pid = child.id();
        self.run = Run::Up {
            child,
            since: Instant::now(),
        };
        Ok(pid)
    }

    /// Reaps an exit and schedules the restart, or restarts when due.
    fn tick(&mut self, now: Instant, backoff: &Backoff) -> Option<Event> {
        match &mut self.run {
            Run::Up { child, since } => {
                let status = match child.try_wait() {
                    Ok(Some(status)) => status,
                    Ok(None) | Err(_) => return None,
                };
                let ran = now.saturating_duration_since(*since);
                let (wait, streak) = backoff.after_exit(ran, self.streak);
                self.streak = streak;
                self.run = Run::Waiting { until: now + wait };
                Some(Event::Exited { status, ran, wait })
            }
            Run::Waiting { until } if now >= *until => {
                self.restarts += 1;
                match self.spawn() {
                    Ok(pid) => Some(Event::Restarted { pid }),
                    Err(e) => {
                        let (wait, streak) = backoff.after_exit(Duration::ZERO, self.streak);
                        self.streak = streak;
                        self.run = Run::Waiting { until: now + wait };
                        Some(Event::SpawnFailed {
                            error: format!("{e:#}"),
                            wait,
                        })
                    }
                }
            }
            Run::Waiting { .. } | Run::Stopped => None,
        }
    }

    fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(20)..].join("\n")
    }

    fn state(&self) -> ProcessState {
        ProcessState {
            name: self.name.clone(),
            pid: self.pid(),
            http: self.ports.map(|(h, _)| format!("127.0.0.1:{h}")),
            grpc: self.ports.map(|(_, g)| format!("127.0.0.1:{g}")),
            restarts: self.restarts,
            log: self.log.clone(),
        }
    }
}

/// Its own process group (a terminal's Ctrl-C is the supervisor's alone) and,
/// on Linux, SIGTERM when the supervisor dies.
fn detach(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    cmd.process_group(0);
    #[cfg(target_os = "linux")]
    // SAFETY: the closure runs in the child between fork and exec and calls
    // only prctl(2), which is async-signal-safe; it touches no memory of
    // the parent. The supervisor spawns from its one thread (a current-
    // thread runtime), whose exit is what PR_SET_PDEATHSIG watches.
    unsafe {
        cmd.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) == -1 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

/// Sends `signal` to `pid`; a process already gone is not an error.
fn send_signal(pid: u32, signal: libc::c_int) {
    if let Ok(pid) = libc::pid_t::try_from(pid) {
        // SAFETY: kill(2) takes plain integers and touches no memory.
        unsafe {
            libc::kill(pid, signal);
        }
    }
}

/// Whether a process with this pid exists (signal 0 checks, sends nothing).
fn alive(pid: u32) -> bool {
    match libc::pid_t::try_from(pid) {
        // SAFETY: as in `send_signal`.
        Ok(pid) if pid > 0 => unsafe { libc::kill(pid, 0) == 0 },
        _ => false,
    }
}

/// Runs `mcapi cluster local` until SIGTERM or Ctrl-C.
pub fn run(args: &LocalArgs) -> Result<()> {
    crate::logging::init_logging();
    let setup = prepare(args)?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(supervise(setup))
}

/// Everything checked and written before a process starts.
struct Setup {
    dir: PathBuf,
    map: ShardMap,
    template: ReplicaTemplate,
    spec: RouterSpec,
    haproxy_cfg: PathBuf,
    admin_socket: PathBuf,
    http: SocketAddr,
    grpc: SocketAddr,
    processes: Vec<Process>,
    ready_timeout: Duration,
    drain_timeout: Duration,
}

fn prepare(args: &LocalArgs) -> Result<Setup> {
    for extra in &args.serve_args {
        if let Some(flag) = MANAGED_FLAGS
            .iter()
            .find(|f| extra == *f || extra.starts_with(&format!("{f}=")))
        {
            bail!(
                "`{flag}` is set by `cluster local` for each replica; leave it out of the serve flags"
            );
        }
    }
    if args.http == args.grpc {
        bail!("--http and --grpc must differ (both are {})", args.http);
    }
    for (flag, addr) in [("--http", args.http), ("--grpc", args.grpc)] {
        TcpListener::bind(addr).with_context(|| {
            format!("{flag} {addr} is not free (another cluster or server running?); choose another address")
        })?;
    }
    let haproxy = match &args.haproxy {
        Some(p) if p.is_file() => p.clone(),
        Some(p) => bail!("--haproxy {}: no such file", p.display()),
        None => find_haproxy().context(
            "`haproxy` is not on PATH (nor in /usr/sbin): install HAProxy 2.6 or newer \
             (apt-get install haproxy) or name it with --haproxy",
        )?,
    };
    let exe = std::env::current_exe().context("finding this executable")?;

    std::fs::create_dir_all(&args.data_dir)
        .with_context(|| format!("creating {}", args.data_dir.display()))?;
    let dir = std::fs::canonicalize(&args.data_dir)?;
    if let Ok(text) = std::fs::read_to_string(dir.join(STATE_FILE))
        && let Ok(state) = serde_json::from_str::<State>(&text)
        && state.supervisor != std::process::id()
        && alive(state.supervisor)
    {
        bail!(
            "a cluster already runs on {} (supervisor pid {}); stop it first, or delete {} if that pid is not `mcapi cluster local`",
            dir.display(),
            state.supervisor,
            dir.join(STATE_FILE).display()
        );
    }
    let map = local_map(&dir, args.replicas.map(usize::from))?;
    for sub in ["replicas", "router", "logs"] {
        std::fs::create_dir_all(dir.join(sub))
            .with_context(|| format!("creating {}", dir.join(sub).display()))?;
    }
    let admin_socket = dir.join("router").join("admin.sock");
    if admin_socket.as_os_str().len() > MAX_SOCKET_PATH {
        bail!(
            "{} is longer than a Unix socket path may be ({MAX_SOCKET_PATH} bytes): use a shorter --data-dir",
            admin_socket.display()
        );
    }

    let admin_key = admin_key(&dir)?;
    let ports = free_ports(map.replicas().len() * 2)?;
    let mut processes = Vec::new();
    let mut backends = Vec::new();
    let template = ReplicaTemplate {
        exe: exe.clone(),
        dir: dir.clone(),
        serve_args: args.serve_args.clone(),
        admin_key,
    };
    for (k, name) in map.replicas().iter().enumerate() {
        let (http, grpc) = (ports[2 * k], ports[2 * k + 1]);
        backends.push(Backend {
            replica: name.clone(),
            rest: format!("127.0.0.1:{http}"),
            grpc: format!("127.0.0.1:{grpc}"),
        });
        // `--joining` for every replica: one that gave all its shards
        // away is no longer named by the map, and must still start again.
        processes.push(template.process(name, http, grpc, true));
    }
    let router_dir = dir.join("router");
    let spec = RouterSpec {
        rest_bind: args.http.to_string(),
        grpc_bind: args.grpc.to_string(),
        map_path: router_dir.join("shards.map"),
        stats_socket: admin_socket.clone(),
        admin_bind: None,
        backends,
        resolvers: false,
    };
    write_router(&router_dir, &map, &spec)?;
    check_router(&haproxy, &router_dir.join("haproxy.cfg"))?;
    let haproxy_cfg = router_dir.join("haproxy.cfg");
    processes.push(Process {
        name: ROUTER.into(),
        program: haproxy,
        args: vec!["-db".into(), "-f".into(), haproxy_cfg.clone().into()],
        env: Vec::new(),
        log: dir.join("logs").join(format!("{ROUTER}.log")),
        ports: None,
        ready_url: format!("http://{}/readyz", args.http),
        run: Run::Stopped,
        streak: 0,
        restarts: 0,
    });
    Ok(Setup {
        dir,
        map,
        template,
        spec,
        haproxy_cfg,
        admin_socket,
        http: args.http,
        grpc: args.grpc,
        processes,
        ready_timeout: Duration::from_secs(args.ready_timeout_secs),
        drain_timeout: Duration::from_secs(args.drain_timeout_secs),
    })
}

/// Checks a written router configuration with `haproxy -c`.
fn check_router(haproxy: &Path, cfg: &Path) -> Result<()> {
    let check = Command::new(haproxy)
        .arg("-c")
        .arg("-f")
        .arg(cfg)
        .output()
        .with_context(|| format!("running {} -c", haproxy.display()))?;
    if !check.status.success() {
        bail!(
            "{} refuses {}:\n{}{}",
            haproxy.display(),
            cfg.display(),
            String::from_utf8_lossy(&check.stdout),
            String::from_utf8_lossy(&check.stderr)
        );
    }
    Ok(())
}

/// The data directory's admin key, made (32 random hex digits, mode 0600)
/// if missing.
fn admin_key(dir: &Path) -> Result<String> {
    use std::os::unix::fs::OpenOptionsExt;
    let path = dir.join(ADMIN_KEY_FILE);
    if let Ok(text) = std::fs::read_to_string(&path)
        && text.trim().len() >= 16
    {
        return Ok(text.trim().to_string());
    }
    let mut bytes = [0u8; 16];
    std::fs::File::open("/dev/urandom")
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut bytes))
        .context("reading /dev/urandom for the admin key")?;
    let key: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .write(true)
        .truncate(true)
        .mode(0o600)
        .open(&path)
        .with_context(|| format!("writing {}", path.display()))?;
    std::io::Write::write_all(&mut f, format!("{key}\n").as_bytes())?;
    Ok(key)
}

/// How a replica process is made.
struct ReplicaTemplate {
    exe: PathBuf,
    dir: PathBuf,
    serve_args: Vec<String>,
    admin_key: String,
}

impl ReplicaTemplate {
    fn process(&self, name: &ReplicaName, http: u16, grpc: u16, joining: bool) -> Process {
        let store = self.dir.join("replicas").join(name.as_str());
        let mut argv: Vec<OsString> = vec![
            "serve".into(),
            "--http".into(),
            format!("127.0.0.1:{http}").into(),
            "--grpc".into(),
            format!("127.0.0.1:{grpc}").into(),
            "--data-dir".into(),
            store.into(),
            "--shard-map".into(),
            self.dir.join(MAP_FILE).into(),
            "--replica".into(),
            name.as_str().into(),
        ];
        if joining {
            argv.push("--joining".into());
        }
        argv.extend(self.serve_args.iter().map(OsString::from));
        Process {
            name: name.to_string(),
            program: self.exe.clone(),
            args: argv,
            env: vec![("MCAPI_ADMIN_KEY".into(), self.admin_key.clone())],
            log: self.dir.join("logs").join(format!("{name}.log")),
            ports: Some((http, grpc)),
            ready_url: format!("http://127.0.0.1:{http}/readyz"),
            run: Run::Stopped,
            streak: 0,
            restarts: 0,
        }
    }
}

/// The data directory's map if it has one (its replicas must match
/// `--replicas` when given), else a new plan over `mcapi-0..N-1`, written.
fn local_map(dir: &Path, replicas: Option<usize>) -> Result<ShardMap> {
    let path = dir.join(MAP_FILE);
    if path.exists() {
        let map = ShardMap::read(&path).with_context(|| format!("shard map {}", path.display()))?;
        let names: Vec<&str> = map.replicas().iter().map(ReplicaName::as_str).collect();
        if map.replicas().len() > MAX_LOCAL_REPLICAS {
            bail!(
                "{} has {} replicas; `cluster local` runs at most {MAX_LOCAL_REPLICAS}",
                path.display(),
                names.len()
            );
        }
        if names.contains(&ROUTER) {
            bail!(
                "{}: `{ROUTER}` names the router here; rename that replica",
                path.display()
            );
        }
        if let Some(n) = replicas
            && n != names.len()
        {
            bail!(
                "{} has {} replicas ({}), not {n}: leave out --replicas, and add replicas to the \
                 running cluster with `mcapi cluster rebalance --replicas {n}` (or use a new --data-dir)",
                path.display(),
                names.len(),
                names.join(", ")
            );
        }
        return Ok(map);
    }
    let n = replicas.unwrap_or(DEFAULT_REPLICAS);
    let names = ordinal_names("mcapi", n).map_err(anyhow::Error::msg)?;
    let map = plan::plan(&names, None)?.map;
    write_atomic(&path, &map.to_text())?;
    Ok(map)
}

/// `n` distinct loopback ports free right now: all are held until all are
/// known, so none is handed out twice.
fn free_ports(n: usize) -> Result<Vec<u16>> {
    let listeners = (0..n)
        .map(|_| TcpListener::bind("127.0.0.1:0"))
        .collect::<std::io::Result<Vec<_>>>()
        .context("finding free loopback ports")?;
    listeners
        .iter()
        .map(|l| Ok(l.local_addr()?.port()))
        .collect()
}

/// The processes, stopped (SIGKILL) if dropped while any still runs: an
/// error on the way out leaves no child behind.
struct Cluster {
    processes: Vec<Process>,
    template: ReplicaTemplate,
    spec: RouterSpec,
    dir: PathBuf,
    state_file: PathBuf,
    state: State,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        for p in &mut self.processes {
            if let Run::Up { child, .. } = &mut p.run {
                let _ = child.kill();
                let _ = child.wait();
            }
            p.run = Run::Stopped;
        }
        let _ = std::fs::remove_file(&self.state_file);
    }
}

impl Cluster {
    fn write_state(&mut self) {
        if let Ok(map) = ShardMap::read(&self.dir.join(MAP_FILE)) {
            self.state.epoch = map.epoch();
        }
        self.state.processes = self.processes.iter().map(Process::state).collect();
        match serde_json::to_string_pretty(&self.state) {
            Ok(text) => {
                if let Err(e) = write_atomic(&self.state_file, &text) {
                    tracing::error!(error = %format!("{e:#}"), "cannot write the state file");
                }
            }
            Err(e) => tracing::error!(error = %e, "cannot encode the state file"),
        }
    }

    /// Starts `range` of the processes and waits until each answers 200 on
    /// its readiness URL; fails if one exits first or the deadline passes.
    async fn start(&mut self, range: std::ops::Range<usize>, timeout: Duration) -> Result<()> {
        for p in &mut self.processes[range.clone()] {
            let pid = p.spawn()?;
            tracing::info!(process = %p.name, pid, "started");
        }
        self.write_state();
        let deadline = Instant::now() + timeout;
        let mut waiting: Vec<usize> = range.collect();
        while !waiting.is_empty() {
            let mut still = Vec::new();
            for &i in &waiting {
                let p = &mut self.processes[i];
                if let Run::Up { child, .. } = &mut p.run
                    && let Ok(Some(status)) = child.try_wait()
                {
                    p.run = Run::Stopped;
                    bail!(
                        "{} exited ({status}) before it was ready; the end of {}:\n{}",
                        p.name,
                        p.log.display(),
                        p.log_tail()
                    );
                }
                if http_ok(&p.ready_url, Duration::from_millis(500)).is_err() {
                    still.push(i);
                }
            }
            waiting = still;
            if waiting.is_empty() {
                break;
            }
            if Instant::now() >= deadline {
                let names: Vec<&str> = waiting
                    .iter()
                    .map(|&i| self.processes[i].name.as_str())
                    .collect();
                bail!(
                    "not ready after {} s: {} (see their logs in {})",
                    timeout.as_secs(),
                    names.join(", "),
                    self.state_file
                        .parent()
                        .map(|d| d.join("logs"))
                        .unwrap_or_default()
                        .display()
                );
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        Ok(())
    }

    /// Looks at every process five times a second, forever: exits are
    /// logged and restarted after their backoff.
    async fn watch(&mut self, backoff: Backoff) {
        loop {
            let now = Instant::now();
            let mut changed = false;
            for p in &mut self.processes {
                let Some(event) = p.tick(now, &backoff) else {
                    continue;
                };
                changed = true;
                match event {
                    Event::Exited { status, ran, wait } => tracing::warn!(
                        process = %p.name,
                        %status,
                        ran_s = ran.as_secs_f64(),
                        restart_in_ms = wait.as_millis() as u64,
                        "exited; starting it again after a backoff"
                    ),
                    Event::Restarted { pid } => tracing::info!(
                        process = %p.name,
                        pid,
                        restarts = p.restarts,
                        "started again"
                    ),
                    Event::SpawnFailed { error, wait } => tracing::error!(
                        process = %p.name,
                        %error,
                        retry_in_ms = wait.as_millis() as u64,
                        "cannot start it again"
                    ),
                }
            }
            if changed {
                self.write_state();
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// SIGTERM to `range`, then SIGKILL to whatever still runs after `grace`.
    async fn stop(&mut self, range: std::ops::Range<usize>, grace: Duration) {
        for p in &mut self.processes[range.clone()] {
            match &p.run {
                Run::Up { child, .. } => send_signal(child.id(), libc::SIGTERM),
                Run::Waiting { .. } | Run::Stopped => p.run = Run::Stopped,
            }
        }
        let deadline = Instant::now() + grace;
        loop {
            let mut running = 0;
            for p in &mut self.processes[range.clone()] {
                if let Run::Up { child, .. } = &mut p.run {
                    match child.try_wait() {
                        Ok(Some(status)) => {
                            tracing::info!(process = %p.name, %status, "stopped");
                            p.run = Run::Stopped;
                        }
                        Ok(None) | Err(_) => running += 1,
                    }
                }
            }
            if running == 0 {
                return;
            }
            if Instant::now() >= deadline {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        for p in &mut self.processes[range] {
            if let Run::Up { child, .. } = &mut p.run {
                tracing::warn!(process = %p.name, grace_s = grace.as_secs(), "did not stop in time: SIGKILL");
                let _ = child.kill();
                let _ = child.wait();
                p.run = Run::Stopped;
            }
        }
    }

    /// A rebalance's request (`rebalance.json`, then SIGHUP): starts the
    /// replicas up to the number asked for (`--joining`: owning nothing
    /// until shards move to them), writes the router's configuration with
    /// them and starts HAProxy again, then records `replicas`.
    async fn grow(&mut self, ready_timeout: Duration) -> Result<()> {
        #[derive(Deserialize)]
        struct Request {
            replicas: usize,
        }
        let path = self.dir.join(REQUEST_FILE);
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let want = serde_json::from_str::<Request>(&text)
            .with_context(|| format!("{} is not a rebalance request", path.display()))?
            .replicas;
        let have = self.processes.len().saturating_sub(1);
        if want > MAX_LOCAL_REPLICAS {
            bail!("{want} replicas asked for; `cluster local` runs at most {MAX_LOCAL_REPLICAS}");
        }
        if want <= have {
            tracing::info!(
                replicas = have,
                asked = want,
                "rebalance request: enough replicas run"
            );
            self.state.replicas = have;
            self.write_state();
            return Ok(());
        }
        let names = ordinal_names("mcapi", want).map_err(anyhow::Error::msg)?;
        let ports = free_ports((want - have) * 2)?;
        let router = self.processes.len() - 1;
        for (k, name) in names[have..].iter().enumerate() {
            let (http, grpc) = (ports[2 * k], ports[2 * k + 1]);
            self.spec.backends.push(Backend {
                replica: name.clone(),
                rest: format!("127.0.0.1:{http}"),
                grpc: format!("127.0.0.1:{grpc}"),
            });
            let p = self.template.process(name, http, grpc, true);
            self.processes.insert(router + k, p);
        }
        self.start(have..want, ready_timeout).await?;
        let map = ShardMap::read(&self.dir.join(MAP_FILE))
            .with_context(|| format!("shard map {}", self.dir.join(MAP_FILE).display()))?;
        write_router(&self.dir.join("router"), &map, &self.spec)?;
        let router = self.processes.len() - 1;
        check_router(
            &self.processes[router].program,
            &self.dir.join("router").join("haproxy.cfg"),
        )?;
        tracing::info!(
            replicas = want,
            "replicas started; starting the router again with them"
        );
        self.stop(router..router + 1, Duration::from_secs(10)).await;
        self.start(router..router + 1, ready_timeout).await?;
        self.state.replicas = want;
        self.write_state();
        tracing::info!(
            replicas = want,
            "rebalance request done: the router knows every replica"
        );
        Ok(())
    }

    /// Replicas first (they drain on SIGTERM), then the router.
    async fn shutdown(&mut self, drain: Duration) {
        let replicas = self.processes.len().saturating_sub(1);
        self.stop(0..replicas, drain).await;
        self.stop(replicas..self.processes.len(), Duration::from_secs(10))
            .await;
        let _ = std::fs::remove_file(&self.state_file);
    }
}

async fn supervise(setup: Setup) -> Result<()> {
    let Setup {
        dir,
        map,
        template,
        spec,
        haproxy_cfg,
        admin_socket,
        http,
        grpc,
        processes,
        ready_timeout,
        drain_timeout,
    } = setup;
    let replicas = processes.len().saturating_sub(1);
    let mut cluster = Cluster {
        processes,
        template,
        spec,
        dir: dir.clone(),
        state_file: dir.join(STATE_FILE),
        state: State {
            supervisor: std::process::id(),
            http: http.to_string(),
            grpc: grpc.to_string(),
            admin_socket: admin_socket.clone(),
            epoch: map.epoch(),
            replicas,
            processes: Vec::new(),
        },
    };
    let signal = crate::signal::shutdown_signal();
    tokio::pin!(signal);
    let started = tokio::select! {
        r = async {
            cluster.start(0..replicas, ready_timeout).await?;
            cluster.start(replicas..replicas + 1, ready_timeout).await
        } => r,
        () = &mut signal => Err(anyhow::anyhow!("interrupted while starting")),
    };
    if let Err(e) = started {
        cluster.shutdown(drain_timeout).await;
        return Err(e);
    }
    cluster.write_state();
    print_banner(&dir, &map, &cluster, &haproxy_cfg, &admin_socket);
    let mut hangup = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup())
        .context("installing the SIGHUP handler (rebalance requests)")?;
    loop {
        tokio::select! {
            () = cluster.watch(Backoff::DEFAULT) => break,
            () = &mut signal => break,
            _ = hangup.recv() => {
                if let Err(e) = cluster.grow(ready_timeout).await {
                    tracing::error!(error = %format!("{e:#}"), "rebalance request refused");
                }
            }
        }
    }
    tracing::info!("shutdown requested: draining the replicas, then the router");
    cluster.shutdown(drain_timeout).await;
    tracing::info!("every process stopped");
    Ok(())
}

/// Where things listen, on stdout (this is a CLI).
fn print_banner(dir: &Path, map: &ShardMap, cluster: &Cluster, cfg: &Path, socket: &Path) {
    let s = &cluster.state;
    let mut out = format!(
        "mcapi cluster local: {} replicas behind HAProxy, shard map epoch {} ({})\n\
         \x20 REST  http://{}\n\
         \x20 gRPC  http://{} (name the session in `x-mcapi-session` metadata)\n",
        map.replicas().len(),
        map.epoch(),
        dir.join(MAP_FILE).display(),
        s.http,
        s.grpc,
    );
    for p in &cluster.processes {
        let pid = p.pid().map_or_else(|| "-".to_string(), |p| p.to_string());
        match p.ports {
            Some((h, g)) => out.push_str(&format!(
                "  {:<10} REST 127.0.0.1:{h:<5}  gRPC 127.0.0.1:{g:<5}  pid {pid:<7}  log {}\n",
                p.name,
                p.log.display()
            )),
            None => out.push_str(&format!(
                "  {:<10} {}  pid {pid:<7}  log {}\n",
                p.name,
                cfg.display(),
                p.log.display()
            )),
        }
    }
    out.push_str(&format!(
        "  Runtime API {}\n  state {}\nCtrl-C or SIGTERM stops everything.\n",
        socket.display(),
        cluster.state_file.display()
    ));
    // Not `print!`, which panics when stdout is a closed pipe: the
    // cluster runs on whether or not anyone reads the banner.
    use std::io::Write;
    let mut stdout = std::io::stdout().lock();
    let _ = stdout.write_all(out.as_bytes());
    let _ = stdout.flush();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_backoff_doubles_to_its_cap_and_resets_after_a_steady_run() {
        let b = Backoff::DEFAULT;
        let quick = Duration::from_secs(1);
        let mut streak = 0;
        let mut waits = Vec::new();
        for _ in 0..10 {
            let (wait, s) = b.after_exit(quick, streak);
            streak = s;
            waits.push(wait.as_millis());
        }
        assert_eq!(
            waits,
            [250, 500, 1000, 2000, 4000, 8000, 16000, 30000, 30000, 30000]
        );
        assert_eq!(b.after_exit(b.steady, streak), (b.first, 1));
        // A streak as long as u32 allows neither overflows nor exceeds the cap.
        assert_eq!(b.after_exit(quick, u32::MAX), (b.max, u32::MAX));
    }

    fn process(dir: &Path, program: &str, args: &[&str]) -> Process {
        Process {
            name: "p".into(),
            program: program.into(),
            args: args.iter().map(OsString::from).collect(),
            env: Vec::new(),
            log: dir.join("p.log"),
            ports: None,
            ready_url: String::new(),
            run: Run::Stopped,
            streak: 0,
            restarts: 0,
        }
    }

    /// Ticks until `event` matches or 10 s pass.
    fn tick_until(p: &mut Process, b: &Backoff, want: fn(&Event) -> bool) -> Event {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if let Some(e) = p.tick(Instant::now(), b)
                && want(&e)
            {
                return e;
            }
            assert!(Instant::now() < deadline, "no such event within 10 s");
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    #[test]
    fn a_process_that_exits_is_started_again_after_its_backoff() {
        let dir = tempfile::tempdir().expect("tempdir");
        let b = Backoff {
            first: Duration::from_millis(30),
            max: Duration::from_millis(60),
            steady: Duration::from_secs(60),
        };
        let mut p = process(dir.path(), "/bin/sh", &["-c", "echo ran >&2; exit 3"]);
        let first = p.spawn().expect("spawns");
        let e = tick_until(&mut p, &b, |e| matches!(e, Event::Exited { .. }));
        let Event::Exited { status, wait, .. } = e else {
            unreachable!("matched above")
        };
        assert_eq!(status.code(), Some(3));
        assert_eq!(wait, b.first);
        assert!(p.pid().is_none(), "no pid while waiting");
        let e = tick_until(&mut p, &b, |e| matches!(e, Event::Restarted { .. }));
        let Event::Restarted { pid } = e else {
            unreachable!("matched above")
        };
        assert_ne!(pid, first);
        assert_eq!(p.restarts, 1);
        let e = tick_until(&mut p, &b, |e| matches!(e, Event::Exited { .. }));
        assert!(
            matches!(e, Event::Exited { wait, .. } if wait == b.max),
            "second quick exit: the doubled wait, capped: {e:?}"
        );
        // The log gathers every run's stderr.
        std::thread::sleep(Duration::from_millis(50));
        assert_eq!(p.log_tail().lines().filter(|l| *l == "ran").count(), 2);

        let mut missing = process(dir.path(), "/nonexistent/program", &[]);
        missing.run = Run::Waiting {
            until: Instant::now(),
        };
        let e = missing.tick(Instant::now(), &b).expect("an event");
        assert!(
            matches!(&e, Event::SpawnFailed { error, .. } if error.contains("/nonexistent/program")),
            "{e:?}"
        );
    }

    #[test]
    fn a_data_dir_keeps_its_map_and_refuses_another_replica_count() {
        let dir = tempfile::tempdir().expect("tempdir");
        let map = local_map(dir.path(), Some(2)).expect("planned");
        assert_eq!(map.replicas().len(), 2);
        let again = local_map(dir.path(), None).expect("reused");
        assert_eq!(again.to_text(), map.to_text());
        let e = local_map(dir.path(), Some(3)).expect_err("2 is not 3");
        assert!(
            format!("{e:#}").contains("has 2 replicas (mcapi-0, mcapi-1), not 3"),
            "{e:#}"
        );
        let fresh = tempfile::tempdir().expect("tempdir");
        assert_eq!(
            local_map(fresh.path(), None)
                .expect("default")
                .replicas()
                .len(),
            DEFAULT_REPLICAS
        );
        // A replica may not take the router's name (its log would be the router's).
        let odd = tempfile::tempdir().expect("tempdir");
        let names = ["haproxy", "mcapi-1"].map(|n| ReplicaName::parse(n).expect("name"));
        let map = plan::plan(&names, None).expect("plan").map;
        std::fs::write(odd.path().join(MAP_FILE), map.to_text()).expect("write");
        let e = local_map(odd.path(), None).expect_err("haproxy");
        assert!(
            format!("{e:#}").contains("`haproxy` names the router"),
            "{e:#}"
        );
    }
}
