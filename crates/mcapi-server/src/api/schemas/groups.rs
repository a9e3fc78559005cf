//! The schemas of the group routes (docs/groups.md): the bodies of
//! `POST /v1/groups` and `POST /v1/groups/{id}/steps` written out with the
//! server's bounds, and the reply of a step, by columns.

use std::borrow::Cow;

use serde::{Deserialize, Serialize};
use serde_json::json;
use utoipa::openapi::RefOr;
use utoipa::openapi::schema::{ObjectBuilder, Schema, Type};
use utoipa::{PartialSchema, ToSchema};

use super::builders::{Bound, U64_MAX, array, closed, integer, number, reference, typed};
use super::request_schemas;
use crate::api::extract::BodyShape;
use crate::service::Limits;
use crate::service::groups::MemberStep;
use mcapi_core::continuous::space::MAX_DIM;
use mcapi_core::error::MAX_STIMULUS;

/// The group schemas, by component name, for these limits.
pub(super) fn schemas(limits: &Limits) -> Vec<(&'static str, RefOr<Schema>)> {
    let max = limits.max_group_members;
    let create = closed(&format!(
        "A request to create a group: a session's model and agent configuration (without \
         `agent.seed` and `agent.curiosity`), the number of members `n` (at most {max}) and the \
         group's `seed`. Member i's seed is output i (from 0) of SplitMix64 seeded with `seed`."
    ))
    .property("model", reference("Model"))
    .property("agent", reference("SessionConfig"))
    .property(
        "n",
        integer(
            1,
            max as u64,
            false,
            &format!("members (limit: at most {max})"),
        ),
    )
    .property(
        "seed",
        integer(
            0,
            U64_MAX,
            true,
            "the group's seed; drawn when absent or null",
        ),
    )
    .required("model")
    .required("n")
    .examples([json!({"model": {"preset": "hallway"}, "n": 4, "seed": 7})]);
    let max_state = (limits.max_pairs as u64).saturating_sub(1);
    let row =
        |what: &str, items: ObjectBuilder, max_len: usize| array(items, 0, max_len, false, what);
    let step = closed(&format!(
        "One step of a group by columns: each array has one entry (or row) per member \
         stepped, in the order of `mask` (all members in order without one), at most {max}."
    ))
    .property(
        "mask",
        array(
            integer(0, (max as u64).saturating_sub(1), false, "a member index"),
            0,
            max,
            true,
            "the members stepped, strictly increasing, each below the group's size; absent: \
             all members",
        ),
    )
    .property(
        "states",
        array(
            integer(0, max_state, false, "a state of the model"),
            0,
            max,
            true,
            "the state each member stepped is in (a model with numbered states)",
        ),
    )
    .property(
        "observations",
        array(
            row(
                "one member's observation vector",
                number(Bound::None, Bound::None, false, "a coordinate (finite)"),
                MAX_DIM,
            ),
            0,
            max,
            true,
            "a continuous model's observation of each member stepped",
        ),
    )
    .property(
        "stimuli",
        array(
            row(
                "one member's stimulus, one component per stimulus dimension",
                number(
                    Bound::Incl(-MAX_STIMULUS),
                    Bound::Incl(MAX_STIMULUS),
                    false,
                    "a component (|x| ≤ 1e12)",
                ),
                limits.max_stimuli,
            ),
            0,
            max,
            true,
            "the stimulus each member stepped received on arrival; absent on the members' \
             first step",
        ),
    )
    .property(
        "action_taken",
        array(
            typed(Type::Integer, true)
                .minimum(Some(0))
                .maximum(Some(u32::MAX - 1))
                .description(Some("an action index, or null for the advised one")),
            0,
            max,
            true,
            "the action each member stepped took; absent: every member took its advised one",
        ),
    )
    .property(
        "seqs",
        array(
            integer(
                0,
                U64_MAX,
                false,
                "the member's observation's 0-based index in its session's stream of applied \
                 observations",
            ),
            0,
            max,
            true,
            "the seq of each member's observation, for exactly-once delivery (docs/sessions.md, \
             \"Delivery guarantees\"): a member whose seq was already applied gets its recorded \
             step (`replayed`) and applies nothing; one whose seq its session refuses gets \
             `seq_gap`, `seq_expired` or `seq_conflict` in `errors`; absent: applied as they \
             come (at least once)",
        ),
    )
    .examples([
        json!({"states": [25, 25, 25, 25]}),
        json!({"states": [26, 24, 26, 25], "stimuli": [[0, 0], [0, 0], [0, 0], [0, 0]],
               "seqs": [1, 1, 1, 1]}),
    ]);
    vec![("CreateGroup", create.into()), ("GroupStep", step.into())]
}

/// A request schema of [`request_schemas`] under the default limits.
fn schema_named(name: &str) -> RefOr<Schema> {
    request_schemas(&Limits::default())
        .into_iter()
        .find(|(n, _)| *n == name)
        .map_or_else(|| RefOr::T(Schema::default()), |(_, s)| s)
}

/// The body of `POST /v1/groups` (schema built by [`request_schemas`]).
pub struct CreateGroupRequest;

impl PartialSchema for CreateGroupRequest {
    fn schema() -> RefOr<Schema> {
        schema_named(Self::name().as_ref())
    }
}

impl ToSchema for CreateGroupRequest {
    fn name() -> Cow<'static, str> {
        Cow::Borrowed("CreateGroup")
    }
}

impl BodyShape for crate::service::groups::CreateGroup {
    const OBJECTS: &'static [&'static str] = <crate::service::CreateSession as BodyShape>::OBJECTS;
}

/// The body of `POST /v1/groups/{id}/steps`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GroupStep {
    /// The members stepped; absent: all.
    #[serde(default)]
    pub mask: Option<Vec<u32>>,
    /// The state of each member stepped.
    #[serde(default)]
    pub states: Option<Vec<u32>>,
    /// A continuous model's observation of each member stepped.
    #[serde(default)]
    pub observations: Option<Vec<Vec<f64>>>,
    /// The stimulus of each member stepped.
    #[serde(default)]
    pub stimuli: Option<Vec<Vec<f64>>>,
    /// The action each member stepped took; null: the advised one.
    #[serde(default)]
    pub action_taken: Option<Vec<Option<u32>>>,
    /// The seq of each member's observation; absent: at least once.
    #[serde(default)]
    pub seqs: Option<Vec<u64>>,
}

impl BodyShape for GroupStep {
    const OBJECTS: &'static [&'static str] = &[""];
}

impl PartialSchema for GroupStep {
    fn schema() -> RefOr<Schema> {
        schema_named(Self::name().as_ref())
    }
}

impl ToSchema for GroupStep {
    fn name() -> Cow<'static, str> {
        Cow::Borrowed("GroupStep")
    }
}

/// The reply to a group step, by columns: one entry per member stepped, in
/// the order of the mask; a refused member's entries are null (`false` in
/// `replayed`) and its error is in `errors`.
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct GroupStepReply {
    /// The next action of each member (its index).
    pub actions: Vec<Option<usize>>,
    /// The drive of each member after the step.
    pub drives: Vec<Option<Vec<f64>>>,
    /// |r| of each member's step.
    pub rewards: Vec<Option<f64>>,
    /// Policy updates applied, per member.
    pub policy_versions: Vec<Option<u64>>,
    /// Ticks so far, per member.
    pub ticks: Vec<Option<u64>>,
    /// The members refused, in mask order; empty when all were applied.
    pub errors: Vec<MemberError>,
    /// Only when the step carried `seqs`: whether each member's step is the
    /// one recorded for its seq, replayed (nothing applied).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub replayed: Vec<bool>,
}

/// Why a member of a step was refused: the error the same observation sent
/// alone would get. Unless `code` is `numerical_failure`, its observation was
/// not applied.
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct MemberError {
    /// The member's index in the group.
    pub index: usize,
    /// The stable error code, e.g. `unknown_state`.
    pub code: String,
    /// The message.
    pub message: String,
    /// `seq_gap`: the seq the member's session takes next.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expected_seq: Option<u64>,
    /// `seq_expired`: the oldest seq the member's session can still replay.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub oldest_seq: Option<u64>,
}

impl GroupStepReply {
    /// The columns of these members' steps; `numbered`: the step carried
    /// `seqs`, and the reply says which members were replayed.
    pub fn of(steps: Vec<MemberStep>, numbered: bool) -> Self {
        let m = steps.len();
        let mut reply = Self {
            actions: Vec::with_capacity(m),
            drives: Vec::with_capacity(m),
            rewards: Vec::with_capacity(m),
            policy_versions: Vec::with_capacity(m),
            ticks: Vec::with_capacity(m),
            errors: Vec::new(),
            replayed: Vec::with_capacity(if numbered { m } else { 0 }),
        };
        for MemberStep { index, result } in steps {
            match result {
                Ok(step) => {
                    reply.actions.push(Some(step.action_index));
                    reply.drives.push(Some(step.drive));
                    reply.rewards.push(Some(step.reward));
                    reply.policy_versions.push(Some(step.policy_version));
                    reply.ticks.push(Some(step.tick));
                    if numbered {
                        reply.replayed.push(step.replayed);
                    }
                }
                Err(e) => {
                    reply.actions.push(None);
                    reply.drives.push(None);
                    reply.rewards.push(None);
                    reply.policy_versions.push(None);
                    reply.ticks.push(None);
                    if numbered {
                        reply.replayed.push(false);
                    }
                    let (status, _, code) = crate::api::error::classify(&e);
                    let (expected_seq, oldest_seq) = crate::api::error::seq_details(&e);
                    reply.errors.push(MemberError {
                        index,
                        code: code.to_string(),
                        message: crate::api::error::public_message(&e, status),
                        expected_seq,
                        oldest_seq,
                    });
                }
            }
        }
        reply
    }
}
