//! The schemas of the OpenAPI document ([`crate::api::openapi`]) that a
//! derive cannot say exactly:
//!
//! - the request bodies, written out from the server's [`Limits`], the
//!   core's constants and the parameter tables, so every bound the server
//!   enforces is a `minimum`/`maximum`/`maxLength`/`maxItems` in the schema,
//!   and every form a body may take is one branch of a `oneOf` (`model`:
//!   preset, grid map, full model with `next`, full model with
//!   `transitions`; the basis; `action_taken`: index or name; a stimulus
//!   rate: constant or named; one observation or a batch). `null` is
//!   allowed exactly where the server reads it as "absent". One file per
//!   request body: [`model`], [`agent`] (from the parameter tables),
//!   [`observe`], [`groups`];
//! - the error responses every operation may answer and the API-key
//!   security scheme ([`responses`]).
//!
//! Checked three ways: this crate's `tests/api/openapi.rs` (each bound
//! equals the limit it describes; documented examples are accepted and
//! near misses refused), schemathesis against the live server (`make
//! contract`) and the fuzzer (this crate's `tests/fuzz/`).

pub mod agent;
mod builders;
mod continuous;
mod groups;
mod model;
mod observe;
mod responses;

use serde_json::json;
use utoipa::openapi::RefOr;
use utoipa::openapi::schema::Schema;

use crate::service::Limits;
use builders::{closed, reference};
pub use groups::{CreateGroupRequest, GroupStep, GroupStepReply, MemberError};
pub use observe::{ObserveBatchReply, ObserveReply, ObserveRequest, SseEvent, history_limit};
pub use responses::{
    BadRequest, BearerAuth, InternalError, MisdirectedRequest, NotFound, PayloadTooLarge,
    SeqConflict, TooManyRequests, Unauthorized, Unavailable,
};

/// Every request-body schema, by component name, for these limits.
pub fn request_schemas(limits: &Limits) -> Vec<(&'static str, RefOr<Schema>)> {
    let limits_note = format!(
        "Bounds marked (limit) are this server's limits (`mcapi serve --help`): at most \
         {} state-action pairs, {} transitions, {} features, {} stimulus dimensions, \
         {}-byte names, {} observations per batch, {} history entries, {} sessions. \
         Beyond the schema, a session's estimated memory (at most {} bytes) and CPU time \
         per observation (at most {} µs) are checked at creation (413), and what an API \
         key holds against its quota (429).",
        limits.max_pairs,
        limits.max_transitions,
        limits.max_features,
        limits.max_stimuli,
        limits.max_name_bytes,
        limits.max_batch,
        limits.max_history,
        limits.max_sessions,
        limits.max_session_bytes,
        limits.max_tick_us
    );

    let create = closed(&format!(
        "A request to create a session: a model and the agent's configuration. {limits_note}"
    ))
    .property("model", reference("Model"))
    .property("agent", reference("SessionConfig"))
    .required("model")
    .examples([json!({"model": {"preset": "hallway"}, "agent": {"seed": 7}})]);
    let mut out = vec![("CreateSession", create.into())];
    out.extend(model::schemas(limits));
    out.extend(continuous::schemas(limits));
    out.extend(agent::schemas(limits));
    out.extend(observe::schemas(limits));
    out.extend(groups::schemas(limits));
    out
}
