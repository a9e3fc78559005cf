//! The writer thread: takes everything queued since its last commit as one
//! group, appends it to the log as one frame and syncs once (group commit);
//! after a storage fault it refuses writes and repairs the log with backoff.

use std::io::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender};

use crate::checkpoint::{self, Frame, ToCheckpoint};
use crate::db;
use crate::error::StoreError;
use crate::retry::Retry;
use crate::shared::Shared;
use crate::wal::{AppendError, Durability, OS_SYNC_INTERVAL, Wal};
use crate::write::{Pending, Write};

/// Most writes folded into one group.
const MAX_GROUP: usize = 8192;

/// The probe file's name in the data directory (written and removed).
const PROBE_FILE: &str = "probe.tmp";

/// The writer thread: group commits to the log, and the log's recovery
/// after a storage fault.
pub(crate) struct Writer {
    pub(crate) wal: Wal,
    pub(crate) data_dir: PathBuf,
    pub(crate) durability: Durability,
    pub(crate) shared: Arc<Shared>,
    /// Wakes the checkpointer (see `checkpoint`'s module docs).
    pub(crate) checkpoint: Sender<ToCheckpoint>,
    /// Frames for the checkpointer, drained when a checkpoint is due.
    pub(crate) frames: Sender<Frame>,
    /// While the log is down: when to try repairing it next.
    pub(crate) retry: Retry,
    /// A failed write may have left part of a frame in the segment.
    pub(crate) dirty: bool,
    /// Under [`Durability::Os`]: when the unsynced frames must be synced.
    pub(crate) sync_due: Option<Instant>,
}

impl Writer {
    pub(crate) fn run(mut self, rx: &Receiver<Pending>) {
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
                if broken.is_empty() {
                    continue;
                }
                if let Some(id) = p
                    .writes
                    .iter()
                    .flat_map(Write::extends)
                    .find(|id| broken.contains(*id))
                {
                    refused.push((i, Arc::clone(id)));
                }
            }
        }
        for (i, id) in refused.iter().rev() {
            let mut p = group.remove(*i);
            // A refused write leaves a hole in the log of every session it
            // extends (a batch's part holds many): they are broken too.
            let mut broken = shared.broken.lock();
            for other in p.writes.iter().flat_map(Write::extends) {
                broken.insert(Arc::clone(other));
            }
            drop(broken);
            if let Some(done) = p.done.take() {
                let _ = done.send(Err(StoreError::Broken(Arc::clone(id))));
            }
        }
        let result = self.commit(&mut group, writes);
        if result.is_err() {
            let mut broken = shared.broken.lock();
            for w in group.iter().flat_map(|p| &p.writes) {
                for id in w.extends() {
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
