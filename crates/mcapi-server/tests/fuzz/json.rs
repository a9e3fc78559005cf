//! The generators of JSON inputs: random values, absurd numbers, long
//! strings, mutations of valid create and observe bodies, raw bytes.

use proptest::prelude::*;
use serde_json::{Map, Value, json};

const KEYS: &[&str] = &[
    "model",
    "agent",
    "preset",
    "grid",
    "sources",
    "stimuli",
    "basis",
    "kind",
    "k",
    "state_features",
    "states",
    "actions",
    "next",
    "transitions",
    "state",
    "action",
    "state_names",
    "eta",
    "gamma",
    "priorities",
    "stimulus_rate",
    "optimistic_sd",
    "ridge",
    "epsilon",
    "seed",
    "update_mode",
    "history",
    "curiosity",
    "signal_dim",
    "params",
    "tau",
    "lag",
    "max_centres",
    "beta",
    "gain",
    "clip",
    "dt",
    "max_sources",
    "freeze_after",
    "stimulus",
    "action_taken",
    "signal",
    "signal_source",
    "seq",
    "observations",
    "observation",
    "observation_space",
    "low",
    "high",
    "out_of_bounds",
    "samples",
    "order",
    "max_coupling",
    "centres_per_dim",
    "width",
    "tilings",
    "tiles_per_dim",
    "table",
    "cells_per_dim",
    "per_cell",
    "max",
    "known_after",
    "neighbours",
    "reach",
];

const WORDS: &[&str] = &[
    "hallway",
    "three_room",
    "indicator",
    "proto_value",
    "custom",
    "sample_mean",
    "lockstep",
    "async",
    "left",
    "right",
    "stay",
    "a",
    "b",
    "#",
    ".",
    "",
    " ",
    "curiosity",
    "\u{0}",
    "é",
    "🦀",
    "#####",
    "#a.b#",
    "null",
    "fourier",
    "rbf",
    "tiles",
    "grid",
    "pvf",
    "clip",
    "refuse",
];

pub(crate) fn absurd_number() -> impl Strategy<Value = Value> {
    prop::sample::select(vec![
        json!(u64::MAX),
        json!(u64::MAX - 1),
        json!(i64::MIN),
        json!(i64::MAX),
        json!(u32::MAX),
        json!(1u64 << 32),
        json!(1u64 << 40),
        json!(1e308),
        json!(-1e308),
        json!(1.7976931348623157e308),
        json!(1e20),
        json!(1e12),
        json!(1e12 + 1.0),
        json!(-1e12 - 1.0),
        json!(9007199254740993u64),
        json!(f64::MIN_POSITIVE),
        json!(5e-324),
        json!(-0.0),
        json!(0),
        json!(-1),
        json!(1),
        json!(2),
        json!(0.5),
        json!(1.5),
        json!(3.0),
        json!(1e-300),
        json!(200_000),
        json!(200_001),
        json!(100_000),
        json!(64),
        json!(65),
    ])
}

pub(crate) fn string() -> impl Strategy<Value = String> {
    prop_oneof![
        prop::sample::select(WORDS).prop_map(str::to_string),
        "\\PC{0,16}",
        (1usize..20_000).prop_map(|n| "x".repeat(n)),
        (1usize..2_000).prop_map(|n| "é".repeat(n)),
    ]
}

fn key() -> impl Strategy<Value = String> {
    prop_oneof![
        4 => prop::sample::select(KEYS).prop_map(str::to_string),
        1 => string(),
    ]
}

fn leaf() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::from),
        (0u64..60).prop_map(Value::from),
        any::<i64>().prop_map(Value::from),
        any::<u64>().prop_map(Value::from),
        absurd_number(),
        any::<f64>().prop_filter_map("finite", |x| x.is_finite().then(|| json!(x))),
        string().prop_map(Value::from),
    ]
}

pub(crate) fn arb_json() -> impl Strategy<Value = Value> {
    leaf().prop_recursive(6, 96, 8, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..8).prop_map(Value::Array),
            prop::collection::vec((key(), inner), 0..8)
                .prop_map(|kv| Value::Object(kv.into_iter().collect::<Map<_, _>>())),
        ]
    })
}

/// The most a `Grow` mutation makes of one array or string, in bytes of
/// JSON and in JSON values (a deeply nested array is small as text and
/// large in memory): the generator's own memory counts in the RSS budget.
const GROWN_BYTES: usize = 2 << 20;
const GROWN_VALUES: usize = 100_000;

fn node_count(v: &Value) -> usize {
    1 + match v {
        Value::Array(items) => items.iter().map(node_count).sum(),
        Value::Object(map) => map.values().map(node_count).sum(),
        _ => 0,
    }
}

/// One change to a JSON value, at the node `at` (an index into its nodes,
/// modulo their number).
#[derive(Debug, Clone)]
enum Mutation {
    Replace(Value),
    Delete,
    Insert(String, Value),
    /// Repeat an array's items (or a string) up to this length.
    Grow(usize),
    /// Wrap in this many arrays.
    Nest(usize),
}

fn mutation() -> impl Strategy<Value = (usize, Mutation)> {
    let m = prop_oneof![
        4 => absurd_number().prop_map(Mutation::Replace),
        3 => arb_json().prop_map(Mutation::Replace),
        2 => Just(Mutation::Delete),
        2 => (key(), arb_json()).prop_map(|(k, v)| Mutation::Insert(k, v)),
        1 => (1usize..12_000).prop_map(Mutation::Grow),
        1 => (1usize..300).prop_map(Mutation::Nest),
    ];
    (any::<usize>(), m)
}

/// JSON pointers of every node, the root first.
fn nodes(v: &Value, at: String, out: &mut Vec<String>) {
    out.push(at.clone());
    match v {
        Value::Array(items) => {
            for (i, x) in items.iter().enumerate() {
                nodes(x, format!("{at}/{i}"), out);
            }
        }
        Value::Object(map) => {
            for (k, x) in map {
                let k = k.replace('~', "~0").replace('/', "~1");
                nodes(x, format!("{at}/{k}"), out);
            }
        }
        _ => {}
    }
}

fn apply(v: &mut Value, (at, m): &(usize, Mutation)) {
    let mut all = Vec::new();
    nodes(v, String::new(), &mut all);
    let path = all[at % all.len()].clone();
    match m {
        Mutation::Replace(x) => {
            if let Some(node) = v.pointer_mut(&path) {
                *node = x.clone();
            }
        }
        Mutation::Delete => {
            let Some(cut) = path.rfind('/') else { return };
            let (parent, last) = (&path[..cut], &path[cut + 1..]);
            let last = last.replace("~1", "/").replace("~0", "~");
            match v.pointer_mut(parent) {
                Some(Value::Object(map)) => {
                    map.remove(&last);
                }
                Some(Value::Array(items)) => {
                    if let Ok(i) = last.parse::<usize>()
                        && i < items.len()
                    {
                        items.remove(i);
                    }
                }
                _ => {}
            }
        }
        Mutation::Insert(k, x) => match v.pointer_mut(&path) {
            Some(Value::Object(map)) => {
                map.insert(k.clone(), x.clone());
            }
            Some(Value::Array(items)) => items.push(x.clone()),
            _ => {}
        },
        Mutation::Grow(n) => match v.pointer_mut(&path) {
            // Up to about GROWN_BYTES of JSON: the generator's own memory
            // counts in the RSS budget too.
            Some(Value::Array(items)) if !items.is_empty() => {
                let original = items.clone();
                let bytes = original
                    .iter()
                    .map(|x| x.to_string().len() + 1)
                    .sum::<usize>();
                let values = original.iter().map(node_count).sum::<usize>();
                let n = (*n)
                    .min(original.len() * GROWN_BYTES / bytes.max(1))
                    .min(original.len() * GROWN_VALUES / values.max(1));
                while items.len() < n {
                    items.push(original[items.len() % original.len()].clone());
                }
            }
            Some(Value::String(s)) if !s.is_empty() => {
                let unit = s.clone();
                while s.len() < (*n).min(GROWN_BYTES) {
                    s.push_str(&unit);
                }
            }
            _ => {}
        },
        Mutation::Nest(depth) => {
            if let Some(node) = v.pointer_mut(&path) {
                let mut x = node.take();
                for _ in 0..*depth {
                    x = Value::Array(vec![x]);
                }
                *node = x;
            }
        }
    }
}

pub(crate) fn create_bases() -> Vec<Value> {
    vec![
        json!({"model": {"preset": "hallway"}, "agent": {"seed": 1}}),
        json!({"model": {"preset": "three_room", "basis": {"kind": "proto_value", "k": 5}},
               "agent": {"update_mode": "async", "history": 10, "seed": 2}}),
        json!({"model": {"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1},
               "stimuli": ["food", "rest"], "basis": {"kind": "indicator"}}}),
        json!({"model": {"states": 3, "actions": ["l", "r"], "stimuli": ["x"],
               "next": [[null, 1], [0, 2], [1, null]], "state_names": ["a", "b", "c"]},
               "agent": {"eta": 0.1, "gamma": 0.5, "priorities": [1.0], "stimulus_rate": 0.5,
                         "optimistic_sd": 0.1, "ridge": 1e-3, "epsilon": 0.1, "seed": 3}}),
        json!({"model": {"states": 2, "actions": ["go"], "stimuli": ["x", "y"],
               "transitions": [{"state": 0, "action": "go", "next": [[0, 0.5], [1, 0.5]]},
                               {"state": 1, "action": 0, "next": [[0, 1.0]]}],
               "basis": {"kind": "custom", "state_features": [[1.0, 0.0], [0.0, 1.0]]}}}),
        json!({"model": {"preset": "hallway"},
               "agent": {"curiosity": {"signal_dim": 2,
                         "params": {"gain": 800, "dt": 0.08, "tau": 20, "lag": 20, "max_centres": 3}}}}),
        json!({"model": {"observation_space": {"low": [0, 0], "high": [1, 1]},
               "actions": ["n", "s", "e", "w"], "stimuli": ["food", "rest"],
               "basis": {"kind": "fourier", "order": 3, "max_coupling": 2},
               "out_of_bounds": "refuse", "samples": {"max": 64, "per_cell": 1}},
               "agent": {"seed": 5}}),
        json!({"model": {"observation_space": {"low": [-1, 0, 0], "high": [1, 10, 1]},
               "actions": ["a", "b"], "stimuli": ["x"],
               "basis": {"kind": "tiles", "tilings": 4, "tiles_per_dim": 6, "table": 512}},
               "agent": {"update_mode": "async"}}),
        json!({"model": {"observation_space": {"low": [0], "high": [1]},
               "actions": ["l", "r"], "stimuli": ["x", "y"],
               "basis": {"kind": "rbf", "centres_per_dim": 10, "width": 0.5},
               "samples": {"cells_per_dim": 20, "known_after": 2}}}),
        json!({"model": {"observation_space": {"low": [0, 0], "high": [2, 1]},
               "actions": ["n", "s", "e", "w"], "stimuli": ["food"],
               "basis": {"kind": "grid", "cells_per_dim": 12, "neighbours": 3, "reach": 2.0}},
               "agent": {"update_mode": "async", "seed": 9}}),
    ]
}

pub(crate) fn observe_bases() -> Vec<Value> {
    vec![
        json!({"state": 25}),
        json!({"state": 1, "stimulus": [0, 0]}),
        json!({"state": 1, "stimulus": [6.0, 0.0], "action_taken": "left"}),
        json!({"state": 0, "stimulus": [0, 0, 1], "action_taken": 1}),
        json!({"observations": [{"state": 1, "stimulus": [0, 0]}, {"state": 0, "stimulus": [0, 0]}]}),
        json!({"state": 1, "stimulus": [0, 0], "signal": [1.0, 1.0], "signal_source": 0}),
        json!({"state": 0, "stimulus": [1]}),
        json!({"state": 1, "stimulus": [0, 0], "seq": 1}),
        json!({"observations": [{"state": 1, "stimulus": [0, 0], "seq": 0}, {"state": 0, "stimulus": [0, 0], "seq": 1}]}),
        json!({"observation": [0.5, 0.25]}),
        json!({"observation": [0.5, 0.25], "stimulus": [0, 1], "action_taken": "e"}),
        json!({"observations": [{"observation": [0.1, 0.9], "stimulus": [1, 0]},
                                {"observation": [1.5, -3], "stimulus": [0, 0]}]}),
    ]
}

/// A request body: a mutated valid body (mostly), random JSON, deep
/// nesting, or raw bytes.
pub(crate) fn body(bases: Vec<Value>) -> impl Strategy<Value = Vec<u8>> {
    let n = bases.len();
    let mutated = (0..n, prop::collection::vec(mutation(), 1..5)).prop_map(move |(i, ms)| {
        let mut v = bases[i].clone();
        for m in &ms {
            apply(&mut v, m);
        }
        v.to_string().into_bytes()
    });
    prop_oneof![
        12 => mutated,
        3 => arb_json().prop_map(|v| v.to_string().into_bytes()),
        1 => (1usize..5_000).prop_map(|d| format!("{}{}", "[".repeat(d), "]".repeat(d)).into_bytes()),
        1 => (1usize..5_000).prop_map(|d| format!("{{\"model\":{}1{}}}", "{\"a\":".repeat(d), "}".repeat(d)).into_bytes()),
        1 => prop::collection::vec(any::<u8>(), 0..512),
        // Beyond the default body limit (16 MiB): 413, not an allocation.
        1 => Just(format!("{}{{}}", " ".repeat(17 << 20)).into_bytes()),
    ]
}
