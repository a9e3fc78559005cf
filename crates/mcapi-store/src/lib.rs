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
//!   checkpointer thread (`checkpoint.rs`) about every 2 s, after
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
//!
//! Many sessions' appends can be sent as one write ([`Batch`], what a group
//! step writes): one record of the log, one commit, expanded into the
//! sessions' logs by the checkpoint that applies it (or the replay at
//! open), so that readers see nothing but ordinary logs.
//!
//! Files, one idea each: [`Store`]'s public API (`store.rs`), the write and
//! its commit (`write.rs`), the batch (`batch.rs`), a record's log key and
//! framing (`record.rs`), the errors (`error.rs`), the state the threads
//! share (`shared.rs`), the writer thread (`writer.rs`), retry with backoff
//! after a storage fault (`retry.rs`), the log ([`wal`]), the redb layout
//! (`db.rs`) and the checkpointer (`checkpoint.rs`).

mod batch;
mod checkpoint;
mod db;
mod error;
mod format;
mod record;
mod retry;
mod shared;
mod store;
pub mod wal;
mod write;
mod writer;

pub use batch::{Batch, Outcome, Sent};
pub use db::{CHUNK, RECORD_V2};
pub use error::StoreError;
pub use format::FORMAT_VERSION;
pub use store::{DEFAULT_CACHE_BYTES, ExportedSession, FILE_NAME, Store, StoredSession};
pub use wal::{Durability, OS_SYNC_INTERVAL};
pub use write::{Appends, Commit, LogId, Write};

#[cfg(test)]
mod tests;
