//! `cluster local --netns`: a replica or the router run in a network
//! namespace of its own (`ip netns exec NETNS ...`, which switches the
//! namespace and then executes the program in place, so the supervisor's
//! pid, signals and `PR_SET_PDEATHSIG` are the program's), a replica
//! listening on an address of that namespace instead of 127.0.0.1. With
//! the namespaces linked (veth pairs, a bridge), iptables rules inside them
//! cut one link at a time: the partition test does that
//! (`tests/integration/cluster/partitions.rs`).
//!
//! The namespaces and their links are the caller's: `cluster local` only
//! starts processes in them, and the supervisor (readiness probes), the
//! mover and clients must reach every address given.

use std::collections::BTreeMap;
use std::ffi::OsString;
use std::net::{IpAddr, Ipv4Addr};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

use mcapi_shards::ReplicaName;

use super::ROUTER;

/// Where a process runs.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Placement {
    netns: String,
    /// A replica's address in `netns`.
    ip: Option<IpAddr>,
}

/// Every `--netns` of a `cluster local`, checked: process name to
/// namespace (and a replica's address).
#[derive(Debug, Clone, Default)]
pub(super) struct Placements {
    /// The `ip` executable (iproute2), found when any `--netns` is given.
    ip: Option<PathBuf>,
    by_name: BTreeMap<String, Placement>,
}

impl Placements {
    /// Parses `NAME=NETNS@IP` (a replica) and `haproxy=NETNS` (the
    /// router); each namespace must exist (`ip netns add`).
    pub(super) fn parse(specs: &[String]) -> Result<Self> {
        let mut out = Self::default();
        for spec in specs {
            let (name, place) = spec.split_once('=').with_context(|| {
                format!("--netns `{spec}`: expected NAME=NETNS@IP or {ROUTER}=NETNS")
            })?;
            let (netns, ip) = match place.split_once('@') {
                Some((n, ip)) => {
                    let ip: IpAddr = ip.parse().with_context(|| {
                        format!("--netns `{spec}`: `{ip}` is not an IP address")
                    })?;
                    if ip.is_unspecified() {
                        bail!(
                            "--netns `{spec}`: {ip} cannot be dialled; give the replica's address in {n}"
                        );
                    }
                    (n, Some(ip))
                }
                None => (place, None),
            };
            if name == ROUTER {
                if ip.is_some() {
                    bail!(
                        "--netns `{spec}`: the router listens on --http and --grpc; give {ROUTER}=NETNS"
                    );
                }
            } else {
                ReplicaName::parse(name).map_err(|e| anyhow::anyhow!("--netns `{spec}`: {e}"))?;
                if ip.is_none() {
                    bail!(
                        "--netns `{spec}`: a replica in a namespace needs the address it listens on there: {name}={netns}@IP"
                    );
                }
            }
            let named_ok = !netns.is_empty()
                && netns.len() <= 200
                && netns
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_' || b == b'.')
                && !netns.starts_with('.');
            if !named_ok {
                bail!(
                    "--netns `{spec}`: `{netns}` is not a namespace name (letters, digits, `-`, `_`, `.`)"
                );
            }
            if !["/run/netns", "/var/run/netns"]
                .iter()
                .any(|d| Path::new(d).join(netns).exists())
            {
                bail!(
                    "--netns `{spec}`: no network namespace `{netns}` (make it with `ip netns add {netns}`)"
                );
            }
            let placement = Placement {
                netns: netns.to_string(),
                ip,
            };
            if out.by_name.insert(name.to_string(), placement).is_some() {
                bail!("--netns: `{name}` is placed twice");
            }
        }
        if !out.by_name.is_empty() {
            out.ip = Some(find_ip().context(
                "--netns needs iproute2's `ip` on PATH (or in /usr/sbin, /sbin, /bin): apt-get install iproute2",
            )?);
        }
        Ok(out)
    }

    /// Whether any `--netns` names `name`.
    pub(super) fn has(&self, name: &str) -> bool {
        self.by_name.contains_key(name)
    }

    /// The names placed, for checking them against the map.
    pub(super) fn names(&self) -> impl Iterator<Item = &str> {
        self.by_name.keys().map(String::as_str)
    }

    /// The address replica `name` listens on: its namespace's, else 127.0.0.1.
    pub(super) fn host(&self, name: &str) -> IpAddr {
        self.by_name
            .get(name)
            .and_then(|p| p.ip)
            .unwrap_or(IpAddr::V4(Ipv4Addr::LOCALHOST))
    }

    /// The program and arguments that run `program args` as process
    /// `name`: unchanged, or behind `ip netns exec NETNS`.
    pub(super) fn command(
        &self,
        name: &str,
        program: PathBuf,
        args: Vec<OsString>,
    ) -> (PathBuf, Vec<OsString>) {
        match (self.by_name.get(name), &self.ip) {
            (Some(p), Some(ip)) => {
                let mut wrapped: Vec<OsString> = vec![
                    "netns".into(),
                    "exec".into(),
                    p.netns.clone().into(),
                    program.into(),
                ];
                wrapped.extend(args);
                (ip.clone(), wrapped)
            }
            _ => (program, args),
        }
    }
}

/// `ip` from PATH, then the usual system directories.
fn find_ip() -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .chain([
            "/usr/sbin".into(),
            "/sbin".into(),
            "/usr/bin".into(),
            "/bin".into(),
        ])
        .map(|d| d.join("ip"))
        .find(|p| p.is_file())
}
