//! The checkpointer thread: applies the write-ahead log's frames to redb in
//! bulk, off the commit path, and deletes the segments it has applied.
//!
//! It receives every frame the writer made durable, keeps them until a
//! checkpoint is due ([`CHECKPOINT_INTERVAL`] after the oldest, or
//! [`CHECKPOINT_BYTES`] of them, or a reader asks for one), then applies
//! them in one redb transaction that also records the last frame's number.
//! A frame is thus applied exactly once: by a checkpoint, or by the replay
//! at the next open if the process dies first.
//!
//! The frames wait in their own channel, which the thread drains only when
//! a checkpoint is due: the writer wakes it ([`ToCheckpoint::Wake`]) for the
//! first frame after a drain and when [`CHECKPOINT_BYTES`] are waiting, not
//! for every group commit. (Woken per frame, this thread took about 7% of a
//! durable server's CPU samples at 32 connections, most of it in context
//! switches; BENCHMARKS.md §8.)
//!
//! It also owns the database's recovery after a storage fault. redb
//! latches the first real I/O error of a `Database` (ENOSPC included):
//! every later call on it, reads too, fails with `StorageError::PreviousIo`
//! until it is closed and opened again. So after a checkpoint fails the
//! thread closes the database at once (readers then get
//! [`StoreError::Unavailable`] instead of the latched error), and reopens
//! it with backoff. A reopen counts only once a probe commit succeeds on
//! the new handle; until then the store reports the fault
//! ([`crate::Store::health`]) and the writer refuses new writes, so the
//! frames waiting here stay bounded. Nothing waiting is lost: the frames are
//! in the log, and the checkpoint is retried after the reopen.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError};
use redb::Database;

use crate::db::{self, DbFailure};
use crate::error::StoreError;
use crate::retry::Retry;
use crate::shared::Shared;
use crate::wal;
use crate::write::Write;

/// Longest a durable frame waits before it is applied to redb.
///
/// A checkpoint reads and rewrites the newest log chunk of every session it
/// touches, however few records each gained: under a steady load that
/// cost is paid per session per checkpoint, not per record. Ten thousand
/// sessions stepped together as a group gained about 4 records each per
/// 500 ms checkpoint, and applying them took 22% of the server's CPU
/// samples; checkpointing every 2 s spreads each chunk's rewrite over four
/// times as many records (BENCHMARKS.md, "Vectorised stepping"). Readers
/// never wait for it (they ask for a checkpoint of what they need), and
/// [`CHECKPOINT_BYTES`] still bounds what waits.
pub const CHECKPOINT_INTERVAL: Duration = Duration::from_secs(2);
/// Bytes of waiting writes that make a checkpoint due at once.
const CHECKPOINT_BYTES: usize = 32 << 20;
/// How long a reopen waits for readers to let go of the failed handle
/// (redb holds the file lock until the last one is dropped).
const RELEASE_WAIT: Duration = Duration::from_secs(2);

/// A frame the log made durable, with its writes (the frames channel).
pub(super) struct Frame {
    pub(super) lsn: u64,
    pub(super) writes: Vec<Write>,
}

impl Frame {
    /// What it adds to [`Shared::frame_bytes`] while it waits in
    /// the channel.
    pub(super) fn size(writes: &[Write]) -> usize {
        writes.iter().map(Write::size).sum()
    }
}

/// What the writer and the readers send the checkpointer (the control
/// channel, which it sleeps on).
pub(super) enum ToCheckpoint {
    /// Frames are waiting: the first since the last drain, or
    /// [`CHECKPOINT_BYTES`] of them.
    Wake,
    /// Apply every frame sent so far now, then answer.
    Flush(crossbeam_channel::Sender<Result<(), StoreError>>),
}

/// Whether adding `added` bytes to the `before` already waiting calls for a
/// [`ToCheckpoint::Wake`] (the writer's side of the protocol above).
pub(super) fn wake_for(before: usize, added: usize) -> bool {
    before == 0 || (before < CHECKPOINT_BYTES && before + added >= CHECKPOINT_BYTES)
}

/// The checkpointer's state.
pub(super) struct Checkpointer {
    /// The redb file.
    path: PathBuf,
    /// Its page cache's ceiling, in bytes (kept for reopening).
    cache_bytes: usize,
    /// The log's directory.
    wal_dir: PathBuf,
    shared: Arc<Shared>,
    /// Writes received and not yet applied, in order.
    waiting: Vec<Write>,
    /// Their bytes (keys and values).
    waiting_bytes: usize,
    /// The number of the newest frame received.
    newest: u64,
    /// When the oldest waiting write arrived.
    oldest: Option<Instant>,
    /// While the database is down: when to try reopening next.
    retry: Retry,
    /// The chunk buffers of the last checkpoints, for the next ones.
    spare: db::Spare,
}

impl Checkpointer {
    pub(super) fn new(
        path: PathBuf,
        cache_bytes: usize,
        wal_dir: PathBuf,
        shared: Arc<Shared>,
        applied: u64,
    ) -> Self {
        Self {
            path,
            cache_bytes,
            wal_dir,
            shared,
            waiting: Vec::new(),
            waiting_bytes: 0,
            newest: applied,
            oldest: None,
            retry: Retry::new(),
            spare: db::Spare::default(),
        }
    }

    pub(super) fn run(mut self, rx: &Receiver<ToCheckpoint>, frames: &Receiver<Frame>) {
        loop {
            // While the database is down, only the reopen is due: a
            // checkpoint cannot succeed before it (and would spin).
            let due = if self.retry.is_scheduled() {
                self.retry.at()
            } else {
                self.oldest.map(|t| t + CHECKPOINT_INTERVAL)
            };
            let msg = match due {
                None => {
                    // Idle until the next write: the buffers kept for busy
                    // checkpoints are given back.
                    self.spare = db::Spare::default();
                    rx.recv().map_err(|_| RecvTimeoutError::Disconnected)
                }
                Some(at) => rx.recv_timeout(at.saturating_duration_since(Instant::now())),
            };
            match msg {
                Ok(ToCheckpoint::Wake) => {
                    // Frames wait from now; drained when the interval ends,
                    // or now if they are many.
                    self.oldest.get_or_insert_with(Instant::now);
                    if self.shared.frame_bytes.load(Ordering::SeqCst) >= CHECKPOINT_BYTES {
                        self.drain(frames);
                        let _ = self.checkpoint();
                    }
                }
                Ok(ToCheckpoint::Flush(reply)) => {
                    // Every frame sent before the request is included: the
                    // writer sends a frame before anyone hears of its commit.
                    let mut replies = vec![reply];
                    while let Ok(msg) = rx.try_recv() {
                        if let ToCheckpoint::Flush(r) = msg {
                            replies.push(r);
                        }
                    }
                    self.drain(frames);
                    let result = self.checkpoint();
                    for r in replies {
                        let _ = r.send(result.clone());
                    }
                }
                Err(RecvTimeoutError::Timeout) => {
                    if self.retry.is_due(Instant::now()) {
                        self.try_reopen();
                    }
                    if self
                        .oldest
                        .is_some_and(|t| t.elapsed() >= CHECKPOINT_INTERVAL)
                    {
                        self.drain(frames);
                        let _ = self.checkpoint();
                    }
                }
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        // The writer is gone: apply the rest, and with it every segment.
        self.drain(frames);
        if !self.shared.crashed.load(Ordering::SeqCst) && self.checkpoint().is_ok() {
            self.remove_segments(u64::MAX);
        }
        self.shared.db.write().take();
    }

    /// Takes every frame waiting in the channel. Frames the writer adds
    /// meanwhile stay counted in `frame_bytes`, and the next checkpoint
    /// keeps `oldest` set for them (the writer does not wake us for them).
    fn drain(&mut self, frames: &Receiver<Frame>) {
        let mut bytes = 0;
        for Frame { lsn, writes } in frames.try_iter() {
            bytes += Frame::size(&writes);
            self.waiting_bytes += Frame::size(&writes);
            self.waiting.extend(writes);
            self.newest = lsn;
            self.oldest.get_or_insert_with(Instant::now);
        }
        self.shared.frame_bytes.fetch_sub(bytes, Ordering::SeqCst);
    }

    /// Applies everything waiting in one transaction; on success the
    /// segments wholly applied are deleted.
    fn checkpoint(&mut self) -> Result<(), StoreError> {
        if self.waiting.is_empty() {
            if self.shared.frame_bytes.load(Ordering::SeqCst) == 0 {
                self.oldest = None;
            }
            return Ok(());
        }
        if self.retry.is_due(Instant::now()) {
            self.try_reopen();
        }
        let db = match self.shared.db() {
            Ok(db) if !self.retry.is_scheduled() => db,
            Ok(_) | Err(_) => {
                return Err(self.shared.db().err().unwrap_or_else(|| {
                    StoreError::Unavailable("the database is being reopened".into())
                }));
            }
        };
        let started = Instant::now();
        let writes = self.waiting.len();
        let outcome = db::apply(&db, self.waiting.iter(), self.newest, &mut self.spare);
        drop(db);
        metrics::histogram!("mcapi_store_checkpoint_seconds")
            .record(started.elapsed().as_secs_f64());
        match outcome {
            Ok(()) => {
                self.waiting.clear();
                self.waiting_bytes = 0;
                // Frames sent since the drain are not applied yet, and the
                // writer will not wake us for them: they wait from now.
                self.oldest =
                    (self.shared.frame_bytes.load(Ordering::SeqCst) > 0).then(Instant::now);
                self.retry.worked();
                self.shared.applied.store(self.newest, Ordering::Release);
                metrics::histogram!("mcapi_store_checkpoint_writes").record(writes as f64);
                self.remove_segments(self.newest);
                Ok(())
            }
            Err(f) => {
                tracing::error!(error = %f.message, writes, reopen = f.reopen, "store checkpoint failed; the writes stay in the log");
                self.down(&f);
                Err(StoreError::Failed(f.message))
            }
        }
    }

    /// Deletes the closed segments whose frames are all at or before
    /// `applied` (every segment, the active one too, with `u64::MAX` at
    /// close).
    fn remove_segments(&self, applied: u64) {
        let mut removed = false;
        let paths: Vec<PathBuf> = if applied == u64::MAX {
            match wal::list_segments(&self.wal_dir) {
                Ok(all) => all.into_iter().map(|(_, p)| p).collect(),
                Err(e) => {
                    tracing::warn!(error = %e, "listing the log segments at close");
                    return;
                }
            }
        } else {
            let mut closed = self.shared.closed.lock();
            let (done, keep): (Vec<_>, Vec<_>) =
                closed.drain(..).partition(|(_, last, _)| *last <= applied);
            *closed = keep;
            done.into_iter().map(|(_, _, p)| p).collect()
        };
        for path in paths {
            match std::fs::remove_file(&path) {
                Ok(()) => removed = true,
                Err(e) => {
                    tracing::warn!(path = %path.display(), error = %e, "removing an applied log segment")
                }
            }
        }
        if removed && let Err(e) = wal::sync_dir(&self.wal_dir) {
            tracing::warn!(error = %e, "syncing the log directory");
        }
    }

    /// The database failed: closes it now (readers get `Unavailable`
    /// instead of the latched error) and schedules a reopen.
    fn down(&mut self, f: &DbFailure) {
        self.shared.set_fault(&self.shared.db_fault, &f.message);
        if f.reopen {
            let taken = self.shared.db.write().take();
            if let Some(db) = taken {
                self.release(db);
            }
        }
        self.retry.went_down();
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
    /// commit; a handle that did not fail is kept), then a probe commit. On
    /// success the database is healthy again and the checkpoint is retried
    /// at once; on failure the next attempt waits twice as long.
    fn try_reopen(&mut self) {
        let started = Instant::now();
        let current = self.shared.db.read().clone();
        let attempt = match current {
            Some(db) => db::probe(&db)
                .map(|()| None)
                .map_err(|f| StoreError::Failed(format!("the probe commit failed: {}", f.message))),
            None => db::open_database(&self.path, self.cache_bytes).and_then(|(db, _)| {
                db::probe(&db).map_err(|f| {
                    StoreError::Failed(format!("the probe commit failed: {}", f.message))
                })?;
                Ok(Some(db))
            }),
        };
        match attempt {
            Ok(db) => {
                if let Some(db) = db {
                    *self.shared.db.write() = Some(Arc::new(db));
                    metrics::counter!("mcapi_store_reopens_total").increment(1);
                }
                self.retry.cleared();
                self.shared.clear_fault(&self.shared.db_fault);
                tracing::info!(
                    part = "database",
                    path = %self.path.display(),
                    seconds = started.elapsed().as_secs_f64(),
                    "store reopened after a storage fault"
                );
                if !self.waiting.is_empty() {
                    let _ = self.checkpoint();
                }
            }
            Err(e) => {
                self.shared.set_fault(&self.shared.db_fault, &e.to_string());
                let wait = self.retry.attempt_failed();
                tracing::warn!(part = "database", error = %e, retry_in_ms = wait.as_millis() as u64, "the store cannot be reopened yet");
            }
        }
    }
}
