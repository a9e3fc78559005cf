//! The durable session store (docs/sessions.md, "Durability and recovery"): one redb file in the
//! data directory holding, per session, its creation record, its newest
//! snapshot and the log of observations since that snapshot.
//!
//! The store knows keys, sequence numbers and bytes, not what they mean: the
//! service encodes its records (`service::durable`). Writes go through one
//! writer thread that commits everything queued since its last commit in a
//! single transaction (group commit), so many concurrent observations share
//! one disk sync. A caller learns that its write is durable by awaiting the
//! [`Commit`] it got back.
//!
//! Layout (format version [`FORMAT_VERSION`]):
//! - `meta`: `"format_version"` → u64;
//! - `sessions`: id → creation record;
//! - `snapshots`: id → (sequence number, snapshot);
//! - `log`: (session key, chunk number) → a chunk of up to [`CHUNK`]
//!   observation records (chunk c holds sequence numbers c·CHUNK to
//!   c·CHUNK + CHUNK − 1, each framed as sequence number, length, bytes).
//!   The session key is the 128-bit ULID of the session id. A snapshot at
//!   sequence number n drops the chunks that end at or before n.
//!
//! Since format 3 every snapshot and log record begins with one byte naming
//! the encoding of the rest, which the service chooses and reads
//! ([`RECORD_V2`] for records written under format 2). Opening a format-2
//! file upgrades it in place, in one transaction, by prefixing each of its
//! records with [`RECORD_V2`]; nothing else changes.
//!
//! A failed commit leaves a hole in the logs of the sessions it wrote to, so
//! from then on the store refuses their appends and snapshots
//! ([`StoreError::Broken`]) instead of writing after the hole, until the
//! service has reloaded the session from what is durable and sent
//! [`Write::Resume`]. Later records therefore never depend on lost ones.
//!
//! Storage faults are survived without a restart. redb latches the first
//! real I/O error of a `Database` (ENOSPC included): every later call on it,
//! reads too, fails with `StorageError::PreviousIo` until it is closed and
//! opened again. So after a commit fails with an I/O error the writer thread
//! closes the database at once (readers then get [`StoreError::Unavailable`]
//! instead of the latched error), and reopens it with backoff: at the next
//! write after the backoff, or by itself when nothing is written (the health
//! probe). A reopen counts only once a probe commit succeeds on the new
//! handle; until then [`Store::health`] says why the store cannot write, and
//! every write fails at once. Opening repairs the file to its last commit, so
//! nothing acknowledged is lost and nothing unacknowledged appears.
//!
//! Chunks, not one record per observation: a B-tree entry per 20-byte
//! observation cost about 140 bytes of file, and the file's size is what
//! opening it (integrity check) and recovery cost.

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender, unbounded};
use parking_lot::{Mutex, RwLock};
use redb::{Database, Durability, ReadableDatabase, ReadableTable, TableDefinition};
use thiserror::Error;
use tokio::sync::oneshot;

/// Version of the on-disk layout. A format-2 file is upgraded at open;
/// a file of any other version is refused.
pub const FORMAT_VERSION: u64 = 3;

/// The record-encoding byte given to records written under format 2.
pub const RECORD_V2: u8 = 2;

/// Name of the store file inside the data directory.
pub const FILE_NAME: &str = "mcapi.redb";

const META: TableDefinition<&str, u64> = TableDefinition::new("meta");
const SESSIONS: TableDefinition<&str, &[u8]> = TableDefinition::new("sessions");
const SNAPSHOTS: TableDefinition<&str, (u64, &[u8])> = TableDefinition::new("snapshots");
const LOG: TableDefinition<(u128, u64), &[u8]> = TableDefinition::new("log");
/// The health probe's scratch table (empty between probes).
const PROBE: TableDefinition<&str, &[u8]> = TableDefinition::new("probe");

/// The log's key of a session: the 128 bits of the ULID in its id
/// (`s<shard>.<ULID>`), or a 128-bit hash of the id for other ids. A number
/// instead of the string keeps the log, which holds most of the file, small:
/// the store's size is what opening (integrity check) and recovery cost.
fn log_key(id: &str) -> u128 {
    if let Some((_, ulid)) = id.split_once('.')
        && let Ok(u) = ulid::Ulid::from_string(ulid)
    {
        return u.0;
    }
    use sha2::Digest;
    let d = sha2::Sha256::digest(id.as_bytes());
    let mut b = [0u8; 16];
    b.copy_from_slice(&d[..16]);
    u128::from_be_bytes(b)
}

/// Observation records per log chunk.
pub const CHUNK: u64 = 64;

/// Most writes folded into one transaction.
const MAX_GROUP: usize = 8192;

/// First wait before reopening the database after a storage fault; doubled
/// after every failed attempt up to [`MAX_BACKOFF`], reset by a successful
/// commit of real writes.
const MIN_BACKOFF: Duration = Duration::from_millis(50);
/// Longest wait between two reopening attempts.
const MAX_BACKOFF: Duration = Duration::from_secs(1);
/// How long a reopen waits for readers to let go of the failed handle
/// (redb holds the file lock until the last one is dropped).
const RELEASE_WAIT: Duration = Duration::from_secs(2);
/// What the health probe writes (and removes again) after a reopen.
const PROBE_BYTES: usize = 256 * 1024;

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
        /// The store file.
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
    /// disk); it is reopened automatically once the fault clears.
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

/// Whether a redb error leaves the `Database` unusable until it is closed and
/// opened again: an I/O error is latched (every later call answers
/// `PreviousIo`), and a failed commit may discard the allocator state (every
/// later write transaction answers `Corrupted`, "reopen the database to
/// repair it").
fn needs_reopen(e: &redb::Error) -> bool {
    matches!(
        e,
        redb::Error::Io(_)
            | redb::Error::PreviousIo
            | redb::Error::DatabaseClosed
            | redb::Error::Corrupted(_)
            | redb::Error::TransactionPoisoned
            | redb::Error::LockPoisoned(_)
            | redb::Error::Backend(_)
    )
}

/// A failure of the database while running, classified: a fault that needs
/// a reopen, or another failure.
#[derive(Debug)]
struct DbFailure {
    reopen: bool,
    message: String,
}

impl DbFailure {
    fn of(e: impl Into<redb::Error>) -> Self {
        let e: redb::Error = e.into();
        Self {
            reopen: needs_reopen(&e),
            message: e.to_string(),
        }
    }

    fn injected() -> Self {
        Self {
            reopen: false,
            message: "injected commit failure".into(),
        }
    }

    fn into_store_error(self) -> StoreError {
        StoreError::Failed(self.message)
    }
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
}

/// What the writer thread shares with the store's handle.
#[derive(Default)]
struct Shared {
    /// Sessions whose log has a hole (a commit with their writes failed).
    broken: Mutex<HashSet<Arc<str>>>,
    /// Commits to fail on purpose (tests of the failure path).
    fail_next: AtomicU32,
    /// The open database; `None` after a storage fault until the writer
    /// has reopened it. Readers clone the handle for one read.
    db: RwLock<Option<Arc<Database>>>,
    /// Why the store cannot write, while it cannot.
    fault: Mutex<Option<String>>,
}

impl Shared {
    /// The open database, or why there is none.
    fn db(&self) -> Result<Arc<Database>, StoreError> {
        if let Some(db) = self.db.read().as_ref() {
            return Ok(Arc::clone(db));
        }
        let why = self
            .fault
            .lock()
            .clone()
            .unwrap_or_else(|| "the database is being reopened".into());
        Err(StoreError::Unavailable(why))
    }

    fn set_fault(&self, why: &str) {
        let mut fault = self.fault.lock();
        if fault.is_none() {
            metrics::gauge!("mcapi_store_healthy").set(0.0);
        }
        *fault = Some(why.to_string());
    }

    fn clear_fault(&self) {
        if self.fault.lock().take().is_some() {
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

/// The store: a redb database and its writer thread.
pub struct Store {
    path: PathBuf,
    shared: Arc<Shared>,
    tx: Mutex<Option<Sender<Pending>>>,
    writer: Mutex<Option<JoinHandle<()>>>,
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store").field("path", &self.path).finish()
    }
}

impl Store {
    /// Opens (or creates) the store in `dir`, checking the file's integrity
    /// and format version.
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(|e| StoreError::Io {
            path: dir.to_path_buf(),
            reason: format!("cannot create the data directory: {e}"),
        })?;
        let path = dir.join(FILE_NAME);
        let db = open_database(&path)?;
        let (tx, rx) = unbounded::<Pending>();
        let shared = Arc::new(Shared::default());
        *shared.db.write() = Some(Arc::new(db));
        let writer_shared = Arc::clone(&shared);
        let writer_path = path.clone();
        let writer = std::thread::Builder::new()
            .name("mcapi-store".into())
            .spawn(move || Writer::new(writer_path, writer_shared).run(&rx))
            .map_err(|e| StoreError::Io {
                path: path.clone(),
                reason: format!("starting the writer thread: {e}"),
            })?;
        Ok(Self {
            path,
            shared,
            tx: Mutex::new(Some(tx)),
            writer: Mutex::new(Some(writer)),
        })
    }

    /// Whether the store can write: `Err` with the reason while it cannot
    /// (after a storage fault, until the database is reopened and a probe
    /// commit succeeds).
    pub fn health(&self) -> Result<(), String> {
        match self.shared.fault.lock().as_ref() {
            Some(why) => Err(why.clone()),
            None => Ok(()),
        }
    }

    /// The open database for one read, or [`StoreError::Unavailable`].
    fn db(&self) -> Result<Arc<Database>, StoreError> {
        self.shared.db()
    }

    /// A failed read: an I/O error (latched by redb) is reported to the
    /// writer, which reopens the database, so a failing read does not wait
    /// for the next write to be noticed.
    fn read_failed(&self, e: impl Into<redb::Error>) -> StoreError {
        let e: redb::Error = e.into();
        // Only an I/O error: a read that finds a damaged page fails alone.
        if matches!(e, redb::Error::Io(_) | redb::Error::PreviousIo) {
            self.shared.set_fault(&e.to_string());
            // An empty write wakes the writer, which sees the fault.
            if let Some(tx) = self.tx.lock().as_ref() {
                let _ = tx.send(Pending {
                    writes: Vec::new(),
                    done: None,
                });
            }
        }
        StoreError::Failed(e.to_string())
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
        let failed = |e: redb::Error| self.read_failed(e);
        let read = self.db()?.begin_read().map_err(|e| failed(e.into()))?;
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

    /// Stops the writer after it has committed everything queued.
    pub fn close(&self) {
        self.tx.lock().take();
        if let Some(h) = self.writer.lock().take()
            && h.join().is_err()
        {
            tracing::error!("the store writer panicked");
        }
    }
}

impl Drop for Store {
    fn drop(&mut self) {
        self.close();
    }
}

/// Opens (or creates) the database file, checking its integrity and format
/// version (upgrading a format-2 file); at start and at every reopen.
fn open_database(path: &Path) -> Result<Database, StoreError> {
    let corrupt = |reason: String| StoreError::Corrupt {
        path: path.to_path_buf(),
        reason,
    };
    // An I/O error (a full disk) is not damage: it is reported as such, at
    // start and at a reopen after a storage fault.
    let failed = |e: redb::Error| match e {
        redb::Error::Io(io)
            if !matches!(
                io.kind(),
                std::io::ErrorKind::InvalidData | std::io::ErrorKind::UnexpectedEof
            ) =>
        {
            StoreError::Io {
                path: path.to_path_buf(),
                reason: io.to_string(),
            }
        }
        redb::Error::PreviousIo => StoreError::Io {
            path: path.to_path_buf(),
            reason: e.to_string(),
        },
        other => corrupt(other.to_string()),
    };
    let existed = path.metadata().map(|m| m.len() > 0).unwrap_or(false);
    let db = Database::builder()
        .set_check_integrity_on_open(true)
        .create(path)
        .map_err(|e| match e {
            redb::DatabaseError::DatabaseAlreadyOpen => StoreError::Io {
                path: path.to_path_buf(),
                reason: "already open in another process (is another mcapi running on this data directory?)".into(),
            },
            other => failed(other.into()),
        })?;
    let mut write = db.begin_write().map_err(|e| failed(e.into()))?;
    write.set_two_phase_commit(true);
    {
        let mut meta = write.open_table(META).map_err(|e| failed(e.into()))?;
        let found = meta
            .get("format_version")
            .map_err(|e| failed(e.into()))?
            .map(|v| v.value());
        match found {
            Some(FORMAT_VERSION) => {}
            Some(2) => {
                let started = Instant::now();
                let records = tag_format_2_records(&write)
                    .map_err(|e| corrupt(format!("upgrading from format version 2: {e}")))?;
                meta.insert("format_version", FORMAT_VERSION)
                    .map_err(|e| failed(e.into()))?;
                tracing::info!(
                    path = %path.display(),
                    records,
                    seconds = started.elapsed().as_secs_f64(),
                    "store upgraded from format version 2 to {FORMAT_VERSION}"
                );
            }
            Some(found) => {
                return Err(StoreError::Version {
                    path: path.to_path_buf(),
                    found,
                });
            }
            None if existed => {
                return Err(corrupt("the format version record is missing".into()));
            }
            None => {
                meta.insert("format_version", FORMAT_VERSION)
                    .map_err(|e| failed(e.into()))?;
            }
        }
        write.open_table(SESSIONS).map_err(|e| failed(e.into()))?;
        write.open_table(SNAPSHOTS).map_err(|e| failed(e.into()))?;
        write.open_table(LOG).map_err(|e| failed(e.into()))?;
    }
    write.commit().map_err(|e| failed(e.into()))?;
    Ok(db)
}

/// The writer thread: group commits, and the database's recovery after a
/// storage fault.
struct Writer {
    path: PathBuf,
    shared: Arc<Shared>,
    /// While the store is down: when to try reopening next.
    retry_at: Option<Instant>,
    /// The wait before the next attempt.
    backoff: Duration,
}

impl Writer {
    fn new(path: PathBuf, shared: Arc<Shared>) -> Self {
        Self {
            path,
            shared,
            retry_at: None,
            backoff: MIN_BACKOFF,
        }
    }

    fn run(mut self, rx: &Receiver<Pending>) {
        loop {
            // While the store is down, wake up to retry even without writes:
            // the health probe.
            let first = match self.retry_at {
                None => match rx.recv() {
                    Ok(p) => p,
                    Err(_) => break,
                },
                Some(at) => match rx.recv_timeout(at.saturating_duration_since(Instant::now())) {
                    Ok(p) => p,
                    Err(RecvTimeoutError::Timeout) => {
                        self.try_reopen();
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
        }
        // Closed: let go of the database (the file lock) with the writer.
        self.shared.db.write().take();
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
        // A reader found a fault the writer has not seen: reopen now.
        if self.retry_at.is_none() && shared.fault.lock().is_some() {
            self.down(None);
        }
        if self.retry_at.is_some_and(|at| Instant::now() >= at) {
            self.try_reopen();
        }
        let result = if group.iter().all(|p| p.writes.is_empty()) {
            // Nothing to commit (a wake-up, or every write refused).
            Ok(())
        } else if self.retry_at.is_some() {
            // Down: fail at once rather than on the latched handle.
            Err(shared.db().err().unwrap_or_else(|| {
                StoreError::Unavailable("the database is being reopened".into())
            }))
        } else {
            let started = Instant::now();
            let injected = shared
                .fail_next
                .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1))
                .is_ok();
            let outcome = if injected {
                Err(DbFailure::injected())
            } else {
                match shared.db() {
                    Ok(db) => commit(&db, &group),
                    Err(e) => Err(DbFailure {
                        reopen: true,
                        message: e.to_string(),
                    }),
                }
            };
            metrics::histogram!("mcapi_store_commit_seconds")
                .record(started.elapsed().as_secs_f64());
            metrics::histogram!("mcapi_store_commit_writes").record(writes as f64);
            match outcome {
                Ok(()) => {
                    self.backoff = MIN_BACKOFF;
                    Ok(())
                }
                Err(f) => {
                    tracing::error!(error = %f.message, writes, reopen = f.reopen, "store commit failed");
                    if f.reopen {
                        self.down(Some(&f.message));
                    }
                    Err(f.into_store_error())
                }
            }
        };
        if result.is_err() {
            let mut broken = shared.broken.lock();
            for w in group.iter().flat_map(|p| &p.writes) {
                if let Some(id) = w.extends() {
                    broken.insert(Arc::clone(id));
                }
            }
        } else {
            // A deleted session's writes are no longer refused (its id is
            // never reused); only once the delete is durable.
            let mut broken = shared.broken.lock();
            for w in group.iter().flat_map(|p| &p.writes) {
                if let Write::Delete { id } = w {
                    broken.remove(id);
                }
            }
        }
        for mut p in group {
            if let Some(done) = p.done.take() {
                let _ = done.send(result.clone());
            }
        }
    }

    /// The database failed and must be reopened: closes it now (readers get
    /// `Unavailable` instead of the latched error) and schedules a reopen.
    fn down(&mut self, why: Option<&str>) {
        if let Some(why) = why {
            self.shared.set_fault(why);
        }
        let taken = self.shared.db.write().take();
        if let Some(db) = taken {
            self.release(db);
        }
        if self.retry_at.is_none() {
            // Doubled here too: a store whose reopen succeeds but whose
            // next commit fails again retries less and less often.
            self.retry_at = Some(Instant::now() + self.backoff);
            self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
        }
    }

    /// Closes a handle once the readers still holding it are done (redb
    /// holds the file lock until its last handle is dropped).
    fn release(&self, mut db: Arc<Database>) {
        let deadline = Instant::now() + RELEASE_WAIT;
        loop {
            match Arc::try_unwrap(db) {
                Ok(db) => {
                    if let Err(e) = db.close() {
                        tracing::warn!(error = %e, "closing the failed store handle");
                    }
                    return;
                }
                Err(shared) if Instant::now() < deadline => {
                    db = shared;
                    std::thread::sleep(Duration::from_millis(1));
                }
                Err(_) => {
                    tracing::warn!(
                        "a reader still holds the failed store handle; reopening anyway"
                    );
                    return;
                }
            }
        }
    }

    /// One reopen attempt: open the file (redb repairs it to its last
    /// commit), then a probe commit on the new handle. On success the store
    /// is healthy again; on failure the next attempt waits twice as long.
    fn try_reopen(&mut self) {
        let started = Instant::now();
        let attempt = open_database(&self.path).and_then(|db| {
            probe(&db).map_err(|f| {
                StoreError::Failed(format!("the probe commit failed: {}", f.message))
            })?;
            Ok(db)
        });
        match attempt {
            Ok(db) => {
                *self.shared.db.write() = Some(Arc::new(db));
                self.retry_at = None;
                self.shared.clear_fault();
                metrics::counter!("mcapi_store_reopens_total").increment(1);
                tracing::info!(
                    path = %self.path.display(),
                    seconds = started.elapsed().as_secs_f64(),
                    "store reopened after a storage fault"
                );
            }
            Err(e) => {
                self.shared.set_fault(&e.to_string());
                self.retry_at = Some(Instant::now() + self.backoff);
                tracing::warn!(error = %e, retry_in_ms = self.backoff.as_millis() as u64, "the store cannot be reopened yet");
                self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
            }
        }
    }
}

/// The health probe: on a freshly opened handle, a durable commit of
/// [`PROBE_BYTES`] of new data, then a second one that removes it. A reopen
/// alone proves little: redb reuses the free pages inside its file, so a
/// small commit can succeed on a full disk while the next real one fails
/// again. Writing more than a small store's free pages needs the disk; a
/// large store whose free pages hold the probe can also take real commits
/// until they run out (and the fault, with a longer backoff, returns).
fn probe(db: &Database) -> Result<(), DbFailure> {
    let blob = vec![0u8; PROBE_BYTES];
    for keep in [true, false] {
        let mut txn = db.begin_write().map_err(DbFailure::of)?;
        txn.set_durability(Durability::Immediate)
            .map_err(DbFailure::of)?;
        txn.set_two_phase_commit(true);
        {
            let mut table = txn.open_table(PROBE).map_err(DbFailure::of)?;
            if keep {
                table
                    .insert("probe", blob.as_slice())
                    .map_err(DbFailure::of)?;
            } else {
                table.remove("probe").map_err(DbFailure::of)?;
            }
        }
        txn.commit().map_err(DbFailure::of)?;
    }
    Ok(())
}

/// The 2 → 3 upgrade: prefixes every snapshot and log record with
/// [`RECORD_V2`]. Returns the number of records rewritten.
fn tag_format_2_records(write: &redb::WriteTransaction) -> Result<u64, String> {
    let e = |e: redb::Error| e.to_string();
    let tagged = |bytes: &[u8]| {
        let mut out = Vec::with_capacity(bytes.len() + 1);
        out.push(RECORD_V2);
        out.extend_from_slice(bytes);
        out
    };
    let mut n = 0u64;
    let mut snapshots = write.open_table(SNAPSHOTS).map_err(|x| e(x.into()))?;
    let mut rows = Vec::new();
    for row in snapshots.iter().map_err(|x| e(x.into()))? {
        let (id, v) = row.map_err(|x| e(x.into()))?;
        let (seq, bytes) = v.value();
        rows.push((id.value().to_string(), seq, tagged(bytes)));
    }
    for (id, seq, bytes) in &rows {
        snapshots
            .insert(id.as_str(), (*seq, bytes.as_slice()))
            .map_err(|x| e(x.into()))?;
        n += 1;
    }
    let mut log = write.open_table(LOG).map_err(|x| e(x.into()))?;
    let mut chunks = Vec::new();
    for row in log.iter().map_err(|x| e(x.into()))? {
        let (key, chunk) = row.map_err(|x| e(x.into()))?;
        let mut rest = chunk.value();
        let mut out = Vec::with_capacity(rest.len() + CHUNK as usize);
        while !rest.is_empty() {
            let (seq, entry, tail) =
                split_entry(rest).ok_or_else(|| "a log chunk is malformed".to_string())?;
            push_entry(&mut out, seq, &tagged(entry));
            n += 1;
            rest = tail;
        }
        chunks.push((key.value(), out));
    }
    for (key, chunk) in &chunks {
        log.insert(*key, chunk.as_slice())
            .map_err(|x| e(x.into()))?;
    }
    Ok(n)
}

/// Frames one record of a chunk: sequence number, length, bytes.
fn push_entry(chunk: &mut Vec<u8>, seq: u64, entry: &[u8]) {
    chunk.extend_from_slice(&seq.to_le_bytes());
    chunk.extend_from_slice(&(entry.len() as u32).to_le_bytes());
    chunk.extend_from_slice(entry);
}

/// The first record of a chunk and the rest.
fn split_entry(chunk: &[u8]) -> Option<(u64, &[u8], &[u8])> {
    let (seq, rest) = chunk.split_first_chunk::<8>()?;
    let (len, rest) = rest.split_first_chunk::<4>()?;
    let len = u32::from_le_bytes(*len) as usize;
    (rest.len() >= len).then(|| (u64::from_le_bytes(*seq), &rest[..len], &rest[len..]))
}

fn commit(db: &Database, group: &[Pending]) -> Result<(), DbFailure> {
    let mut txn = db.begin_write().map_err(DbFailure::of)?;
    txn.set_durability(Durability::Immediate)
        .map_err(DbFailure::of)?;
    // Two-phase: a damaged newest commit is then reported as corruption
    // instead of being taken for a torn write and silently rolled back
    // (which would lose acknowledged observations). Costs a second sync.
    txn.set_two_phase_commit(true);
    {
        let mut sessions = txn.open_table(SESSIONS).map_err(DbFailure::of)?;
        let mut snapshots = txn.open_table(SNAPSHOTS).map_err(DbFailure::of)?;
        let mut log = txn.open_table(LOG).map_err(DbFailure::of)?;
        for write in group.iter().flat_map(|p| &p.writes) {
            match write {
                Write::Session { id, record } => {
                    sessions
                        .insert(&**id, record.as_slice())
                        .map_err(DbFailure::of)?;
                }
                Write::Append { id, seq, entry } => {
                    let at = (log_key(id), seq / CHUNK);
                    let mut chunk = log
                        .get(at)
                        .map_err(DbFailure::of)?
                        .map(|v| v.value().to_vec())
                        .unwrap_or_default();
                    push_entry(&mut chunk, *seq, entry);
                    log.insert(at, chunk.as_slice()).map_err(DbFailure::of)?;
                }
                Write::Snapshot { id, seq, snapshot } => {
                    snapshots
                        .insert(&**id, (*seq, snapshot.as_slice()))
                        .map_err(DbFailure::of)?;
                    // Chunks wholly at or before `seq`; a partial chunk
                    // stays, and reads skip its covered records.
                    let key = log_key(id);
                    let whole = (seq.saturating_add(1)) / CHUNK;
                    log.retain_in((key, 0)..(key, whole), |_, _| false)
                        .map_err(DbFailure::of)?;
                }
                Write::Resume { .. } => {}
                Write::Delete { id } => {
                    sessions.remove(&**id).map_err(DbFailure::of)?;
                    snapshots.remove(&**id).map_err(DbFailure::of)?;
                    let key = log_key(id);
                    log.retain_in((key, 0)..=(key, u64::MAX), |_, _| false)
                        .map_err(DbFailure::of)?;
                }
            }
        }
    }
    txn.commit().map_err(DbFailure::of)
}

#[cfg(test)]
mod tests {
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
}
