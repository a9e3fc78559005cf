//! A batch: the appends of many sessions gathered by one thread and sent to
//! the writer as few writes ([`Write::Appends`]), each one commit, instead
//! of one write, one queue entry and one commit per record. What a group
//! step writes (docs/groups.md, "Durability, shards and clusters").
//!
//! A session's writes must reach the writer in the order of its sequence
//! numbers: a later write committed before an earlier one could be
//! acknowledged and then survive a crash that loses the earlier. A batch
//! holds its records until it is sent, so whoever writes next to a session
//! with a record in an unsent batch sends that batch first ([`Batch::send`],
//! under the session's lock, which the batch's owner also holds while it
//! appends to the session). Nobody waits for anybody: a batch sent early is
//! sent in parts, each a commit of its own, and the owner awaits them all
//! ([`Batch::finish`]). A batch dropped unsent (its owner panicked) is sent
//! by its `Drop`, so no record applied in memory is left out of the log.

use std::ops::Range;
use std::sync::Arc;

use parking_lot::Mutex;

use crate::error::StoreError;
use crate::store::Store;
use crate::write::{Appends, Commit, LogId, Write};

/// Appends to many sessions' logs, sent as few writes.
pub struct Batch {
    store: Arc<Store>,
    inner: Mutex<Inner>,
}

impl std::fmt::Debug for Batch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Batch").finish_non_exhaustive()
    }
}

#[derive(Default)]
struct Inner {
    /// Records the owner expects to append ([`Batch::expecting`]); 0 once
    /// the first is appended and room made for them all.
    expected: usize,
    /// Writes queued and not sent yet; consecutive appends share the last
    /// [`Write::Appends`].
    writes: Vec<Write>,
    /// Writes added so far, sent or not (each append counts one): the
    /// position of the next.
    added: usize,
    /// The parts sent: the position after each one's last write, and its
    /// commit.
    sent: Vec<(usize, Commit)>,
}

impl Batch {
    /// An empty batch of writes to `store`.
    pub fn new(store: Arc<Store>) -> Self {
        Self {
            store,
            inner: Mutex::new(Inner::default()),
        }
    }

    /// An empty batch whose owner expects to append about `records`
    /// records of one size (a group step's chunk: one per member). Once the
    /// first is encoded, its buffer is sized for all of them, so it is
    /// written once instead of growing by doubling: each doubling copied
    /// what was there and took fresh memory.
    pub fn expecting(store: Arc<Store>, records: usize) -> Self {
        let batch = Self::new(store);
        batch.inner.lock().expected = records;
        batch
    }

    /// Appends one record to session `id`'s log at sequence number `seq`;
    /// `encode` writes the entry's bytes at the end of the buffer it is
    /// given (nothing is added if it fails). Returns the record's position
    /// in the batch ([`Outcome::of`]).
    pub fn append<E>(
        &self,
        id: &LogId,
        seq: u64,
        encode: impl FnOnce(&mut Vec<u8>) -> Result<(), E>,
    ) -> Result<usize, E> {
        let mut inner = self.inner.lock();
        if !matches!(inner.writes.last(), Some(Write::Appends(_))) {
            inner.writes.push(Write::Appends(Appends::default()));
        }
        let expected = std::mem::take(&mut inner.expected);
        if let Some(Write::Appends(appends)) = inner.writes.last_mut() {
            appends.push(id, seq, encode)?;
            if expected > 1 {
                // The rest at the first one's size, and 1/16 for their
                // differences (varints, optional fields). Once only: a
                // part begun after a snapshot or an early send grows as it
                // goes (a group's members snapshot at the same step, so
                // reserving for every part would reserve for the chunk
                // again and again).
                let rest = (expected - 1) * appends.records.len();
                appends.records.reserve_exact(rest + rest / 16);
            }
        }
        inner.added += 1;
        Ok(inner.added - 1)
    }

    /// Queues another write (a snapshot) after everything added so far.
    /// Returns its position.
    pub fn push(&self, write: Write) -> usize {
        let mut inner = self.inner.lock();
        inner.writes.push(write);
        inner.added += 1;
        inner.added - 1
    }

    /// Sends what is queued, if anything, as one part (one commit): what a
    /// write to a session with a record in this batch does first.
    pub fn send(&self) {
        let mut inner = self.inner.lock();
        if inner.writes.is_empty() {
            return;
        }
        let writes = std::mem::take(&mut inner.writes);
        let commit = self.store.submit(writes);
        let end = inner.added;
        inner.sent.push((end, commit));
    }

    /// Sends the rest and hands over the commits of every part.
    pub fn finish(&self) -> Sent {
        self.send();
        Sent(std::mem::take(&mut self.inner.lock().sent))
    }
}

impl Drop for Batch {
    /// Its records are applied in memory: they go to the log even if the
    /// batch's owner never finished it.
    fn drop(&mut self) {
        self.send();
    }
}

/// The commits of a batch's parts ([`Batch::finish`]).
#[derive(Debug, Default)]
pub struct Sent(Vec<(usize, Commit)>);

impl Sent {
    /// Waits for every part's commit.
    pub async fn wait(self) -> Outcome {
        let mut out = Vec::with_capacity(self.0.len());
        for (end, commit) in self.0 {
            out.push((end, commit.wait().await));
        }
        Outcome(out)
    }

    /// Waits for every part's commit, blocking the thread (not for async
    /// code).
    pub fn wait_blocking(self) -> Outcome {
        Outcome(
            self.0
                .into_iter()
                .map(|(end, commit)| (end, commit.wait_blocking()))
                .collect(),
        )
    }
}

/// What became of a batch's parts ([`Sent::wait`]).
#[derive(Debug, Default)]
pub struct Outcome(Vec<(usize, Result<(), StoreError>)>);

impl Outcome {
    /// Whether the writes at `positions` are durable: the first failure of
    /// a part holding one of them, if any.
    pub fn of(&self, positions: Range<usize>) -> Result<(), StoreError> {
        let mut start = 0;
        for (end, result) in &self.0 {
            if *end > positions.start && start < positions.end {
                result.clone()?;
            }
            start = *end;
        }
        if positions.end > start {
            // Never sent: the batch was finished before they were added.
            return Err(StoreError::Closed);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The capacity of each part's buffer, in order.
    fn capacities(batch: &Batch) -> Vec<usize> {
        let inner = batch.inner.lock();
        inner
            .writes
            .iter()
            .filter_map(|w| match w {
                Write::Appends(a) => Some(a.records.capacity()),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn a_batch_expecting_its_records_sizes_its_buffer_once() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Arc::new(Store::open(dir.path()).expect("open"));
        let ids: Vec<LogId> = (0..100)
            .map(|i| LogId::new(Arc::from(format!("m{i}"))))
            .collect();
        let append = |batch: &Batch, id: &LogId| {
            batch
                .append(id, 7, |out| {
                    out.extend_from_slice(&[1; 40]);
                    Ok::<(), StoreError>(())
                })
                .expect("append")
        };
        let batch = Batch::expecting(Arc::clone(&store), ids.len());
        append(&batch, &ids[0]);
        let sized = capacities(&batch);
        let record = 16 + 8 + 4 + 40;
        assert_eq!(sized.len(), 1);
        assert!(sized[0] >= 100 * record, "{sized:?}");
        for id in &ids[1..] {
            append(&batch, id);
        }
        assert_eq!(capacities(&batch), sized, "never grown again");
        // A part begun after another write grows as it goes: the room for
        // the whole batch is made once.
        batch.push(Write::Resume {
            id: Arc::clone(ids[0].id()),
        });
        append(&batch, &ids[1]);
        assert!(capacities(&batch)[1] < 10 * record);
        batch
            .finish()
            .wait_blocking()
            .of(0..102)
            .expect("committed");
    }
}
