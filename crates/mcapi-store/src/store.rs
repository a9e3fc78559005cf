//! The store's public API: opening (integrity, format upgrade, replay of
//! the log), submitting writes, reads at run time, closing.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::thread::JoinHandle;
use std::time::Instant;

use crossbeam_channel::{Sender, unbounded};
use parking_lot::Mutex;
use redb::{Database, ReadableDatabase, ReadableTable};
use tokio::sync::oneshot;

use crate::checkpoint::{Checkpointer, Frame, ToCheckpoint};
use crate::db::{self, CHUNK, LOG, SESSIONS, SNAPSHOTS};
use crate::error::StoreError;
use crate::record::{log_key, split_entry};
use crate::retry::Retry;
use crate::shared::Shared;
use crate::wal::{self, Durability, Wal};
use crate::write::{Commit, Pending, Write};
use crate::writer::Writer;

/// Name of the redb file inside the data directory.
pub const FILE_NAME: &str = "mcapi.redb";

/// Default ceiling of the database's page cache (`--store-cache-mib`):
/// enough for the B-tree's interior pages of millions of sessions; the
/// snapshots and logs themselves are read once per recovery or load.
pub const DEFAULT_CACHE_BYTES: usize = 64 << 20;

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
    pub(crate) shared: Arc<Shared>,
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
    pub(crate) fn db(&self) -> Result<Arc<Database>, StoreError> {
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
