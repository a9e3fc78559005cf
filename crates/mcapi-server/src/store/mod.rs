//! The durable session store (docs/sessions.md, "Durability and recovery"):
//! per session, its creation record, its newest snapshot and the log of
//! observations since that snapshot, in the data directory.
//!
//! The store knows keys, sequence numbers and bytes, not what they mean: the
//! service encodes its records (`service::durable`). Writes go through one
//! writer thread that takes everything queued since its last commit as one
//! group (group commit), so many concurrent observations share one disk
//! sync. A caller learns that its write is durable by awaiting the
//! [`Commit`] it got back.
//!
//! Two files make one store:
//! - the **write-ahead log** (`wal/`, [`wal`]): a group commit is one frame
//!   appended to it, then one `fdatasync` ([`Durability::Sync`], the
//!   default) or none ([`Durability::Os`], synced in the background every
//!   [`OS_SYNC_INTERVAL`]);
//! - the **redb file** (`mcapi.redb`, layout in `db.rs`): sessions,
//!   snapshots and the log in chunks, brought up to date in bulk by the
//!   checkpointer thread (`checkpoint.rs`) about twice a second, after
//!   which the segments it applied are deleted. Opening the store applies
//!   whatever the log holds beyond the file's last checkpoint, so reads see
//!   every acknowledged write; a reader at run time first asks for a
//!   checkpoint of what it may need.
//!
//! A failed commit leaves a hole in the logs of the sessions it wrote to, so
//! from then on the store refuses their appends and snapshots
//! ([`StoreError::Broken`]) instead of writing after the hole, until the
//! service has reloaded the session from what is durable and sent
//! [`Write::Resume`]. Later records therefore never depend on lost ones. A
//! failed frame is cut off the log before anything else is written, so it
//! can never be read back.
//!
//! Storage faults are survived without a restart: after a failed append or
//! sync the writer refuses every write at once and retries with backoff
//! (cutting the log back to its last good frame and writing a probe file);
//! after a failed checkpoint the checkpointer reopens the database. While
//! either is down, [`Store::health`] says why.

mod checkpoint;
mod db;
pub mod wal;

use std::collections::HashSet;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender, unbounded};
use parking_lot::{Mutex, RwLock};
use redb::{Database, ReadableDatabase, ReadableTable};
use thiserror::Error;
use tokio::sync::oneshot;

use checkpoint::{Checkpointer, Frame, ToCheckpoint};
pub use db::{CHUNK, FORMAT_VERSION, RECORD_V2};
use db::{LOG, SESSIONS, SNAPSHOTS, log_key, split_entry};
pub use wal::Durability;
use wal::{AppendError, Wal};

/// Name of the redb file inside the data directory.
pub const FILE_NAME: &str = "mcapi.redb";

/// Default ceiling of the database's page cache (`--store-cache-mib`):
/// enough for the B-tree's interior pages of millions of sessions; the
/// snapshots and logs themselves are read once per recovery or load.
pub const DEFAULT_CACHE_BYTES: usize = 64 << 20;

/// Under [`Durability::Os`], how long a frame may stay unsynced.
pub const OS_SYNC_INTERVAL: Duration = Duration::from_millis(5);

/// Most writes folded into one group.
const MAX_GROUP: usize = 8192;

/// First wait before repairing the log or reopening the database after a
/// storage fault; doubled after every failed attempt up to [`MAX_BACKOFF`],
/// reset by a success.
const MIN_BACKOFF: Duration = Duration::from_millis(50);
/// Longest wait between two repair or reopening attempts.
const MAX_BACKOFF: Duration = Duration::from_secs(1);

/// When a failed part of the store (the log, the database) is tried again:
/// [`MIN_BACKOFF`] after the first failure, twice as long after every
/// failed attempt up to [`MAX_BACKOFF`], back to the start once the part
/// has done its work again.
#[derive(Debug)]
struct Retry {
    /// When to try next, while the part is down.
    at: Option<Instant>,
    /// The wait after the next failed attempt.
    backoff: Duration,
}

impl Retry {
    fn new() -> Self {
        Self {
            at: None,
            backoff: MIN_BACKOFF,
        }
    }

    /// When the next attempt is due, while the part is down.
    fn at(&self) -> Option<Instant> {
        self.at
    }

    fn is_due(&self, now: Instant) -> bool {
        self.at.is_some_and(|at| now >= at)
    }

    fn is_scheduled(&self) -> bool {
        self.at.is_some()
    }

    /// The part went down: an attempt is scheduled unless one already is.
    fn went_down(&mut self) {
        if self.at.is_none() {
            self.attempt_failed();
        }
    }

    /// An attempt failed: the next one is scheduled; the wait until it.
    fn attempt_failed(&mut self) -> Duration {
        let wait = self.backoff;
        self.at = Some(Instant::now() + wait);
        self.backoff = (wait * 2).min(MAX_BACKOFF);
        wait
    }

    /// The part is up again (the backoff stays until [`Self::worked`]).
    fn cleared(&mut self) {
        self.at = None;
    }

    /// The part did its work: the next failure waits [`MIN_BACKOFF`].
    fn worked(&mut self) {
        self.backoff = MIN_BACKOFF;
    }
}
/// The probe file's name in the data directory (written and removed).
const PROBE_FILE: &str = "probe.tmp";

/// What can go wrong with the store.
#[derive(Debug, Clone, Error)]
pub enum StoreError {
    /// The data directory or file cannot be used.
    #[error("{path}: {reason}")]
    Io {
        /// The path concerned.
        path: PathBuf,
        /// What failed.
        reason: String,
    },
    /// The file is damaged: truncated, overwritten, or a record that does
    /// not decode.
    #[error("the store {path} is corrupt: {reason}")]
    Corrupt {
        /// The damaged file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The file was written by an incompatible version of mcapi.
    #[error(
        "the store {path} has format version {found}; this mcapi reads version {FORMAT_VERSION}"
    )]
    Version {
        /// The store file.
        path: PathBuf,
        /// The version found.
        found: u64,
    },
    /// A read or write failed while running.
    #[error("store failure: {0}")]
    Failed(String),
    /// The store cannot write after a storage fault (a full or failing
    /// disk); it recovers automatically once the fault clears.
    #[error("the store is unavailable after a storage fault ({0}); it is reopened automatically")]
    Unavailable(String),
    /// An earlier write of this session failed; its writes are refused
    /// until it is reloaded ([`Write::Resume`]).
    #[error(
        "an earlier write of session `{0}` failed; its writes are refused until it is reloaded"
    )]
    Broken(Arc<str>),
    /// The store was closed.
    #[error("the store is closed")]
    Closed,
}

/// One write.
#[derive(Debug, Clone)]
pub enum Write {
    /// Creates (or replaces) a session's creation record.
    Session {
        /// Session id.
        id: Arc<str>,
        /// The encoded record.
        record: Vec<u8>,
    },
    /// Appends one observation record to a session's log.
    Append {
        /// Session id.
        id: Arc<str>,
        /// Sequence number (strictly increasing per session).
        seq: u64,
        /// The encoded observation.
        entry: Vec<u8>,
    },
    /// Replaces a session's snapshot and trims its log up to `seq`.
    Snapshot {
        /// Session id.
        id: Arc<str>,
        /// Sequence number of the last observation the snapshot covers.
        seq: u64,
        /// The encoded snapshot.
        snapshot: Vec<u8>,
    },
    /// Deletes a session's record, snapshot and log.
    Delete {
        /// Session id.
        id: Arc<str>,
    },
    /// Accepts a broken session's writes again: the service reloaded it
    /// from its durable state, so what follows continues that state.
    Resume {
        /// Session id.
        id: Arc<str>,
    },
}

impl Write {
    /// The session an append or snapshot extends (what a broken session
    /// may not get).
    fn extends(&self) -> Option<&Arc<str>> {
        match self {
            Self::Append { id, .. } | Self::Snapshot { id, .. } => Some(id),
            Self::Session { .. } | Self::Delete { .. } | Self::Resume { .. } => None,
        }
    }

    /// Whether the write is stored (a `Resume` only changes what the writer
    /// accepts).
    fn is_logged(&self) -> bool {
        !matches!(self, Self::Resume { .. })
    }

    /// Bytes it holds, roughly (what waiting for a checkpoint costs).
    fn size(&self) -> usize {
        match self {
            Self::Session { id, record } => id.len() + record.len(),
            Self::Append { id, entry, .. } => id.len() + entry.len() + 8,
            Self::Snapshot { id, snapshot, .. } => id.len() + snapshot.len() + 8,
            Self::Delete { id } | Self::Resume { id } => id.len(),
        }
    }
}

/// What the writer and checkpointer threads share with the store's handle.
#[derive(Default)]
struct Shared {
    /// Sessions whose log has a hole (a commit with their writes failed).
    broken: Mutex<HashSet<Arc<str>>>,
    /// Commits to fail on purpose (tests of the failure path).
    fail_next: AtomicU32,
    /// The open database; `None` after a storage fault until the
    /// checkpointer has reopened it. Readers clone the handle for one read.
    db: RwLock<Option<Arc<Database>>>,
    /// Why the log cannot be written, while it cannot.
    wal_fault: Mutex<Option<String>>,
    /// Why the database cannot be written, while it cannot.
    db_fault: Mutex<Option<String>>,
    /// The newest frame handed to the checkpointer.
    forwarded: AtomicU64,
    /// Bytes of frames in the checkpointer's frames channel, not yet
    /// drained (added by the writer before it sends a frame).
    frame_bytes: std::sync::atomic::AtomicUsize,
    /// The newest frame applied to the database.
    applied: AtomicU64,
    /// Closed log segments not yet deleted: first and last frame, path.
    closed: Mutex<Vec<(u64, u64, PathBuf)>>,
    /// Set by [`Store::crash`]: stop without the final checkpoint.
    crashed: std::sync::atomic::AtomicBool,
}

impl Shared {
    /// The open database, or why there is none.
    fn db(&self) -> Result<Arc<Database>, StoreError> {
        if let Some(db) = self.db.read().as_ref() {
            return Ok(Arc::clone(db));
        }
        let why = self
            .db_fault
            .lock()
            .clone()
            .unwrap_or_else(|| "the database is being reopened".into());
        Err(StoreError::Unavailable(why))
    }

    /// Why the store cannot write, if it cannot.
    fn fault(&self) -> Option<String> {
        self.wal_fault
            .lock()
            .clone()
            .or_else(|| self.db_fault.lock().clone())
    }

    fn set_fault(&self, which: &Mutex<Option<String>>, why: &str) {
        let healthy = self.fault().is_none();
        *which.lock() = Some(why.to_string());
        if healthy {
            metrics::gauge!("mcapi_store_healthy").set(0.0);
        }
    }

    fn clear_fault(&self, which: &Mutex<Option<String>>) {
        let cleared = which.lock().take().is_some();
        if cleared && self.fault().is_none() {
            metrics::gauge!("mcapi_store_healthy").set(1.0);
        }
    }
}

struct Pending {
    writes: Vec<Write>,
    done: Option<oneshot::Sender<Result<(), StoreError>>>,
}

/// Resolves when the writes it was returned for are durable.
#[derive(Debug)]
pub struct Commit(oneshot::Receiver<Result<(), StoreError>>);

impl Commit {
    /// Waits for the commit.
    pub async fn wait(self) -> Result<(), StoreError> {
        self.0.await.unwrap_or(Err(StoreError::Closed))
    }

    /// Waits for the commit, blocking the thread (not for async code).
    pub fn wait_blocking(self) -> Result<(), StoreError> {
        self.0.blocking_recv().unwrap_or(Err(StoreError::Closed))
    }
}

/// A stored session as found at start.
#[derive(Debug, Clone)]
pub struct StoredSession {
    /// Session id.
    pub id: String,
    /// The creation record.
    pub record: Vec<u8>,
    /// The newest snapshot and the sequence number it covers.
    pub snapshot: Option<(u64, Vec<u8>)>,
}

/// A stored session whole, as a shard move sends it.
#[derive(Debug, Clone)]
pub struct ExportedSession {
    /// Session id.
    pub id: String,
    /// The creation record.
    pub record: Vec<u8>,
    /// The newest snapshot and the sequence number it covers.
    pub snapshot: Option<(u64, Vec<u8>)>,
    /// The log after the snapshot: sequence number and entry, in order.
    pub entries: Vec<(u64, Vec<u8>)>,
}

/// The store: the log's writer thread, the checkpointer thread and the
/// redb database they share with readers.
pub struct Store {
    path: PathBuf,
    durability: Durability,
    shared: Arc<Shared>,
    tx: Mutex<Option<Sender<Pending>>>,
    checkpoint_tx: Mutex<Option<Sender<ToCheckpoint>>>,
    threads: Mutex<Vec<JoinHandle<()>>>,
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store")
            .field("path", &self.path)
            .field("durability", &self.durability)
            .finish()
    }
}

impl Store {
    /// Opens (or creates) the store in `dir` with [`Durability::Sync`].
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        Self::open_with(dir, Durability::Sync)
    }

    /// Opens (or creates) the store in `dir`: checks the database's
    /// integrity and format version (upgrading older formats), applies the
    /// log beyond its last checkpoint, and starts the writer and the
    /// checkpointer.
    pub fn open_with(dir: &Path, durability: Durability) -> Result<Self, StoreError> {
        Self::open_configured(dir, durability, DEFAULT_CACHE_BYTES)
    }

    /// [`Store::open_with`], with the database's page cache bounded to
    /// `cache_bytes` (`--store-cache-mib`).
    pub fn open_configured(
        dir: &Path,
        durability: Durability,
        cache_bytes: usize,
    ) -> Result<Self, StoreError> {
        let io = |path: &Path, what: &str, e: std::io::Error| StoreError::Io {
            path: path.to_path_buf(),
            reason: format!("{what}: {e}"),
        };
        std::fs::create_dir_all(dir).map_err(|e| io(dir, "cannot create the data directory", e))?;
        let path = dir.join(FILE_NAME);
        let wal_dir = dir.join(wal::WAL_DIR);
        let (db, applied) = db::open_database(&path, cache_bytes)?;
        if !wal_dir.exists() {
            std::fs::create_dir_all(&wal_dir)
                .map_err(|e| io(&wal_dir, "cannot create the log directory", e))?;
            wal::sync_dir(dir).map_err(|e| io(dir, "syncing the data directory", e))?;
        }
        let started = Instant::now();
        let replayed = db::replay_wal(&db, &wal_dir, applied)?;
        if replayed.frames > 0 || replayed.torn {
            tracing::info!(
                frames = replayed.frames,
                torn_tail_cut = replayed.torn,
                seconds = started.elapsed().as_secs_f64(),
                "write-ahead log applied to the store"
            );
        }
        let applied = replayed.next_lsn - 1;
        let wal = Wal::create(&wal_dir, replayed.next_lsn)
            .map_err(|e| io(&wal_dir, "creating a log segment", e))?;
        let shared = Arc::new(Shared::default());
        *shared.db.write() = Some(Arc::new(db));
        shared.applied.store(applied, Ordering::Release);
        shared.forwarded.store(applied, Ordering::Release);

        let (checkpoint_tx, checkpoint_rx) = unbounded::<ToCheckpoint>();
        let (frames_tx, frames_rx) = unbounded::<Frame>();
        let checkpointer = Checkpointer::new(
            path.clone(),
            cache_bytes,
            wal_dir,
            Arc::clone(&shared),
            applied,
        );
        let spawn = |name: &str, f: Box<dyn FnOnce() + Send>| {
            std::thread::Builder::new()
                .name(name.into())
                .spawn(f)
                .map_err(|e| io(&path, "starting a store thread", e))
        };
        let mut threads = vec![spawn(
            "mcapi-checkpoint",
            Box::new(move || checkpointer.run(&checkpoint_rx, &frames_rx)),
        )?];
        let (tx, rx) = unbounded::<Pending>();
        let writer = Writer {
            wal,
            data_dir: dir.to_path_buf(),
            durability,
            shared: Arc::clone(&shared),
            checkpoint: checkpoint_tx.clone(),
            frames: frames_tx,
            retry: Retry::new(),
            dirty: false,
            sync_due: None,
        };
        threads.push(spawn("mcapi-store", Box::new(move || writer.run(&rx)))?);
        Ok(Self {
            path,
            durability,
            shared,
            tx: Mutex::new(Some(tx)),
            checkpoint_tx: Mutex::new(Some(checkpoint_tx)),
            threads: Mutex::new(threads),
        })
    }

    /// When commits are acknowledged.
    pub fn durability(&self) -> Durability {
        self.durability
    }

    /// Whether the store can write: `Err` with the reason while it cannot
    /// (after a storage fault, until the log is repaired and the database
    /// reopened).
    pub fn health(&self) -> Result<(), String> {
        match self.shared.fault() {
            Some(why) => Err(why),
            None => Ok(()),
        }
    }

    /// Applies every acknowledged write to the database now (blocking until
    /// done). Reads call it when the database is behind the log.
    pub fn checkpoint(&self) -> Result<(), StoreError> {
        let (reply, answer) = crossbeam_channel::bounded(1);
        let sent = self
            .checkpoint_tx
            .lock()
            .as_ref()
            .is_some_and(|tx| tx.send(ToCheckpoint::Flush(reply)).is_ok());
        if !sent {
            return Err(StoreError::Closed);
        }
        answer.recv().unwrap_or(Err(StoreError::Closed))
    }

    /// The open database for one read, brought up to date with every write
    /// acknowledged so far.
    fn db(&self) -> Result<Arc<Database>, StoreError> {
        let forwarded = self.shared.forwarded.load(Ordering::Acquire);
        if self.shared.applied.load(Ordering::Acquire) < forwarded {
            self.checkpoint()?;
        }
        self.shared.db()
    }

    /// A failed read.
    fn read_failed(&self, e: impl Into<redb::Error>) -> StoreError {
        StoreError::Failed(e.into().to_string())
    }

    /// The store file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Queues writes for the next group commit. They become durable together
    /// and in order; writes submitted later never commit before them.
    pub fn submit(&self, writes: Vec<Write>) -> Commit {
        let (done, rx) = oneshot::channel();
        let pending = Pending {
            writes,
            done: Some(done),
        };
        if let Some(tx) = self.tx.lock().as_ref()
            && tx.send(pending).is_ok()
        {
            return Commit(rx);
        }
        let (done, rx) = oneshot::channel();
        let _ = done.send(Err(StoreError::Closed));
        Commit(rx)
    }

    /// Whether session `id` is broken: a commit with its writes failed and
    /// no [`Write::Resume`] has been processed since.
    pub fn is_broken(&self, id: &str) -> bool {
        self.shared.broken.lock().contains(id)
    }

    /// Makes the next `n` commits fail without writing anything, as a
    /// failing disk would (for tests of the failure path).
    #[doc(hidden)]
    pub fn fail_next_commits(&self, n: u32) {
        self.shared.fail_next.store(n, Ordering::SeqCst);
    }

    /// One stored session: its record and newest snapshot, if it exists.
    pub fn session(&self, id: &str) -> Result<Option<StoredSession>, StoreError> {
        self.read_session(&*self.db()?, id)
    }

    /// The number of the newest frame committed. Every write whose commit
    /// has returned is in a frame up to it.
    pub fn committed(&self) -> u64 {
        self.shared.forwarded.load(Ordering::Acquire)
    }

    /// [`Store::session`] for a session none of whose writes is newer than
    /// frame `lsn` (read from [`Store::committed`] after they returned):
    /// the database is brought up to date only if it has not applied that
    /// frame yet, so reading an idle session does not wait for a
    /// checkpoint of everybody else's writes.
    pub fn session_since(&self, id: &str, lsn: u64) -> Result<Option<StoredSession>, StoreError> {
        if self.shared.applied.load(Ordering::Acquire) < lsn {
            self.checkpoint()?;
        }
        self.read_session(&*self.shared.db()?, id)
    }

    fn read_session(&self, db: &Database, id: &str) -> Result<Option<StoredSession>, StoreError> {
        let failed = |e: redb::Error| self.read_failed(e);
        let read = db.begin_read().map_err(|e| failed(e.into()))?;
        let sessions = read.open_table(SESSIONS).map_err(|e| failed(e.into()))?;
        let Some(record) = sessions.get(id).map_err(|e| failed(e.into()))? else {
            return Ok(None);
        };
        let snapshots = read.open_table(SNAPSHOTS).map_err(|e| failed(e.into()))?;
        let snapshot = snapshots.get(id).map_err(|e| failed(e.into()))?.map(|v| {
            let (seq, bytes) = v.value();
            (seq, bytes.to_vec())
        });
        Ok(Some(StoredSession {
            id: id.to_string(),
            record: record.value().to_vec(),
            snapshot,
        }))
    }

    /// Every stored session: its record and newest snapshot.
    pub fn sessions(&self) -> Result<Vec<StoredSession>, StoreError> {
        let failed = |e: redb::Error| self.read_failed(e);
        let read = self.db()?.begin_read().map_err(|e| failed(e.into()))?;
        let sessions = read.open_table(SESSIONS).map_err(|e| failed(e.into()))?;
        let snapshots = read.open_table(SNAPSHOTS).map_err(|e| failed(e.into()))?;
        let mut out = Vec::new();
        for row in sessions.iter().map_err(|e| failed(e.into()))? {
            let (id, record) = row.map_err(|e| failed(e.into()))?;
            let id = id.value().to_string();
            let snapshot = snapshots
                .get(id.as_str())
                .map_err(|e| failed(e.into()))?
                .map(|v| {
                    let (seq, bytes) = v.value();
                    (seq, bytes.to_vec())
                });
            out.push(StoredSession {
                id,
                record: record.value().to_vec(),
                snapshot,
            });
        }
        Ok(out)
    }

    /// Every stored session whose id begins with `prefix` (a shard's
    /// `s03a7.`), read in one transaction so each session's record,
    /// snapshot and log agree: the log entries returned are those after the
    /// snapshot, in order. What a shard move streams (docs/cluster.md).
    pub fn sessions_with_prefix(&self, prefix: &str) -> Result<Vec<ExportedSession>, StoreError> {
        let failed = |e: redb::Error| self.read_failed(e);
        let read = self.db()?.begin_read().map_err(|e| failed(e.into()))?;
        let sessions = read.open_table(SESSIONS).map_err(|e| failed(e.into()))?;
        let snapshots = read.open_table(SNAPSHOTS).map_err(|e| failed(e.into()))?;
        let log = read.open_table(LOG).map_err(|e| failed(e.into()))?;
        let mut out = Vec::new();
        for row in sessions.range(prefix..).map_err(|e| failed(e.into()))? {
            let (id, record) = row.map_err(|e| failed(e.into()))?;
            let id = id.value().to_string();
            if !id.starts_with(prefix) {
                break;
            }
            let snapshot = snapshots
                .get(id.as_str())
                .map_err(|e| failed(e.into()))?
                .map(|v| {
                    let (seq, bytes) = v.value();
                    (seq, bytes.to_vec())
                });
            let start = snapshot.as_ref().map_or(0, |(s, _)| s.saturating_add(1));
            let key = log_key(&id);
            let mut entries = Vec::new();
            for chunk in log
                .range((key, start / CHUNK)..=(key, u64::MAX))
                .map_err(|e| failed(e.into()))?
            {
                let (_, chunk) = chunk.map_err(|e| failed(e.into()))?;
                let mut rest = chunk.value();
                while !rest.is_empty() {
                    let (seq, entry, tail) =
                        split_entry(rest).ok_or_else(|| StoreError::Corrupt {
                            path: self.path.clone(),
                            reason: format!("a log chunk of session `{id}` is malformed"),
                        })?;
                    rest = tail;
                    if seq >= start {
                        entries.push((seq, entry.to_vec()));
                    }
                }
            }
            out.push(ExportedSession {
                id,
                record: record.value().to_vec(),
                snapshot,
                entries,
            });
        }
        Ok(out)
    }

    /// Calls `f(seq, entry)` for each log entry of session `id` after
    /// sequence number `after`, in order. The first error stops the read:
    /// the visitor's own, or the store's (converted with `E::from`), so a
    /// caller's errors stay its own type and never pass through
    /// [`StoreError`].
    pub fn for_each_entry<E: From<StoreError>>(
        &self,
        id: &str,
        after: Option<u64>,
        mut f: impl FnMut(u64, &[u8]) -> Result<(), E>,
    ) -> Result<(), E> {
        let failed = |e: redb::Error| self.read_failed(e);
        let read = self.db()?.begin_read().map_err(|e| failed(e.into()))?;
        let log = read.open_table(LOG).map_err(|e| failed(e.into()))?;
        let start = after.map_or(0, |a| a.saturating_add(1));
        if after == Some(u64::MAX) {
            return Ok(());
        }
        let key = log_key(id);
        for row in log
            .range((key, start / CHUNK)..=(key, u64::MAX))
            .map_err(|e| failed(e.into()))?
        {
            let (_, chunk) = row.map_err(|e| failed(e.into()))?;
            let mut rest = chunk.value();
            while !rest.is_empty() {
                let (seq, entry, tail) = split_entry(rest).ok_or_else(|| StoreError::Corrupt {
                    path: self.path.clone(),
                    reason: format!("a log chunk of session `{id}` is malformed"),
                })?;
                rest = tail;
                if seq >= start {
                    f(seq, entry)?;
                }
            }
        }
        Ok(())
    }

    /// Stops the threads as a `kill -9` would leave the files: the log's
    /// frames are not applied to the database and stay in the log (for
    /// tests of the replay at open).
    #[doc(hidden)]
    pub fn crash(&self) {
        self.shared.crashed.store(true, Ordering::SeqCst);
        self.close();
    }

    /// Stops the writer after it has committed everything queued, then the
    /// checkpointer after it has applied everything (a clean close leaves
    /// an empty log).
    pub fn close(&self) {
        self.tx.lock().take();
        self.checkpoint_tx.lock().take();
        for h in self.threads.lock().drain(..).rev() {
            if h.join().is_err() {
                tracing::error!("a store thread panicked");
            }
        }
    }
}

impl Drop for Store {
    fn drop(&mut self) {
        self.close();
    }
}

/// The writer thread: group commits to the log, and the log's recovery
/// after a storage fault.
struct Writer {
    wal: Wal,
    data_dir: PathBuf,
    durability: Durability,
    shared: Arc<Shared>,
    /// Wakes the checkpointer (see `checkpoint`'s module docs).
    checkpoint: Sender<ToCheckpoint>,
    /// Frames for the checkpointer, drained when a checkpoint is due.
    frames: Sender<Frame>,
    /// While the log is down: when to try repairing it next.
    retry: Retry,
    /// A failed write may have left part of a frame in the segment.
    dirty: bool,
    /// Under [`Durability::Os`]: when the unsynced frames must be synced.
    sync_due: Option<Instant>,
}

impl Writer {
    fn run(mut self, rx: &Receiver<Pending>) {
        loop {
            let due = [self.retry.at(), self.sync_due].into_iter().flatten().min();
            let first = match due {
                None => match rx.recv() {
                    Ok(p) => p,
                    Err(_) => break,
                },
                Some(at) => match rx.recv_timeout(at.saturating_duration_since(Instant::now())) {
                    Ok(p) => p,
                    Err(RecvTimeoutError::Timeout) => {
                        self.timers();
                        continue;
                    }
                    Err(RecvTimeoutError::Disconnected) => break,
                },
            };
            let mut group = vec![first];
            let mut writes = group[0].writes.len();
            while writes < MAX_GROUP
                && let Ok(next) = rx.try_recv()
            {
                writes += next.writes.len();
                group.push(next);
            }
            self.process(group, writes);
            self.timers();
        }
        // Closed: what the kernel holds goes to disk before the
        // checkpointer applies it and deletes the log.
        if self.wal.unsynced()
            && let Err(e) = self.wal.sync()
        {
            tracing::error!(error = %e, "syncing the log at close");
        }
    }

    /// The background sync and the repair, when due.
    fn timers(&mut self) {
        let now = Instant::now();
        if self.sync_due.is_some_and(|at| now >= at) {
            self.sync_due = None;
            if let Err(e) = self.wal.sync() {
                // Acknowledged frames may not be on disk: a power cut would
                // lose them. Writes stop until a sync succeeds again.
                tracing::error!(error = %e, "the background sync of the log failed");
                self.down(&format!("syncing the log: {e}"));
            }
        }
        if self.retry.is_due(now) {
            self.try_repair();
        }
    }

    fn process(&mut self, mut group: Vec<Pending>, writes: usize) {
        let shared = Arc::clone(&self.shared);
        // In queue order: a `Resume` readmits its session's later writes;
        // writes extending a broken session are refused.
        let mut refused: Vec<(usize, Arc<str>)> = Vec::new();
        {
            let mut broken = shared.broken.lock();
            for (i, p) in group.iter().enumerate() {
                for w in &p.writes {
                    if let Write::Resume { id } = w {
                        broken.remove(id);
                    }
                }
                if let Some(id) = p
                    .writes
                    .iter()
                    .filter_map(Write::extends)
                    .find(|id| broken.contains(*id))
                {
                    refused.push((i, Arc::clone(id)));
                }
            }
        }
        for (i, id) in refused.iter().rev() {
            let mut p = group.remove(*i);
            if let Some(done) = p.done.take() {
                let _ = done.send(Err(StoreError::Broken(Arc::clone(id))));
            }
        }
        let result = self.commit(&mut group, writes);
        if result.is_err() {
            let mut broken = shared.broken.lock();
            for w in group.iter().flat_map(|p| &p.writes) {
                if let Some(id) = w.extends() {
                    broken.insert(Arc::clone(id));
                }
            }
        }
        for mut p in group {
            if let Some(done) = p.done.take() {
                let _ = done.send(result.clone());
            }
        }
    }

    /// Appends the group as one frame and makes it durable as promised;
    /// then hands its writes to the checkpointer (before anyone hears of
    /// the commit, so a reader that asks for a checkpoint sees them).
    fn commit(&mut self, group: &mut [Pending], writes: usize) -> Result<(), StoreError> {
        if !group.iter().flat_map(|p| &p.writes).any(Write::is_logged) {
            // Nothing to store (a wake-up, a resume, or every write refused).
            return Ok(());
        }
        if self.retry.is_due(Instant::now()) {
            self.try_repair();
        }
        if let Some(why) = self.shared.fault() {
            // Down: fail at once, before anything is written.
            return Err(StoreError::Unavailable(why));
        }
        if self
            .shared
            .fail_next
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1))
            .is_ok()
        {
            tracing::error!(writes, "store commit failed: injected commit failure");
            return Err(StoreError::Failed("injected commit failure".into()));
        }
        let started = Instant::now();
        let appended = self.wal.append(
            group
                .iter()
                .flat_map(|p| &p.writes)
                .filter(|w| w.is_logged()),
        );
        // A frame that did not fit closed the active segment (synced): it is
        // deleted once the checkpointer has applied it.
        let closed = self.wal.take_closed();
        if !closed.is_empty() {
            self.shared.closed.lock().extend(closed);
        }
        let lsn = match appended {
            Ok(lsn) => lsn,
            Err(e) => {
                tracing::error!(error = %e, writes, "appending to the log failed");
                self.dirty = matches!(e, AppendError::Dirty(_));
                self.down(&format!("appending to the log: {e}"));
                return Err(StoreError::Failed(format!("appending to the log: {e}")));
            }
        };
        match self.durability {
            Durability::Sync => {
                if let Err(e) = self.wal.sync() {
                    tracing::error!(error = %e, writes, "syncing the log failed");
                    // The frame may or may not be on disk: cut it off, so
                    // that it is never read back.
                    if let Err(cut) = self.wal.cut_unsynced() {
                        tracing::error!(error = %cut, "cutting the failed frame off the log");
                        self.dirty = true;
                    }
                    self.down(&format!("syncing the log: {e}"));
                    return Err(StoreError::Failed(format!("syncing the log: {e}")));
                }
            }
            Durability::Os => {
                self.sync_due
                    .get_or_insert_with(|| Instant::now() + OS_SYNC_INTERVAL);
            }
        }
        metrics::histogram!("mcapi_store_commit_seconds").record(started.elapsed().as_secs_f64());
        metrics::histogram!("mcapi_store_commit_writes").record(writes as f64);
        self.retry.worked();
        let logged: Vec<Write> = group
            .iter_mut()
            .flat_map(|p| std::mem::take(&mut p.writes))
            .filter(Write::is_logged)
            .collect();
        // A deleted session's writes are no longer refused (its id is never
        // reused); only once the delete is durable.
        {
            let mut broken = self.shared.broken.lock();
            for w in &logged {
                if let Write::Delete { id } = w {
                    broken.remove(id);
                }
            }
        }
        // Counted before it is sent, so a drain never subtracts bytes not
        // yet added.
        let bytes = Frame::size(&logged);
        let before = self.shared.frame_bytes.fetch_add(bytes, Ordering::SeqCst);
        if self
            .frames
            .send(Frame {
                lsn,
                writes: logged,
            })
            .is_ok()
        {
            self.shared.forwarded.store(lsn, Ordering::Release);
            if checkpoint::wake_for(before, bytes) {
                let _ = self.checkpoint.send(ToCheckpoint::Wake);
            }
        } else {
            self.shared.frame_bytes.fetch_sub(bytes, Ordering::SeqCst);
        }
        Ok(())
    }

    /// The log failed: every write fails at once until a repair succeeds.
    fn down(&mut self, why: &str) {
        self.shared.set_fault(&self.shared.wal_fault, why);
        self.retry.went_down();
    }

    /// One repair attempt: cut the segment back to its last whole frame if
    /// a failed write may have left part of one, sync what is
    /// acknowledged, and prove the disk takes new data (a probe file of
    /// [`db::PROBE_BYTES`], synced and removed). On failure the next attempt
    /// waits twice as long.
    fn try_repair(&mut self) {
        let attempt = (|| -> Result<(), String> {
            if self.dirty {
                self.wal.repair()?;
                self.dirty = false;
            }
            self.wal
                .sync()
                .map_err(|e| format!("syncing the log: {e}"))?;
            self.sync_due = None;
            let probe = self.data_dir.join(PROBE_FILE);
            let written = std::fs::File::create(&probe).and_then(|mut f| {
                f.write_all(&vec![0u8; db::PROBE_BYTES])?;
                f.sync_data()
            });
            let _ = std::fs::remove_file(&probe);
            written.map_err(|e| format!("the probe write failed: {e}"))?;
            Ok(())
        })();
        match attempt {
            Ok(()) => {
                self.retry.cleared();
                self.shared.clear_fault(&self.shared.wal_fault);
                tracing::info!(part = "log", "store reopened after a storage fault");
            }
            Err(e) => {
                self.shared.set_fault(&self.shared.wal_fault, &e);
                let wait = self.retry.attempt_failed();
                tracing::warn!(part = "log", error = %e, retry_in_ms = wait.as_millis() as u64, "the store cannot be reopened yet");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::db::META;
    use super::*;
    use redb::ReadableTableMetadata;

    fn id(s: &str) -> Arc<str> {
        Arc::from(s)
    }

    fn entries(store: &Store, s: &str, after: Option<u64>) -> Vec<(u64, Vec<u8>)> {
        let mut out = Vec::new();
        store
            .for_each_entry(s, after, |seq, e| {
                out.push((seq, e.to_vec()));
                Ok::<(), StoreError>(())
            })
            .expect("read log");
        out
    }

    #[test]
    fn writes_survive_reopening_and_snapshots_trim_the_log() {
        let dir = tempfile::tempdir().expect("tempdir");
        {
            let store = Store::open(dir.path()).expect("open");
            let mut writes = vec![Write::Session {
                id: id("a"),
                record: b"ra".to_vec(),
            }];
            writes.extend((0..5).map(|seq| Write::Append {
                id: id("a"),
                seq,
                entry: vec![seq as u8],
            }));
            writes.push(Write::Session {
                id: id("ab"),
                record: b"rab".to_vec(),
            });
            writes.push(Write::Append {
                id: id("ab"),
                seq: 0,
                entry: vec![9],
            });
            store.submit(writes).wait_blocking().expect("commit");
            store
                .submit(vec![Write::Snapshot {
                    id: id("a"),
                    seq: 2,
                    snapshot: b"snap".to_vec(),
                }])
                .wait_blocking()
                .expect("snapshot");
            store.close();
        }
        let store = Store::open(dir.path()).expect("reopen");
        let sessions = store.sessions().expect("sessions");
        assert_eq!(sessions.len(), 2);
        assert_eq!(sessions[0].id, "a");
        assert_eq!(sessions[0].record, b"ra");
        assert_eq!(sessions[0].snapshot, Some((2, b"snap".to_vec())));
        assert_eq!(sessions[1].snapshot, None);
        // Reads after the snapshot skip what it covers; "ab" is not mixed into "a".
        assert_eq!(
            entries(&store, "a", Some(2)),
            vec![(3, vec![3]), (4, vec![4])]
        );
        assert_eq!(entries(&store, "a", Some(3)), vec![(4, vec![4])]);
        assert_eq!(entries(&store, "ab", None), vec![(0, vec![9])]);
        store
            .submit(vec![Write::Delete { id: id("a") }])
            .wait_blocking()
            .expect("delete");
        assert_eq!(store.sessions().expect("sessions").len(), 1);
        assert!(entries(&store, "a", None).is_empty());
    }

    #[test]
    fn chunks_are_trimmed_only_when_wholly_covered() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::open(dir.path()).expect("open");
        let n = 3 * CHUNK + 5;
        for seq in 0..n {
            store
                .submit(vec![Write::Append {
                    id: id("s0001.01ARZ3NDEKTSV4RRFFQ69G5FAV"),
                    seq,
                    entry: seq.to_le_bytes().to_vec(),
                }])
                .wait_blocking()
                .expect("append");
        }
        let all = entries(&store, "s0001.01ARZ3NDEKTSV4RRFFQ69G5FAV", None);
        assert_eq!(all.len() as u64, n);
        assert!(all.iter().all(|(seq, e)| e == &seq.to_le_bytes().to_vec()));
        let cut = CHUNK + 3;
        store
            .submit(vec![Write::Snapshot {
                id: id("s0001.01ARZ3NDEKTSV4RRFFQ69G5FAV"),
                seq: cut,
                snapshot: vec![1],
            }])
            .wait_blocking()
            .expect("snapshot");
        let after = entries(&store, "s0001.01ARZ3NDEKTSV4RRFFQ69G5FAV", Some(cut));
        assert_eq!(after.first().map(|e| e.0), Some(cut + 1));
        assert_eq!(after.len() as u64, n - cut - 1);
        // The first chunk is gone; the second (partly covered) is kept.
        let read = store.db().expect("db").begin_read().expect("read");
        let log = read.open_table(LOG).expect("log");
        assert_eq!(log.len().expect("len"), 3);
    }

    #[test]
    fn concurrent_submissions_share_commits_and_all_land() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Arc::new(Store::open(dir.path()).expect("open"));
        let threads: Vec<_> = (0..8)
            .map(|t| {
                let store = Arc::clone(&store);
                std::thread::spawn(move || {
                    let sid = id(&format!("s{t}"));
                    for seq in 0..50 {
                        store
                            .submit(vec![Write::Append {
                                id: Arc::clone(&sid),
                                seq,
                                entry: vec![t as u8],
                            }])
                            .wait_blocking()
                            .expect("commit");
                    }
                })
            })
            .collect();
        for t in threads {
            t.join().expect("thread");
        }
        for t in 0..8 {
            let got = entries(&store, &format!("s{t}"), None);
            assert_eq!(got.len(), 50);
            assert!(got.iter().enumerate().all(|(i, (seq, _))| *seq == i as u64));
        }
    }

    #[test]
    fn a_damaged_file_is_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        {
            let store = Store::open(dir.path()).expect("open");
            let writes = (0..2000)
                .map(|seq| Write::Append {
                    id: id("a"),
                    seq,
                    entry: vec![7; 64],
                })
                .collect();
            store.submit(writes).wait_blocking().expect("commit");
        }
        let path = dir.path().join(FILE_NAME);
        let len = std::fs::metadata(&path).expect("meta").len();
        let file = std::fs::OpenOptions::new()
            .write(true)
            .open(&path)
            .expect("open file");
        file.set_len(len / 2).expect("truncate");
        drop(file);
        let err = Store::open(dir.path()).expect_err("a truncated store must not open");
        assert!(matches!(err, StoreError::Corrupt { .. }), "{err}");
    }

    #[test]
    fn garbage_is_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join(FILE_NAME), vec![0x5a; 1 << 16]).expect("write");
        let err = Store::open(dir.path()).expect_err("garbage must not open");
        assert!(matches!(err, StoreError::Corrupt { .. }), "{err}");
    }

    #[test]
    fn another_format_version_is_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        {
            let db = Database::create(dir.path().join(FILE_NAME)).expect("db");
            let w = db.begin_write().expect("write");
            w.open_table(META)
                .expect("meta")
                .insert("format_version", FORMAT_VERSION + 1)
                .expect("insert");
            w.commit().expect("commit");
        }
        let err = Store::open(dir.path()).expect_err("version");
        assert!(
            matches!(err, StoreError::Version { found, .. } if found == FORMAT_VERSION + 1),
            "{err}"
        );
    }

    fn set_version(dir: &Path, version: u64) {
        let db = Database::create(dir.join(FILE_NAME)).expect("db");
        let w = db.begin_write().expect("write");
        w.open_table(META)
            .expect("meta")
            .insert("format_version", version)
            .expect("insert");
        w.commit().expect("commit");
    }

    #[test]
    fn a_format_2_file_is_upgraded_by_tagging_its_records() {
        let dir = tempfile::tempdir().expect("tempdir");
        let n = 2 * CHUNK + 7;
        {
            let store = Store::open(dir.path()).expect("open");
            let mut writes = vec![Write::Session {
                id: id("a"),
                record: b"ra".to_vec(),
            }];
            writes.extend((0..n).map(|seq| Write::Append {
                id: id("a"),
                seq,
                entry: vec![seq as u8, 0xAB],
            }));
            writes.push(Write::Snapshot {
                id: id("a"),
                seq: CHUNK + 1,
                snapshot: b"snap".to_vec(),
            });
            store.submit(writes).wait_blocking().expect("commit");
            store.close();
        }
        // The records above stand for untagged format-2 records.
        set_version(dir.path(), 2);
        let store = Store::open(dir.path()).expect("upgrade");
        let sessions = store.sessions().expect("sessions");
        assert_eq!(sessions[0].record, b"ra", "creation records are unchanged");
        assert_eq!(
            sessions[0].snapshot,
            Some((CHUNK + 1, vec![RECORD_V2, b's', b'n', b'a', b'p']))
        );
        let log = entries(&store, "a", Some(CHUNK + 1));
        let want: Vec<_> = (CHUNK + 2..n)
            .map(|seq| (seq, vec![RECORD_V2, seq as u8, 0xAB]))
            .collect();
        assert_eq!(log, want);
        store.close();
        drop(store);
        // Upgraded once: reopening does not tag again.
        let store = Store::open(dir.path()).expect("reopen");
        assert_eq!(entries(&store, "a", Some(CHUNK + 1)), want);
        let read = store.db().expect("db").begin_read().expect("read");
        let meta = read.open_table(META).expect("meta");
        let v = meta.get("format_version").expect("get").map(|v| v.value());
        assert_eq!(v, Some(FORMAT_VERSION));
    }

    #[test]
    fn after_a_failed_commit_a_session_is_refused_until_resumed() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::open(dir.path()).expect("open");
        let append = |s: &str, seq: u64| Write::Append {
            id: id(s),
            seq,
            entry: vec![seq as u8],
        };
        store
            .submit(vec![append("a", 0), append("b", 0)])
            .wait_blocking()
            .expect("commit");
        store.fail_next_commits(1);
        let err = store
            .submit(vec![append("a", 1)])
            .wait_blocking()
            .expect_err("injected failure");
        assert!(matches!(err, StoreError::Failed(_)), "{err}");
        assert!(store.is_broken("a") && !store.is_broken("b"));
        // Writes after the hole are refused; other sessions go on.
        let err = store
            .submit(vec![append("a", 2)])
            .wait_blocking()
            .expect_err("a is broken");
        assert!(
            matches!(&err, StoreError::Broken(s) if &**s == "a"),
            "{err}"
        );
        store
            .submit(vec![append("b", 1)])
            .wait_blocking()
            .expect("b is fine");
        // A resume in the same queue readmits what follows it.
        let resumed = store.submit(vec![Write::Resume { id: id("a") }]);
        store
            .submit(vec![append("a", 1)])
            .wait_blocking()
            .expect("a after its resume");
        resumed.wait_blocking().expect("resume");
        assert!(!store.is_broken("a"));
        assert_eq!(entries(&store, "a", None), vec![(0, vec![0]), (1, vec![1])]);
        assert_eq!(entries(&store, "b", None), vec![(0, vec![0]), (1, vec![1])]);
    }

    fn appends(s: &str, seqs: std::ops::Range<u64>, bytes: usize) -> Vec<Write> {
        seqs.map(|seq| Write::Append {
            id: id(s),
            seq,
            entry: vec![seq as u8; bytes],
        })
        .collect()
    }

    fn segments(dir: &Path) -> Vec<(u64, PathBuf)> {
        wal::list_segments(&dir.join(wal::WAL_DIR)).expect("segments")
    }

    #[test]
    fn a_clean_close_applies_the_log_and_leaves_it_empty() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::open(dir.path()).expect("open");
        store
            .submit(appends("a", 0..10, 8))
            .wait_blocking()
            .expect("commit");
        store.close();
        assert!(segments(dir.path()).is_empty());
        let read = Database::open(dir.path().join(FILE_NAME)).expect("db");
        let read = read.begin_read().expect("read");
        let meta = read.open_table(META).expect("meta");
        assert_eq!(
            meta.get("wal_lsn").expect("get").map(|v| v.value()),
            Some(1)
        );
        let log = read.open_table(LOG).expect("log");
        assert_eq!(log.len().expect("len"), 1);
    }

    #[test]
    fn after_a_crash_the_log_is_replayed_into_the_database_exactly_once() {
        for durability in [Durability::Sync, Durability::Os] {
            let dir = tempfile::tempdir().expect("tempdir");
            let store = Store::open_with(dir.path(), durability).expect("open");
            for seq in 0..20 {
                store
                    .submit(appends("a", seq..seq + 1, 4))
                    .wait_blocking()
                    .expect("commit");
            }
            // Half of it applied by a checkpoint before the crash.
            store.checkpoint().expect("checkpoint");
            for seq in 20..40 {
                store
                    .submit(appends("a", seq..seq + 1, 4))
                    .wait_blocking()
                    .expect("commit");
            }
            store.crash();
            drop(store);
            assert!(
                !segments(dir.path()).is_empty(),
                "{durability}: the log stays"
            );
            for round in 0..2 {
                let store = Store::open_with(dir.path(), durability).expect("reopen");
                let got = entries(&store, "a", None);
                assert_eq!(
                    got,
                    (0..40).map(|s| (s, vec![s as u8; 4])).collect::<Vec<_>>(),
                    "{durability}, round {round}: every acknowledged write, once"
                );
                store.crash();
            }
        }
    }

    #[test]
    fn a_torn_tail_is_cut_and_a_damaged_frame_refuses_the_open() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::open(dir.path()).expect("open");
        // Frames of four 512-byte sectors each.
        let bytes = 2000;
        for seq in 0..3 {
            store
                .submit(appends("a", seq..seq + 1, bytes))
                .wait_blocking()
                .expect("commit");
        }
        store.crash();
        drop(store);
        let (_, path) = segments(dir.path()).pop().expect("segment");
        let whole = std::fs::read(&path).expect("bytes");
        // The last sector written: the end of the last frame.
        let last = whole
            .chunks_exact(512)
            .rposition(|s| s.iter().any(|&b| b != 0))
            .expect("frames")
            * 512;
        // Damage inside the last frame: refused, naming the segment.
        let mut damaged = whole.clone();
        damaged[last + 10] ^= 1;
        std::fs::write(&path, &damaged).expect("write");
        let err = Store::open(dir.path()).expect_err("damage");
        assert!(
            matches!(&err, StoreError::Corrupt { path: p, .. } if *p == path),
            "{err}"
        );
        // A sector of the last frame never written (a power cut mid-write):
        // cut, and the frames before it are kept.
        let mut torn = whole.clone();
        torn[last..last + 512].fill(0);
        std::fs::write(&path, &torn).expect("write");
        let store = Store::open(dir.path()).expect("a torn tail is not damage");
        assert_eq!(
            entries(&store, "a", None),
            vec![(0, vec![0; bytes]), (1, vec![1; bytes])]
        );
        // The next frame follows on and survives another crash.
        store
            .submit(appends("a", 2..3, bytes))
            .wait_blocking()
            .expect("commit");
        store.crash();
        drop(store);
        let store = Store::open(dir.path()).expect("reopen");
        assert_eq!(entries(&store, "a", None).len(), 3);
    }

    #[test]
    fn a_version_1_log_left_by_a_crash_is_replayed_and_the_log_goes_on_in_version_2() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::open(dir.path()).expect("open");
        store
            .submit(appends("a", 0..2, 8))
            .wait_blocking()
            .expect("commit");
        store.close();
        drop(store);
        // What an older mcapi left when a power cut hit after two more
        // acknowledged commits: frames 2 to 4 in a version 1 segment, the
        // third torn (never acknowledged).
        let wal_dir = dir.path().join(wal::WAL_DIR);
        let path = wal::segment_path(&wal_dir, 2);
        let ends = wal::v1_segment(
            &path,
            2,
            &[
                appends("a", 2..3, 8),
                appends("a", 3..4, 8),
                appends("a", 4..5, 8),
            ],
        );
        let bytes = std::fs::read(&path).expect("bytes");
        std::fs::write(&path, &bytes[..ends[2] - 3]).expect("torn");
        let store = Store::open(dir.path()).expect("upgrade");
        assert_eq!(
            entries(&store, "a", None),
            (0..4).map(|s| (s, vec![s as u8; 8])).collect::<Vec<_>>()
        );
        store
            .submit(appends("a", 4..5, 8))
            .wait_blocking()
            .expect("commit");
        store.crash();
        drop(store);
        let (first, path) = segments(dir.path()).pop().expect("segment");
        assert_eq!(first, 4, "the log goes on after the replayed frames");
        let header = std::fs::read(&path).expect("bytes");
        assert_eq!(header[8..12], 2u32.to_le_bytes(), "a version 2 segment");
        let store = Store::open(dir.path()).expect("reopen");
        assert_eq!(entries(&store, "a", None).len(), 5);
    }

    #[test]
    fn the_checkpointer_applies_frames_by_itself_round_after_round() {
        // Nobody asks for a checkpoint here: each round's first frame must
        // wake the checkpointer (it drains its frames only when woken or
        // due), or `applied` would stay behind until the close.
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::open(dir.path()).expect("open");
        let applied_all = |store: &Store| {
            let deadline = Instant::now() + 10 * checkpoint::CHECKPOINT_INTERVAL;
            while Instant::now() < deadline {
                let forwarded = store.shared.forwarded.load(Ordering::Acquire);
                if store.shared.applied.load(Ordering::Acquire) == forwarded {
                    return true;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            false
        };
        for round in 0..3u64 {
            for seq in round * 5..round * 5 + 5 {
                store
                    .submit(appends("a", seq..seq + 1, 16))
                    .wait_blocking()
                    .expect("commit");
            }
            assert!(applied_all(&store), "round {round} was applied");
            assert_eq!(store.shared.frame_bytes.load(Ordering::SeqCst), 0);
        }
        assert_eq!(entries(&store, "a", None).len(), 15);
    }

    #[test]
    fn full_segments_are_closed_and_deleted_once_applied() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::open(dir.path()).expect("open");
        let frame = 1 << 20;
        let n = wal::SEGMENT_BYTES / frame as u64 + 2;
        for seq in 0..n {
            store
                .submit(appends("a", seq..seq + 1, frame))
                .wait_blocking()
                .expect("commit");
        }
        assert!(segments(dir.path()).len() >= 2, "a new segment was begun");
        store.checkpoint().expect("checkpoint");
        assert_eq!(
            segments(dir.path()).len(),
            1,
            "the closed segment is deleted"
        );
        assert_eq!(entries(&store, "a", None).len() as u64, n);
    }

    #[test]
    fn a_format_3_file_is_upgraded_to_4() {
        let dir = tempfile::tempdir().expect("tempdir");
        {
            let store = Store::open(dir.path()).expect("open");
            store
                .submit(appends("a", 0..3, 2))
                .wait_blocking()
                .expect("commit");
            store.close();
        }
        // A format-3 file: no log directory, no `wal_lsn`.
        std::fs::remove_dir(dir.path().join(wal::WAL_DIR)).expect("rmdir");
        {
            let db = Database::create(dir.path().join(FILE_NAME)).expect("db");
            let w = db.begin_write().expect("write");
            {
                let mut meta = w.open_table(META).expect("meta");
                meta.insert("format_version", 3).expect("insert");
                meta.remove("wal_lsn").expect("remove");
            }
            w.commit().expect("commit");
        }
        let store = Store::open(dir.path()).expect("upgrade");
        assert_eq!(entries(&store, "a", None).len(), 3);
        store
            .submit(appends("a", 3..4, 2))
            .wait_blocking()
            .expect("commit");
        store.crash();
        drop(store);
        let store = Store::open(dir.path()).expect("reopen");
        assert_eq!(entries(&store, "a", None).len(), 4);
        let read = store.db().expect("db").begin_read().expect("read");
        let meta = read.open_table(META).expect("meta");
        let v = meta.get("format_version").expect("get").map(|v| v.value());
        assert_eq!(v, Some(FORMAT_VERSION));
    }
}
