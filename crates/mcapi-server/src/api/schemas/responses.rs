//! What every operation may answer besides its success: the error
//! responses (reusable components `BadRequest`, `Unauthorized`, ... with
//! the `{"code","message"}` body), and the API-key security scheme.

use serde_json::json;
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::openapi::{ContentBuilder, OpenApi, RefOr, Response, ResponseBuilder};
use utoipa::{Modify, ToResponse};

use super::builders::reference;

/// Declares the `Authorization: Bearer <key>` scheme (required when the
/// server runs with API keys; the empty requirement covers servers without).
pub struct BearerAuth;

impl Modify for BearerAuth {
    fn modify(&self, openapi: &mut OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "api_key",
            SecurityScheme::Http(
                HttpBuilder::new()
                    .scheme(HttpAuthScheme::Bearer)
                    .description(Some(
                        "An API key given to the server with --api-key / MCAPI_API_KEYS. \
                         Required by every /v1 operation when the server has keys; a \
                         server without keys takes requests without one.",
                    ))
                    .build(),
            ),
        );
    }
}

fn error_response(description: &str, example: serde_json::Value) -> RefOr<Response> {
    ResponseBuilder::new()
        .description(description)
        .content(
            "application/json",
            ContentBuilder::new()
                .schema(Some(reference("ErrorBody")))
                .example(Some(example))
                .build(),
        )
        .build()
        .into()
}

macro_rules! error_responses {
    ($($(#[$doc:meta])* $ty:ident = ($description:expr, $code:expr, $message:expr);)*) => {$(
        $(#[$doc])*
        pub struct $ty;

        impl<'r> ToResponse<'r> for $ty {
            fn response() -> (&'r str, RefOr<Response>) {
                (
                    stringify!($ty),
                    error_response($description, json!({"code": $code, "message": $message})),
                )
            }
        }
    )*};
}

error_responses! {
    /// 400.
    BadRequest = (
        "The request is malformed or invalid: a body or query that does not parse, or a \
         value the server refuses for what it means (an unknown state, a stimulus of the \
         wrong length, an inconsistent model). `code` says which: `bad_request`, \
         `invalid_model`, `invalid_basis`, `invalid_parameter`, `unknown_state`, \
         `unknown_action`, `action_not_available`, `stimulus_length`, \
         `stimulus_too_large`, `non_finite_number`, `first_observation`, `missing_stimulus`.",
        "stimulus_length",
        "stimulus has 1 components, expected 2"
    );
    /// 401.
    Unauthorized = (
        "The server has API keys and the request carries none, a malformed one or an \
         unknown one (`WWW-Authenticate: Bearer`).",
        "unauthenticated",
        "an API key is required: send `Authorization: Bearer <key>`"
    );
    /// 404.
    NotFound = (
        "No such session, or it belongs to another API key.",
        "not_found",
        "session `01J0000000000000000000000` not found"
    );
    /// 413.
    PayloadTooLarge = (
        "A limit of the server is exceeded: the body's size (`payload_too_large`) or a \
         size the limits bound (`limit_exceeded`: model pairs, transitions, features, \
         stimulus dimensions, name bytes, curiosity windows, batch length or its \
         estimated CPU time, history length, a session's estimated memory or CPU time per \
         observation, the size of a response of value tables or history).",
        "limit_exceeded",
        "`model` states x actions is 1500000; the limit is 1000000"
    );
    /// 429.
    TooManyRequests = (
        "The server holds its maximum number of sessions (`too_many_sessions`), the API \
         key its quota of sessions or estimated memory (`quota_exceeded`), or the caller \
         its maximum of open event streams (`too_many_streams`).",
        "too_many_sessions",
        "the server already holds its maximum of 1000000 sessions"
    );
    /// 500.
    InternalError = (
        "The session's policy update failed numerically (`numerical_failure`; the \
         observation was applied and logged, do not resend it) or the session is \
         quarantined after a fault of the server (`session_failed`: delete it and create \
         it again), or the server failed (`internal`; `internal_panic` when its handler \
         panicked).",
        "session_failed",
        "session `s0001.01J0000000000000000000000` failed while applying an update and is quarantined; its state is not served. Delete it and create it again"
    );
    /// 409 of an observation.
    SeqConflict = (
        "An observation's `seq` does not fit the session (docs/sessions.md, \"Delivery \
         guarantees\"): `seq_gap`, beyond the next seq (`expected_seq` in the body names it); \
         `seq_expired`, applied but older than the replay window (`oldest_seq` names its \
         start); `seq_conflict`, applied with other content. Nothing was applied.",
        "seq_gap",
        "`seq` is 7, but the session has applied 5 observations: the next one must have seq 5 (send the missing ones first); nothing was applied"
    );
    /// 421.
    MisdirectedRequest = (
        "Clustered replicas only (docs/cluster.md): the session's shard belongs to another \
         replica, named in the message and the `x-mcapi-owner` header (`wrong_replica`). \
         Nothing was done; retry through the router.",
        "wrong_replica",
        "session `s0001.01J0000000000000000000000` is in shard s0001, owned by replica `mcapi-2` (shard map epoch 3), not by this replica `mcapi-0`; retry through the router"
    );
    /// 503.
    Unavailable = (
        "The server is recovering its sessions, stopping, its tick queue is full, its \
         store failed, the request took longer than the server's request timeout, or \
         (clustered) the session's shard is being moved, or responses in flight hold the \
         server's response memory (`unavailable`, `storage_unavailable`, `request_timeout`, \
         `shard_moving`, `responses_busy`; `unavailable`, `shard_moving` and \
         `responses_busy` with `Retry-After`); may be retried.",
        "unavailable",
        "the server is recovering its stored sessions; retry shortly"
    );
}
