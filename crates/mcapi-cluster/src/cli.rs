//! `mcapi cluster ...`: the command-line side of the cluster (the `mcapi`
//! binary's `main.rs` only dispatches here). This is a CLI: it prints.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};

use mcapi_shards::plan::{self, ordinal_names};
use mcapi_shards::{ReplicaName, ShardMap};

use crate::files::write_atomic;
use crate::haproxy::{self, Backend, RouterSpec, write_router};

/// `mcapi cluster` subcommands.
#[derive(Debug, Subcommand)]
pub enum ClusterCommand {
    /// Propose a shard map by rendezvous hashing (from an earlier map: with the fewest moves).
    Plan(PlanArgs),
    /// Write an HAProxy 2.6 configuration and map file from a shard map.
    HaproxyConfig(HaproxyArgs),
    /// Run a whole cluster on this machine: N replicas and HAProxy on
    /// loopback, supervised (a replica that dies is started again) until
    /// SIGTERM or Ctrl-C.
    Local(crate::local::LocalArgs),
    /// Move one shard of a running `mcapi cluster local` to another
    /// replica, live: snapshot, freeze, delta, flip the map, drop at the
    /// source (docs/cluster.md).
    Move(MoveArgs),
    /// Grow or shrink a running `mcapi cluster local`, live: move the
    /// shards the rendezvous plan for N replicas gives to others (first
    /// finishing what dead movers left half done), starting new replicas
    /// before, or stopping the ones beyond N after.
    Rebalance(RebalanceArgs),
    /// Show a running `mcapi cluster local`'s replicas and every shard not
    /// plainly served by its map's owner: frozen (with the lease left),
    /// half-moved, being imported, not released. Exits 1 if any shard needs
    /// attention or a replica does not answer, 0 otherwise.
    Status(StatusArgs),
}

/// The lease of a freeze, in milliseconds: a shard frozen by a mover that
/// died is served by its source again after this.
fn lease_parser() -> clap::builder::RangedU64ValueParser<u64> {
    clap::value_parser!(u64).range(100..=600_000)
}

/// The time one admin call of a mover may take, in seconds.
fn call_timeout_parser() -> clap::builder::RangedU64ValueParser<u64> {
    clap::value_parser!(u64).range(1..=3600)
}

/// `mcapi cluster status`.
#[derive(Debug, Args)]
pub struct StatusArgs {
    /// The running `mcapi cluster local`'s directory.
    #[arg(long, default_value = "./cluster")]
    pub data_dir: PathBuf,
}

/// `mcapi cluster move`.
#[derive(Debug, Args)]
pub struct MoveArgs {
    /// The running `mcapi cluster local`'s directory.
    #[arg(long, default_value = "./cluster")]
    pub data_dir: PathBuf,
    /// The shard to move (`s03a7`).
    #[arg(long)]
    pub shard: String,
    /// The replica to move it to (one the cluster runs).
    #[arg(long)]
    pub to: String,
    /// The freeze's lease (ms, 100 to 600000): past it without a commit,
    /// the source serves the shard again by itself and refuses the commit.
    #[arg(long, default_value_t = crate::mover::DEFAULT_LEASE_MS, value_parser = lease_parser())]
    pub freeze_lease_ms: u64,
    /// Seconds (1 to 3600) each call to a replica may take before it
    /// counts as unanswered. A commit left unanswered is not undone unless
    /// the source says it did not make it.
    #[arg(long, default_value_t = crate::mover::DEFAULT_CALL_TIMEOUT_SECS, value_parser = call_timeout_parser())]
    pub call_timeout_secs: u64,
}

/// `mcapi cluster rebalance`.
#[derive(Debug, Args)]
pub struct RebalanceArgs {
    /// The running `mcapi cluster local`'s directory.
    #[arg(long, default_value = "./cluster")]
    pub data_dir: PathBuf,
    /// Replicas after it (1 to 64). More than run: new replicas start
    /// and shards move to them. Fewer: every shard moves off the replicas
    /// beyond N, which then leave the router and stop.
    #[arg(long, value_parser = clap::value_parser!(u16).range(1..=crate::local::MAX_LOCAL_REPLICAS as i64))]
    pub replicas: u16,
    /// Each freeze's lease (ms, 100 to 600000), as for `move`.
    #[arg(long, default_value_t = crate::mover::DEFAULT_LEASE_MS, value_parser = lease_parser())]
    pub freeze_lease_ms: u64,
    /// Seconds (1 to 3600) each call to a replica may take, as for `move`.
    #[arg(long, default_value_t = crate::mover::DEFAULT_CALL_TIMEOUT_SECS, value_parser = call_timeout_parser())]
    pub call_timeout_secs: u64,
}

/// `mcapi cluster plan`.
#[derive(Debug, Args)]
pub struct PlanArgs {
    /// Number of replicas, named PREFIX-0 .. PREFIX-(N-1) (a StatefulSet's pods).
    #[arg(long, required_unless_present = "names")]
    pub replicas: Option<usize>,
    /// Prefix of the replica names.
    #[arg(long, default_value = "mcapi")]
    pub prefix: String,
    /// Explicit replica names instead of --replicas (comma-separated).
    #[arg(long, value_delimiter = ',', conflicts_with = "replicas")]
    pub names: Vec<String>,
    /// The map in force: shards stay where they are unless their replica is
    /// gone or over its share; the epoch becomes its epoch + 1.
    #[arg(long)]
    pub from: Option<PathBuf>,
    /// Write the map here (default: standard output).
    #[arg(long, short)]
    pub out: Option<PathBuf>,
}

/// `mcapi cluster haproxy-config`.
#[derive(Debug, Args)]
pub struct HaproxyArgs {
    /// The shard map.
    #[arg(long)]
    pub map: PathBuf,
    /// Directory for haproxy.cfg and shards.map (created if missing).
    #[arg(long)]
    pub out_dir: PathBuf,
    /// A replica's addresses: NAME=REST_HOST:PORT,GRPC_HOST:PORT (repeat).
    #[arg(long = "backend")]
    pub backends: Vec<String>,
    /// Addresses of the replicas without --backend, `{replica}` standing for
    /// the name: REST_TEMPLATE,GRPC_TEMPLATE, e.g.
    /// `{replica}.mcapi-headless:8080,{replica}.mcapi-headless:50051`.
    #[arg(long)]
    pub backend_template: Option<String>,
    /// The router's REST listen address.
    #[arg(long, default_value = ":8080")]
    pub rest_bind: String,
    /// The router's gRPC listen address (h2c).
    #[arg(long, default_value = ":50051")]
    pub grpc_bind: String,
    /// Where HAProxy will find shards.map (default: in --out-dir).
    #[arg(long)]
    pub map_path: Option<PathBuf>,
    /// The Runtime API socket (default: admin.sock in --out-dir).
    #[arg(long)]
    pub stats_socket: Option<PathBuf>,
    /// Serve the Runtime API on this TCP address too (e.g. 127.0.0.1:9999
    /// inside a pod, reached with `kubectl port-forward`).
    #[arg(long)]
    pub admin_bind: Option<String>,
    /// Follow the backends' DNS names at run time (an HAProxy `resolvers`
    /// section over /etc/resolv.conf), as Kubernetes pod names need; the
    /// names must be fully qualified.
    #[arg(long)]
    pub resolvers: bool,
    /// Also write DIR/NAME.yaml: a Kubernetes ConfigMap NAME with
    /// haproxy.cfg, HAProxy's shards.map and the shard map itself
    /// (mcapi-shards.map, for the replicas).
    #[arg(long, value_name = "NAME")]
    pub configmap: Option<String>,
    /// The ConfigMap's namespace.
    #[arg(long, requires = "configmap")]
    pub namespace: Option<String>,
}

/// Runs a `mcapi cluster` subcommand. `stop` makes the future that ends a
/// supervised cluster (`cluster local`): the binary's signal handler.
pub fn run<S, F>(cmd: ClusterCommand, stop: S) -> Result<()>
where
    S: FnOnce() -> F,
    F: Future<Output = ()> + Send,
{
    match cmd {
        ClusterCommand::Plan(args) => run_plan(&args),
        ClusterCommand::HaproxyConfig(args) => run_haproxy(&args),
        ClusterCommand::Local(args) => crate::local::run(&args, stop),
        ClusterCommand::Move(args) => run_move(&args),
        ClusterCommand::Rebalance(args) => run_rebalance(&args),
        ClusterCommand::Status(args) => run_status(&args),
    }
}

fn run_move(args: &MoveArgs) -> Result<()> {
    crate::logging::init_logging();
    // The message the replicas give for a bad shard in a path, as before.
    let shard = mcapi_shards::parse_shard(&args.shard)
        .map_err(|e| anyhow::anyhow!("--shard: `shard`: {e}"))?;
    let to = ReplicaName::parse(&args.to).map_err(|e| anyhow::anyhow!("--to: {e}"))?;
    let dir = std::fs::canonicalize(&args.data_dir)
        .with_context(|| format!("--data-dir {}", args.data_dir.display()))?;
    let mut mover = crate::mover::Mover::open(&dir)?;
    mover.set_lease_ms(args.freeze_lease_ms);
    mover.set_call_timeout(std::time::Duration::from_secs(args.call_timeout_secs));
    match mover.move_shard(shard, &to)? {
        Some(r) => println!("{}", crate::mover::report_line(&r)),
        None => println!(
            "{} is on {to} already (any unfinished step is done)",
            args.shard
        ),
    }
    Ok(())
}

fn run_rebalance(args: &RebalanceArgs) -> Result<()> {
    crate::logging::init_logging();
    let dir = std::fs::canonicalize(&args.data_dir)
        .with_context(|| format!("--data-dir {}", args.data_dir.display()))?;
    let started = std::time::Instant::now();
    let reports = crate::mover::rebalance(
        &dir,
        usize::from(args.replicas),
        args.freeze_lease_ms,
        std::time::Duration::from_secs(args.call_timeout_secs),
    )?;
    let mut pauses: Vec<f64> = reports
        .iter()
        .map(|r| r.pause.as_secs_f64() * 1e3)
        .collect();
    pauses.sort_by(f64::total_cmp);
    let pct = |q: f64| {
        pauses
            .get(((pauses.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(0.0)
    };
    println!(
        "rebalanced to {} replicas: {} shards moved, {} sessions, in {:.1} s; pause per shard p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        args.replicas,
        reports.len(),
        reports.iter().map(|r| r.sessions).sum::<usize>(),
        started.elapsed().as_secs_f64(),
        pct(0.5),
        pct(0.99),
        pauses.last().copied().unwrap_or(0.0)
    );
    Ok(())
}

fn run_status(args: &StatusArgs) -> Result<()> {
    let dir = std::fs::canonicalize(&args.data_dir)
        .with_context(|| format!("--data-dir {}", args.data_dir.display()))?;
    let st = crate::mover::status(&dir)?;
    let mut out = format!(
        "shard map epoch {} ({}): {} replicas\n",
        st.map.epoch(),
        dir.join(crate::local::MAP_FILE).display(),
        st.map.replicas().len()
    );
    for (name, listing) in &st.replicas {
        match listing {
            Ok(l) => {
                let owned = l.shards.iter().filter(|s| s.state == "owned").count();
                let sessions: usize = l.shards.iter().map(|s| s.sessions).sum();
                out.push_str(&format!(
                    "  {name:<10} epoch {:<5} owns {owned:>4} shards, {sessions} sessions in memory\n",
                    l.epoch
                ));
            }
            Err(e) => out.push_str(&format!("  {name:<10} not answering: {e}\n")),
        }
    }
    if st.findings.is_empty() {
        out.push_str("every shard is served by its map's owner; none is frozen or half-moved\n");
    } else {
        for (shard, f) in &st.findings {
            out.push_str(&format!("  {} {f}\n", mcapi_shards::shard_key(*shard)));
        }
    }
    print!("{out}");
    // A script (or a readiness probe) reads the exit status: 0 only when
    // every replica answered and every shard is plainly served.
    let silent = st.replicas.iter().filter(|(_, l)| l.is_err()).count();
    if silent > 0 || !st.findings.is_empty() {
        bail!(
            "{} shard(s) frozen, half-moved, importing or not released, {silent} replica(s) not \
             answering (listed above)",
            st.findings.len()
        );
    }
    Ok(())
}

fn read_map(path: &Path) -> Result<ShardMap> {
    ShardMap::read(path).with_context(|| format!("shard map {}", path.display()))
}

fn run_plan(args: &PlanArgs) -> Result<()> {
    let names: Vec<ReplicaName> = if args.names.is_empty() {
        let n = args.replicas.unwrap_or(0);
        if n == 0 || n > mcapi_shards::map::MAX_REPLICAS {
            bail!(
                "--replicas must be between 1 and {}",
                mcapi_shards::map::MAX_REPLICAS
            );
        }
        ordinal_names(&args.prefix, n).map_err(anyhow::Error::msg)?
    } else {
        args.names
            .iter()
            .map(|n| ReplicaName::parse(n.trim()))
            .collect::<Result<_, _>>()
            .map_err(anyhow::Error::msg)?
    };
    let from = args.from.as_deref().map(read_map).transpose()?;
    let p = plan::plan(&names, from.as_ref())?;
    let text = p.map.to_text();
    match &args.out {
        Some(path) => write_atomic(path, &text)?,
        None => print!("{text}"),
    }
    let counts = p.map.counts();
    let min = counts.iter().map(|(_, c)| *c).min().unwrap_or(0);
    let max = counts.iter().map(|(_, c)| *c).max().unwrap_or(0);
    eprintln!(
        "epoch {}: {} replicas, {min}-{max} shards each",
        p.map.epoch(),
        counts.len()
    );
    if let Some(old) = &from {
        let mut to: Vec<(ReplicaName, usize)> = Vec::new();
        for m in &p.moved {
            match to.iter_mut().find(|(r, _)| *r == m.to) {
                Some((_, c)) => *c += 1,
                None => to.push((m.to.clone(), 1)),
            }
        }
        let to: Vec<String> = to.iter().map(|(r, c)| format!("{c} to {r}")).collect();
        eprintln!(
            "from epoch {}: {} of 1024 shards move ({:.1}%){}{}",
            old.epoch(),
            p.moved.len(),
            100.0 * p.moved.len() as f64 / 1024.0,
            if to.is_empty() { "" } else { ": " },
            to.join(", ")
        );
    }
    Ok(())
}

fn run_haproxy(args: &HaproxyArgs) -> Result<()> {
    let map = read_map(&args.map)?;
    let mut backends: Vec<Backend> = args
        .backends
        .iter()
        .map(|b| Backend::parse(b))
        .collect::<Result<_, _>>()
        .map_err(anyhow::Error::msg)?;
    if let Some(t) = &args.backend_template {
        let (rest, grpc) = t
            .split_once(',')
            .context("--backend-template: expected REST_TEMPLATE,GRPC_TEMPLATE")?;
        for r in map.replicas() {
            if !backends.iter().any(|b| &b.replica == r) {
                backends.push(Backend::from_templates(r, rest, grpc).map_err(anyhow::Error::msg)?);
            }
        }
    }
    std::fs::create_dir_all(&args.out_dir)
        .with_context(|| format!("creating {}", args.out_dir.display()))?;
    let out_dir = std::fs::canonicalize(&args.out_dir)?;
    let spec = RouterSpec {
        rest_bind: args.rest_bind.clone(),
        grpc_bind: args.grpc_bind.clone(),
        map_path: args
            .map_path
            .clone()
            .unwrap_or_else(|| out_dir.join("shards.map")),
        stats_socket: args
            .stats_socket
            .clone()
            .unwrap_or_else(|| out_dir.join("admin.sock")),
        admin_bind: args.admin_bind.clone(),
        backends,
        resolvers: args.resolvers,
        spare: Vec::new(),
        expose_listeners: false,
    };
    write_router(&out_dir, &map, &spec)?;
    if let Some(name) = &args.configmap {
        let label = |what: &str, v: &str| {
            ReplicaName::parse(v).map_err(|e| anyhow::anyhow!("--{what}: {e}"))
        };
        let name = label("configmap", name)?;
        let namespace = args
            .namespace
            .as_deref()
            .map(|n| label("namespace", n))
            .transpose()?;
        let yaml = haproxy::configmap(&map, &spec, &name, namespace.as_ref())
            .map_err(anyhow::Error::msg)?;
        write_atomic(&out_dir.join(format!("{name}.yaml")), &yaml)?;
        eprintln!("wrote {}/{name}.yaml", out_dir.display());
    }
    eprintln!(
        "wrote {0}/haproxy.cfg and {0}/shards.map (epoch {1}, {2} replicas); run: haproxy -f {0}/haproxy.cfg",
        out_dir.display(),
        map.epoch(),
        map.replicas().len()
    );
    Ok(())
}
