//! What `mcapi cluster local` checks and writes before a process starts:
//! the flags, the shard map (planned or the data directory's), the admin
//! key, the router's files and free loopback ports.

use std::ffi::OsString;
use std::net::{IpAddr, SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use anyhow::{Context, Result, bail};

use mcapi_shards::plan::{self, ordinal_names};
use mcapi_shards::{ReplicaName, ShardMap};

use super::netns::Placements;
use super::process::{Process, Run, alive};
use super::state::State;
use super::{
    ADMIN_KEY_FILE, DEFAULT_REPLICAS, LocalArgs, MANAGED_FLAGS, MAP_FILE, MAX_LOCAL_REPLICAS,
    MAX_SOCKET_PATH, ROUTER, RouterUpdate, STATE_FILE,
};
use crate::files::write_atomic;
use crate::haproxy::write_router;
use crate::haproxy::{Backend, RouterSpec, find_haproxy};

/// Everything checked and written before a process starts.
pub(super) struct Setup {
    pub(super) dir: PathBuf,
    pub(super) map: ShardMap,
    pub(super) template: ReplicaTemplate,
    pub(super) spec: RouterSpec,
    pub(super) haproxy: PathBuf,
    pub(super) haproxy_cfg: PathBuf,
    pub(super) admin_socket: PathBuf,
    pub(super) http: SocketAddr,
    pub(super) grpc: SocketAddr,
    pub(super) processes: Vec<Process>,
    pub(super) ready_timeout: Duration,
    pub(super) drain_timeout: Duration,
    pub(super) router_update: RouterUpdate,
}

pub(super) fn prepare(args: &LocalArgs) -> Result<Setup> {
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
    let placements = Placements::parse(&args.netns)?;
    // The router's addresses are held until the replicas' ports are
    // chosen, so that no replica is given one of them: a replica on the
    // router's port would answer the router's readiness probe, and every
    // request after it, in HAProxy's place. A router in a namespace of its
    // own listens on addresses of that namespace, which cannot be bound
    // from here.
    let router_held = if placements.has(ROUTER) {
        Vec::new()
    } else {
        hold_router_addresses(args.http, args.grpc)?
    };
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
    let known = ordinal_names("mcapi", MAX_LOCAL_REPLICAS).map_err(anyhow::Error::msg)?;
    for name in placements.names() {
        let replica = map
            .replicas()
            .iter()
            .chain(&known)
            .any(|r| r.as_str() == name);
        if name != ROUTER && !replica {
            bail!(
                "--netns: `{name}` is neither `{ROUTER}` nor a replica this cluster runs or may add"
            );
        }
    }
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
    let ports = free_ports(map.replicas().len() * 2, &[])?;
    drop(router_held);
    let mut processes = Vec::new();
    let mut backends = Vec::new();
    let template = ReplicaTemplate {
        exe: exe.clone(),
        dir: dir.clone(),
        serve_args: args.serve_args.clone(),
        admin_key,
        placements,
    };
    for (k, name) in map.replicas().iter().enumerate() {
        let (http, grpc) = (ports[2 * k], ports[2 * k + 1]);
        backends.push(template.backend(name, http, grpc));
        // `--joining` for every replica: one that gave all its shards
        // away is no longer named by the map, and must still start again.
        processes.push(template.process(name, http, grpc, true));
    }
    let router_dir = dir.join("router");
    // Every name a rebalance may add (`mcapi-k` up to the most this runs)
    // has its backends from the start: joining is then a Runtime API
    // call, never a restart of the router.
    let spare = ordinal_names("mcapi", MAX_LOCAL_REPLICAS)
        .map_err(anyhow::Error::msg)?
        .into_iter()
        .filter(|n| !map.has_replica(n))
        .collect();
    let spec = RouterSpec {
        rest_bind: args.http.to_string(),
        grpc_bind: args.grpc.to_string(),
        map_path: router_dir.join("shards.map"),
        stats_socket: admin_socket.clone(),
        admin_bind: None,
        backends,
        resolvers: false,
        spare,
        expose_listeners: args.router_update == RouterUpdate::Reload,
    };
    write_router(&router_dir, &map, &spec)?;
    check_router(&haproxy, &router_dir.join("haproxy.cfg"))?;
    let haproxy_cfg = router_dir.join("haproxy.cfg");
    let (program, router_args) = template.placements.command(
        ROUTER,
        haproxy.clone(),
        match args.router_update {
            RouterUpdate::Runtime | RouterUpdate::Restart => {
                vec!["-db".into(), "-f".into(), haproxy_cfg.clone().into()]
            }
            // The master stays in the foreground and re-executes itself on
            // SIGUSR2, handing the listeners to the new worker.
            RouterUpdate::Reload => vec![
                "-W".into(),
                "-db".into(),
                "-f".into(),
                haproxy_cfg.clone().into(),
            ],
        },
    );
    processes.push(Process {
        name: ROUTER.into(),
        program,
        args: router_args,
        env: Vec::new(),
        log: dir.join("logs").join(format!("{ROUTER}.log")),
        listen: None,
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
        haproxy,
        haproxy_cfg,
        admin_socket,
        http: args.http,
        grpc: args.grpc,
        processes,
        ready_timeout: Duration::from_secs(args.ready_timeout_secs),
        drain_timeout: Duration::from_secs(args.drain_timeout_secs),
        router_update: args.router_update,
    })
}

/// Checks a written router configuration with `haproxy -c`.
pub(super) fn check_router(haproxy: &Path, cfg: &Path) -> Result<()> {
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
pub(super) fn admin_key(dir: &Path) -> Result<String> {
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
pub(super) struct ReplicaTemplate {
    pub(super) exe: PathBuf,
    pub(super) dir: PathBuf,
    pub(super) serve_args: Vec<String>,
    pub(super) admin_key: String,
    /// `--netns`: where each process runs, and a replica's address.
    pub(super) placements: Placements,
}

impl ReplicaTemplate {
    /// Where replica `name` listens on these ports.
    fn listen(&self, name: &ReplicaName, http: u16, grpc: u16) -> (SocketAddr, SocketAddr) {
        let host: IpAddr = self.placements.host(name.as_str());
        (SocketAddr::new(host, http), SocketAddr::new(host, grpc))
    }

    /// The router's backend of replica `name` on these ports.
    pub(super) fn backend(&self, name: &ReplicaName, http: u16, grpc: u16) -> Backend {
        let (rest, grpc) = self.listen(name, http, grpc);
        Backend {
            replica: name.clone(),
            rest: rest.to_string(),
            grpc: grpc.to_string(),
        }
    }

    pub(super) fn process(
        &self,
        name: &ReplicaName,
        http: u16,
        grpc: u16,
        joining: bool,
    ) -> Process {
        let store = self.dir.join("replicas").join(name.as_str());
        let (rest_addr, grpc_addr) = self.listen(name, http, grpc);
        let mut argv: Vec<OsString> = vec![
            "serve".into(),
            "--http".into(),
            rest_addr.to_string().into(),
            "--grpc".into(),
            grpc_addr.to_string().into(),
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
        let (program, args) = self
            .placements
            .command(name.as_str(), self.exe.clone(), argv);
        Process {
            name: name.to_string(),
            program,
            args,
            env: vec![("MCAPI_ADMIN_KEY".into(), self.admin_key.clone())],
            log: self.dir.join("logs").join(format!("{name}.log")),
            listen: Some((rest_addr, grpc_addr)),
            ready_url: format!("http://{rest_addr}/readyz"),
            run: Run::Stopped,
            streak: 0,
            restarts: 0,
        }
    }
}

/// The data directory's map if it has one (its replicas must match
/// `--replicas` when given), else a new plan over `mcapi-0..N-1`, written.
pub(super) fn local_map(dir: &Path, replicas: Option<usize>) -> Result<ShardMap> {
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

/// Binds the router's two addresses, to show they are free and to keep
/// them from [`free_ports`] while the listeners live.
pub(super) fn hold_router_addresses(
    http: SocketAddr,
    grpc: SocketAddr,
) -> Result<Vec<TcpListener>> {
    [("--http", http), ("--grpc", grpc)]
        .into_iter()
        .map(|(flag, addr)| {
            TcpListener::bind(addr).with_context(|| {
                format!("{flag} {addr} is not free (another cluster or server running?); choose another address")
            })
        })
        .collect()
}

/// `n` distinct loopback ports free right now and not in `taken` (the
/// ports of processes that may be down for a moment, restarting): all are
/// held until all are known, so none is handed out twice.
///
/// They are chosen below the kernel's ephemeral range, from a place that
/// differs from run to run. A port the kernel handed out for port 0 and
/// got back would be handed out again, as a listener's port or as the
/// source port of any outgoing connection on the machine (a test client's,
/// a health check's), and the replica that then binds it would find it
/// taken. Below the range only an explicit bind takes a port. Where that
/// range leaves no room (it starts below 4096), ports come from port 0.
pub(super) fn free_ports(n: usize, taken: &[u16]) -> Result<Vec<u16>> {
    let low = ephemeral_start().unwrap_or(32_768);
    if low < 4096 {
        return kernel_ports(n, taken);
    }
    // Candidates: [low / 2, low), from a start that differs per process and
    // call, so two clusters started together rarely meet.
    let (first, span) = (low / 2, low - low / 2);
    let seed = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos())
        ^ std::process::id().rotate_left(16);
    let start = seed % u32::from(span);
    let mut held = Vec::with_capacity(n);
    let mut ports = Vec::with_capacity(n);
    for i in 0..u32::from(span) {
        if ports.len() == n {
            break;
        }
        let port = first + ((start + i) % u32::from(span)) as u16;
        if taken.contains(&port) {
            continue;
        }
        // Taken by another process, or not ours to bind: the next one.
        if let Ok(l) = TcpListener::bind(("127.0.0.1", port)) {
            ports.push(port);
            held.push(l);
        }
    }
    if ports.len() < n {
        bail!(
            "finding free loopback ports: only {} of {n} free below {low}",
            ports.len()
        );
    }
    Ok(ports)
}

/// The first port of the kernel's ephemeral range (Linux:
/// `/proc/sys/net/ipv4/ip_local_port_range`).
pub(super) fn ephemeral_start() -> Option<u16> {
    let range = std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range").ok()?;
    range.split_whitespace().next()?.parse().ok()
}

/// [`free_ports`] from the kernel's port 0.
fn kernel_ports(n: usize, taken: &[u16]) -> Result<Vec<u16>> {
    let mut held = Vec::with_capacity(n);
    let mut ports = Vec::with_capacity(n);
    // Each port `taken` can be handed out at most once while it is held.
    while ports.len() < n {
        if held.len() >= n + taken.len() {
            bail!("finding free loopback ports: the kernel handed out only taken ones");
        }
        let l = TcpListener::bind("127.0.0.1:0").context("finding free loopback ports")?;
        let port = l.local_addr()?.port();
        if !taken.contains(&port) {
            ports.push(port);
        }
        held.push(l);
    }
    Ok(ports)
}
