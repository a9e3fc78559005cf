//! The service's one error type. Transports map it to HTTP and gRPC in one
//! table (`api::error`); messages of user errors go to clients verbatim.

use std::path::PathBuf;

use thiserror::Error;

use mcapi_core::AlgoError;
use mcapi_shards::{PlacementError, ShardFrozen, WrongReplica};
use mcapi_store::StoreError;

/// Everything a service call can fail with.
#[derive(Debug, Error)]
pub enum ServiceError {
    /// The core refused the input (model, parameters, observation).
    #[error(transparent)]
    Algo(#[from] AlgoError),
    /// Malformed request content; the message names the field.
    #[error("{0}")]
    BadRequest(String),
    /// No such session (or not visible to the caller).
    #[error("session `{0}` not found")]
    NotFound(String),
    /// No such group (or not visible to the caller, docs/groups.md).
    #[error("group `{0}` not found")]
    GroupNotFound(String),
    /// A column of a group step whose length disagrees with the members
    /// stepped, the stimulus dimensions or the observation dimensions
    /// (docs/groups.md, "Stepping"); nothing was applied.
    #[error("{0}")]
    ColumnLength(String),
    /// A group step's mask that is not strictly increasing or names a
    /// member beyond the group; nothing was applied.
    #[error("{0}")]
    InvalidMask(String),
    /// A `StepGroup` message whose `seq` is not the previous one's plus
    /// one; nothing was applied, and the stream ends.
    #[error("{0}")]
    SequenceOutOfOrder(String),
    /// An observation's `seq` is beyond the session's next one: some
    /// observation before it never arrived (docs/sessions.md, "Delivery
    /// guarantees"); nothing was applied.
    #[error(
        "`seq` is {got}, but the session has applied {expected} observations: the next one must \
         have seq {expected} (send the missing ones first); nothing was applied"
    )]
    SeqGap {
        /// The seq the session takes next.
        expected: u64,
        /// The seq the observation carried.
        got: u64,
    },
    /// An observation's `seq` was applied, but its reply has left the
    /// session's replay window (its history ring); nothing was applied.
    #[error(
        "`seq` {got} was applied, but it is older than the session's replay window, which begins \
         at seq {oldest} (the window is the session's history ring, `agent.history` \
         observations); nothing was applied"
    )]
    SeqExpired {
        /// The oldest seq the session can replay (its next seq when it can
        /// replay none).
        oldest: u64,
        /// The seq the observation carried.
        got: u64,
    },
    /// An observation resent with an applied `seq` whose content (state or
    /// observation, stimulus, action taken, signal) differs from what was
    /// applied with that seq; nothing was applied.
    #[error(
        "an observation with seq {0} was applied with other content (state or observation, \
         stimulus, action_taken or signal); a resent observation must be the same; nothing was \
         applied"
    )]
    SeqConflict(u64),
    /// No such route (REST).
    #[error("no route for {0}")]
    UnknownRoute(String),
    /// A known route that does not take this method (REST).
    #[error("{0}")]
    MethodNotAllowed(String),
    /// A size limit of the server was exceeded.
    #[error("{0}")]
    LimitExceeded(String),
    /// The request body is larger than the server accepts.
    #[error("{0}")]
    PayloadTooLarge(String),
    /// A per-key quota (sessions, estimated bytes) would be exceeded.
    #[error("{0}")]
    QuotaExceeded(String),
    /// The session's update panicked: it is quarantined (never served
    /// half-updated) and answers this until it is deleted.
    #[error(
        "session `{0}` failed while applying an update and is quarantined; its state is not served. Delete it and create it again"
    )]
    SessionFailed(String),
    /// The session limit is reached.
    #[error("the server already holds its maximum of {0} sessions")]
    TooManySessions(usize),
    /// The tick queue is full or the server is stopping.
    #[error("{0}")]
    Unavailable(String),
    /// No valid API key: the header is missing, malformed or unknown. The
    /// message says which, never the key.
    #[error("{0}")]
    Unauthenticated(String),
    /// The durable store failed; the request's effect was not made durable
    /// (the manager rolls an observed session back by reloading it).
    #[error("storage failure: {0}")]
    Storage(#[from] StorageError),
    /// A fault of the server, not the client's; details are logged, not sent.
    #[error("internal error")]
    Internal(String),
    /// A request's handler panicked (a bug of the server): that request,
    /// or that stream, ends with it; the panic's message is kept here, its
    /// backtrace is logged once per place in the code
    /// (`telemetry::install_panic_hook`), nothing of it is sent.
    #[error("internal error")]
    Panicked(String),
    /// The caller already holds its maximum of concurrent watch streams
    /// (REST events, gRPC `Watch`).
    #[error("{0}")]
    TooManyStreams(String),
    /// Responses in flight hold the server's response memory
    /// (`--max-response-bytes-total`); retry shortly.
    #[error("{0}")]
    ResponsesBusy(String),
    /// The request did not finish within the server's request timeout.
    #[error("{0}")]
    RequestTimeout(String),
    /// The session's shard belongs to another replica (docs/cluster.md): a
    /// router with a stale map sent the request here.
    #[error(transparent)]
    WrongReplica(WrongReplica),
    /// The session's shard is being moved to another replica
    /// (docs/cluster.md).
    #[error(transparent)]
    ShardFrozen(ShardFrozen),
    /// An admin call (shard moves, docs/cluster.md) without the admin key,
    /// or to a server with no admin key configured.
    #[error("{0}")]
    Forbidden(String),
    /// A shard move step that does not fit the shard's state or epoch here
    /// (a stale or concurrent mover): nothing was done.
    #[error("{0}")]
    MoveConflict(String),
}

impl ServiceError {
    /// A malformed field: "`field`: reason".
    pub fn field(field: &str, reason: impl std::fmt::Display) -> Self {
        Self::BadRequest(format!("`{field}`: {reason}"))
    }

    /// An algorithm error about a part of the request, with its path: an
    /// invalid parameter keeps its kind and names both (`invalid parameter
    /// `agent.curiosity.params`: `gain` must be ...`); any other error is a
    /// [`ServiceError::field`] of `field`.
    pub fn algo_at(field: &'static str, e: mcapi_core::AlgoError) -> Self {
        match e {
            mcapi_core::AlgoError::InvalidParameter { name, reason } => {
                mcapi_core::AlgoError::InvalidParameter {
                    name: field,
                    reason: format!("`{name}` {reason}"),
                }
                .into()
            }
            e => Self::field(field, e),
        }
    }
}

/// A replica's placement refuses with the service error of the same name,
/// carrying the same refusal.
impl From<PlacementError> for ServiceError {
    fn from(e: PlacementError) -> Self {
        match e {
            PlacementError::NotFound(id) => Self::NotFound(id),
            PlacementError::WrongReplica(w) => Self::WrongReplica(w),
            PlacementError::ShardFrozen(f) => Self::ShardFrozen(f),
            PlacementError::MoveConflict(why) => Self::MoveConflict(why),
        }
    }
}

impl From<StoreError> for ServiceError {
    fn from(e: StoreError) -> Self {
        Self::Storage(StorageError::Store(e))
    }
}

/// Why a request could not be made durable, or a stored session not be
/// read back: the store's own error ([`StoreError`]) or the service's view
/// of the store, each with its cause as `source`. All of them are
/// `storage_unavailable` to a client (`api::error`).
#[derive(Debug, Error)]
pub enum StorageError {
    /// The store failed a read, a write or a commit.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The store cannot write after a storage fault (a full or failing
    /// disk); writes are refused at once, before anything is applied.
    #[error(
        "the store {path} cannot write after a storage fault ({why}); it is reopened automatically once the fault clears"
    )]
    Down {
        /// The store file.
        path: PathBuf,
        /// The fault.
        why: String,
    },
    /// The session is being rolled back to its durable state.
    #[error("session `{0}` is being rolled back to its durable state after a storage failure")]
    RollingBack(String),
    /// The rollback of a session to its durable state failed.
    #[error(
        "session `{id}` cannot be rolled back to its durable state after a storage failure ({source})"
    )]
    Rollback {
        /// The session.
        id: String,
        /// Why its durable state could not be rebuilt.
        source: Box<RecoveryError>,
    },
    /// An evicted session could not be loaded back from the store.
    #[error("session `{id}` was evicted to the store and cannot be loaded back ({source})")]
    Load {
        /// The session.
        id: String,
        /// Why its stored state could not be rebuilt.
        source: Box<RecoveryError>,
    },
    /// The store could not be read to recover the stored sessions at start.
    #[error("reading the store {path} to recover session `{id}`: {source}")]
    Recovery {
        /// The store file.
        path: PathBuf,
        /// The session being read.
        id: String,
        /// The store's error.
        source: StoreError,
    },
}

/// Why a stored session could not be rebuilt.
#[derive(Debug, Error)]
pub enum RecoveryError {
    /// The store could not be read: nothing says the session is bad.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The session is not in the store (deleted meanwhile).
    #[error("session `{0}` is not in the store")]
    Missing(String),
    /// Its records do not decode or replay: this session's damage.
    #[error("session `{id}`: {source}")]
    Records {
        /// The session.
        id: String,
        /// What is wrong with its records.
        source: RecordError,
    },
}

/// What is wrong with the stored records of one session.
#[derive(Debug, Error)]
pub enum RecordError {
    /// The creation record is not the JSON this version writes.
    #[error("its record does not decode: {0}")]
    Record(#[source] serde_json::Error),
    /// The model in the creation record is not JSON.
    #[error("its model does not decode: {0}")]
    Model(#[source] serde_json::Error),
    /// The recorded model or configuration does not build a session.
    #[error(transparent)]
    Setup(Box<ServiceError>),
    /// A snapshot or log entry does not decode.
    #[error(transparent)]
    Decode(#[from] DecodeError),
    /// The snapshot does not fit the learner of the record.
    #[error("{0}")]
    Mismatch(&'static str),
    /// The snapshot does not restore.
    #[error(transparent)]
    Restore(AlgoError),
    /// A log entry is missing: the log has a hole.
    #[error("log entry {expected} is missing (found {found})")]
    Gap {
        /// The sequence number expected next.
        expected: u64,
        /// The one found.
        found: u64,
    },
    /// A log entry does not replay.
    #[error("log entry {seq}: {source}")]
    Replay {
        /// Its sequence number.
        seq: u64,
        /// The refusal of the learner.
        source: Box<ServiceError>,
    },
    /// A log chunk of this session is malformed.
    #[error(transparent)]
    Corrupt(StoreError),
}

/// A snapshot or log entry that does not decode: which one, and why.
#[derive(Debug, Error)]
#[error("{what} {fault}")]
pub struct DecodeError {
    /// The record, e.g. "log entry 7" or "its snapshot".
    pub what: String,
    /// What is wrong with it.
    #[source]
    pub fault: DecodeFault,
}

/// What is wrong with a record that does not decode.
#[derive(Debug, Error)]
pub enum DecodeFault {
    /// No bytes at all.
    #[error("is empty")]
    Empty,
    /// A record version this mcapi does not know.
    #[error("has unknown record version {0}")]
    Version(u8),
    /// The postcard payload does not decode.
    #[error("does not decode: {0}")]
    Postcard(#[from] postcard::Error),
}
