//! The schemas of the OpenAPI document ([`crate::api::openapi`]) that a
//! derive cannot say exactly:
//!
//! - the request bodies, written out by hand from the server's [`Limits`]
//!   and the core's constants, so every bound the server enforces is a
//!   `minimum`/`maximum`/`maxLength`/`maxItems` in the schema, and every
//!   form a body may take is one branch of a `oneOf` (`model`: preset, grid
//!   map, full model with `next`, full model with `transitions`; the basis;
//!   `action_taken`: index or name; a stimulus rate: constant or named; one
//!   observation or a batch). `null` is allowed exactly where the server
//!   reads it as "absent";
//! - the error responses every operation may answer (reusable components
//!   `BadRequest`, `Unauthorized`, ... with the `{"code","message"}` body);
//! - the API-key security scheme and the operation tags.
//!
//! Checked three ways: `tests/integration/openapi.rs` (each bound equals the limit it
//! describes; documented examples are accepted and near misses refused),
//! schemathesis against the live server (`make contract`) and the fuzzer
//! (`tests/fuzz/`).

use std::borrow::Cow;

use serde::Serialize;
use serde_json::json;
use utoipa::openapi::schema::{
    AdditionalProperties, ArrayBuilder, ArrayItems, ObjectBuilder, OneOfBuilder, Schema,
    SchemaType, Type,
};
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::openapi::{ContentBuilder, OpenApi, Ref, RefOr, Response, ResponseBuilder};
use utoipa::{Modify, PartialSchema, ToResponse, ToSchema};

use crate::service::Limits;
use mcapi_core::curiosity::{MAX_CENTRES, MAX_SIGNAL_DIM, MAX_SOURCES_LIMIT, MAX_WINDOW};
use mcapi_core::error::MAX_STIMULUS;

/// Largest JSON integer the server reads into a `u64`/`usize`.
const U64_MAX: u64 = u64::MAX;

/// Characters Rust's `str::trim` removes (Unicode `White_Space`), as a
/// regular-expression class body that ECMA-262 and Python both read.
const WHITE_SPACE: &str = r"\t-\r \x85\xa0\u1680\u2000-\u200a\u2028\u2029\u202f\u205f\u3000";

fn reference(name: &str) -> RefOr<Schema> {
    Ref::from_schema_name(name).into()
}

/// `$ref`, or `null` (a field the server reads as absent when null).
fn nullable_ref(name: &str, description: &str) -> RefOr<Schema> {
    OneOfBuilder::new()
        .item(ObjectBuilder::new().schema_type(Type::Null))
        .item(reference(name))
        .description(Some(description))
        .into()
}

fn typed(t: Type, nullable: bool) -> ObjectBuilder {
    if nullable {
        ObjectBuilder::new().schema_type(SchemaType::from_iter([t, Type::Null]))
    } else {
        ObjectBuilder::new().schema_type(t)
    }
}

/// An integer in `min..=max`.
fn integer(min: u64, max: u64, nullable: bool, description: &str) -> ObjectBuilder {
    typed(Type::Integer, nullable)
        .minimum(Some(as_number(min)))
        .maximum(Some(as_number(max)))
        .description(Some(description))
}

fn as_number(x: u64) -> utoipa::Number {
    utoipa::Number::UInt(usize::try_from(x).unwrap_or(usize::MAX))
}

/// Bounds of a JSON number.
#[derive(Clone, Copy)]
enum Bound {
    Incl(f64),
    Excl(f64),
    None,
}

fn number(lower: Bound, upper: Bound, nullable: bool, description: &str) -> ObjectBuilder {
    let mut o = typed(Type::Number, nullable).description(Some(description));
    o = match lower {
        Bound::Incl(x) => o.minimum(Some(x)),
        Bound::Excl(x) => o.exclusive_minimum(Some(x)),
        Bound::None => o,
    };
    match upper {
        Bound::Incl(x) => o.maximum(Some(x)),
        Bound::Excl(x) => o.exclusive_maximum(Some(x)),
        Bound::None => o,
    }
}

fn array(
    items: impl Into<RefOr<Schema>>,
    min: usize,
    max: usize,
    nullable: bool,
    description: &str,
) -> ArrayBuilder {
    let a = ArrayBuilder::new()
        .items(ArrayItems::RefOrSchema(Box::new(items.into())))
        .min_items((min > 0).then_some(min))
        .max_items(Some(max))
        .description(Some(description));
    if nullable {
        a.schema_type(SchemaType::from_iter([Type::Array, Type::Null]))
    } else {
        a
    }
}

/// An object that takes only the properties listed (serde's
/// `deny_unknown_fields`).
fn closed(description: &str) -> ObjectBuilder {
    ObjectBuilder::new()
        .schema_type(Type::Object)
        .additional_properties(Some(AdditionalProperties::<Schema>::FreeForm(false)))
        .description(Some(description))
}

/// A name (action, stimulus, state) of at most `max_bytes` bytes of UTF-8.
/// `maxLength` counts characters: an ASCII name may have `max_bytes` of
/// them, others fewer (the server counts bytes and answers 413 beyond).
fn name(max_bytes: usize, description: &str) -> ObjectBuilder {
    typed(Type::String, false)
        .max_length(Some(max_bytes))
        .description(Some(format!(
            "{description} (limit: at most {max_bytes} bytes of UTF-8)"
        )))
}

/// A [`name`] with at least one character that is not white space.
fn non_blank_name(max_bytes: usize, description: &str) -> ObjectBuilder {
    name(max_bytes, description).pattern(Some(format!("[^{WHITE_SPACE}]")))
}

/// Every request-body schema, by component name, for these limits.
pub fn request_schemas(limits: &Limits) -> Vec<(&'static str, RefOr<Schema>)> {
    let max_pairs = limits.max_pairs as u64;
    let max_name = limits.max_name_bytes;
    let max_window = limits.max_curiosity_window.min(MAX_WINDOW) as u64;
    let max_centres = limits.max_roc_centres.min(MAX_CENTRES) as u64;
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

    // serde ignores other keys next to the tag of a unit variant, so this
    // branch is open (the others take only their keys).
    let basis_indicator = ObjectBuilder::new()
        .schema_type(Type::Object)
        .description(Some("One feature per valid state-action pair (Φ = I)."))
        .property(
            "kind",
            typed(Type::String, false).enum_values(Some(["indicator"])),
        )
        .required("kind");
    let basis_pvf = closed(
        "The k smoothest proto-value functions of the state graph, per action \
         (k ≤ states; k × actions ≤ the feature limit; the model may have at most the \
         server's proto-value state limit of states).",
    )
    .property(
        "kind",
        typed(Type::String, false).enum_values(Some(["proto_value"])),
    )
    .property(
        "k",
        integer(
            1,
            limits.max_features as u64,
            false,
            "features per action (limit: k × actions)",
        ),
    )
    .required("kind")
    .required("k");
    let basis_custom = closed(
        "Client-given state features: one row of k numbers per state, the same k \
         for every state (k × actions ≤ the feature limit).",
    )
    .property(
        "kind",
        typed(Type::String, false).enum_values(Some(["custom"])),
    )
    .property(
        "state_features",
        array(
            array(
                typed(Type::Number, false),
                1,
                limits.max_features,
                false,
                "v(s), k features",
            ),
            1,
            limits.max_pairs,
            false,
            "one row per state",
        ),
    )
    .required("kind")
    .required("state_features");
    let basis = OneOfBuilder::new()
        .item(basis_indicator)
        .item(basis_pvf)
        .item(basis_custom)
        .description(Some(
            "The feature basis of LSTDQ, by `kind`. Default: `indicator` up to 2000 \
             state-action pairs, else 30 proto-value functions.",
        ));

    let action_ref = OneOfBuilder::new()
        .item(integer(
            0,
            max_state,
            false,
            "the action's index in `actions`",
        ))
        .item(name(max_name, "one of the names in `actions`"))
        .description(Some("An action, by index or by name."));

    let successor = ArrayBuilder::new()
        .prefix_items([
            Schema::from(integer(0, max_state, false, "the successor state s'")),
            Schema::from(number(
                Bound::Excl(0.0),
                Bound::Incl(1.0),
                false,
                "its probability p",
            )),
        ])
        .items(ArrayItems::False)
        .min_items(Some(2))
        .description(Some("`[s', p]`"));
    let transition = closed(
        "The successors of one state-action pair; pairs not listed are unavailable. \
         Probabilities sum to 1 (within 1e-9), each successor at most once, each pair at \
         most once.",
    )
    .property(
        "state",
        integer(0, max_state, false, "the state s (below `states`)"),
    )
    .property("action", reference("ActionRef"))
    .property(
        "next",
        array(successor, 1, limits.max_pairs, false, "`[[s', p], ...]`"),
    )
    .required("state")
    .required("action")
    .required("next");

    let names_of = |what: &str, max: usize, unique: bool| {
        array(
            non_blank_name(max_name, &format!("the name of a{what}")),
            1,
            max,
            false,
            &format!("names of the{what}s, each with a non-blank character"),
        )
        .unique_items(unique)
    };
    // A full model: one schema per encoding of P, so `next` and
    // `transitions` exclude each other (the other one may only be null).
    let full_model = |with: &str, description: &str| {
        let next = array(
            array(
                typed(Type::Integer, true)
                    .minimum(Some(0))
                    .maximum(Some(as_number(max_state)))
                    .description(Some("s' = next[s][a], or null where a is unavailable in s")),
                1,
                limits.max_pairs,
                false,
                "one entry per action",
            ),
            1,
            limits.max_pairs,
            false,
            "Deterministic P: one row per state.",
        );
        let transitions = array(
            reference("Transition"),
            1,
            limits.max_pairs,
            false,
            "Stochastic P, sparse: one entry per available state-action pair.",
        );
        let null = ObjectBuilder::new()
            .schema_type(Type::Null)
            .description(Some("give either `next` or `transitions`"));
        let o = closed(description)
            .property(
                "states",
                integer(
                    1,
                    max_pairs,
                    false,
                    "|S|; states are 0..states (limit: states × actions pairs)",
                ),
            )
            .property(
                "state_names",
                array(
                    name(max_name, "a state's display name"),
                    1,
                    limits.max_pairs,
                    true,
                    "display names, one per state",
                ),
            )
            .property("actions", names_of("n action", limits.max_pairs, true))
            .property(
                "stimuli",
                names_of(" stimulus dimension", max_stimuli, true),
            )
            .property(
                "basis",
                nullable_ref("Basis", "the basis (default by size)"),
            )
            .required("states")
            .required("actions")
            .required("stimuli")
            .required(if with == "learn" { "transitions" } else { with });
        match with {
            "next" => o.property("next", next).property("transitions", null),
            "learn" => o
                .property(
                    "transitions",
                    typed(Type::String, false)
                        .enum_values(Some(["learn"]))
                        .description(Some(
                            "no table: every action is available in every state and the \
                             agent learns P from its observations (docs/algorithm.md §8)",
                        )),
                )
                .property(
                    "learning",
                    nullable_ref(
                        "LearnedParams",
                        "m and the optimism rule (defaults: 3, absorbing)",
                    ),
                ),
            _ => o
                .property("transitions", transitions)
                .property("next", null),
        }
    };
    let learned_params = closed(
        "How the agent learns its transition model (docs/algorithm.md §8). A pair seen \
         fewer than `known_after` times is optimistic; `absorbing` (R-max) needs the \
         indicator basis.",
    )
    .property(
        "known_after",
        integer(
            1,
            u64::from(mcapi_core::learned::MAX_KNOWN_AFTER),
            true,
            "m: visits after which a pair's row of P̂ is used (default 3)",
        ),
    )
    .property(
        "optimism",
        typed(Type::String, true)
            .enum_values(Some(["absorbing", "stimulus"]))
            .description(Some(
                "`absorbing` (default): unknown pairs lead to a state worth the largest \
                 reward forever; `stimulus`: unknown pairs stay put, Ξ's optimistic start \
                 is the only optimism",
            )),
    );

    let preset = closed("A model of the paper: the 50-state hallway or the three-room maze.")
        .property(
            "preset",
            typed(Type::String, false).enum_values(Some(["hallway", "three_room"])),
        )
        .property(
            "basis",
            nullable_ref("Basis", "the basis (default: the preset's)"),
        )
        .required("preset")
        .examples([json!({"preset": "hallway"})]);
    let mark = typed(Type::String, false)
        .pattern(Some(r"^[\x21\x22\x24-\x2d\x2f-\x7e]$"))
        .description(Some(
            "one printable ASCII character other than `#` and `.`, marking cells of the map",
        ));
    let grid = closed(
        "An ASCII grid map: `#` walls, `.` free cells, any other printable ASCII \
         character a free cell with that mark. Rows have equal width; trailing blank rows \
         are ignored; rows × widest row ≤ the pair limit. Actions: left, right, north, \
         south, stay.",
    )
    .property(
        "grid",
        array(
            typed(Type::String, false),
            1,
            limits.max_pairs,
            false,
            "the map's rows",
        ),
    )
    .property(
        "sources",
        ObjectBuilder::new()
            .schema_type(Type::Object)
            .property_names(Some(mark))
            .additional_properties(Some(AdditionalProperties::RefOr(RefOr::T(Schema::from(
                integer(
                    0,
                    max_stimuli.saturating_sub(1) as u64,
                    false,
                    "the stimulus dimension delivered at the marked cells",
                ),
            )))))
            .min_properties(Some(1))
            .max_properties(Some(max_stimuli))
            .description(Some(
                "Mark → stimulus dimension (0-based); each dimension once, each mark on the map.",
            )),
    )
    .property(
        "stimuli",
        names_of(" stimulus dimension", max_stimuli, true)
            .schema_type(SchemaType::from_iter([Type::Array, Type::Null]))
            .description(Some(
                "names of the stimulus dimensions, one per dimension `sources` uses \
                 (default: the marks)",
            )),
    )
    .property(
        "basis",
        nullable_ref("Basis", "the basis (default by size)"),
    )
    .required("grid")
    .required("sources")
    .build();
    // The learned grid is the grid with `learn: true` required; the plain
    // one takes `learn` only as `false`, so the two exclude each other.
    let learn_flag = |value: bool, description: &str| -> RefOr<Schema> {
        Schema::from(
            typed(Type::Boolean, false)
                .enum_values(Some([value]))
                .description(Some(description)),
        )
        .into()
    };
    let mut grid_learned = grid.clone();
    grid_learned.description = Some(
        "A grid map whose transitions the agent learns (`\"learn\": true`, \
         docs/algorithm.md §8): the map gives the states, actions and basis; the agent \
         never sees its moves, only the observations."
            .into(),
    );
    grid_learned.properties.insert(
        "learn".into(),
        learn_flag(true, "the agent learns the transitions"),
    );
    grid_learned.properties.insert(
        "learning".into(),
        nullable_ref(
            "LearnedParams",
            "m and the optimism rule (defaults: 3, absorbing)",
        ),
    );
    grid_learned.required.push("learn".into());
    grid_learned.examples = vec![json!({"grid": ["#####", "#a.b#", "#####"],
        "sources": {"a": 0, "b": 1}, "learn": true, "learning": {"known_after": 3}})];
    let mut grid = grid;
    grid.properties.insert(
        "learn".into(),
        learn_flag(false, "`true`: see GridModelLearned"),
    );
    grid.examples = vec![json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1}})];
    let model = OneOfBuilder::new()
        .item(reference("PresetModel"))
        .item(reference("GridModel"))
        .item(reference("FullModelNext"))
        .item(reference("FullModelTransitions"))
        .item(reference("GridModelLearned"))
        .item(reference("FullModelLearned"))
        .description(Some(
            "The environment model, in one of its forms: a preset, a grid map, or a full \
             model with deterministic `next` or stochastic `transitions`; or a grid map or \
             full model whose transitions the agent learns (`\"learn\": true`, \
             `\"transitions\": \"learn\"`).",
        ));

    let stimulus_rate = OneOfBuilder::new()
        .item(number(
            Bound::Excl(0.0),
            Bound::Incl(1.0),
            false,
            "a constant learning rate of Ξ",
        ))
        .item(
            typed(Type::String, false)
                .enum_values(Some(["sample_mean"]))
                .description(Some("Ξ is the sample mean of what each pair delivered")),
        )
        .description(Some("How Ξ learns (default `sample_mean`)."));

    let window = "(the server allocates it for every curiosity module)";
    let curiosity_params = closed(
        "The curiosity channel's constants (docs/algorithm.md §7); each defaults to the \
         reproduction's value.",
    )
    .property(
        "max_centres",
        integer(
            2,
            max_centres,
            false,
            "N_max, ROC centres (default 3; limit)",
        ),
    )
    .property(
        "beta",
        number(
            Bound::Excl(0.0),
            Bound::Incl(1.0),
            false,
            "β, smallest ROC step (default 0.01)",
        ),
    )
    .property(
        "tau",
        integer(
            1,
            max_window,
            false,
            &format!("τ, the error window (default 20; limit) {window}"),
        ),
    )
    .property(
        "lag",
        integer(
            1,
            max_window,
            false,
            &format!("L of Eq. 7 (default 20; limit) {window}"),
        ),
    )
    .property(
        "eta_c",
        number(
            Bound::Excl(0.0),
            Bound::Excl(1.0),
            false,
            "η_c, the slow-feature MCA rate (default 0.03)",
        ),
    )
    .property(
        "gain",
        number(
            Bound::Excl(0.0),
            Bound::None,
            false,
            "g of Eq. 7 (default 800)",
        ),
    )
    .property(
        "clip",
        number(
            Bound::Excl(0.0),
            Bound::None,
            false,
            "upper clip of ξ_cur (default 12)",
        ),
    )
    .property(
        "delta",
        number(
            Bound::Excl(0.0),
            Bound::None,
            false,
            "δ, the freeze threshold (default 0.3)",
        ),
    )
    .property(
        "freeze_after",
        integer(
            1,
            u64::from(u32::MAX),
            false,
            "learned samples below δ before a freeze (default 100)",
        ),
    )
    .property(
        "explain_below",
        number(
            Bound::Excl(0.0),
            Bound::None,
            false,
            "error below which a frozen module explains a source (default 0.3)",
        ),
    )
    .property(
        "explain_min_samples",
        integer(
            1,
            U64_MAX,
            false,
            "samples a frozen module needs to explain a source (default 20)",
        ),
    )
    .property(
        "dt",
        number(
            Bound::Excl(0.0),
            Bound::None,
            false,
            "the signal clock's step (default 0.08)",
        ),
    )
    .property(
        "floor_rel",
        number(
            Bound::Incl(0.0),
            Bound::Excl(1.0),
            false,
            "whitening floor, relative (default 1e-3)",
        ),
    )
    .property(
        "floor_abs",
        number(
            Bound::Excl(0.0),
            Bound::None,
            false,
            "whitening floor, absolute (default 1e-8)",
        ),
    )
    .property(
        "initial_error",
        number(
            Bound::Incl(0.0),
            Bound::None,
            false,
            "a fresh module's error fill (default 1)",
        ),
    )
    .property(
        "max_sources",
        integer(
            1,
            max_sources,
            false,
            "signal sources are 0..max_sources (default 64; limit)",
        ),
    );
    let curiosity = closed(
        "A curiosity channel (docs/algorithm.md §7): the server appends a stimulus dimension \
         `curiosity`, last, computed from the raw `signal` of observations.",
    )
    .property(
        "signal_dim",
        integer(
            1,
            MAX_SIGNAL_DIM as u64,
            false,
            "dimension m of the raw signal (2 for the paper's Eq. 6)",
        ),
    )
    .property("params", reference("CuriosityParams"))
    .required("signal_dim");

    let config = closed("The agent's configuration; every field is optional (null = absent).")
        .property(
            "eta",
            number(
                Bound::Excl(0.0),
                Bound::Incl(0.5),
                true,
                "MCA rate η (Eq. 1); default 0.01",
            ),
        )
        .property(
            "gamma",
            number(
                Bound::Incl(0.0),
                Bound::Excl(1.0),
                true,
                "discount γ; default 0.95",
            ),
        )
        .property(
            "priorities",
            array(
                number(Bound::Excl(0.0), Bound::Incl(1.0), false, "ρ_i"),
                0,
                max_stimuli,
                true,
                "priorities ρ, one per stimulus dimension (the curiosity dimension \
                 included); default all 1",
            ),
        )
        .property(
            "stimulus_rate",
            nullable_ref("StimulusRate", "how Ξ learns"),
        )
        .property(
            "optimistic_sd",
            number(
                Bound::Incl(0.0),
                Bound::None,
                true,
                "σ of Ξ's optimistic initialisation; default 0.3",
            ),
        )
        .property(
            "ridge",
            number(
                Bound::Excl(0.0),
                Bound::None,
                true,
                "ridge added to A only when singular; default 1e-6",
            ),
        )
        .property(
            "epsilon",
            number(
                Bound::Incl(0.0),
                Bound::Incl(1.0),
                true,
                "ε-greedy exploration; default 0",
            ),
        )
        .property(
            "seed",
            integer(
                0,
                U64_MAX,
                true,
                "seed of the session's RNG; drawn when absent and returned",
            ),
        )
        .property(
            "update_mode",
            typed(Type::String, true)
                .enum_values(Some([json!("lockstep"), json!("async"), json!(null)]))
                .description(Some(
                    "`lockstep` (default): the reply follows exactly one policy update; \
                     `async`: the reply comes at once, the tick loop updates behind it",
                )),
        )
        .property(
            "history",
            integer(
                0,
                limits.max_history as u64,
                true,
                "recent ticks kept for /history (limit); default 256",
            ),
        )
        .property(
            "curiosity",
            nullable_ref("CuriosityConfig", "a curiosity channel"),
        );

    let create = closed(&format!(
        "A request to create a session: a model and the agent's configuration. {limits_note}"
    ))
    .property("model", reference("Model"))
    .property("agent", reference("SessionConfig"))
    .required("model")
    .examples([json!({"model": {"preset": "hallway"}, "agent": {"seed": 7}})]);

    let observation = closed(
        "One observation: the state the agent is in and, from the second observation on, \
         the stimulus it received on arrival.",
    )
    .property(
        "state",
        integer(
            0,
            max_state,
            false,
            "the state the agent is in now (below the model's `states`)",
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
    .required("state")
    .examples([json!({"state": 26, "stimulus": [0.0, 0.0]})]);
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
        ("CreateSession", create.into()),
        ("Model", model.into()),
        ("PresetModel", preset.into()),
        ("GridModel", grid.into()),
        (
            "FullModelNext",
            full_model(
                "next",
                "A full model with deterministic transitions `next`.",
            )
            .into(),
        ),
        (
            "FullModelTransitions",
            full_model(
                "transitions",
                "A full model with stochastic transitions `transitions`.",
            )
            .into(),
        ),
        ("GridModelLearned", grid_learned.into()),
        (
            "FullModelLearned",
            full_model(
                "learn",
                "A full model whose transitions the agent learns (`\"transitions\": \"learn\"`, \
                 docs/algorithm.md §8): every action available in every state. Its basis is \
                 `indicator` (the default) or `custom` with `\"optimism\": \"stimulus\"`; \
                 proto-value functions are refused (no transition graph).",
            )
            .examples([
                json!({"states": 3, "actions": ["left", "right"], "stimuli": ["food"],
                              "transitions": "learn",
                              "learning": {"known_after": 2, "optimism": "absorbing"}}),
            ])
            .into(),
        ),
        ("LearnedParams", learned_params.into()),
        ("Transition", transition.into()),
        ("ActionRef", action_ref.into()),
        ("Basis", basis.into()),
        ("SessionConfig", config.into()),
        ("StimulusRate", stimulus_rate.into()),
        ("CuriosityConfig", curiosity.into()),
        ("CuriosityParams", curiosity_params.into()),
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
        "the server already holds its maximum of 250000 sessions"
    );
    /// 500.
    InternalError = (
        "The session's policy update failed numerically (`numerical_failure`; the \
         observation was applied and logged, do not resend it) or the session is \
         quarantined after a fault of the server (`session_failed`: delete it and create \
         it again).",
        "session_failed",
        "session `s0001.01J0000000000000000000000` failed while applying an update and is quarantined; its state is not served. Delete it and create it again"
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
         (clustered) the session's shard is being moved (`unavailable`, \
         `storage_unavailable`, `request_timeout`, `shard_moving` with `Retry-After`); \
         may be retried.",
        "unavailable",
        "the server is recovering its stored sessions; retry shortly"
    );
}
