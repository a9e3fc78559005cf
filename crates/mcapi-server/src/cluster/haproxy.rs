//! HAProxy (2.6, Debian's `haproxy`) as the router (docs/cluster.md):
//! `mcapi cluster haproxy-config` writes `haproxy.cfg` and the HAProxy map
//! file `shards.map` from a shard map; [`set_owner`] flips one shard live
//! through the Runtime API (`set map` on the stats socket), with no reload.
//!
//! - REST: the shard is the first five characters of the fourth path field
//!   (`/v1/sessions/s03a7.01JD…/observations`); the owner comes from the map
//!   file; `POST /v1/sessions` and `GET /v1/sessions` have no shard and go
//!   round-robin over every replica.
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

use super::map::{ReplicaName, SHARDS, ShardMap, shard_key};

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
    /// Every replica of the map, with its addresses.
    pub backends: Vec<Backend>,
}

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
    let found = format!("{{ var(txn.shard),map({map_path}) -m found }}");
    let mut c = String::new();
    c.push_str(&format!(
        "# HAProxy 2.6 router of an mcapi cluster, shard map epoch {epoch}.\n\
         # Written by `mcapi cluster haproxy-config`; flip a shard live with\n\
         #   echo 'set map {map_path} s03a7 <replica>' | socat stdio unix:{socket}\n\
         # and write the same line into {map_path} so a reload keeps it.\n\
         global\n\
         \x20 stats socket {socket} mode 600 level admin\n\
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
         \n\
         frontend fe_rest\n\
         \x20 bind {rest}\n\
         \x20 http-request set-var(txn.shard) path,field(4,/),field(1,.) if {{ path_beg /v1/sessions/ }}\n\
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
    ));
    let backends: Vec<&Backend> = map
        .replicas()
        .iter()
        .filter_map(|r| spec.backends.iter().find(|b| &b.replica == r))
        .collect();
    let check = "option httpchk GET /readyz\n  default-server inter 2s fall 2 rise 1\n";
    let rest_server = |b: &Backend| format!("  server {} {} check\n", b.replica, b.rest);
    let grpc_server = |b: &Backend| {
        let (host, port) = b.rest.rsplit_once(':').unwrap_or((b.rest.as_str(), "0"));
        let host = host.trim_start_matches('[').trim_end_matches(']');
        format!(
            "  server {} {} proto h2 check addr {host} port {port} check-proto h1\n",
            b.replica, b.grpc
        )
    };
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cluster::plan::{ordinal_names, plan};

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
            backends: vec![Backend::parse("mcapi-0=127.0.0.1:1,127.0.0.1:2").expect("b")],
        };
        let e = config(&map, &spec).expect_err("mcapi-1 has no address");
        assert!(e.contains("mcapi-1"), "{e}");
        spec.backends
            .push(Backend::parse("mcapi-1=127.0.0.1:3,127.0.0.1:4").expect("b"));
        let cfg = config(&map, &spec).expect("config");
        for want in [
            "backend be_rest_mcapi-0",
            "backend be_grpc_mcapi-1",
            "server mcapi-1 127.0.0.1:4 proto h2 check addr 127.0.0.1 port 3 check-proto h1",
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
        spec.map_path = "relative.map".into();
        assert!(config(&map, &spec).is_err());
    }
}
