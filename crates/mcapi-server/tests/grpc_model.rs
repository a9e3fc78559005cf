//! The typed gRPC `Model` (docs/grpc.md) on the full server
//! (`server::start`, both ports on real sockets, a durable store):
//! - a typed preset, grid map and full table (deterministic and stochastic)
//!   each create a session whose model summary equals the one the
//!   equivalent REST JSON creates, and the one the deprecated `model_json`
//!   creates; typed sessions survive a restart;
//! - an invalid typed model gets the gRPC status and `x-mcapi-error-code`
//!   of the equivalent REST JSON, absurd counts without absurd allocation;
//! - `model` and `model_json` both set, or neither, is INVALID_ARGUMENT.
//!
//! A test binary of its own: it measures its own process's peak resident
//! memory (the absurd counts), which other tests would disturb.

use std::time::{Duration, Instant};

use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_testkit::start_in_process as start;
use serde_json::{Value, json};
use tonic::Code;
use tonic::transport::Channel;

async fn grpc_client(running: &mcapi_server::server::Running) -> AgentsClient<Channel> {
    AgentsClient::connect(format!("http://{}", running.grpc_addr))
        .await
        .expect("grpc connects")
}

fn typed(model: pb::Model) -> pb::CreateSessionRequest {
    pb::CreateSessionRequest {
        model: Some(model),
        agent: Some(pb::SessionConfig {
            seed: Some(7),
            ..Default::default()
        }),
        ..Default::default()
    }
}

#[allow(deprecated)]
fn legacy(json: &Value) -> pb::CreateSessionRequest {
    pb::CreateSessionRequest {
        model_json: json.to_string(),
        model: None,
        agent: Some(pb::SessionConfig {
            seed: Some(7),
            ..Default::default()
        }),
    }
}

fn form(f: pb::model::Form) -> pb::Model {
    pb::Model { form: Some(f) }
}

fn basis(k: pb::basis::Kind) -> Option<pb::Basis> {
    Some(pb::Basis { kind: Some(k) })
}

fn strings(names: &[&str]) -> Vec<String> {
    names.iter().map(|s| s.to_string()).collect()
}

fn full(
    states: u64,
    actions: &[&str],
    stimuli: &[&str],
    transitions: pb::full_model::Transitions,
) -> pb::FullModel {
    pb::FullModel {
        states,
        state_names: vec![],
        actions: strings(actions),
        stimuli: strings(stimuli),
        transitions: Some(transitions),
        basis: None,
    }
}

fn next(rows: &[&[i64]]) -> pb::full_model::Transitions {
    pb::full_model::Transitions::Next(pb::DeterministicTransitions {
        rows: rows
            .iter()
            .map(|r| pb::NextRow { next: r.to_vec() })
            .collect(),
    })
}

enum A {
    I(u64),
    N(&'static str),
}

/// A pair's row: state, action, successors with probabilities.
type Row<'a> = (u64, A, &'a [(u64, f64)]);

fn stochastic(t: &[Row<'_>]) -> pb::full_model::Transitions {
    pb::full_model::Transitions::Stochastic(pb::StochasticTransitions {
        transitions: t
            .iter()
            .map(|(s, a, next)| pb::Transition {
                state: *s,
                action: Some(match a {
                    A::I(i) => pb::transition::Action::ActionIndex(*i),
                    A::N(n) => pb::transition::Action::ActionName(n.to_string()),
                }),
                next: next
                    .iter()
                    .map(|&(state, probability)| pb::Successor { state, probability })
                    .collect(),
            })
            .collect(),
    })
}

/// The gRPC model summary in the REST JSON shape.
fn summary_json(m: &pb::ModelSummary) -> Value {
    let basis = m.basis.as_ref().expect("basis");
    let mut v = json!({
        "states": m.states,
        "actions": m.actions,
        "stimuli": m.stimuli,
        "pairs": m.pairs,
        "transitions": m.transitions,
        "deterministic": m.deterministic,
        "basis": {"kind": basis.kind, "k": basis.k},
        "features": m.features,
    });
    if let Some(l) = &m.layout {
        v["layout"] = json!({
            "rows": l.rows,
            "cols": l.cols,
            "cells": l.cells.iter().map(|c| [c.row, c.col]).collect::<Vec<_>>(),
            "marks": l.marks.iter().map(|m| json!({"mark": m.mark, "state": m.state})).collect::<Vec<_>>(),
        });
    }
    if let Some(l) = &m.learned {
        let optimism = match pb::Optimism::try_from(l.optimism) {
            Ok(pb::Optimism::Absorbing) => "absorbing",
            Ok(pb::Optimism::Stimulus) => "stimulus",
            other => panic!("the server sent optimism {other:?}"),
        };
        v["learned"] = json!({
            "known_after": l.known_after,
            "optimism": optimism,
            "max_transitions": l.max_transitions,
        });
    }
    v
}

fn learned(known_after: Option<u32>, optimism: pb::Optimism) -> pb::LearnedTransitions {
    pb::LearnedTransitions {
        known_after,
        optimism: optimism.into(),
    }
}

/// Every valid model in both encodings: (name, typed, REST JSON).
fn valid_models() -> Vec<(&'static str, pb::Model, Value)> {
    use pb::basis::Kind;
    use pb::model::Form;
    vec![
        (
            "preset",
            pb::Model::preset("hallway"),
            json!({"preset": "hallway"}),
        ),
        (
            "preset with a basis",
            form(Form::Preset(pb::PresetModel {
                name: "three_room".into(),
                basis: basis(Kind::ProtoValue(pb::ProtoValueBasis { k: 4 })),
            })),
            json!({"preset": "three_room", "basis": {"kind": "proto_value", "k": 4}}),
        ),
        (
            "grid",
            form(Form::Grid(pb::GridModel {
                rows: strings(&["#######", "#a..#.#", "#.#...#", "#..b..#", "#######"]),
                sources: [("a".to_string(), 0), ("b".to_string(), 1)].into(),
                stimuli: strings(&["food", "water"]),
                basis: basis(Kind::Indicator(pb::IndicatorBasis {})),
                learn: false,
                learning: None,
            })),
            json!({
                "grid": ["#######", "#a..#.#", "#.#...#", "#..b..#", "#######"],
                "sources": {"a": 0, "b": 1},
                "stimuli": ["food", "water"],
                "basis": {"kind": "indicator"},
            }),
        ),
        (
            "grid with defaults",
            form(Form::Grid(pb::GridModel {
                rows: strings(&["#####", "#a.b#", "#####"]),
                sources: [("b".to_string(), 0), ("a".to_string(), 1)].into(),
                stimuli: vec![],
                basis: None,
                learn: false,
                learning: None,
            })),
            json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"b": 0, "a": 1}}),
        ),
        (
            "grid, learned with defaults",
            form(Form::Grid(pb::GridModel {
                rows: strings(&["#####", "#a.b#", "#####"]),
                sources: [("a".to_string(), 0), ("b".to_string(), 1)].into(),
                stimuli: vec![],
                basis: None,
                learn: true,
                learning: None,
            })),
            json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1},
                   "learn": true}),
        ),
        (
            "grid, learned with m and optimism",
            form(Form::Grid(pb::GridModel {
                rows: strings(&["#####", "#a.b#", "#####"]),
                sources: [("a".to_string(), 0), ("b".to_string(), 1)].into(),
                stimuli: vec![],
                basis: None,
                learn: true,
                learning: Some(learned(Some(5), pb::Optimism::Stimulus)),
            })),
            json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1},
                   "learn": true, "learning": {"known_after": 5, "optimism": "stimulus"}}),
        ),
        (
            "full, learned",
            form(Form::Full(pb::FullModel {
                state_names: strings(&["left end", "middle", "right end"]),
                ..full(
                    3,
                    &["left", "right"],
                    &["x"],
                    pb::full_model::Transitions::Learn(learned(Some(1), pb::Optimism::Absorbing)),
                )
            })),
            json!({"states": 3, "state_names": ["left end", "middle", "right end"],
                   "actions": ["left", "right"], "stimuli": ["x"], "transitions": "learn",
                   "learning": {"known_after": 1, "optimism": "absorbing"}}),
        ),
        (
            "full, deterministic",
            form(Form::Full(pb::FullModel {
                state_names: strings(&["left end", "middle", "right end"]),
                ..full(
                    3,
                    &["left", "right"],
                    &["x"],
                    next(&[&[0, 1], &[0, 2], &[1, -1]]),
                )
            })),
            json!({
                "states": 3,
                "state_names": ["left end", "middle", "right end"],
                "actions": ["left", "right"],
                "next": [[0, 1], [0, 2], [1, null]],
                "stimuli": ["x"],
            }),
        ),
        (
            "full, stochastic, custom basis",
            form(Form::Full(pb::FullModel {
                basis: basis(Kind::Custom(pb::CustomBasis {
                    state_features: [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]
                        .iter()
                        .map(|r| pb::FeatureRow {
                            features: r.to_vec(),
                        })
                        .collect(),
                })),
                ..full(
                    3,
                    &["stay", "go"],
                    &["a", "b"],
                    stochastic(&[
                        (0, A::N("go"), &[(1, 0.25), (2, 0.75)]),
                        (0, A::I(0), &[(0, 1.0)]),
                        (1, A::I(1), &[(2, 1.0)]),
                        (2, A::N("stay"), &[(2, 0.5), (0, 0.5)]),
                    ]),
                )
            })),
            json!({
                "states": 3,
                "actions": ["stay", "go"],
                "transitions": [
                    {"state": 0, "action": "go", "next": [[1, 0.25], [2, 0.75]]},
                    {"state": 0, "action": 0, "next": [[0, 1.0]]},
                    {"state": 1, "action": 1, "next": [[2, 1.0]]},
                    {"state": 2, "action": "stay", "next": [[2, 0.5], [0, 0.5]]},
                ],
                "stimuli": ["a", "b"],
                "basis": {"kind": "custom", "state_features": [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]},
            }),
        ),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn typed_models_create_the_sessions_their_rest_json_creates() {
    let data = tempfile::tempdir().expect("data dir");
    let running = start(data.path()).await;
    let base = format!("http://{}", running.http_addr);
    let http = reqwest::Client::new();
    let mut grpc = grpc_client(&running).await;
    let mut typed_ids = vec![];
    for (name, model, rest_json) in valid_models() {
        let rest: Value = http
            .post(format!("{base}/v1/sessions"))
            .json(&json!({"model": rest_json, "agent": {"seed": 7}}))
            .send()
            .await
            .expect("create over REST")
            .json()
            .await
            .expect("json");
        assert!(rest["model"].is_object(), "`{name}` over REST: {rest}");
        let info = grpc
            .create_session(typed(model))
            .await
            .unwrap_or_else(|s| panic!("`{name}` typed: {s:?}"))
            .into_inner();
        let summary = info.model.as_ref().expect("model summary");
        assert_eq!(
            summary_json(summary),
            rest["model"],
            "`{name}`: typed vs REST"
        );
        let old = grpc
            .create_session(legacy(&rest_json))
            .await
            .unwrap_or_else(|s| panic!("`{name}` model_json: {s:?}"))
            .into_inner();
        assert_eq!(old.model, info.model, "`{name}`: typed vs model_json");
        assert_eq!(old.agent, info.agent, "`{name}`: same effective config");
        assert_eq!(old.cost, info.cost, "`{name}`: same cost");
        typed_ids.push((info.id, rest["model"].clone()));
    }
    // A typed model is stored as its REST JSON: the sessions come back.
    running.shutdown();
    running.wait().await.expect("clean shutdown");
    let running = start(data.path()).await;
    let base = format!("http://{}", running.http_addr);
    for (id, model) in typed_ids {
        let got: Value = http
            .get(format!("{base}/v1/sessions/{id}"))
            .send()
            .await
            .expect("get over REST")
            .json()
            .await
            .expect("json");
        assert_eq!(got["model"], model, "session {id} after a restart");
    }
    running.shutdown();
    running.wait().await.expect("clean shutdown");
}

/// Peak resident memory of this process (the server runs in it).
fn peak_rss() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

fn grpc_code(http: u16) -> Code {
    match http {
        400 | 422 => Code::InvalidArgument,
        413 => Code::ResourceExhausted,
        other => panic!("unexpected REST status {other}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_typed_models_get_the_code_of_their_rest_json() {
    use pb::basis::Kind;
    use pb::model::Form;
    let data = tempfile::tempdir().expect("data dir");
    let running = start(data.path()).await;
    let base = format!("http://{}", running.http_addr);
    let http = reqwest::Client::new();
    let mut grpc = grpc_client(&running).await;
    let many: Vec<String> = (0..300_000).map(|i| format!("n{i}")).collect();
    let many_refs: Vec<&str> = many.iter().map(String::as_str).collect();
    // More actions than `--max-pairs` (1,000,000).
    let too_many: Vec<String> = (0..1_000_001).map(|i| format!("n{i}")).collect();
    let too_many_refs: Vec<&str> = too_many.iter().map(String::as_str).collect();
    let learn = |l| pb::full_model::Transitions::Learn(l);
    let cases: Vec<(&str, pb::Model, Value, &str)> = vec![
        (
            "learned, m of 0",
            form(Form::Full(full(
                3,
                &["go"],
                &["x"],
                learn(learned(Some(0), pb::Optimism::Unspecified)),
            ))),
            json!({"states": 3, "actions": ["go"], "stimuli": ["x"], "transitions": "learn",
                   "learning": {"known_after": 0}}),
            "invalid_parameter",
        ),
        (
            "learned, m of 4 000 000 000",
            form(Form::Full(full(
                3,
                &["go"],
                &["x"],
                learn(learned(Some(4_000_000_000), pb::Optimism::Unspecified)),
            ))),
            json!({"states": 3, "actions": ["go"], "stimuli": ["x"], "transitions": "learn",
                   "learning": {"known_after": 4_000_000_000u64}}),
            "invalid_parameter",
        ),
        (
            "learned, 10^18 states",
            form(Form::Full(full(
                1_000_000_000_000_000_000,
                &["go"],
                &["x"],
                learn(learned(None, pb::Optimism::Unspecified)),
            ))),
            json!({"states": 1_000_000_000_000_000_000u64, "actions": ["go"], "stimuli": ["x"],
                   "transitions": "learn"}),
            "limit_exceeded",
        ),
        (
            "learned, 10^18 states without actions",
            form(Form::Full(full(
                1_000_000_000_000_000_000,
                &[],
                &["x"],
                learn(learned(None, pb::Optimism::Unspecified)),
            ))),
            json!({"states": 1_000_000_000_000_000_000u64, "actions": [], "stimuli": ["x"],
                   "transitions": "learn"}),
            "bad_request",
        ),
        (
            "learned with proto-value functions (no graph)",
            form(Form::Full(pb::FullModel {
                basis: basis(Kind::ProtoValue(pb::ProtoValueBasis { k: 2 })),
                ..full(
                    4,
                    &["go", "stay"],
                    &["x"],
                    learn(learned(None, pb::Optimism::Absorbing)),
                )
            })),
            json!({"states": 4, "actions": ["go", "stay"], "stimuli": ["x"],
                   "transitions": "learn", "basis": {"kind": "proto_value", "k": 2},
                   "learning": {"optimism": "absorbing"}}),
            "bad_request",
        ),
        (
            "probabilities summing to 0.9",
            form(Form::Full(full(
                3,
                &["go"],
                &["x"],
                stochastic(&[(0, A::I(0), &[(1, 0.4), (2, 0.5)])]),
            ))),
            json!({"states": 3, "actions": ["go"], "stimuli": ["x"],
                   "transitions": [{"state": 0, "action": 0, "next": [[1, 0.4], [2, 0.5]]}]}),
            "",
        ),
        (
            "deterministic next out of range",
            form(Form::Full(full(
                3,
                &["go"],
                &["x"],
                next(&[&[1], &[7], &[0]]),
            ))),
            json!({"states": 3, "actions": ["go"], "stimuli": ["x"], "next": [[1], [7], [0]]}),
            "",
        ),
        (
            "stochastic next out of range",
            form(Form::Full(full(
                3,
                &["go"],
                &["x"],
                stochastic(&[(0, A::I(0), &[(5, 1.0)])]),
            ))),
            json!({"states": 3, "actions": ["go"], "stimuli": ["x"],
                   "transitions": [{"state": 0, "action": 0, "next": [[5, 1.0]]}]}),
            "",
        ),
        (
            "unknown action name",
            form(Form::Full(full(
                2,
                &["go"],
                &["x"],
                stochastic(&[(0, A::N("fly"), &[(1, 1.0)])]),
            ))),
            json!({"states": 2, "actions": ["go"], "stimuli": ["x"],
                   "transitions": [{"state": 0, "action": "fly", "next": [[1, 1.0]]}]}),
            "",
        ),
        (
            "next rows not one per state",
            form(Form::Full(full(3, &["go"], &["x"], next(&[&[1], &[0]])))),
            json!({"states": 3, "actions": ["go"], "stimuli": ["x"], "next": [[1], [0]]}),
            "",
        ),
        (
            "10^9 states",
            form(Form::Full(full(1_000_000_000, &["go"], &["x"], next(&[])))),
            json!({"states": 1_000_000_000u64, "actions": ["go"], "stimuli": ["x"], "next": []}),
            "limit_exceeded",
        ),
        (
            "10^18 states, stochastic",
            form(Form::Full(full(
                1_000_000_000_000_000_000,
                &["go", "stay"],
                &["x"],
                stochastic(&[]),
            ))),
            json!({"states": 1_000_000_000_000_000_000u64, "actions": ["go", "stay"],
                   "stimuli": ["x"], "transitions": []}),
            "limit_exceeded",
        ),
        (
            "1 000 001 actions",
            form(Form::Full(full(1, &too_many_refs, &["x"], next(&[])))),
            json!({"states": 1, "actions": too_many, "stimuli": ["x"], "next": []}),
            "limit_exceeded",
        ),
        (
            "300 000 stimuli",
            form(Form::Full(full(1, &["go"], &many_refs, next(&[&[0]])))),
            json!({"states": 1, "actions": ["go"], "stimuli": many, "next": [[0]]}),
            "limit_exceeded",
        ),
        (
            "unknown preset",
            pb::Model::preset("maze"),
            json!({"preset": "maze"}),
            "bad_request",
        ),
        (
            "proto-value k of 10^12",
            form(Form::Preset(pb::PresetModel {
                name: "hallway".into(),
                basis: basis(Kind::ProtoValue(pb::ProtoValueBasis {
                    k: 1_000_000_000_000,
                })),
            })),
            json!({"preset": "hallway", "basis": {"kind": "proto_value", "k": 1_000_000_000_000u64}}),
            "limit_exceeded",
        ),
        (
            "custom basis rows not one per state",
            form(Form::Full(pb::FullModel {
                basis: basis(Kind::Custom(pb::CustomBasis {
                    state_features: vec![pb::FeatureRow {
                        features: vec![1.0],
                    }],
                })),
                ..full(2, &["go"], &["x"], next(&[&[1], &[0]]))
            })),
            json!({"states": 2, "actions": ["go"], "stimuli": ["x"], "next": [[1], [0]],
                   "basis": {"kind": "custom", "state_features": [[1.0]]}}),
            "",
        ),
        (
            "grid source dimension u64::MAX",
            form(Form::Grid(pb::GridModel {
                rows: strings(&["#####", "#.a.#", "#####"]),
                sources: [("a".to_string(), u64::MAX)].into(),
                stimuli: vec![],
                basis: None,
                learn: false,
                learning: None,
            })),
            json!({"grid": ["#####", "#.a.#", "#####"], "sources": {"a": u64::MAX}}),
            "limit_exceeded",
        ),
        (
            "grid source mark not on the map",
            form(Form::Grid(pb::GridModel {
                rows: strings(&["#####", "#.a.#", "#####"]),
                sources: [("z".to_string(), 0)].into(),
                stimuli: vec![],
                basis: None,
                learn: false,
                learning: None,
            })),
            json!({"grid": ["#####", "#.a.#", "#####"], "sources": {"z": 0}}),
            "bad_request",
        ),
        (
            "grid stimuli not one per dimension",
            form(Form::Grid(pb::GridModel {
                rows: strings(&["#####", "#.a.#", "#####"]),
                sources: [("a".to_string(), 0)].into(),
                stimuli: strings(&["food", "water"]),
                basis: None,
                learn: false,
                learning: None,
            })),
            json!({"grid": ["#####", "#.a.#", "#####"], "sources": {"a": 0},
                   "stimuli": ["food", "water"]}),
            "bad_request",
        ),
        (
            "state names not one per state",
            form(Form::Full(pb::FullModel {
                state_names: strings(&["only one"]),
                ..full(2, &["go"], &["x"], next(&[&[1], &[0]]))
            })),
            json!({"states": 2, "state_names": ["only one"], "actions": ["go"],
                   "stimuli": ["x"], "next": [[1], [0]]}),
            "",
        ),
    ];
    let before = peak_rss();
    for (name, model, rest_json, want) in cases {
        let reply = http
            .post(format!("{base}/v1/sessions"))
            .json(&json!({"model": rest_json, "agent": {"seed": 7}}))
            .send()
            .await
            .expect("create over REST");
        let status = reply.status().as_u16();
        let body: Value = reply.json().await.expect("json error body");
        let rest_code = body["code"].as_str().expect("error code").to_string();
        if !want.is_empty() {
            assert_eq!(rest_code, want, "`{name}` over REST: {body}");
        }
        let started = Instant::now();
        let err = grpc.create_session(typed(model)).await.expect_err(name);
        assert!(
            started.elapsed() < Duration::from_secs(5),
            "`{name}` took {:?}",
            started.elapsed()
        );
        assert_eq!(
            err.code(),
            grpc_code(status),
            "`{name}`: {err:?} vs REST {body}"
        );
        let trailer = err
            .metadata()
            .get("x-mcapi-error-code")
            .and_then(|v| v.to_str().ok());
        assert_eq!(
            trailer,
            Some(rest_code.as_str()),
            "`{name}`: {err:?} vs REST {body}"
        );
    }
    let grown = peak_rss().saturating_sub(before);
    assert!(grown < 512 << 20, "peak memory grew by {grown} bytes");
    running.shutdown();
    running.wait().await.expect("clean shutdown");
}

fn assert_invalid<T: std::fmt::Debug>(r: Result<T, tonic::Status>, needle: &str) {
    let err = r.expect_err(needle);
    assert_eq!(err.code(), Code::InvalidArgument, "{err:?}");
    assert!(
        err.message().contains(needle),
        "`{}` should mention `{needle}`",
        err.message()
    );
    assert_eq!(
        err.metadata()
            .get("x-mcapi-error-code")
            .and_then(|v| v.to_str().ok()),
        Some("bad_request"),
        "{err:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[allow(deprecated)]
async fn exactly_one_of_model_and_model_json() {
    let data = tempfile::tempdir().expect("data dir");
    let running = start(data.path()).await;
    let mut grpc = grpc_client(&running).await;
    let both = pb::CreateSessionRequest {
        model_json: r#"{"preset": "hallway"}"#.into(),
        model: Some(pb::Model::preset("hallway")),
        agent: None,
    };
    assert_invalid(grpc.create_session(both).await, "both set");
    let neither = pb::CreateSessionRequest::default();
    assert_invalid(grpc.create_session(neither).await, "is required");
    // What only the typed form can get wrong: unset oneofs, a negative state.
    let unset = pb::Model { form: None };
    assert_invalid(grpc.create_session(typed(unset)).await, "no form");
    let no_kind = pb::Model {
        form: Some(pb::model::Form::Preset(pb::PresetModel {
            name: "hallway".into(),
            basis: Some(pb::Basis { kind: None }),
        })),
    };
    assert_invalid(grpc.create_session(typed(no_kind)).await, "model.basis");
    let negative = form(pb::model::Form::Full(full(
        2,
        &["go"],
        &["x"],
        next(&[&[1], &[-2]]),
    )));
    assert_invalid(
        grpc.create_session(typed(negative)).await,
        "model.next[1][0]",
    );
    let mut no_action = stochastic(&[(0, A::I(0), &[(1, 1.0)])]);
    if let pb::full_model::Transitions::Stochastic(t) = &mut no_action {
        t.transitions[0].action = None;
    }
    let no_action = form(pb::model::Form::Full(full(2, &["go"], &["x"], no_action)));
    assert_invalid(
        grpc.create_session(typed(no_action)).await,
        "model.transitions[0].action",
    );
    // An optimism the proto does not define, and `learning` without `learn`.
    let unknown_optimism = form(pb::model::Form::Full(full(
        2,
        &["go"],
        &["x"],
        pb::full_model::Transitions::Learn(pb::LearnedTransitions {
            known_after: None,
            optimism: 7,
        }),
    )));
    assert_invalid(
        grpc.create_session(typed(unknown_optimism)).await,
        "`model.learning.optimism`: unknown value 7",
    );
    let learning_alone = form(pb::model::Form::Grid(pb::GridModel {
        rows: strings(&["#####", "#a.b#", "#####"]),
        sources: [("a".to_string(), 0)].into(),
        stimuli: vec![],
        basis: None,
        learn: false,
        learning: Some(learned(Some(2), pb::Optimism::Unspecified)),
    }));
    assert_invalid(
        grpc.create_session(typed(learning_alone)).await,
        "`model.learning`: is only taken with `learn` set",
    );
    // The deprecated field alone still works.
    let old = grpc
        .create_session(legacy(&json!({"preset": "hallway"})))
        .await
        .expect("model_json alone")
        .into_inner();
    assert_eq!(old.model.expect("model").states, 50);
    running.shutdown();
    running.wait().await.expect("clean shutdown");
}
