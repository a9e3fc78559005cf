//! One write to the store ([`Write`]), the writer thread's queue entry
//! that carries it ([`Pending`]) and what its caller awaits ([`Commit`]).

use std::sync::Arc;

use tokio::sync::oneshot;

use crate::error::StoreError;
use crate::record::{self, FRAME};

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
    /// Appends records to many sessions' logs (a [`crate::Batch`]'s part):
    /// one write, one record of the log, however many sessions.
    Appends(Appends),
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
    /// The sessions an append or snapshot extends (what a broken session
    /// may not get).
    pub(crate) fn extends(&self) -> &[Arc<str>] {
        match self {
            Self::Append { id, .. } | Self::Snapshot { id, .. } => std::slice::from_ref(id),
            Self::Appends(a) => &a.ids,
            Self::Session { .. } | Self::Delete { .. } | Self::Resume { .. } => &[],
        }
    }

    /// Whether the write is stored (a `Resume` only changes what the writer
    /// accepts).
    pub(crate) fn is_logged(&self) -> bool {
        !matches!(self, Self::Resume { .. })
    }

    /// Bytes it holds, roughly (what waiting for a checkpoint costs).
    pub(crate) fn size(&self) -> usize {
        match self {
            Self::Session { id, record } => id.len() + record.len(),
            Self::Append { id, entry, .. } => id.len() + entry.len() + 8,
            Self::Appends(a) => a.records.len(),
            Self::Snapshot { id, snapshot, .. } => id.len() + snapshot.len() + 8,
            Self::Delete { id } | Self::Resume { id } => id.len(),
        }
    }
}

/// Records appended to many sessions' logs, back to back in one buffer
/// (no allocation per record): each is the session's log key (16 bytes,
/// little-endian), then the record as a log chunk frames it (sequence
/// number, length, entry; `db.rs`), so a checkpoint copies it into the
/// chunk as it is.
#[derive(Debug, Clone, Default)]
pub struct Appends {
    /// The session of each record, in order (what a failed commit marks
    /// broken). Kept in memory only: the log holds the keys, which is all
    /// a replay needs, so appends read back from it have none.
    pub(crate) ids: Vec<Arc<str>>,
    /// The records.
    pub(crate) records: Vec<u8>,
}

/// Bytes of a record of [`Appends`] before its entry: key, sequence
/// number, length.
const APPEND_HEADER: usize = 16 + FRAME;

/// A session's id with its log key, worked out once (the key of a
/// `s<shard>.<ULID>` id is the ULID's bits, parsed from the text): what a
/// session that appends to [`Appends`] again and again keeps, instead of
/// parsing its id per record.
#[derive(Debug, Clone)]
pub struct LogId {
    id: Arc<str>,
    key: u128,
}

impl LogId {
    /// The log id of session `id`.
    pub fn new(id: Arc<str>) -> Self {
        let key = record::log_key(&id);
        Self { id, key }
    }

    /// The session's id.
    pub fn id(&self) -> &Arc<str> {
        &self.id
    }
}

impl Appends {
    /// Appends a record to session `id`'s log; `encode` writes the entry at
    /// the end of the buffer (nothing is added if it fails).
    pub(crate) fn push<E>(
        &mut self,
        id: &LogId,
        seq: u64,
        encode: impl FnOnce(&mut Vec<u8>) -> Result<(), E>,
    ) -> Result<(), E> {
        let start = self.records.len();
        self.records.extend_from_slice(&id.key.to_le_bytes());
        self.records.extend_from_slice(&seq.to_le_bytes());
        self.records.extend_from_slice(&[0; 4]);
        if let Err(e) = encode(&mut self.records) {
            self.records.truncate(start);
            return Err(e);
        }
        let len = (self.records.len() - start - APPEND_HEADER) as u32;
        self.records[start + 16 + 8..start + APPEND_HEADER].copy_from_slice(&len.to_le_bytes());
        self.ids.push(Arc::clone(&id.id));
        Ok(())
    }

    /// Appends read back from the log: `None` unless `records` is whole
    /// records.
    pub(crate) fn decoded(records: Vec<u8>) -> Option<Self> {
        let appends = Self {
            ids: Vec::new(),
            records,
        };
        let mut rest = appends.records.as_slice();
        while !rest.is_empty() {
            let (_, _, tail) = split_record(rest)?;
            rest = tail;
        }
        Some(appends)
    }

    /// The records in order: the session's log key, the sequence number
    /// and the record as a chunk frames it. Stops at a malformed record
    /// (never made: [`Self::decoded`] checks what the log gives back).
    pub(crate) fn records(&self) -> impl Iterator<Item = (u128, u64, &[u8])> {
        let mut rest = self.records.as_slice();
        std::iter::from_fn(move || {
            let (key, framed, tail) = split_record(rest)?;
            rest = tail;
            let seq = u64::from_le_bytes(*framed.first_chunk::<8>()?);
            Some((key, seq, framed))
        })
    }

    /// Number of records.
    pub fn len(&self) -> usize {
        self.records().count()
    }

    /// Whether it holds no record.
    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }
}

/// The first record of [`Appends::records`] (its key and the record as a
/// chunk frames it) and the rest.
fn split_record(bytes: &[u8]) -> Option<(u128, &[u8], &[u8])> {
    let (key, framed) = bytes.split_first_chunk::<16>()?;
    let (_, entry, _) = record::split_entry(framed)?;
    let (framed, tail) = framed.split_at_checked(FRAME + entry.len())?;
    Some((u128::from_le_bytes(*key), framed, tail))
}

pub(crate) struct Pending {
    pub(crate) writes: Vec<Write>,
    pub(crate) done: Option<oneshot::Sender<Result<(), StoreError>>>,
}

/// Resolves when the writes it was returned for are durable.
#[derive(Debug)]
pub struct Commit(pub(crate) oneshot::Receiver<Result<(), StoreError>>);

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
