//! Network namespaces for the partition test ([`super::partitions`]): one
//! namespace per member (the test's client and the supervisor, the mover,
//! the router, each replica), each with one address on a bridge in a hub
//! namespace, so that every link can be cut alone by iptables rules
//! inside the namespaces. Nothing is added to the host's own interfaces:
//! each veth pair is made in the hub with its other end created straight
//! into its member's namespace.
//!
//! Names carry the test's pid and a random tag (`mcapi-pt-<pid>-<tag>-<role>`),
//! so parallel runs do not collide and a run killed before it cleaned up
//! is recognised (its pid is gone) and removed by the next one. [`Net`]
//! removes its namespaces when dropped, killing first any process still
//! in them, also when the test fails.

use std::net::Ipv4Addr;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

/// The prefix of every namespace this test makes.
const PREFIX: &str = "mcapi-pt-";
/// The members' subnet, a /24 on the hub's bridge (private to the namespaces).
const SUBNET: [u8; 3] = [10, 213, 0];

/// Where namespaces named by `ip netns` live.
fn netns_dir() -> PathBuf {
    ["/run/netns", "/var/run/netns"]
        .iter()
        .map(PathBuf::from)
        .find(|d| d.is_dir())
        .unwrap_or_else(|| PathBuf::from("/run/netns"))
}

fn ip(args: &[&str]) -> Result<(), String> {
    run("ip", args)
}

fn run(program: &str, args: &[&str]) -> Result<(), String> {
    let out = Command::new(program)
        .args(args)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("{program}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{program} {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

/// `program args` inside namespace `ns` (`ip netns exec`).
pub(super) fn exec_in(ns: &str, program: &str, args: &[&str]) -> Output {
    Command::new("ip")
        .args(["netns", "exec", ns, program])
        .args(args)
        .stdin(Stdio::null())
        .output()
        .expect("ip netns exec runs")
}

/// Deletes a namespace, killing the processes still in it first (never
/// this test process, whose threads may have entered it).
fn delete(ns: &str) {
    if let Ok(out) = Command::new("ip").args(["netns", "pids", ns]).output() {
        let me = std::process::id();
        for pid in String::from_utf8_lossy(&out.stdout)
            .split_whitespace()
            .filter_map(|p| p.parse::<i32>().ok())
            .filter(|&p| p > 1 && p as u32 != me)
        {
            // SAFETY: kill(2) with plain integers, on a process of this
            // test's own namespace.
            unsafe {
                libc::kill(pid, libc::SIGKILL);
            }
        }
    }
    let _ = ip(&["netns", "delete", ns]);
}

/// Whether this machine lets the test make namespaces and cut links in
/// them: root, `ip netns`, iptables with the `string` and `recent`
/// matches. `Err` says what is missing.
pub(super) fn usable() -> Result<(), String> {
    // SAFETY: geteuid(2) takes nothing and cannot fail.
    if unsafe { libc::geteuid() } != 0 {
        return Err("not root (network namespaces and iptables need it)".into());
    }
    run("ip", &["-V"]).map_err(|e| format!("no iproute2 `ip`: {e}"))?;
    let probe = format!("{PREFIX}{}-{}-probe", std::process::id(), tag());
    ip(&["netns", "add", &probe]).map_err(|e| format!("`ip netns add` fails: {e}"))?;
    let rule = exec_in(
        &probe,
        "iptables",
        &[
            "-w",
            "-A",
            "OUTPUT",
            "-p",
            "tcp",
            "-d",
            "10.213.0.1",
            "-m",
            "string",
            "--algo",
            "bm",
            "--string",
            "probe",
            "-m",
            "recent",
            "--set",
            "--name",
            "probe",
            "--rsource",
        ],
    );
    delete(&probe);
    if !rule.status.success() {
        return Err(format!(
            "iptables in a namespace fails (missing, or without the string and recent matches): {}",
            String::from_utf8_lossy(&rule.stderr).trim()
        ));
    }
    Ok(())
}

/// Four hex digits from the clock: with the pid, a name no other run has.
fn tag() -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    format!("{:04x}", (nanos >> 10) & 0xffff)
}

/// Removes the namespaces of earlier runs whose process is gone.
pub(super) fn remove_stale() {
    let Ok(entries) = std::fs::read_dir(netns_dir()) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(rest) = name.strip_prefix(PREFIX) else {
            continue;
        };
        let pid = rest.split('-').next().and_then(|p| p.parse::<u32>().ok());
        if let Some(pid) = pid
            && pid != std::process::id()
            && !Path::new(&format!("/proc/{pid}")).exists()
        {
            delete(&name);
        }
    }
}

/// One member of the network: its namespace and address.
#[derive(Debug, Clone)]
pub(super) struct Member {
    pub(super) role: String,
    pub(super) ns: String,
    pub(super) ip: Ipv4Addr,
}

/// The namespaces of one run, linked through a bridge in a hub namespace;
/// every one of them deleted when dropped.
pub(super) struct Net {
    hub: String,
    members: Vec<Member>,
    /// Every namespace made so far (a failed setup cleans up what it made).
    made: Vec<String>,
}

impl Drop for Net {
    fn drop(&mut self) {
        for ns in self.made.iter().rev() {
            delete(ns);
        }
    }
}

impl Net {
    /// Makes the hub and one namespace per `(role, last octet)`.
    pub(super) fn create(members: &[(&str, u8)]) -> Self {
        let base = format!("{PREFIX}{}-{}", std::process::id(), tag());
        let hub = format!("{base}-hub");
        let mut net = Self {
            hub: hub.clone(),
            members: Vec::new(),
            made: Vec::new(),
        };
        let must = |r: Result<(), String>| r.unwrap_or_else(|e| panic!("network setup: {e}"));
        must(ip(&["netns", "add", &hub]));
        net.made.push(hub.clone());
        must(ip(&["-n", &hub, "link", "set", "lo", "up"]));
        must(ip(&["-n", &hub, "link", "add", "br0", "type", "bridge"]));
        must(ip(&["-n", &hub, "link", "set", "br0", "up"]));
        for (k, (role, octet)) in members.iter().enumerate() {
            let ns = format!("{base}-{role}");
            must(ip(&["netns", "add", &ns]));
            net.made.push(ns.clone());
            let port = format!("v{k}");
            must(ip(&[
                "-n", &hub, "link", "add", &port, "type", "veth", "peer", "name", "eth0", "netns",
                &ns,
            ]));
            must(ip(&["-n", &hub, "link", "set", &port, "master", "br0"]));
            must(ip(&["-n", &hub, "link", "set", &port, "up"]));
            let addr = Ipv4Addr::new(SUBNET[0], SUBNET[1], SUBNET[2], *octet);
            must(ip(&[
                "-n",
                &ns,
                "addr",
                "add",
                &format!("{addr}/24"),
                "dev",
                "eth0",
            ]));
            must(ip(&["-n", &ns, "link", "set", "eth0", "up"]));
            must(ip(&["-n", &ns, "link", "set", "lo", "up"]));
            net.members.push(Member {
                role: role.to_string(),
                ns,
                ip: addr,
            });
        }
        net
    }

    pub(super) fn member(&self, role: &str) -> &Member {
        self.members
            .iter()
            .find(|m| m.role == role)
            .unwrap_or_else(|| panic!("no member {role}"))
    }

    /// Runs this thread's code in `role`'s namespace from now on: sockets
    /// it opens, threads and processes it starts are there.
    pub(super) fn enter(&self, role: &str) {
        let path = netns_dir().join(&self.member(role).ns);
        let file = std::fs::File::open(&path).expect("the namespace's file");
        // SAFETY: setns(2) on a file descriptor held open for the call;
        // it changes this thread's network namespace only.
        let rc = unsafe { libc::setns(file.as_raw_fd(), libc::CLONE_NEWNET) };
        assert_eq!(rc, 0, "setns: {}", std::io::Error::last_os_error());
    }

    fn iptables(&self, role: &str, rule: &[&str]) {
        let ns = &self.member(role).ns;
        let mut args = vec!["-w"];
        args.extend_from_slice(rule);
        let out = exec_in(ns, "iptables", &args);
        assert!(
            out.status.success(),
            "iptables {} in {ns}: {}",
            rule.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
    }

    /// Packets from `a` to `b` vanish: dropped as they leave `a` and as
    /// they reach `b`. The other direction still flows.
    pub(super) fn cut_one_way(&self, a: &str, b: &str) {
        let (ia, ib) = (self.member(a).ip.to_string(), self.member(b).ip.to_string());
        self.iptables(a, &["-I", "OUTPUT", "-d", &ib, "-j", "DROP"]);
        self.iptables(b, &["-I", "INPUT", "-s", &ia, "-j", "DROP"]);
    }

    /// The link between `a` and `b` is cut both ways.
    pub(super) fn cut(&self, a: &str, b: &str) {
        self.cut_one_way(a, b);
        self.cut_one_way(b, a);
    }

    /// From the moment `role` sends a TCP segment carrying `text` to
    /// `trigger`, `role`'s new connections to `victim` vanish (their SYNs
    /// are dropped): the link goes down at a chosen step of a protocol
    /// without the test racing it. Connections already open (the one that
    /// carried `text`) still finish.
    pub(super) fn cut_after(&self, role: &str, trigger: &str, text: &str, victim: &str) {
        let (it, iv) = (
            self.member(trigger).ip.to_string(),
            self.member(victim).ip.to_string(),
        );
        self.iptables(
            role,
            &[
                "-A",
                "OUTPUT",
                "-p",
                "tcp",
                "-d",
                &iv,
                "--syn",
                "-m",
                "recent",
                "--rcheck",
                "--name",
                "cut",
                "--rsource",
                "-j",
                "DROP",
            ],
        );
        self.iptables(
            role,
            &[
                "-A",
                "OUTPUT",
                "-p",
                "tcp",
                "-d",
                &it,
                "-m",
                "string",
                "--algo",
                "bm",
                "--string",
                text,
                "-m",
                "recent",
                "--set",
                "--name",
                "cut",
                "--rsource",
            ],
        );
    }

    /// From the moment `role` sends a TCP segment carrying `text` to
    /// `peer`, every packet from `peer` to `role` vanishes: the answer to
    /// that request is lost, and so is everything after it.
    pub(super) fn cut_answers_after(&self, role: &str, peer: &str, text: &str) {
        let ip = self.member(peer).ip.to_string();
        self.iptables(
            role,
            &[
                "-A", "INPUT", "-s", &ip, "-m", "recent", "--rcheck", "--name", "cut", "--rdest",
                "-j", "DROP",
            ],
        );
        self.iptables(
            role,
            &[
                "-A",
                "OUTPUT",
                "-p",
                "tcp",
                "-d",
                &ip,
                "-m",
                "string",
                "--algo",
                "bm",
                "--string",
                text,
                "-m",
                "recent",
                "--set",
                "--name",
                "cut",
                "--rsource",
            ],
        );
    }

    /// Every link heals: every rule of every member goes (and the
    /// triggers' memory with them).
    pub(super) fn heal(&self) {
        for m in &self.members {
            self.iptables(&m.role, &["-F", "INPUT"]);
            self.iptables(&m.role, &["-F", "OUTPUT"]);
            // The `recent` list outlives a flush; a rule that sets it anew
            // starts it empty again only once removed, so it is cleared.
            let list = Path::new("/proc/net/xt_recent/cut");
            let _ = exec_in(
                &m.ns,
                "sh",
                &[
                    "-c",
                    &format!("[ -e {0} ] && echo / > {0} || true", list.display()),
                ],
            );
        }
    }

    /// The namespace of `role`, for `ip netns exec`.
    pub(super) fn ns(&self, role: &str) -> &str {
        &self.member(role).ns
    }

    /// Every namespace's name, the hub's first (for messages).
    pub(super) fn names(&self) -> Vec<&str> {
        std::iter::once(self.hub.as_str())
            .chain(self.members.iter().map(|m| m.ns.as_str()))
            .collect()
    }
}
