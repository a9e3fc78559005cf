//! The OpenAPI document served at `/v1/openapi.json`: the paths and response
//! types come from the `utoipa::path` annotations of the handlers
//! ([`crate::api::rest`], the events stream of [`crate::api::dashboard`]);
//! [`document`] completes them with the request schemas of the server's
//! limits ([`crate::api::schemas`]).

use utoipa::OpenApi;

use crate::api::error::ErrorBody;
use crate::api::schemas::{
    BadRequest, BearerAuth, GroupStepReply, InternalError, MemberError, MisdirectedRequest,
    NotFound, ObserveBatchReply, PayloadTooLarge, SeqConflict, SseEvent, TooManyRequests,
    Unauthorized, Unavailable, request_schemas,
};
use crate::service::Limits;
use crate::service::groups::GroupInfo;

/// The paths of the OpenAPI document; [`document`] completes it with the request schemas of the server's limits.
#[derive(OpenApi)]
#[openapi(
    info(
        title = "mcapi",
        description = "Motivated reinforcement-learning agents (MCA-PI, Kompella et al. 2014) \
            hosted as sessions. Create a session from a model, report observations, get the \
            next action; read its values, history and live events. Errors are \
            `{\"code\", \"message\"}` with a stable `code`."
    ),
    paths(
        crate::api::rest::create_session,
        crate::api::rest::list_sessions,
        crate::api::rest::get_session,
        crate::api::rest::delete_session,
        crate::api::rest::observe,
        crate::api::rest::values,
        crate::api::rest::history,
        crate::api::dashboard::events,
        crate::api::rest::create_group,
        crate::api::rest::get_group,
        crate::api::rest::delete_group,
        crate::api::rest::step_group,
        crate::api::rest::healthz,
        crate::api::rest::readyz,
        crate::api::rest::metrics_text
    ),
    components(
        schemas(ErrorBody, ObserveBatchReply, SseEvent, GroupInfo, GroupStepReply, MemberError),
        responses(BadRequest, Unauthorized, NotFound, SeqConflict, MisdirectedRequest, PayloadTooLarge, TooManyRequests, InternalError, Unavailable)
    ),
    modifiers(&BearerAuth),
    security(("api_key" = []), ()),
    tags(
        (name = "sessions", description = "Create, list, read and delete sessions."),
        (name = "observations", description = "Report what the agent observed; get its next action."),
        (name = "inspection", description = "A session's value tables, recent ticks and live event stream."),
        (name = "groups", description = "Groups of sessions of one model and configuration, created, read, deleted and stepped together by columns."),
        (name = "operations", description = "Liveness, readiness and Prometheus metrics (no API key needed).")
    )
)]
pub struct ApiDoc;

/// The OpenAPI document of a server with the default limits.
pub fn openapi() -> utoipa::openapi::OpenApi {
    document(&Limits::default())
}

/// The document for a server with these limits.
pub fn document(limits: &Limits) -> utoipa::openapi::OpenApi {
    let mut doc = ApiDoc::openapi();
    let components = doc.components.get_or_insert_with(Default::default);
    for (name, schema) in request_schemas(limits) {
        components.schemas.insert(name.to_string(), schema);
    }
    doc
}
