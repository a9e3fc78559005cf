//! HAProxy (2.6, Debian's `haproxy`) as the router (docs/cluster.md):
//! `mcapi cluster haproxy-config` writes `haproxy.cfg` and the HAProxy map
//! file `shards.map` from a shard map; [`set_owner`] flips one shard live
//! through the Runtime API (`set map` on the stats socket), with no reload,
//! and [`add_backend`] puts a joining replica behind the running router
//! (`add server` into backends declared spare), with no restart either.
//!
//! - REST: the shard is the first five characters of the fourth path field
//!   (`/v1/sessions/s03a7.01JD…/observations`, `/v1/groups/s03a7.g01JD…/steps`:
//!   a group's id carries its members' shard); the owner comes from the map
//!   file; `POST /v1/sessions`, `GET /v1/sessions` and `POST /v1/groups`
//!   have no shard and go round-robin over every replica.
//! - gRPC: h2 on both sides; the shard comes from the `x-mcapi-session`
//!   metadata; calls without it (`CreateSession`, `ListSessions`) go
//!   round-robin.
//! - Health: every server is checked with `GET /readyz` on its REST port
//!   (HTTP/1.1), so a replica still recovering takes no creates.

use std::io::{Read, Write};
use std::net::SocketAddr;
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use mcapi_shards::{ReplicaName, SHARDS, ShardMap, shard_key};

/// Where one replica listens.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Backend {
    /// The replica.
    pub replica: ReplicaName,
    /// Its REST address (`host:port`).
    pub rest: String,
    /// Its gRPC address (`host:port`).
    pub grpc: String,
}

impl Backend {
    /// Parses `NAME=REST_ADDR,GRPC_ADDR`, e.g.
    /// `mcapi-0=10.0.0.5:8080,10.0.0.5:50051`.
    pub fn parse(spec: &str) -> Result<Self, String> {
        let (name, addrs) = spec
            .split_once('=')
            .ok_or_else(|| format!("`{spec}`: expected NAME=REST_HOST:PORT,GRPC_HOST:PORT"))?;
        let (rest, grpc) = addrs
            .split_once(',')
            .ok_or_else(|| format!("`{spec}`: expected NAME=REST_HOST:PORT,GRPC_HOST:PORT"))?;
        Ok(Self {
            replica: ReplicaName::parse(name)?,
            rest: host_port(rest)?,
            grpc: host_port(grpc)?,
        })
    }

    /// The backend of `replica` from templates in which `{replica}` stands
    /// for its name, e.g. `{replica}.mcapi-headless:8080`.
    pub fn from_templates(replica: &ReplicaName, rest: &str, grpc: &str) -> Result<Self, String> {
        Ok(Self {
            replica: replica.clone(),
            rest: host_port(&rest.replace("{replica}", replica.as_str()))?,
            grpc: host_port(&grpc.replace("{replica}", replica.as_str()))?,
        })
    }
}

/// A `host:port` with a host of DNS characters (or an IPv4/bracketed IPv6
/// literal) and a port 1..65535: nothing that could break a config line.
fn host_port(s: &str) -> Result<String, String> {
    if let Ok(addr) = s.parse::<SocketAddr>() {
        return Ok(addr.to_string());
    }
    let (host, port) = s
        .rsplit_once(':')
        .ok_or_else(|| format!("`{s}`: expected HOST:PORT"))?;
    let port: u16 = port
        .parse()
        .ok()
        .filter(|p| *p > 0)
        .ok_or_else(|| format!("`{s}`: the port must be 1 to 65535"))?;
    let host_ok = !host.is_empty()
        && host.len() <= 253
        && host
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'.');
    if !host_ok {
        return Err(format!(
            "`{s}`: the host must be a DNS name or an IP address"
        ));
    }
    Ok(format!("{host}:{port}"))
}

/// How `haproxy-config` lays the router out.
#[derive(Debug, Clone)]
pub struct RouterSpec {
    /// The REST frontend's bind address, e.g. `:8080`.
    pub rest_bind: String,
    /// The gRPC frontend's bind address, e.g. `:50051`.
    pub grpc_bind: String,
    /// The HAProxy map file's path as HAProxy will see it (absolute).
    pub map_path: PathBuf,
    /// The Runtime API socket's path (absolute).
    pub stats_socket: PathBuf,
    /// The Runtime API on a TCP address as well (`host:port`), e.g.
    /// `127.0.0.1:9999` inside a pod, reached with `kubectl port-forward`.
    pub admin_bind: Option<String>,
    /// Every replica of the map, with its addresses.
    pub backends: Vec<Backend>,
    /// Resolve the backends' names at run time through the nameservers of
    /// /etc/resolv.conf (an HAProxy `resolvers` section), following a pod's
    /// address when it changes; a server has no address, and is down, until
    /// its name resolves. For Kubernetes pod names (`deploy/k8s/`).
    pub resolvers: bool,
    /// Replicas that may join later (`cluster local`'s `mcapi-k` up to its
    /// most): each gets its two backends, empty, so that joining is a few
    /// Runtime API commands ([`add_backend`]) and never a restart or a
    /// reload of HAProxy. HAProxy 2.6 can add a server to a backend at run
    /// time but not a backend, and `use_backend` finds a replica's backend
    /// by name, so the backends must exist from the start.
    pub spare: Vec<ReplicaName>,
    /// Let a new HAProxy process take the listening sockets over from the
    /// old one (`expose-fd listeners` on the Runtime API socket, for a
    /// master-worker reload). Only for measuring a reload against the
    /// Runtime API (`cluster local --router-update reload`).
    pub expose_listeners: bool,
}

/// The `resolvers` section of a router that follows DNS names.
const RESOLVERS: &str = "\nresolvers dns\n\
  \x20 # The nameservers of the router's own /etc/resolv.conf (cluster DNS in\n\
  \x20 # Kubernetes); names must be fully qualified: HAProxy does not search.\n\
  \x20 parse-resolv-conf\n\
  \x20 resolve_retries 3\n\
  \x20 timeout resolve 1s\n\
  \x20 timeout retry 1s\n\
  \x20 hold valid 10s\n\
  \x20 hold nx 5s\n\
  \x20 hold obsolete 30s\n\
  \x20 accepted_payload_size 8192\n";

/// The HAProxy map file: `<shard> <replica>` per shard (the same lines as
/// the shard map, which HAProxy keys on), the epoch in a comment.
pub fn map_file(map: &ShardMap) -> String {
    let mut out = String::with_capacity(SHARDS * 16 + 64);
    out.push_str(&format!(
        "# mcapi shard map epoch {} for HAProxy (written by `mcapi cluster haproxy-config`)\n",
        map.epoch()
    ));
    for s in 0..SHARDS as u16 {
        out.push_str(&format!("{} {}\n", shard_key(s), map.owner(s)));
    }
    out
}

/// A Kubernetes ConfigMap (YAML) holding the router's files and the shard
/// map: `haproxy.cfg`, HAProxy's `shards.map`, and `mcapi-shards.map`, the
/// shard map the replicas read (`deploy/k8s/`). `name` and `namespace` must
/// be DNS labels (the caller checks them with [`ReplicaName::parse`]).
pub fn configmap(
    map: &ShardMap,
    spec: &RouterSpec,
    name: &ReplicaName,
    namespace: Option<&ReplicaName>,
) -> Result<String, String> {
    let cfg = config(map, spec)?;
    let block = |text: &str| {
        text.lines()
            .map(|l| {
                if l.is_empty() {
                    "\n".to_string()
                } else {
                    format!("    {l}\n")
                }
            })
            .collect::<String>()
    };
    let mut y = format!(
        "# The router's configuration and the shard map of an mcapi cluster, epoch {}.\n\
         # Written by `mcapi cluster haproxy-config --configmap`: regenerate, do not edit.\n\
         apiVersion: v1\n\
         kind: ConfigMap\n\
         metadata:\n\
         \x20 name: {name}\n",
        map.epoch()
    );
    if let Some(ns) = namespace {
        y.push_str(&format!("  namespace: {ns}\n"));
    }
    y.push_str(&format!(
        "  labels:\n\
         \x20   app.kubernetes.io/name: mcapi\n\
         \x20   app.kubernetes.io/component: shard-map\n\
         data:\n\
         \x20 haproxy.cfg: |\n{}\
         \x20 shards.map: |\n{}\
         \x20 mcapi-shards.map: |\n{}",
        block(&cfg),
        block(&map_file(map)),
        block(&map.to_text())
    ));
    Ok(y)
}

/// `haproxy.cfg` for a map. Every replica of the map needs a backend.
pub fn config(map: &ShardMap, spec: &RouterSpec) -> Result<String, String> {
    for r in map.replicas() {
        if !spec.backends.iter().any(|b| &b.replica == r) {
            return Err(format!(
                "replica `{r}` of the shard map has no address (--backend {r}=REST,GRPC or --backend-template)"
            ));
        }
    }
    for pair in [&spec.rest_bind, &spec.grpc_bind] {
        if pair.is_empty() || pair.bytes().any(|b| b.is_ascii_whitespace()) {
            return Err(format!(
                "bind address `{pair}`: must be non-empty, without spaces"
            ));
        }
    }
    let map_path = path_text(&spec.map_path)?;
    let socket = path_text(&spec.stats_socket)?;
    let (admin_tcp, flip_tcp) = match &spec.admin_bind {
        Some(a) => {
            let a = host_port(a)?;
            let (host, port) = a.rsplit_once(':').unwrap_or((a.as_str(), ""));
            (
                format!("  stats socket ipv4@{a} level admin\n"),
                format!("#   (or | nc -q1 {host} {port}, the same Runtime API over TCP)\n"),
            )
        }
        None => (String::new(), String::new()),
    };
    let found = format!("{{ var(txn.shard),map({map_path}) -m found }}");
    let mut c = String::new();
    c.push_str(&format!(
        "# HAProxy 2.6 router of an mcapi cluster, shard map epoch {epoch}.\n\
         # Written by `mcapi cluster haproxy-config`; flip a shard live with\n\
         #   echo 'set map {map_path} s03a7 <replica>' | socat stdio unix:{socket}\n\
         {flip_tcp}\
         # and write the same line into {map_path} (or into what it is made\n\
         # from, such as a Kubernetes ConfigMap) so a reload keeps it.\n\
         global\n\
         \x20 stats socket {socket} mode 600 level admin{expose}\n\
         {admin_tcp}\
         \x20 stats timeout 30s\n\
         \n\
         defaults\n\
         \x20 mode http\n\
         \x20 option http-keep-alive\n\
         \x20 timeout connect 2s\n\
         \x20 timeout http-request 10s\n\
         \x20 # Long enough for gRPC Interact and Watch streams.\n\
         \x20 timeout client 1h\n\
         \x20 timeout server 1h\n\
         \x20 timeout tunnel 1h\n\
         {resolvers}\
         \n\
         frontend fe_rest\n\
         \x20 bind {rest}\n\
         \x20 http-request set-var(txn.shard) path,field(4,/),field(1,.) if {{ path_beg /v1/sessions/ /v1/groups/ }}\n\
         \x20 use_backend be_rest_%[var(txn.shard),map({map_path})] if {found}\n\
         \x20 # Creates and listings: no shard, round-robin.\n\
         \x20 default_backend be_rest_any\n\
         \n\
         frontend fe_grpc\n\
         \x20 bind {grpc} proto h2\n\
         \x20 http-request set-var(txn.shard) req.hdr(x-mcapi-session),field(1,.)\n\
         \x20 use_backend be_grpc_%[var(txn.shard),map({map_path})] if {found}\n\
         \x20 default_backend be_grpc_any\n",
        epoch = map.epoch(),
        rest = spec.rest_bind,
        grpc = spec.grpc_bind,
        resolvers = if spec.resolvers { RESOLVERS } else { "" },
        expose = if spec.expose_listeners {
            " expose-fd listeners"
        } else {
            ""
        },
    ));
    // The map's replicas, then any other backend (a replica joining the
    // cluster, owning no shard yet), by name.
    let mut backends: Vec<&Backend> = map
        .replicas()
        .iter()
        .filter_map(|r| spec.backends.iter().find(|b| &b.replica == r))
        .collect();
    let mut joining: Vec<&Backend> = spec
        .backends
        .iter()
        .filter(|b| !map.has_replica(&b.replica))
        .collect();
    joining.sort_by(|a, b| a.replica.cmp(&b.replica));
    backends.extend(joining);
    let check = "option httpchk GET /readyz\n  default-server inter 2s fall 2 rise 1\n";
    let dns = if spec.resolvers {
        " resolvers dns init-addr none"
    } else {
        ""
    };
    let rest_server = |b: &Backend| format!("  server {}{dns}\n", rest_server_args(b));
    let grpc_server = |b: &Backend| format!("  server {}{dns}\n", grpc_server_args(b));
    for b in &backends {
        c.push_str(&format!(
            "\nbackend be_rest_{}\n  {check}{}",
            b.replica,
            rest_server(b)
        ));
        c.push_str(&format!(
            "\nbackend be_grpc_{}\n  {check}{}",
            b.replica,
            grpc_server(b)
        ));
    }
    // Empty until the replica joins ([`add_backend`]); a spare name that
    // is also a backend above is not declared twice.
    let mut spare: Vec<&ReplicaName> = spec
        .spare
        .iter()
        .filter(|r| !backends.iter().any(|b| &b.replica == *r))
        .collect();
    spare.sort();
    spare.dedup();
    for r in spare {
        c.push_str(&format!(
            "\nbackend be_rest_{r}\n  {check}\nbackend be_grpc_{r}\n  {check}"
        ));
    }
    c.push_str(&format!(
        "\nbackend be_rest_any\n  balance roundrobin\n  {check}"
    ));
    for b in &backends {
        c.push_str(&rest_server(b));
    }
    c.push_str(&format!(
        "\nbackend be_grpc_any\n  balance roundrobin\n  {check}"
    ));
    for b in &backends {
        c.push_str(&grpc_server(b));
    }
    Ok(c)
}

/// A replica's REST server line after `server`: its name, address and check.
fn rest_server_args(b: &Backend) -> String {
    format!("{} {} check", b.replica, b.rest)
}

/// A replica's gRPC server line after `server`: h2, checked on the
/// replica's REST port over HTTP/1.1 (at the REST host if it differs).
fn grpc_server_args(b: &Backend) -> String {
    let (host, port) = b.rest.rsplit_once(':').unwrap_or((b.rest.as_str(), "0"));
    let same_host = b.grpc.rsplit_once(':').map(|(h, _)| h) == Some(host);
    let addr = if same_host {
        String::new()
    } else {
        format!(
            " addr {}",
            host.trim_start_matches('[').trim_end_matches(']')
        )
    };
    format!(
        "{} {} proto h2 check{addr} port {port} check-proto h1",
        b.replica, b.grpc
    )
}

fn path_text(p: &Path) -> Result<String, String> {
    let s = p
        .to_str()
        .ok_or_else(|| format!("{}: not UTF-8", p.display()))?;
    if !p.is_absolute() || s.bytes().any(|b| b.is_ascii_whitespace() || b == b'#') {
        return Err(format!(
            "{s}: HAProxy needs an absolute path without spaces or `#`"
        ));
    }
    Ok(s.to_string())
}

/// `haproxy` from PATH. Debian installs it in /usr/sbin, which a user's
/// PATH may lack: that and /usr/local/sbin are looked at too.
pub fn find_haproxy() -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .chain(["/usr/sbin".into(), "/usr/local/sbin".into()])
        .map(|d| d.join("haproxy"))
        .find(|p| p.is_file())
}

/// Sends one command to HAProxy's Runtime API and returns its answer.
pub fn runtime_command(socket: &Path, command: &str) -> std::io::Result<String> {
    let mut stream = UnixStream::connect(socket)?;
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    stream.set_write_timeout(Some(Duration::from_secs(5)))?;
    stream.write_all(command.as_bytes())?;
    stream.write_all(b"\n")?;
    let mut answer = String::new();
    // The answer is short; HAProxy closes the connection after it.
    stream.take(1 << 20).read_to_string(&mut answer)?;
    Ok(answer)
}

/// Points one shard at a new owner in the running router, live
/// (`set map`); HAProxy answers nothing on success.
pub fn set_owner(
    socket: &Path,
    map_path: &Path,
    shard: u16,
    owner: &ReplicaName,
) -> std::io::Result<()> {
    let command = format!(
        "set map {} {} {}",
        map_path.display(),
        shard_key(shard),
        owner
    );
    let answer = runtime_command(socket, &command)?;
    if answer.trim().is_empty() {
        Ok(())
    } else {
        Err(std::io::Error::other(format!(
            "HAProxy refused `{command}`: {}",
            answer.trim()
        )))
    }
}

/// The check settings of the configuration's `default-server`, which a
/// server added at run time does not inherit.
const DYNAMIC_CHECK: &str = "inter 2s fall 2 rise 1";

/// Puts a joining replica behind the running router, live: its servers in
/// its own two (spare) backends and in the round-robin ones, then their
/// health checks and traffic enabled. HAProxy is neither restarted nor
/// reloaded, so no connection of a client is touched (a restart cut every
/// connection and refused new ones until the new process listened). A
/// server HAProxy already has (it was restarted with a configuration
/// naming the replica) is left as it is. The caller also writes the
/// configuration naming the replica, so that a restarted HAProxy keeps it.
pub fn add_backend(socket: &Path, b: &Backend) -> std::io::Result<()> {
    let r = &b.replica;
    let (rest, grpc) = (rest_server_args(b), grpc_server_args(b));
    let servers = server_slots(r)
        .into_iter()
        .zip([&rest, &grpc, &rest, &grpc]);
    let mut added = Vec::new();
    for (backend, args) in servers {
        // `args` starts with the server's name.
        let command = format!("add server {backend}/{args} {DYNAMIC_CHECK}");
        let answer = runtime_command(socket, &command)?;
        let answer = answer.trim();
        if answer.starts_with("New server registered") {
            added.push(backend);
        } else if !answer.starts_with("Already exists a server") {
            return Err(std::io::Error::other(format!(
                "HAProxy refused `{command}`: {answer}"
            )));
        }
    }
    // A server added at run time starts in maintenance, its check off.
    for backend in added {
        for command in [
            format!("enable health {backend}/{r}"),
            format!("enable server {backend}/{r}"),
        ] {
            let answer = runtime_command(socket, &command)?;
            if !answer.trim().is_empty() {
                return Err(std::io::Error::other(format!(
                    "HAProxy refused `{command}`: {}",
                    answer.trim()
                )));
            }
        }
    }
    Ok(())
}

/// The backends a replica's servers live in: its own two, then the
/// round-robin ones.
fn server_slots(r: &ReplicaName) -> [String; 4] {
    [
        format!("be_rest_{r}"),
        format!("be_grpc_{r}"),
        "be_rest_any".to_string(),
        "be_grpc_any".to_string(),
    ]
}

/// Sends `command` and fails unless HAProxy answers nothing (its answer to
/// a command that succeeded) or one of `fine` (prefixes of answers that
/// mean "already so").
fn runtime_quiet(socket: &Path, command: &str, fine: &[&str]) -> std::io::Result<()> {
    let answer = runtime_command(socket, command)?;
    let answer = answer.trim();
    if answer.is_empty() || fine.iter().any(|f| answer.starts_with(f)) {
        Ok(())
    } else {
        Err(std::io::Error::other(format!(
            "HAProxy refused `{command}`: {answer}"
        )))
    }
}

/// First half of taking a leaving replica from behind the running router:
/// its servers go to maintenance, so HAProxy sends them nothing new while
/// the requests already sent finish. The replica is then stopped (it
/// drains what it accepted), and [`remove_backend`] deletes the servers.
/// A server HAProxy does not have is skipped.
pub fn drain_backend(socket: &Path, r: &ReplicaName) -> std::io::Result<()> {
    for backend in server_slots(r) {
        runtime_quiet(
            socket,
            &format!("set server {backend}/{r} state maint"),
            &["No such server"],
        )?;
    }
    Ok(())
}

/// Second half: deletes the leaving replica's servers from the running
/// router (its two own backends stay, empty, as a spare name's do, ready
/// for [`add_backend`] if it joins again). HAProxy deletes a server only
/// once it holds no connection, so this retries for up to `patience` after
/// closing any left (the replica has stopped by now, so none carries a
/// request). No restart or reload: no client connection is touched.
pub fn remove_backend(socket: &Path, r: &ReplicaName, patience: Duration) -> std::io::Result<()> {
    let deadline = std::time::Instant::now() + patience;
    for backend in server_slots(r) {
        let server = format!("{backend}/{r}");
        runtime_quiet(
            socket,
            &format!("set server {server} state maint"),
            &["No such server"],
        )?;
        runtime_quiet(
            socket,
            &format!("shutdown sessions server {server}"),
            &["No such server"],
        )?;
        loop {
            let command = format!("del server {server}");
            let answer = runtime_command(socket, &command)?;
            let answer = answer.trim();
            if answer.starts_with("Server deleted") || answer.starts_with("No such server") {
                break;
            }
            if std::time::Instant::now() >= deadline {
                return Err(std::io::Error::other(format!(
                    "HAProxy refused `{command}` for {} s: {answer}",
                    patience.as_secs()
                )));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
    Ok(())
}

/// Writes `haproxy.cfg` and the HAProxy map file `shards.map` into
/// `out_dir` (`haproxy-config`, and `cluster local` on every start).
pub(crate) fn write_router(
    out_dir: &std::path::Path,
    map: &ShardMap,
    spec: &RouterSpec,
) -> anyhow::Result<()> {
    let cfg = config(map, spec).map_err(anyhow::Error::msg)?;
    crate::files::write_atomic(&out_dir.join("shards.map"), &map_file(map))?;
    crate::files::write_atomic(&out_dir.join("haproxy.cfg"), &cfg)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use mcapi_shards::plan::{ordinal_names, plan};

    #[test]
    fn backends_parse_and_refuse_junk() {
        let b = Backend::parse("mcapi-0=127.0.0.1:8080,127.0.0.1:50051").expect("parses");
        assert_eq!(b.rest, "127.0.0.1:8080");
        let t = Backend::from_templates(&b.replica, "{replica}.svc:8080", "{replica}.svc:50051")
            .expect("template");
        assert_eq!(t.grpc, "mcapi-0.svc:50051");
        for bad in [
            "mcapi-0",
            "mcapi-0=a:1",
            "mcapi-0=a:0,b:1",
            "mcapi-0=a b:1,b:2",
            "mcapi-0=a:1,b\n:2",
            "BAD=a:1,b:2",
        ] {
            assert!(Backend::parse(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn the_config_routes_every_replica() {
        let names = ordinal_names("mcapi", 2).expect("names");
        let map = plan(&names, None).expect("plan").map;
        let mut spec = RouterSpec {
            rest_bind: "127.0.0.1:18080".into(),
            grpc_bind: "127.0.0.1:18443".into(),
            map_path: "/tmp/x/shards.map".into(),
            stats_socket: "/tmp/x/admin.sock".into(),
            admin_bind: None,
            backends: vec![Backend::parse("mcapi-0=127.0.0.1:1,127.0.0.2:2").expect("b")],
            resolvers: false,
            spare: Vec::new(),
            expose_listeners: false,
        };
        let e = config(&map, &spec).expect_err("mcapi-1 has no address");
        assert!(e.contains("mcapi-1"), "{e}");
        spec.backends
            .push(Backend::parse("mcapi-1=127.0.0.1:3,127.0.0.1:4").expect("b"));
        let cfg = config(&map, &spec).expect("config");
        for want in [
            "backend be_rest_mcapi-0",
            "backend be_grpc_mcapi-1",
            "server mcapi-1 127.0.0.1:4 proto h2 check port 3 check-proto h1\n",
            "bind 127.0.0.1:18443 proto h2",
            "req.hdr(x-mcapi-session),field(1,.)",
            "map(/tmp/x/shards.map)",
            "stats socket /tmp/x/admin.sock",
            "balance roundrobin",
        ] {
            assert!(cfg.contains(want), "missing {want:?}");
        }
        let file = map_file(&map);
        assert_eq!(file.lines().count(), SHARDS + 1);
        assert!(file.contains(&format!("s03ff {}", map.owner(0x3ff))));
        assert!(
            cfg.contains(
                "server mcapi-0 127.0.0.2:2 proto h2 check addr 127.0.0.1 port 1 check-proto h1\n"
            ),
            "a gRPC address on another host than REST: checked at the REST host"
        );
        assert!(!cfg.contains("resolvers"));

        // Spare names: their two backends, empty, for `add server` later;
        // a spare name that is a replica already is not declared twice.
        spec.spare = ["mcapi-5", "mcapi-1"]
            .map(|n| ReplicaName::parse(n).expect("name"))
            .to_vec();
        let cfg = config(&map, &spec).expect("config");
        assert!(
            cfg.contains("\nbackend be_rest_mcapi-5\n  option httpchk GET /readyz\n"),
            "{cfg}"
        );
        assert!(cfg.contains("\nbackend be_grpc_mcapi-5\n"), "{cfg}");
        assert!(!cfg.contains("server mcapi-5"), "{cfg}");
        assert_eq!(cfg.matches("\nbackend be_rest_mcapi-1\n").count(), 1);
        spec.spare.clear();

        // Kubernetes: names followed through DNS, and the ConfigMap.
        spec.resolvers = true;
        spec.admin_bind = Some("127.0.0.1:9999".into());
        spec.backends = map
            .replicas()
            .iter()
            .map(|r| {
                Backend::from_templates(r, "{replica}.h.ns.svc:8080", "{replica}.h.ns.svc:50051")
            })
            .collect::<Result<_, _>>()
            .expect("templates");
        let cfg = config(&map, &spec).expect("config");
        assert!(cfg.contains("\nresolvers dns\n  # "), "{cfg}");
        assert!(
            cfg.contains("  stats socket ipv4@127.0.0.1:9999 level admin\n"),
            "{cfg}"
        );
        assert!(cfg.contains("| nc -q1 127.0.0.1 9999,"), "{cfg}");
        assert!(cfg.contains(
            "server mcapi-1 mcapi-1.h.ns.svc:50051 proto h2 check port 8080 check-proto h1 resolvers dns init-addr none\n"
        ));
        assert!(
            cfg.contains(
                "server mcapi-0 mcapi-0.h.ns.svc:8080 check resolvers dns init-addr none\n"
            )
        );
        let name = ReplicaName::parse("mcapi-router").expect("name");
        let ns = ReplicaName::parse("mcapi").expect("ns");
        let y = configmap(&map, &spec, &name, Some(&ns)).expect("configmap");
        assert!(
            y.contains("\nkind: ConfigMap\nmetadata:\n  name: mcapi-router\n  namespace: mcapi\n"),
            "{y}"
        );
        assert!(
            y.contains("\n  haproxy.cfg: |\n    # HAProxy 2.6 router"),
            "{y}"
        );
        assert!(
            y.contains("\n  mcapi-shards.map: |\n    # mcapi shard map"),
            "{y}"
        );
        assert!(
            y.contains(&format!("\n    epoch 1\n    s0000 {}\n", map.owner(0))),
            "{y}"
        );
        // Every line of the data is indented under its key: nothing escapes the block.
        let data = y.split_once("\ndata:\n").expect("data").1;
        for line in data.lines().filter(|l| !l.is_empty()) {
            assert!(
                line.starts_with("    ") || line.ends_with(": |"),
                "{line:?}"
            );
        }

        spec.map_path = "relative.map".into();
        assert!(config(&map, &spec).is_err());
    }
}
