//! The schemas of an observation: one, or a batch under `observations`,
//! and the shapes of their replies and of the event stream.

use std::borrow::Cow;

use serde::Serialize;
use serde_json::json;
use utoipa::openapi::RefOr;
use utoipa::openapi::schema::{OneOfBuilder, Schema};
use utoipa::{PartialSchema, ToSchema};

use super::builders::{Bound, U64_MAX, array, closed, integer, nullable_ref, number, reference};
use super::request_schemas;
use crate::service::Limits;
use mcapi_core::continuous::space::MAX_DIM;
use mcapi_core::curiosity::{MAX_SIGNAL_DIM, MAX_SOURCES_LIMIT};
use mcapi_core::error::MAX_STIMULUS;

/// The observation schemas, by component name, for these limits.
pub(super) fn schemas(limits: &Limits) -> Vec<(&'static str, RefOr<Schema>)> {
    let max_pairs = limits.max_pairs as u64;
    let max_sources = limits.max_signal_sources.min(MAX_SOURCES_LIMIT) as u64;
    let max_state = max_pairs.saturating_sub(1);
    let max_stimuli = limits.max_stimuli;
    let stimulus = || {
        number(
            Bound::Incl(-MAX_STIMULUS),
            Bound::Incl(MAX_STIMULUS),
            false,
            "a component (|x| ≤ 1e12)",
        )
    };
    let observation = closed(
        "One observation: the state the agent is in (or, for a continuous model, its \
         observation vector; exactly one of the two) and, from the second observation on, \
         the stimulus it received on arrival.",
    )
    .property(
        "state",
        integer(
            0,
            max_state,
            false,
            "the state the agent is in now (below the model's `states`); not for a \
             continuous model",
        ),
    )
    .property(
        "observation",
        array(
            number(Bound::None, Bound::None, false, "a coordinate (finite)"),
            1,
            MAX_DIM,
            false,
            "the observation vector of a continuous model, one coordinate per dimension \
             of its `observation_space`",
        ),
    )
    .property(
        "stimulus",
        array(
            stimulus(),
            0,
            max_stimuli,
            true,
            "the stimulus received on arrival, one component per stimulus dimension of \
             the model (for a curious session: the extrinsic ones); omitted on the first \
             observation",
        ),
    )
    .property(
        "action_taken",
        nullable_ref(
            "ActionRef",
            "the action actually taken, if not the advised one",
        ),
    )
    .property(
        "signal",
        array(
            stimulus(),
            1,
            MAX_SIGNAL_DIM,
            true,
            "a raw signal sample x(t), `signal_dim` components (curious sessions only)",
        ),
    )
    .property(
        "signal_source",
        integer(
            0,
            max_sources.saturating_sub(1),
            true,
            "the signal's source, below the channel's `max_sources` (limit); default 0",
        ),
    )
    .property(
        "seq",
        integer(
            0,
            U64_MAX,
            true,
            "the observation's 0-based index in the session's stream of applied observations \
             (the first has seq 0), for exactly-once delivery: one resent with a seq already \
             applied gets its recorded reply with `replayed: true` and is not applied again; \
             one beyond the next seq is refused (409 `seq_gap`). In a batch, every observation \
             carries one, consecutive, or none does. Absent: applied as it comes",
        ),
    )
    .examples([
        json!({"state": 26, "stimulus": [0.0, 0.0]}),
        json!({"observation": [0.31, 0.72], "stimulus": [0.0, 1.0]}),
        json!({"state": 27, "stimulus": [1.0, 0.0], "seq": 12}),
    ]);
    let batch = closed("A batch of observations, applied in order.")
        .property(
            "observations",
            array(
                reference("Observation"),
                1,
                limits.max_batch,
                false,
                "the observations (limit)",
            ),
        )
        .required("observations");
    let observe = OneOfBuilder::new()
        .item(reference("Observation"))
        .item(reference("ObserveBatch"))
        .description(Some(
            "One observation, or a batch under `observations` (replied to with `steps`).",
        ));
    vec![
        ("Observation", observation.into()),
        ("ObserveBatch", batch.into()),
        ("ObserveRequest", observe.into()),
    ]
}

/// The body of `POST /v1/sessions/{id}/observations` (schema built by
/// [`request_schemas`]).
pub struct ObserveRequest;

impl PartialSchema for ObserveRequest {
    fn schema() -> RefOr<Schema> {
        schema_named(Self::name().as_ref())
    }
}

impl ToSchema for ObserveRequest {
    fn name() -> Cow<'static, str> {
        Cow::Borrowed("ObserveRequest")
    }
}

/// A request schema of [`request_schemas`] under the default limits.
fn schema_named(name: &str) -> RefOr<Schema> {
    request_schemas(&Limits::default())
        .into_iter()
        .find(|(n, _)| *n == name)
        .map_or_else(|| RefOr::T(Schema::default()), |(_, s)| s)
}

/// The reply to an observation: one step, or `steps` for a batch.
#[derive(Serialize, ToSchema)]
#[serde(untagged)]
#[allow(dead_code)] // a schema only
pub enum ObserveReply {
    /// The reply to one observation.
    Step(crate::service::StepOut),
    /// The replies to a batch, in order.
    Batch(ObserveBatchReply),
}

/// One reply per observation of a batch.
#[derive(Serialize, ToSchema)]
pub struct ObserveBatchReply {
    /// The replies, in order.
    pub steps: Vec<crate::service::StepOut>,
}

/// One server-sent event of `GET /v1/sessions/{id}/events`, as an SSE
/// reader sees it. `data` is JSON: for `session`, the session as
/// `GET /v1/sessions/{id}`; for `tick`, a history entry as in `/history`;
/// for `values`, V and the greedy policy; for `end`, `{"id","reason"}`;
/// for `error`, an error body `{"code","message"}`.
#[derive(Serialize, ToSchema)]
pub struct SseEvent {
    /// The event's name.
    #[schema(value_type = String, pattern = "^(session|tick|values|end|error)$")]
    pub event: String,
    /// The event's JSON payload.
    pub data: String,
}

/// The history `limit`: any count from 1 (no integer format: the server
/// reads up to 2^64 - 1).
pub fn history_limit() -> Schema {
    integer(
        1,
        U64_MAX,
        false,
        "At most this many recent ticks, at least 1 (default: all kept).",
    )
    .into()
}
