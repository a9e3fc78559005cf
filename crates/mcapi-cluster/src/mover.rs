//! The mover: `mcapi cluster move` and `mcapi cluster rebalance` on a
//! running `mcapi cluster local` (docs/cluster.md, "How a shard moves").
//! It drives the replicas' admin routes (mcapi-server's `api::admin`, over HTTP) step by step,
//! relaying the shard's data from the source to the target itself (the
//! replicas never call each other), writes the shard map file (the commit
//! point of a move) and flips HAProxy's map through its Runtime API.
//!
//! The commit point is the source's `commit`: it gives the shard to the
//! target at the next epoch only while the freeze's lease runs (a source
//! whose lease expired serves the shard again and refuses it); the map file
//! is written right after. A move that fails before the commit is undone:
//! the source is thawed (it serves the shard again; had the mover died, the
//! lease would thaw it) and the target's copy deleted. One that fails after
//! it is finished by running `move` or `rebalance` again: the map names the
//! target, or the source says it gave the shard away, and the remaining
//! steps are done. One mover at a time per data directory (`move.lock`,
//! flock).

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};

use mcapi_shards::moves::{Manifest, ReplicaShards, ShardData, ShardStatus};
use mcapi_shards::{ReplicaName, ShardMap, shard_key};

use crate::files::write_atomic;
use crate::haproxy;
use crate::local::{ADMIN_KEY_FILE, MAP_FILE, STATE_FILE, State};

/// Longest answer read from a replica (a shard's data).
const MAX_ANSWER_BYTES: usize = 1 << 30;
/// Time allowed for one admin call when `--call-timeout-secs` is not
/// given (s): a shard's data may take long to export or import.
pub const DEFAULT_CALL_TIMEOUT_SECS: u64 = 120;

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
fn http_call(
    addr: &str,
    method: &str,
    path: &str,
    key: &str,
    body: &[u8],
    timeout: Duration,
) -> Result<Answer> {
    let sock = addr
        .to_socket_addrs()?
        .next()
        .ok_or_else(|| anyhow!("cannot resolve {addr}"))?;
    let mut stream = TcpStream::connect_timeout(&sock, Duration::from_secs(5))
        .with_context(|| format!("connecting to {addr}"))?;
    stream.set_read_timeout(Some(timeout))?;
    stream.set_write_timeout(Some(timeout))?;
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

/// A freeze's lease when `--freeze-lease-ms` is not given (ms), the
/// replicas' own default.
pub const DEFAULT_LEASE_MS: u64 = 30_000;

/// A running local cluster as the mover sees it.
pub struct Mover {
    dir: PathBuf,
    key: String,
    replicas: BTreeMap<String, String>,
    socket: PathBuf,
    router_map: PathBuf,
    /// The lease of each freeze (ms).
    lease_ms: u64,
    /// Time allowed for one admin call.
    call_timeout: Duration,
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
            lease_ms: DEFAULT_LEASE_MS,
            call_timeout: Duration::from_secs(DEFAULT_CALL_TIMEOUT_SECS),
            _lock: lock,
        };
        mover.refresh(&state);
        Ok(mover)
    }

    /// The lease each freeze of this mover asks for (ms; the replicas
    /// refuse one outside 100 to 600000).
    pub fn set_lease_ms(&mut self, ms: u64) {
        self.lease_ms = ms;
    }

    /// The time each admin call of this mover may take before it counts
    /// as unanswered.
    pub fn set_call_timeout(&mut self, timeout: Duration) {
        self.call_timeout = timeout;
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
        let a = http_call(addr, method, path, &self.key, body, self.call_timeout)
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

    /// Every shard of a replica (`GET /admin/shards`).
    fn all_shards(&self, replica: &ReplicaName) -> Result<ReplicaShards> {
        let body = self.call(replica, "GET", "/admin/shards", &[])?;
        serde_json::from_slice(&body).context("a shard listing that is not JSON")
    }

    /// A move whose source committed (it gave the shard to `owner` at an
    /// epoch above the map's) but whose mover died before writing the map
    /// file: writes it and finishes. `None` when `from` did not commit.
    fn finish_committed(
        &self,
        shard: u16,
        from: &ReplicaName,
        map: &ShardMap,
    ) -> Result<Option<ReplicaName>> {
        let st = self.status(from, shard)?;
        if st.state != "foreign" || st.owner == from.as_str() || st.epoch <= map.epoch() {
            return Ok(None);
        }
        let owner = ReplicaName::parse(&st.owner).map_err(anyhow::Error::msg)?;
        let epoch = map.epoch() + 1;
        if st.epoch != epoch {
            bail!(
                "{}: {from} gave the shard to {owner} at epoch {}, but the map is at epoch {}:                  the map file changed since; fix it by hand",
                shard_key(shard),
                st.epoch,
                map.epoch()
            );
        }
        tracing::warn!(shard = %shard_key(shard), %from, to = %owner, epoch, "a move past its commit point: writing the map and finishing it");
        let next = map.with_owner(shard, &owner, epoch)?;
        write_atomic(&self.dir.join(MAP_FILE), &next.to_text())?;
        self.finish(shard, &owner, &next, None)?;
        Ok(Some(owner))
    }

    /// Moves one shard to `to`, live. Already there: finishes what a
    /// failed earlier move left (activation, router, release), if anything.
    pub fn move_shard(&self, shard: u16, to: &ReplicaName) -> Result<Option<MoveReport>> {
        let started = Instant::now();
        let mut map = self.map()?;
        let mut from = map.owner(shard).clone();
        let key = shard_key(shard);
        if &from != to
            && self.addr(&from).is_ok()
            && self.finish_committed(shard, &from, &map)?.is_some()
        {
            map = self.map()?;
            from = map.owner(shard).clone();
        }
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
            .call(
                &from,
                "POST",
                &format!("{base}/freeze?lease_ms={}", self.lease_ms),
                &[],
            )
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
        // 5: the commit point. The source gives the shard away only if
        // the freeze is still its own (same process, same token) and its
        // lease has not run out: otherwise it may have served requests the
        // target does not have, and the move is undone.
        let token = frozen
            .freeze_token
            .ok_or_else(|| undo(anyhow!("{from} answered the freeze without a token")))?;
        let epoch = map.epoch() + 1;
        let commit = format!("{base}/commit?epoch={epoch}&owner={to}&token={token}");
        if let Err(e) = self.call(&from, "POST", &commit, &[]) {
            self.after_unanswered_commit(shard, &from, to, epoch, e)?;
        }
        // From here on the move is finished by a rerun, never undone.
        let next = map.with_owner(shard, to, epoch)?;
        write_atomic(&self.dir.join(MAP_FILE), &next.to_text()).with_context(|| {
            format!("{key} is committed to {to} but the map was not written: run the move again")
        })?;
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

    /// A commit that failed without a refusal may still have been made:
    /// its answer can be lost after the source committed. The source is
    /// asked; `Ok` if it committed (the move goes on), else the error. The
    /// move is undone only if the source says it did not commit, and the
    /// target's copy deleted only once no commit of this freeze can land
    /// any more (the source thawed, or serving the shard again after its
    /// lease); if the source cannot be asked, nothing is touched, for a
    /// rerun to settle (`move`, or `rebalance`, which finishes a commit
    /// or thaws by the lease's end).
    fn after_unanswered_commit(
        &self,
        shard: u16,
        from: &ReplicaName,
        to: &ReplicaName,
        epoch: u64,
        e: anyhow::Error,
    ) -> Result<()> {
        let key = shard_key(shard);
        let base = format!("/admin/shards/{key}");
        match self.status(from, shard) {
            Ok(st) if st.state == "foreign" && st.owner == to.as_str() && st.epoch == epoch => {
                tracing::warn!(shard = %key, %from, %to, epoch, error = %format!("{e:#}"), "the commit's answer was lost, but the source committed: the move goes on");
                Ok(())
            }
            Ok(st) if st.state == "frozen" || st.state == "owned" => {
                let thawed = st.state == "owned"
                    || self
                        .call(from, "POST", &format!("{base}/thaw"), &[])
                        .is_ok();
                let aborted =
                    thawed && self.call(to, "POST", &format!("{base}/abort"), &[]).is_ok();
                tracing::warn!(shard = %key, error = %format!("{e:#}"), thawed, aborted, "move undone: the source did not commit");
                Err(e.context(format!(
                    "moving {key} from {from} to {to} failed at its commit, which {from} did not make; \
                     undone (source thawed: {thawed}, target's copy deleted: {aborted})"
                )))
            }
            Ok(st) => Err(e.context(format!(
                "moving {key} from {from} to {to}: the commit failed and {from} has the shard {} \
                 (owner {}, epoch {}); nothing undone: see `mcapi cluster status`",
                st.state, st.owner, st.epoch
            ))),
            Err(asking) => {
                tracing::warn!(shard = %key, %from, error = %format!("{e:#}"), asking = %format!("{asking:#}"), "the commit's outcome is unknown: nothing undone");
                Err(e.context(format!(
                    "moving {key} from {from} to {to}: the commit got no answer and {from} cannot \
                     be asked whether it made it ({asking:#}); nothing undone: run the move (or \
                     `rebalance`) again once {from} answers"
                )))
            }
        }
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
            // The committed source, or leftovers of the shard in a store.
            // Never a frozen replica: only its commit, which checks the
            // freeze's lease, may give the shard away.
            if st.state == "foreign" {
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

/// What a replica's listing says of a shard that is not plainly served
/// by the map's owner.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Finding {
    /// Frozen on `replica`, served again there in `lease_ms` at most.
    Frozen {
        /// The replica.
        replica: String,
        /// Lease left.
        lease_ms: Option<u64>,
    },
    /// `replica` gave the shard to `to` (the source's commit), but the map
    /// file still names `replica`: half-moved, past its commit point.
    Committed {
        /// The source.
        replica: String,
        /// The new owner.
        to: String,
    },
    /// The map names `replica`, which still imports it: half-moved, past
    /// its commit point (activation pending).
    Activating {
        /// The target.
        replica: String,
    },
    /// `replica` imports a shard the map does not give it: a move in
    /// progress or an undone one's leftover.
    Importing {
        /// The replica.
        replica: String,
    },
    /// `replica` no longer owns the shard but still holds its sessions in
    /// memory (the release step is pending).
    NotReleased {
        /// The replica.
        replica: String,
        /// Sessions still held.
        sessions: usize,
    },
}

impl std::fmt::Display for Finding {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Frozen { replica, lease_ms } => match lease_ms {
                Some(ms) => write!(f, "frozen on {replica}, its lease ends in {ms} ms"),
                None => write!(f, "frozen on {replica}, without a lease"),
            },
            Self::Committed { replica, to } => write!(
                f,
                "half-moved: {replica} gave it to {to} but the map still names {replica} (run `move` or `rebalance` again)"
            ),
            Self::Activating { replica } => write!(
                f,
                "half-moved: the map names {replica}, which has not activated it yet (run `move` or `rebalance` again)"
            ),
            Self::Importing { replica } => write!(f, "being imported by {replica}"),
            Self::NotReleased { replica, sessions } => write!(
                f,
                "{replica} no longer owns it but still holds {sessions} of its sessions (run `move` or `rebalance` again)"
            ),
        }
    }
}

/// What `mcapi cluster status` found: each replica's listing (or why it
/// did not answer) and the shards that are not plainly served.
pub struct ClusterStatus {
    /// The map file.
    pub map: ShardMap,
    /// Each replica's listing, or the error reaching it.
    pub replicas: Vec<(String, Result<ReplicaShards, String>)>,
    /// Shard by shard, what is not plain.
    pub findings: Vec<(u16, Finding)>,
}

/// Compares each replica's listing with the map file.
pub fn findings(map: &ShardMap, listings: &[&ReplicaShards]) -> Vec<(u16, Finding)> {
    let mut out = Vec::new();
    for l in listings {
        for (s, line) in (0..mcapi_shards::SHARDS as u16).zip(&l.shards) {
            let named = map.owner(s).as_str() == l.replica;
            let replica = l.replica.clone();
            let finding = match line.state.as_str() {
                "frozen" => Some(Finding::Frozen {
                    replica,
                    lease_ms: line.lease_ms,
                }),
                "importing" if named => Some(Finding::Activating { replica }),
                "importing" => Some(Finding::Importing { replica }),
                "foreign" if named && line.owner != l.replica => Some(Finding::Committed {
                    replica,
                    to: line.owner.clone(),
                }),
                "foreign" if line.sessions > 0 => Some(Finding::NotReleased {
                    replica,
                    sessions: line.sessions,
                }),
                _ => None,
            };
            if let Some(f) = finding {
                out.push((s, f));
            }
        }
    }
    out.sort_by_key(|(s, _)| *s);
    out
}

/// `mcapi cluster status`: asks every replica of the running cluster of
/// `dir` for its shards (no lock: it changes nothing).
pub fn status(dir: &Path) -> Result<ClusterStatus> {
    let state = read_state(dir)?;
    let key = std::fs::read_to_string(dir.join(ADMIN_KEY_FILE))
        .with_context(|| format!("reading {}", dir.join(ADMIN_KEY_FILE).display()))?
        .trim()
        .to_string();
    let path = dir.join(MAP_FILE);
    let map = ShardMap::read(&path).with_context(|| format!("shard map {}", path.display()))?;
    let mut replicas = Vec::new();
    for p in &state.processes {
        let Some(addr) = &p.http else { continue };
        let timeout = Duration::from_secs(DEFAULT_CALL_TIMEOUT_SECS);
        let listing = http_call(addr, "GET", "/admin/shards", &key, &[], timeout)
            .and_then(|a| {
                if a.status != 200 {
                    bail!("{} {}", a.status, a.text());
                }
                serde_json::from_slice::<ReplicaShards>(&a.body)
                    .context("a shard listing that is not JSON")
            })
            .map_err(|e| format!("{e:#}"));
        replicas.push((p.name.clone(), listing));
    }
    let listings: Vec<&ReplicaShards> = replicas
        .iter()
        .filter_map(|(_, l)| l.as_ref().ok())
        .collect();
    let findings = findings(&map, &listings);
    Ok(ClusterStatus {
        map,
        replicas,
        findings,
    })
}

impl Mover {
    /// Finishes or undoes what dead movers left, before a rebalance plans:
    /// a frozen shard is thawed (this mover holds the lock, so no move is
    /// running), a move past its commit point is finished, and an import
    /// the map does not give is deleted.
    pub fn repair(&self) -> Result<usize> {
        let mut listings = Vec::new();
        for name in self.replicas.keys() {
            let Ok(r) = ReplicaName::parse(name) else {
                continue;
            };
            match self.all_shards(&r) {
                Ok(l) => listings.push(l),
                Err(e) => {
                    tracing::warn!(replica = %r, error = %format!("{e:#}"), "no shard listing: not repaired");
                }
            }
        }
        let refs: Vec<&ReplicaShards> = listings.iter().collect();
        let map = self.map()?;
        let found = findings(&map, &refs);
        // An import that a source committed to is the shard's only
        // future: finished with that commit, never deleted (whichever of
        // the two findings comes first).
        let committed: Vec<(u16, String)> = found
            .iter()
            .filter_map(|(s, f)| match f {
                Finding::Committed { to, .. } => Some((*s, to.clone())),
                _ => None,
            })
            .collect();
        let mut repaired = 0;
        for (shard, finding) in found {
            let base = format!("/admin/shards/{}", shard_key(shard));
            let parse = |n: &str| ReplicaName::parse(n).map_err(anyhow::Error::msg);
            tracing::warn!(shard = %shard_key(shard), finding = %finding, "repairing");
            match &finding {
                Finding::Frozen { replica, .. } => {
                    self.call(&parse(replica)?, "POST", &format!("{base}/thaw"), &[])?;
                }
                Finding::Committed { replica, .. } => {
                    let map = self.map()?;
                    self.finish_committed(shard, &parse(replica)?, &map)?;
                }
                Finding::Activating { replica } | Finding::NotReleased { replica, .. } => {
                    let map = self.map()?;
                    let owner = map.owner(shard).clone();
                    if replica != owner.as_str() || matches!(finding, Finding::Activating { .. }) {
                        self.finish(shard, &owner, &map, None)?;
                    }
                }
                Finding::Importing { replica } => {
                    if committed.contains(&(shard, replica.clone())) {
                        continue;
                    }
                    self.call(&parse(replica)?, "POST", &format!("{base}/abort"), &[])?;
                }
            }
            repaired += 1;
        }
        Ok(repaired)
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

/// `mcapi cluster rebalance`: to grow, asks the supervisor for `n`
/// replicas and waits until it runs them behind the router; then moves
/// every shard the plan for `n` replicas gives to another replica, one at
/// a time; to shrink, then asks the supervisor to take the replicas beyond
/// `n`, which own nothing by now, out of the router and stop them. The
/// move lock is held throughout, so no other mover gives them a shard
/// meanwhile.
pub fn rebalance(
    dir: &Path,
    n: usize,
    lease_ms: u64,
    call_timeout: Duration,
) -> Result<Vec<MoveReport>> {
    let state = read_state(dir)?;
    let running = state.replicas;
    if n > running {
        ask_supervisor(dir, &state, n, "start")?;
    }
    let mut mover = Mover::open(dir)?;
    mover.refresh(&read_state(dir)?);
    mover.set_lease_ms(lease_ms);
    mover.set_call_timeout(call_timeout);
    let repaired = mover.repair()?;
    if repaired > 0 {
        eprintln!("repaired {repaired} shards that earlier moves left half done");
    }
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
    if n < running {
        // Every shard has left the replicas beyond n (a move that could not
        // finish stopped the rebalance above): only now may they stop.
        let map = mover.map()?;
        if let Some(r) = map.replicas().iter().find(|r| !names.contains(r)) {
            bail!(
                "{r} still owns {} shards after the moves; nothing was stopped (run rebalance again)",
                map.shards_of(r).len()
            );
        }
        ask_supervisor(dir, &read_state(dir)?, n, "stop")?;
    }
    Ok(reports)
}

/// Asks `cluster local`'s supervisor to run `n` replicas (its request
/// file, then SIGHUP) and waits until its state file says it does: new
/// replicas started and behind the router, or leaving ones out of the
/// router and stopped (`what` names which, for the error).
fn ask_supervisor(dir: &Path, state: &State, n: usize, what: &str) -> Result<()> {
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
            && s.replicas == n
        {
            return Ok(());
        }
        if Instant::now() >= deadline {
            bail!("the supervisor did not {what} replicas to run {n} within 180 s (see its log)");
        }
    }
}
