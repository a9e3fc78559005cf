//! The one mapping of service errors to HTTP status, gRPC code and stable
//! snake_case code (docs/architecture.md). Every variant is listed; no `_ =>`.

use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Serialize;

use crate::service::ServiceError;
use mcapi_core::AlgoError;

/// HTTP status, gRPC code and stable code of an error.
pub fn classify(e: &ServiceError) -> (StatusCode, tonic::Code, &'static str) {
    use StatusCode as H;
    use tonic::Code as G;
    match e {
        ServiceError::Algo(a) => match a {
            AlgoError::InvalidModel(_) => (H::BAD_REQUEST, G::InvalidArgument, "invalid_model"),
            AlgoError::InvalidSnapshot(_) => (H::INTERNAL_SERVER_ERROR, G::Internal, "internal"),
            AlgoError::InvalidParameter { .. } => {
                (H::BAD_REQUEST, G::InvalidArgument, "invalid_parameter")
            }
            AlgoError::InvalidBasis(_) => (H::BAD_REQUEST, G::InvalidArgument, "invalid_basis"),
            AlgoError::StateOutOfRange { .. } => {
                (H::BAD_REQUEST, G::InvalidArgument, "unknown_state")
            }
            AlgoError::ActionOutOfRange { .. } => {
                (H::BAD_REQUEST, G::InvalidArgument, "unknown_action")
            }
            AlgoError::ActionNotAvailable { .. } => {
                (H::BAD_REQUEST, G::InvalidArgument, "action_not_available")
            }
            AlgoError::StimulusLength { .. } | AlgoError::ExtrinsicStimulusLength { .. } => {
                (H::BAD_REQUEST, G::InvalidArgument, "stimulus_length")
            }
            AlgoError::NonFinite { .. } => {
                (H::BAD_REQUEST, G::InvalidArgument, "non_finite_number")
            }
            AlgoError::StimulusTooLarge { .. } => {
                (H::BAD_REQUEST, G::InvalidArgument, "stimulus_too_large")
            }
            AlgoError::FirstObservation { .. } => {
                (H::BAD_REQUEST, G::InvalidArgument, "first_observation")
            }
            AlgoError::MissingStimulus => (H::BAD_REQUEST, G::InvalidArgument, "missing_stimulus"),
            AlgoError::InvalidObservation(_) => {
                (H::BAD_REQUEST, G::InvalidArgument, "invalid_observation")
            }
            AlgoError::Numerical(_) => (H::INTERNAL_SERVER_ERROR, G::Internal, "numerical_failure"),
            // A build stopped by its time budget (setup says so as a
            // `LimitExceeded`, this is the same answer).
            AlgoError::BuildStopped(_) => {
                (H::PAYLOAD_TOO_LARGE, G::ResourceExhausted, "limit_exceeded")
            }
        },
        ServiceError::BadRequest(_) => (H::BAD_REQUEST, G::InvalidArgument, "bad_request"),
        ServiceError::NotFound(_) | ServiceError::GroupNotFound(_) => {
            (H::NOT_FOUND, G::NotFound, "not_found")
        }
        ServiceError::ColumnLength(_) => (H::BAD_REQUEST, G::InvalidArgument, "column_length"),
        ServiceError::InvalidMask(_) => (H::BAD_REQUEST, G::InvalidArgument, "invalid_mask"),
        ServiceError::SequenceOutOfOrder(_) => {
            (H::BAD_REQUEST, G::InvalidArgument, "sequence_out_of_order")
        }
        // FAILED_PRECONDITION: the session's state refuses the request as
        // it is (a different seq or content may be right); not to be
        // retried unchanged.
        ServiceError::SeqGap { .. } => (H::CONFLICT, G::FailedPrecondition, "seq_gap"),
        ServiceError::SeqExpired { .. } => (H::CONFLICT, G::FailedPrecondition, "seq_expired"),
        ServiceError::SeqConflict(_) => (H::CONFLICT, G::FailedPrecondition, "seq_conflict"),
        ServiceError::UnknownRoute(_) => (H::NOT_FOUND, G::Unimplemented, "unknown_route"),
        ServiceError::MethodNotAllowed(_) => (
            H::METHOD_NOT_ALLOWED,
            G::Unimplemented,
            "method_not_allowed",
        ),
        ServiceError::LimitExceeded(_) => {
            (H::PAYLOAD_TOO_LARGE, G::ResourceExhausted, "limit_exceeded")
        }
        ServiceError::PayloadTooLarge(_) => (
            H::PAYLOAD_TOO_LARGE,
            G::ResourceExhausted,
            "payload_too_large",
        ),
        ServiceError::QuotaExceeded(_) => {
            (H::TOO_MANY_REQUESTS, G::ResourceExhausted, "quota_exceeded")
        }
        ServiceError::SessionFailed(_) => (H::INTERNAL_SERVER_ERROR, G::Internal, "session_failed"),
        ServiceError::TooManySessions(_) => (
            H::TOO_MANY_REQUESTS,
            G::ResourceExhausted,
            "too_many_sessions",
        ),
        ServiceError::Unavailable(_) => (H::SERVICE_UNAVAILABLE, G::Unavailable, "unavailable"),
        ServiceError::Unauthenticated(_) => {
            (H::UNAUTHORIZED, G::Unauthenticated, "unauthenticated")
        }
        ServiceError::Storage(_) => (
            H::SERVICE_UNAVAILABLE,
            G::Unavailable,
            "storage_unavailable",
        ),
        ServiceError::Internal(_) => (H::INTERNAL_SERVER_ERROR, G::Internal, "internal"),
        ServiceError::Panicked(_) => (H::INTERNAL_SERVER_ERROR, G::Internal, "internal_panic"),
        ServiceError::TooManyStreams(_) => (
            H::TOO_MANY_REQUESTS,
            G::ResourceExhausted,
            "too_many_streams",
        ),
        ServiceError::RequestTimeout(_) => (
            H::SERVICE_UNAVAILABLE,
            G::DeadlineExceeded,
            "request_timeout",
        ),
        // RFC 9110 §15.5.20: not authoritative here, retry elsewhere; for
        // gRPC, UNAVAILABLE is the code a client may retry as is.
        ServiceError::WrongReplica(_) => (H::MISDIRECTED_REQUEST, G::Unavailable, "wrong_replica"),
        ServiceError::ShardFrozen(_) => (H::SERVICE_UNAVAILABLE, G::Unavailable, "shard_moving"),
        ServiceError::ResponsesBusy(_) => {
            (H::SERVICE_UNAVAILABLE, G::Unavailable, "responses_busy")
        }
        ServiceError::Forbidden(_) => (H::FORBIDDEN, G::PermissionDenied, "forbidden"),
        ServiceError::MoveConflict(_) => (H::CONFLICT, G::FailedPrecondition, "move_conflict"),
    }
}

/// The message a client sees: verbatim for its own mistakes, generic for
/// internal faults (which are logged once here instead).
pub fn public_message(e: &ServiceError, status: StatusCode) -> String {
    if let ServiceError::Storage(detail) = e {
        tracing::error!(error = %detail, "storage failure");
        return "the session store failed, so the request was not made durable; its effect is \
                rolled back (the session is reloaded from its last durable state before it takes \
                another observation), so it is safe to retry (details in the server log)"
            .to_string();
    }
    if let ServiceError::Algo(AlgoError::Numerical(detail)) = e {
        tracing::error!(error = %detail, "policy update failed");
        return "the observation was applied and logged, but the policy update after it failed \
                numerically (details in the server log); do not send it again: the next \
                observation plans anew"
            .to_string();
    }
    if let ServiceError::Panicked(detail) = e {
        // The panic hook logged its backtrace once for its place in the
        // code and counts every one (`mcapi_panics_total`): not a line per
        // request here, which a client repeating it could flood the log with.
        tracing::debug!(panic = %detail, "a request panicked");
        return "internal error".to_string();
    }
    if let ServiceError::SessionFailed(_) = e {
        // A server fault, but the client must learn what to do about it.
        return e.to_string();
    }
    if status.is_server_error() && status != StatusCode::SERVICE_UNAVAILABLE {
        tracing::error!(error = ?e, "internal error");
        return "internal error".to_string();
    }
    capped(e.to_string())
}

/// Longest message sent, in bytes. A message may quote the input (serde's
/// "invalid type: string \"...\""); over gRPC it travels in a trailer, and
/// a trailer beyond the client's header-list limit (16 KiB by default)
/// breaks the call with an HTTP/2 protocol error instead of the status.
pub const MAX_MESSAGE_BYTES: usize = 1024;

fn capped(mut message: String) -> String {
    if message.len() <= MAX_MESSAGE_BYTES {
        return message;
    }
    let total = message.len();
    let mut end = MAX_MESSAGE_BYTES;
    while !message.is_char_boundary(end) {
        end -= 1;
    }
    message.truncate(end);
    message.push_str(&format!("... ({} more bytes)", total - end));
    message
}

/// The JSON error body: `{"code", "message"}`, and for the sequence
/// errors the seq a client resumes from.
#[derive(Debug, Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct ErrorBody {
    /// Stable snake_case code.
    pub code: String,
    /// Human-readable message naming the field.
    pub message: String,
    /// `seq_gap`: the seq the session takes next.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expected_seq: Option<u64>,
    /// `seq_expired`: the oldest seq the session can still replay.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub oldest_seq: Option<u64>,
}

/// The seq details of an error: `(expected_seq, oldest_seq)`.
pub(crate) fn seq_details(e: &ServiceError) -> (Option<u64>, Option<u64>) {
    match e {
        ServiceError::SeqGap { expected, .. } => (Some(*expected), None),
        ServiceError::SeqExpired { oldest, .. } => (None, Some(*oldest)),
        _ => (None, None),
    }
}

/// A REST error response.
#[derive(Debug)]
pub struct ApiError(pub ServiceError);

impl From<ServiceError> for ApiError {
    fn from(e: ServiceError) -> Self {
        Self(e)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (status, _, code) = classify(&self.0);
        let (expected_seq, oldest_seq) = seq_details(&self.0);
        let body = ErrorBody {
            code: code.to_string(),
            message: public_message(&self.0, status),
            expected_seq,
            oldest_seq,
        };
        let mut response = (status, Json(body)).into_response();
        if status == StatusCode::UNAUTHORIZED {
            response.headers_mut().insert(
                axum::http::header::WWW_AUTHENTICATE,
                axum::http::HeaderValue::from_static("Bearer realm=\"mcapi\""),
            );
        }
        for (name, value) in cluster_headers(&self.0) {
            if let Ok(v) = axum::http::HeaderValue::from_str(&value) {
                response.headers_mut().insert(name, v);
            }
        }
        response
    }
}

/// A gRPC status from a service error.
pub fn to_status(e: ServiceError) -> tonic::Status {
    let (http, code, stable) = classify(&e);
    let message = public_message(&e, http);
    let mut status = tonic::Status::new(code, message);
    if let Ok(v) = stable.parse() {
        status.metadata_mut().insert("x-mcapi-error-code", v);
    }
    for (name, value) in cluster_headers(&e) {
        if let Ok(v) = value.parse() {
            status.metadata_mut().insert(name, v);
        }
    }
    let (expected_seq, oldest_seq) = seq_details(&e);
    for (name, seq) in [
        (EXPECTED_SEQ_TRAILER, expected_seq),
        (OLDEST_SEQ_TRAILER, oldest_seq),
    ] {
        if let Some(Ok(v)) = seq.map(|s| s.to_string().parse()) {
            status.metadata_mut().insert(name, v);
        }
    }
    status
}

/// gRPC trailer of `seq_gap`: the seq the session takes next (REST:
/// `expected_seq` in the body).
pub const EXPECTED_SEQ_TRAILER: &str = "x-mcapi-expected-seq";

/// gRPC trailer of `seq_expired`: the oldest seq the session can replay
/// (REST: `oldest_seq` in the body).
pub const OLDEST_SEQ_TRAILER: &str = "x-mcapi-oldest-seq";

/// An `InteractBatch` entry's error: what [`to_status`] would end an
/// `Interact` stream with, as a message.
pub fn step_error(e: ServiceError) -> mcapi_proto::StepError {
    let (http, code, stable) = classify(&e);
    let owner = match &e {
        ServiceError::WrongReplica(w) => w.owner.clone(),
        _ => String::new(),
    };
    mcapi_proto::StepError {
        status: code as u32,
        code: stable.to_string(),
        message: public_message(&e, http),
        owner,
    }
}

/// Header (REST) or trailer (gRPC) naming the owner of a misdirected
/// session's shard (docs/cluster.md).
pub const OWNER_HEADER: &str = "x-mcapi-owner";

/// The headers a refusal carries besides its body: the owner of a
/// misdirected session's shard; the wait for a frozen one, for the
/// response memory, or for whatever made the server `unavailable` (a full
/// queue, a recovery, a session that cannot be loaded back within its
/// key's quota yet).
fn cluster_headers(e: &ServiceError) -> Vec<(&'static str, String)> {
    let wait = || {
        vec![(
            "retry-after",
            crate::service::budget::RETRY_AFTER_SECS.to_string(),
        )]
    };
    match e {
        ServiceError::WrongReplica(w) => vec![(OWNER_HEADER, w.owner.clone())],
        ServiceError::ShardFrozen(f) => vec![("retry-after", f.retry_after_secs.to_string())],
        ServiceError::ResponsesBusy(_) | ServiceError::Unavailable(_) => wait(),
        _ => Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 503 that asks the client to come back says when, on both
    /// transports; one that does not (a failed commit) says nothing.
    #[test]
    fn unavailable_says_when_to_retry() {
        let refused = || ServiceError::Unavailable("the tick queue is full".into());
        let response = ApiError(refused()).into_response();
        assert_eq!(response.status(), StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(response.headers()["retry-after"], "1");
        let status = to_status(refused());
        assert_eq!(status.code(), tonic::Code::Unavailable);
        assert_eq!(
            status
                .metadata()
                .get("retry-after")
                .map(|v| v.to_str().ok()),
            Some(Some("1"))
        );
        let response = ApiError(ServiceError::TooManySessions(3)).into_response();
        assert!(response.headers().get("retry-after").is_none());
    }
}
