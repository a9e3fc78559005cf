//! What can go wrong with the store.

use std::path::PathBuf;
use std::sync::Arc;

use thiserror::Error;

use crate::format::FORMAT_VERSION;

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
    /// until it is reloaded ([`Write::Resume`](crate::Write::Resume)).
    #[error(
        "an earlier write of session `{0}` failed; its writes are refused until it is reloaded"
    )]
    Broken(Arc<str>),
    /// The store was closed.
    #[error("the store is closed")]
    Closed,
}
