//! What the writer and checkpointer threads share with the store's handle:
//! the open database, the broken sessions, the faults and the progress of
//! the log's frames.

use std::collections::HashSet;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64};

use parking_lot::{Mutex, RwLock};
use redb::Database;

use crate::error::StoreError;

/// What the writer and checkpointer threads share with the store's handle.
#[derive(Default)]
pub(crate) struct Shared {
    /// Sessions whose log has a hole (a commit with their writes failed).
    pub(crate) broken: Mutex<HashSet<Arc<str>>>,
    /// Commits to fail on purpose (tests of the failure path).
    pub(crate) fail_next: AtomicU32,
    /// The open database; `None` after a storage fault until the
    /// checkpointer has reopened it. Readers clone the handle for one read.
    pub(crate) db: RwLock<Option<Arc<Database>>>,
    /// Why the log cannot be written, while it cannot.
    pub(crate) wal_fault: Mutex<Option<String>>,
    /// Why the database cannot be written, while it cannot.
    pub(crate) db_fault: Mutex<Option<String>>,
    /// The newest frame handed to the checkpointer.
    pub(crate) forwarded: AtomicU64,
    /// Bytes of frames in the checkpointer's frames channel, not yet
    /// drained (added by the writer before it sends a frame).
    pub(crate) frame_bytes: std::sync::atomic::AtomicUsize,
    /// The newest frame applied to the database.
    pub(crate) applied: AtomicU64,
    /// Closed log segments not yet deleted: first and last frame, path.
    pub(crate) closed: Mutex<Vec<(u64, u64, PathBuf)>>,
    /// Set by [`Store::crash`]: stop without the final checkpoint.
    pub(crate) crashed: std::sync::atomic::AtomicBool,
}

impl Shared {
    /// The open database, or why there is none.
    pub(crate) fn db(&self) -> Result<Arc<Database>, StoreError> {
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
    pub(crate) fn fault(&self) -> Option<String> {
        self.wal_fault
            .lock()
            .clone()
            .or_else(|| self.db_fault.lock().clone())
    }

    pub(crate) fn set_fault(&self, which: &Mutex<Option<String>>, why: &str) {
        let healthy = self.fault().is_none();
        *which.lock() = Some(why.to_string());
        if healthy {
            metrics::gauge!("mcapi_store_healthy").set(0.0);
        }
    }

    pub(crate) fn clear_fault(&self, which: &Mutex<Option<String>>) {
        let cleared = which.lock().take().is_some();
        if cleared && self.fault().is_none() {
            metrics::gauge!("mcapi_store_healthy").set(1.0);
        }
    }
}
