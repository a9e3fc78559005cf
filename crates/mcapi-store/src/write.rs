//! One write to the store ([`Write`]), the writer thread's queue entry
//! that carries it ([`Pending`]) and what its caller awaits ([`Commit`]).

use std::sync::Arc;

use tokio::sync::oneshot;

use crate::error::StoreError;

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
    pub(crate) fn extends(&self) -> Option<&Arc<str>> {
        match self {
            Self::Append { id, .. } | Self::Snapshot { id, .. } => Some(id),
            Self::Session { .. } | Self::Delete { .. } | Self::Resume { .. } => None,
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
            Self::Snapshot { id, snapshot, .. } => id.len() + snapshot.len() + 8,
            Self::Delete { id } | Self::Resume { id } => id.len(),
        }
    }
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
