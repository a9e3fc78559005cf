//! The mover: `mcapi cluster move` and `mcapi cluster rebalance` on a
//! running `mcapi cluster local` (docs/cluster.md, "How a shard moves").
//! It drives the replicas' admin routes (mcapi-server's `api::admin`, over HTTP) step by step,
//! relaying the shard's data from the source to the target itself (the
//! replicas never call each other), writes the shard map file (the commit
//! point of a move) and flips HAProxy's map through its Runtime API.
//!
//! A move that fails before the map file is written is undone: the source
//! is thawed (it serves the shard again) and the target's copy deleted.
//! One that fails after it is finished by running the same `move` again
//! (the map then already names the target: the remaining steps are done).
//! One mover at a time per data directory (`move.lock`, flock).

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};

use mcapi_shards::moves::{Manifest, ShardData, ShardStatus};
use mcapi_shards::{ReplicaName, ShardMap, shard_key};

use crate::files::write_atomic;
use crate::haproxy;
use crate::local::{ADMIN_KEY_FILE, MAP_FILE, STATE_FILE, State};

/// Longest answer read from a replica (a shard's data).
const MAX_ANSWER_BYTES: usize = 1 << 30;
/// Time allowed for one admin call.
const CALL_TIMEOUT: Duration = Duration::from_secs(120);

/// One admin call's answer: status and body.
struct Answer {
    status: u16,
    body: Vec<u8>,
}

impl Answer {
    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body[..self.body.len().min(2048)]).into_owned()
    }
}

/// A plain HTTP/1.1 call with `Connection: close` (no client crate: the
/// replicas are on loopback and each call is one request).
fn http_call(addr: &str, method: &str, path: &str, key: &str, body: &[u8]) -> Result<Answer> {
    let sock = addr
        .to_socket_addrs()?
        .next()
        .ok_or_else(|| anyhow!("cannot resolve {addr}"))?;
    let mut stream = TcpStream::connect_timeout(&sock, Duration::from_secs(5))
        .with_context(|| format!("connecting to {addr}"))?;
    stream.set_read_timeout(Some(CALL_TIMEOUT))?;
    stream.set_write_timeout(Some(CALL_TIMEOUT))?;
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {key}\r\n\
         Content-Type: application/octet-stream\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes())?;
    stream.write_all(body)?;
    let mut raw = Vec::new();
    stream
        .take(MAX_ANSWER_BYTES as u64 + 64 * 1024)
        .read_to_end(&mut raw)
        .with_context(|| format!("reading the answer of {method} {path} from {addr}"))?;
    let end = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or_else(|| anyhow!("{addr} answered {method} {path} without a complete head"))?;
    let head = String::from_utf8_lossy(&raw[..end]).into_owned();
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse::<u16>().ok())
        .ok_or_else(|| anyhow!("{addr}: no status line"))?;
    let mut body = raw.split_off(end + 4);
    let chunked = head.lines().any(|l| {
        let l = l.to_ascii_lowercase();
        l.starts_with("transfer-encoding:") && l.contains("chunked")
    });
    if chunked {
        body = dechunk(&body).ok_or_else(|| anyhow!("{addr}: a malformed chunked body"))?;
    }
    Ok(Answer { status, body })
}

fn dechunk(mut raw: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let eol = raw.windows(2).position(|w| w == b"\r\n")?;
        let size_text = std::str::from_utf8(&raw[..eol]).ok()?;
        let size = usize::from_str_radix(size_text.split(';').next()?.trim(), 16).ok()?;
        raw = &raw[eol + 2..];
        if size == 0 {
            return Some(out);
        }
        out.extend_from_slice(raw.get(..size)?);
        raw = raw.get(size + 2..)?;
    }
}

/// What a move measured.
#[derive(Debug, Clone)]
pub struct MoveReport {
    /// The shard.
    pub shard: u16,
    /// Its old owner.
    pub from: ReplicaName,
    /// Its new owner.
    pub to: ReplicaName,
    /// Sessions moved.
    pub sessions: usize,
    /// Sessions (whole or tails) and deletions sent after the freeze.
    pub delta: usize,
    /// From the freeze until the router sends the shard to its new owner:
    /// what a client of the shard waits at most.
    pub pause: Duration,
    /// The whole move.
    pub total: Duration,
    /// The map's epoch after it.
    pub epoch: u64,
}

/// A running local cluster as the mover sees it.
pub struct Mover {
    dir: PathBuf,
    key: String,
    replicas: BTreeMap<String, String>,
    socket: PathBuf,
    router_map: PathBuf,
    _lock: std::fs::File,
}

impl Mover {
    /// Reads the running cluster of `dir` (its `cluster.json`, admin key
    /// and map) and takes the move lock.
    pub fn open(dir: &Path) -> Result<Self> {
        let state = read_state(dir)?;
        let key = std::fs::read_to_string(dir.join(ADMIN_KEY_FILE))
            .with_context(|| format!("reading {}", dir.join(ADMIN_KEY_FILE).display()))?
            .trim()
            .to_string();
        let lock_path = dir.join("move.lock");
        let lock = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&lock_path)
            .with_context(|| format!("opening {}", lock_path.display()))?;
        // SAFETY: flock on a file descriptor this function owns.
        let locked = unsafe { libc::flock(lock.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if locked != 0 {
            bail!(
                "another `mcapi cluster move` or `rebalance` runs on {} (it holds {})",
                dir.display(),
                lock_path.display()
            );
        }
        let mut mover = Self {
            dir: dir.to_path_buf(),
            key,
            replicas: BTreeMap::new(),
            socket: state.admin_socket.clone(),
            router_map: dir.join("router").join("shards.map"),
            _lock: lock,
        };
        mover.refresh(&state);
        Ok(mover)
    }

    fn refresh(&mut self, state: &State) {
        self.replicas = state
            .processes
            .iter()
            .filter_map(|p| p.http.clone().map(|h| (p.name.clone(), h)))
            .collect();
    }

    /// The map in force.
    pub fn map(&self) -> Result<ShardMap> {
        let path = self.dir.join(MAP_FILE);
        ShardMap::read(&path).with_context(|| format!("shard map {}", path.display()))
    }

    fn addr(&self, replica: &ReplicaName) -> Result<&str> {
        self.replicas
            .get(replica.as_str())
            .map(String::as_str)
            .ok_or_else(|| {
                anyhow!("replica `{replica}` does not run in this cluster (see cluster.json)")
            })
    }

    fn call(
        &self,
        replica: &ReplicaName,
        method: &str,
        path: &str,
        body: &[u8],
    ) -> Result<Vec<u8>> {
        let addr = self.addr(replica)?;
        let a = http_call(addr, method, path, &self.key, body)
            .with_context(|| format!("{method} {path} on {replica}"))?;
        if a.status != 200 {
            bail!("{method} {path} on {replica}: {} {}", a.status, a.text());
        }
        Ok(a.body)
    }

    fn status(&self, replica: &ReplicaName, shard: u16) -> Result<ShardStatus> {
        let body = self.call(
            replica,
            "GET",
            &format!("/admin/shards/{}", shard_key(shard)),
            &[],
        )?;
        serde_json::from_slice(&body).context("a shard status that is not JSON")
    }

    /// Moves one shard to `to`, live. Already there: finishes what a
    /// failed earlier move left (activation, router, release), if anything.
    pub fn move_shard(&self, shard: u16, to: &ReplicaName) -> Result<Option<MoveReport>> {
        let started = Instant::now();
        let map = self.map()?;
        let from = map.owner(shard).clone();
        let key = shard_key(shard);
        if &from == to {
            return self.finish(shard, to, &map, None).map(|_| None);
        }
        self.addr(to)?;
        self.addr(&from)?;
        tracing::info!(shard = %key, %from, %to, "moving");
        let base = format!("/admin/shards/{key}");
        // 1-2: the snapshot, made durable on the target.
        let snapshot = self.call(&from, "POST", &format!("{base}/export"), &[])?;
        let data: ShardData =
            postcard::from_bytes(&snapshot).context("the snapshot does not decode")?;
        let undo = |e: anyhow::Error| -> anyhow::Error {
            let thaw = self.call(&from, "POST", &format!("{base}/thaw"), &[]);
            let abort = self.call(to, "POST", &format!("{base}/abort"), &[]);
            tracing::warn!(shard = %key, error = %format!("{e:#}"), thawed = thaw.is_ok(), aborted = abort.is_ok(), "move undone: the source serves the shard");
            e.context(format!(
                "moving {key} from {from} to {to} failed; undone (source thawed: {}, target's copy deleted: {})",
                thaw.is_ok(),
                abort.is_ok()
            ))
        };
        self.call(to, "POST", &format!("{base}/import?begin=true"), &snapshot)
            .map_err(undo)?;
        let manifest = data.manifest(&Manifest::default());
        drop(data);
        // 3: frozen; nothing changes the shard from here on.
        let frozen_at = Instant::now();
        let frozen: ShardStatus = self
            .call(&from, "POST", &format!("{base}/freeze"), &[])
            .and_then(|b| serde_json::from_slice(&b).context("a freeze answer that is not JSON"))
            .map_err(undo)?;
        // 4: the delta, made durable on the target.
        let manifest_bytes = postcard::to_allocvec(&manifest).map_err(|e| undo(e.into()))?;
        let delta = self
            .call(&from, "POST", &format!("{base}/export"), &manifest_bytes)
            .map_err(undo)?;
        let delta_data: ShardData = postcard::from_bytes(&delta)
            .context("the delta does not decode")
            .map_err(undo)?;
        let delta_n = delta_data.sessions.len() + delta_data.deleted.len();
        let sessions = delta_data.manifest(&manifest).sessions.len();
        drop(delta_data);
        self.call(to, "POST", &format!("{base}/import?begin=false"), &delta)
            .map_err(undo)?;
        // The source must still be the process that froze the shard: one
        // restarted since serves the shard unfrozen from its map.
        let now = self.status(&from, shard).map_err(undo)?;
        if now.boot != frozen.boot || now.state != "frozen" {
            return Err(undo(anyhow!(
                "{from} restarted or thawed the shard during the move ({})",
                now.state
            )));
        }
        // 5: the commit point.
        let epoch = map.epoch() + 1;
        let next = map.with_owner(shard, to, epoch)?;
        write_atomic(&self.dir.join(MAP_FILE), &next.to_text()).map_err(undo)?;
        // 6-7: served by the target, routed there, dropped at the source.
        let pause = self.finish(shard, to, &next, Some(frozen_at))?;
        let report = MoveReport {
            shard,
            from,
            to: to.clone(),
            sessions,
            delta: delta_n,
            pause,
            total: started.elapsed(),
            epoch,
        };
        tracing::info!(
            shard = %key,
            from = %report.from,
            to = %report.to,
            sessions = report.sessions,
            delta = report.delta,
            pause_ms = pause.as_secs_f64() * 1e3,
            total_ms = report.total.as_secs_f64() * 1e3,
            epoch,
            "shard moved"
        );
        Ok(Some(report))
    }

    /// Steps 6 and 7 of a move whose map file already names `to`: each is
    /// done only if still needed, so a rerun finishes a broken move.
    /// Returns the time from `frozen_at` to the router's flip.
    fn finish(
        &self,
        shard: u16,
        to: &ReplicaName,
        map: &ShardMap,
        frozen_at: Option<Instant>,
    ) -> Result<Duration> {
        let key = shard_key(shard);
        let base = format!("/admin/shards/{key}");
        let epoch = map.epoch();
        let target = self.status(to, shard)?;
        if target.state == "importing" {
            self.call(to, "POST", &format!("{base}/activate?epoch={epoch}"), &[])?;
        } else if target.state != "owned" {
            bail!(
                "{key}: the map names {to} but it has the shard {} (a move to it never reached the commit point)",
                target.state
            );
        }
        haproxy::set_owner(&self.socket, &self.router_map, shard, to)
            .with_context(|| format!("flipping {key} to {to} in HAProxy"))?;
        let pause = frozen_at.map(|t| t.elapsed()).unwrap_or_default();
        write_atomic(&self.router_map, &haproxy::map_file(map))?;
        for (name, _) in self.replicas.clone() {
            let Ok(replica) = ReplicaName::parse(&name) else {
                continue;
            };
            if &replica == to {
                continue;
            }
            let Ok(st) = self.status(&replica, shard) else {
                continue;
            };
            // A frozen source, or leftovers of the shard in a store.
            if st.state == "frozen" || st.state == "foreign" {
                self.call(
                    &replica,
                    "POST",
                    &format!("{base}/release?epoch={epoch}&owner={to}"),
                    &[],
                )?;
            }
        }
        Ok(pause)
    }
}

fn read_state(dir: &Path) -> Result<State> {
    let path = dir.join(STATE_FILE);
    let text = std::fs::read_to_string(&path).with_context(|| {
        format!(
            "reading {}: is `mcapi cluster local --data-dir {}` running?",
            path.display(),
            dir.display()
        )
    })?;
    serde_json::from_str(&text)
        .with_context(|| format!("{} is not a cluster state", path.display()))
}

/// Prints a move's report line (a CLI).
pub fn report_line(r: &MoveReport) -> String {
    format!(
        "{} {} -> {}: {} sessions, delta {}, pause {:.1} ms, total {:.1} ms, epoch {}",
        shard_key(r.shard),
        r.from,
        r.to,
        r.sessions,
        r.delta,
        r.pause.as_secs_f64() * 1e3,
        r.total.as_secs_f64() * 1e3,
        r.epoch
    )
}

/// `mcapi cluster rebalance`: asks the supervisor for `n` replicas, waits
/// until it runs them behind the router, then moves every shard the plan
/// gives to another replica, one at a time.
pub fn rebalance(dir: &Path, n: usize) -> Result<Vec<MoveReport>> {
    let state = read_state(dir)?;
    let running = state.replicas;
    if n < running {
        bail!(
            "the cluster runs {running} replicas; rebalance adds replicas, it does not remove them (asked for {n})"
        );
    }
    if n > running {
        write_atomic(
            &dir.join(crate::local::REQUEST_FILE),
            &format!("{{\"replicas\": {n}}}\n"),
        )?;
        let pid = i32::try_from(state.supervisor).context("a supervisor pid")?;
        // SAFETY: a signal to the supervisor's pid, read from its state file.
        if unsafe { libc::kill(pid, libc::SIGHUP) } != 0 {
            bail!("cannot signal the supervisor (pid {pid}): is it running?");
        }
        let deadline = Instant::now() + Duration::from_secs(180);
        loop {
            std::thread::sleep(Duration::from_millis(100));
            if let Ok(s) = read_state(dir)
                && s.replicas >= n
            {
                break;
            }
            if Instant::now() >= deadline {
                bail!("the supervisor did not start {n} replicas within 180 s (see its log)");
            }
        }
    }
    let mut mover = Mover::open(dir)?;
    mover.refresh(&read_state(dir)?);
    let map = mover.map()?;
    let names = mcapi_shards::plan::ordinal_names("mcapi", n).map_err(anyhow::Error::msg)?;
    let planned = mcapi_shards::plan::plan(&names, Some(&map))?.map;
    let mut reports = Vec::new();
    for shard in 0..mcapi_shards::SHARDS as u16 {
        let to = planned.owner(shard);
        if map.owner(shard) != to {
            if let Some(r) = mover.move_shard(shard, to)? {
                eprintln!("{}", report_line(&r));
                reports.push(r);
            }
        }
    }
    Ok(reports)
}
