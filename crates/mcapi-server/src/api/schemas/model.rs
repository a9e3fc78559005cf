//! The schemas of a model: a preset, a grid map (plain or learned) or a
//! full model (`next`, `transitions` or learned), its basis, its
//! transitions and the way an action is named.

use serde_json::json;
use utoipa::openapi::RefOr;
use utoipa::openapi::schema::{
    AdditionalProperties, ArrayBuilder, ArrayItems, ObjectBuilder, OneOfBuilder, Schema,
    SchemaType, Type,
};

use super::builders::{
    Bound, array, as_number, closed, integer, name, non_blank_name, nullable_ref, number,
    reference, typed,
};
use crate::service::Limits;
use mcapi_core::basis::MAX_FEATURE;

/// The model schemas, by component name, for these limits.
pub(super) fn schemas(limits: &Limits) -> Vec<(&'static str, RefOr<Schema>)> {
    let max_pairs = limits.max_pairs as u64;
    let max_name = limits.max_name_bytes;
    let max_state = max_pairs.saturating_sub(1);
    let max_stimuli = limits.max_stimuli;
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
         for every state (k × actions ≤ the feature limit), each within ±1e6. The \
         table's condition number must be at most 1e5 (independent columns alike in \
         scale) and the planner's first policy update must succeed with it; otherwise \
         400 `invalid_basis`.",
    )
    .property(
        "kind",
        typed(Type::String, false).enum_values(Some(["custom"])),
    )
    .property(
        "state_features",
        array(
            array(
                number(
                    Bound::Incl(-MAX_FEATURE),
                    Bound::Incl(MAX_FEATURE),
                    false,
                    "a feature (|x| ≤ 1e6)",
                ),
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
        .item(reference("ContinuousModel"))
        .description(Some(
            "The environment model, in one of its forms: a preset, a grid map, or a full \
             model with deterministic `next` or stochastic `transitions`; or a grid map or \
             full model whose transitions the agent learns (`\"learn\": true`, \
             `\"transitions\": \"learn\"`); or a continuous world (`observation_space`).",
        ));

    vec![
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
    ]
}
