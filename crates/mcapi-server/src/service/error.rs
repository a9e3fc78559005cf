//! The service's one error type. Transports map it to HTTP and gRPC in one
//! table (`api::error`); messages of user errors go to clients verbatim.

use thiserror::Error;

use mcapi_core::AlgoError;

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
    /// No such route or method (REST).
    #[error("no route for {0}")]
    UnknownRoute(String),
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
    Storage(String),
    /// A fault of the server, not the client's; details are logged, not sent.
    #[error("internal error")]
    Internal(String),
    /// The caller already holds its maximum of concurrent watch streams
    /// (REST events, gRPC `Watch`).
    #[error("{0}")]
    TooManyStreams(String),
    /// The request did not finish within the server's request timeout.
    #[error("{0}")]
    RequestTimeout(String),
}

impl ServiceError {
    /// A malformed field: "`field`: reason".
    pub fn field(field: &str, reason: impl std::fmt::Display) -> Self {
        Self::BadRequest(format!("`{field}`: {reason}"))
    }
}
