//! A battery of hostile requests over REST and gRPC against the real
//! binary: absurd numbers, lengths and counts, malformed bodies, wrong
//! types, missing or wrong keys. For every one the server must stay alive
//! (`/healthz` answers after it), answer a 4xx or the matching gRPC status
//! with the stable code the error table gives it, and never a 500 or a
//! panic; at the end its peak memory must be within the declared budget.
//!
//! Time is judged in the benchmark (BENCHMARKS.md), not here.
// These tests still send the deprecated `model_json` (accepted for one
// more release, docs/grpc.md).
#![allow(deprecated)]

use crate::common;

use std::time::Duration;

use common::{Launch, Server};
use mcapi_server::api::grpc::SESSION_METADATA;
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use reqwest::Method;
use serde_json::{Value, json};
use tonic::Code;

mod battery;

use battery::{Battery, Body, KEY, RSS_BUDGET_BYTES, authed, big, chain};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_requests_get_precise_refusals_and_the_server_stays_up() {
    let dir = tempfile::tempdir().expect("tempdir");
    let launch = Launch::new(
        dir.path(),
        &[
            "--api-key",
            KEY,
            "--max-key-bytes",
            "268435456",
            "--max-session-bytes",
            "67108864",
            "--max-key-sessions",
            "50",
            "--max-response-bytes",
            "10000",
            "--max-pvf-states",
            "400",
        ],
    );
    let server = Server::start(&launch, dir.path().join("server.log")).await;
    // A fresh connection per request: a refused upload (413) closes its
    // connection, which a pooled client would reuse and fail on.
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(60))
        .pool_max_idle_per_host(0)
        .build()
        .expect("client");
    let grpc = AgentsClient::connect(server.grpc_url())
        .await
        .expect("gRPC connects")
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(64 << 20);
    let mut b = Battery {
        client,
        base: server.base(),
        pid: server.pid(),
        cases: 0,
        grpc,
    };
    let rss_before = b.rss("VmRSS:");

    // ------------------------------------------------------ creates: sizes
    let hallway = |agent: Value| json!({"model": {"preset": "hallway"}, "agent": agent});
    for (field, value) in [
        ("tau", json!(100_000_000_000u64)),
        ("lag", json!(100_000_000_000u64)),
        ("max_centres", json!(1_000_000_000u64)),
        ("max_sources", json!(1_000_000_000u64)),
    ] {
        b.create(
            &format!("curiosity {field} absurd"),
            hallway(json!({"curiosity": {"signal_dim": 2, "params": {field: value}}})),
            413,
            "limit_exceeded",
        )
        .await;
    }
    b.create(
        "curiosity signal_dim 64 (an O(d^3) eigendecomposition per sample)",
        hallway(json!({"curiosity": {"signal_dim": 64}})),
        413,
        "limit_exceeded",
    )
    .await;
    // Continuous worlds: every size bounded before anything is built.
    let square = |extra: Value| {
        let mut m = json!({"observation_space": {"low": [0, 0], "high": [1, 1]},
                           "actions": ["a"], "stimuli": ["x"]});
        for (k, v) in extra.as_object().into_iter().flatten() {
            m[k] = v.clone();
        }
        json!({"model": m})
    };
    for (name, extra, status, code) in [
        (
            "continuous fourier order 10^12",
            json!({"basis": {"kind": "fourier", "order": 1_000_000_000_000u64}}),
            400,
            "bad_request",
        ),
        (
            "continuous sample store of 10^9",
            json!({"samples": {"max": 1_000_000_000u64}}),
            400,
            "invalid_parameter",
        ),
        (
            "continuous space of 10^5 dimensions",
            json!({"observation_space": {"low": vec![0; 100_000], "high": vec![1; 100_000]}}),
            400,
            "invalid_model",
        ),
        (
            "continuous grid of 4294967295 cells per dimension",
            json!({"basis": {"kind": "grid", "cells_per_dim": u32::MAX}}),
            400,
            "invalid_basis",
        ),
        (
            "continuous grid keeping 4294967295 moves per cell",
            json!({"basis": {"kind": "grid", "cells_per_dim": 64, "neighbours": u32::MAX}}),
            400,
            "invalid_basis",
        ),
        (
            "continuous grid reaching 1e300 cells",
            json!({"basis": {"kind": "grid", "cells_per_dim": 64, "reach": 1e300}}),
            400,
            "invalid_basis",
        ),
        (
            "continuous 2025 features over 16384 samples (gigabytes)",
            json!({"basis": {"kind": "fourier", "order": 44}, "samples": {"max": 16384}}),
            413,
            "limit_exceeded",
        ),
    ] {
        b.create(name, square(extra), status, code).await;
    }
    b.create(
        "curiosity signal_dim 10^12",
        hallway(json!({"curiosity": {"signal_dim": 1_000_000_000_000u64}})),
        400,
        "invalid_parameter",
    )
    .await;
    b.create(
        "curiosity signal_dim 0",
        hallway(json!({"curiosity": {"signal_dim": 0}})),
        400,
        "invalid_parameter",
    )
    .await;
    b.create(
        "curiosity tau 0",
        hallway(json!({"curiosity": {"signal_dim": 2, "params": {"tau": 0}}})),
        400,
        "invalid_parameter",
    )
    .await;
    b.create(
        "curiosity unknown parameter",
        hallway(json!({"curiosity": {"signal_dim": 2, "params": {"nope": 1}}})),
        400,
        "bad_request",
    )
    .await;
    let grid = |sources: Value| json!({"model": {"grid": ["#####", "#.a.#", "#####"], "sources": sources}});
    b.create(
        "grid source dimension 10^12",
        grid(json!({"a": 1_000_000_000_000u64})),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "grid source dimension u64::MAX",
        grid(json!({"a": u64::MAX})),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "grid source dimension negative",
        grid(json!({"a": -1})),
        400,
        "bad_request",
    )
    .await;
    b.create(
        "grid source key of 200 kB",
        grid(json!({big(200_000): 0})),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "grid source mark missing from the map",
        grid(json!({"z": 0})),
        400,
        "bad_request",
    )
    .await;
    let mut lines = vec![big(200_000)];
    lines.extend(std::iter::repeat_n(String::new(), 10_000));
    lines.push("x".into());
    b.create(
        "grid with a huge bounding box",
        json!({"model": {"grid": lines, "sources": {"x": 0}}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "grid with 10^5 sources",
        json!({"model": {"grid": ["#####", "#.a.#", "#####"],
            "sources": (0..100_000).map(|i| (format!("{i}"), json!(0))).collect::<serde_json::Map<_, _>>()}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "action name of 200 kB",
        json!({"model": {"states": 2, "actions": [big(200_000)], "stimuli": ["a"], "next": [[1], [0]]}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "stimulus name of 200 kB",
        json!({"model": {"states": 2, "actions": ["go"], "stimuli": [big(200_000)], "next": [[1], [0]]}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "state name of 200 kB",
        json!({"model": {"states": 2, "state_names": ["a", big(200_000)], "actions": ["go"], "stimuli": ["a"], "next": [[1], [0]]}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "preset name of 200 kB",
        json!({"model": {"preset": big(200_000)}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "unknown preset",
        json!({"model": {"preset": "labyrinth"}}),
        400,
        "bad_request",
    )
    .await;
    b.create(
        "10^15 states",
        json!({"model": {"states": 1_000_000_000_000_000u64, "actions": ["a", "b"], "stimuli": ["s"], "next": []}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "u64::MAX states",
        json!({"model": {"states": u64::MAX, "actions": ["a"], "stimuli": ["s"], "next": []}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "zero states",
        json!({"model": {"states": 0, "actions": ["a"], "stimuli": ["s"], "next": []}}),
        400,
        "invalid_model",
    )
    .await;
    b.create(
        "next pointing outside the model",
        json!({"model": {"states": 2, "actions": ["a"], "stimuli": ["s"], "next": [[u64::MAX], [0]]}}),
        400,
        "invalid_model",
    )
    .await;
    b.create(
        "next with the wrong number of rows",
        json!({"model": {"states": 3, "actions": ["a"], "stimuli": ["s"], "next": [[1], [0]]}}),
        400,
        "invalid_model",
    )
    .await;
    b.create(
        "transition probabilities that do not sum to 1",
        json!({"model": {"states": 2, "actions": ["a"], "stimuli": ["s"],
            "transitions": [{"state": 0, "action": 0, "next": [[1, 0.5]]}, {"state": 1, "action": 0, "next": [[0, 1.0]]}]}}),
        400,
        "invalid_model",
    )
    .await;
    b.create(
        "transition with a negative probability",
        json!({"model": {"states": 2, "actions": ["a"], "stimuli": ["s"],
            "transitions": [{"state": 0, "action": 0, "next": [[1, -1.0], [0, 2.0]]}, {"state": 1, "action": 0, "next": [[0, 1.0]]}]}}),
        400,
        "invalid_model",
    )
    .await;
    b.create(
        "100 stimulus dimensions",
        json!({"model": {"states": 2, "actions": ["a"],
            "stimuli": (0..100).map(|i| format!("s{i}")).collect::<Vec<_>>(), "next": [[1], [0]]}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "proto-value basis with k = 10^12",
        json!({"model": {"preset": "hallway", "basis": {"kind": "proto_value", "k": 1_000_000_000_000u64}}}),
        413,
        "limit_exceeded",
    )
    .await;
    let mut pvf = chain(1500);
    pvf["basis"] = json!({"kind": "proto_value", "k": 30});
    b.create(
        "proto-value basis on 1,500 states (a dense eigendecomposition)",
        json!({"model": pvf}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "custom basis with 10^4 features per state",
        json!({"model": {"preset": "hallway", "basis": {"kind": "custom",
            "state_features": vec![vec![0.5; 10_000]; 50]}}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "history of 10^12 ticks",
        hallway(json!({"history": 1_000_000_000_000u64})),
        413,
        "limit_exceeded",
    )
    .await;
    let mut wide = chain(60_000);
    wide["stimuli"] = json!((0..40).map(|i| format!("s{i}")).collect::<Vec<_>>());
    wide["basis"] = json!({"kind": "indicator"});
    b.create(
        "a session over the memory budget (40 stimuli, the longest history)",
        json!({"model": wide, "agent": {"history": 100_000}}),
        413,
        "limit_exceeded",
    )
    .await;
    let mut slow = chain(20_000);
    slow["transitions"] = json!(
        (0..20_000)
            .flat_map(
                |s: usize| (0..2).map(move |a| json!({"state": s, "action": a,
            "next": [[s.saturating_sub(1), 0.5], [(s + 1).min(19_999), 0.5]]}))
            )
            .collect::<Vec<_>>()
    );
    slow.as_object_mut().expect("object").remove("next");
    slow["basis"] = json!({"kind": "indicator"});
    b.create(
        "a session over the CPU budget (gamma near 1 on a stochastic model)",
        json!({"model": slow, "agent": {"gamma": 0.999999}}),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "10^6 priorities",
        hallway(json!({"priorities": vec![1.0; 1_000_000]})),
        413,
        "limit_exceeded",
    )
    .await;
    b.create(
        "eta 1e308",
        hallway(json!({"eta": 1e308})),
        400,
        "invalid_parameter",
    )
    .await;
    b.create(
        "gamma 1",
        hallway(json!({"gamma": 1.0})),
        400,
        "invalid_parameter",
    )
    .await;
    // Numbers the arithmetic cannot carry: refused at creation, not
    // accepted and then answered 500 at every observation.
    for (what, agent) in [
        (
            "priorities [5e-324, 1]",
            json!({"priorities": [5e-324, 1.0]}),
        ),
        ("optimistic_sd 1e308", json!({"optimistic_sd": 1e308})),
        ("ridge 5e-324", json!({"ridge": 5e-324})),
        (
            "curiosity gain and clip 1e308",
            json!({"curiosity": {"signal_dim": 2, "params": {"gain": 1e308, "clip": 1e308}}}),
        ),
    ] {
        b.create(what, hallway(agent), 400, "invalid_parameter")
            .await;
    }
    for (what, rows) in [
        (
            "custom basis [[1e6, 0], [0, 1]]",
            json!([[1e6, 0.0], [0.0, 1.0]]),
        ),
        (
            "custom basis [[1e100, 1], [1, 1e-100]]",
            json!([[1e100, 1.0], [1.0, 1e-100]]),
        ),
    ] {
        b.create(
            what,
            json!({"model": {"states": 2, "actions": ["a"], "stimuli": ["s"], "next": [[1], [0]],
                "basis": {"kind": "custom", "state_features": rows}}}),
            400,
            "invalid_basis",
        )
        .await;
    }
    b.create("seed -1", hallway(json!({"seed": -1})), 400, "bad_request")
        .await;
    b.create(
        "update_mode unknown",
        hallway(json!({"update_mode": "turbo"})),
        400,
        "bad_request",
    )
    .await;
    b.create("model {}", json!({"model": {}}), 400, "").await;
    b.create("model a number", json!({"model": 7}), 400, "bad_request")
        .await;
    b.create("no model", json!({"agent": {}}), 400, "bad_request")
        .await;
    b.rest(
        "deeply nested JSON",
        Method::POST,
        "/v1/sessions",
        Body::Raw(
            format!("{}{}", "[".repeat(100_000), "]".repeat(100_000)).into_bytes(),
            "application/json",
        ),
        400,
        "bad_request",
    )
    .await;
    b.rest(
        "body that is not JSON",
        Method::POST,
        "/v1/sessions",
        Body::Raw(b"\xff\xfe garbage".to_vec(), "application/json"),
        400,
        "bad_request",
    )
    .await;
    b.rest(
        "body without a JSON content type",
        Method::POST,
        "/v1/sessions",
        Body::Raw(b"{}".to_vec(), "text/plain"),
        400,
        "bad_request",
    )
    .await;
    // The server answers 413 as soon as the declared length is over the
    // limit and closes the connection without reading the rest: the client
    // may see that answer or, still uploading, a reset. Either way the
    // server must stay up; when the answer arrives it must be the right one.
    let oversized = b
        .client
        .post(format!("{}/v1/sessions", b.base))
        .bearer_auth(KEY)
        .header(reqwest::header::CONTENT_TYPE, "application/json")
        .body(format!("{{\"model\": \"{}\"}}", big(17 << 20)))
        .send()
        .await;
    if let Ok(resp) = oversized {
        assert_eq!(resp.status(), 413, "body over the size limit");
        let body: Value = resp.json().await.unwrap_or(Value::Null);
        assert_eq!(body["code"], "payload_too_large", "{body}");
    }
    b.cases += 1;
    b.alive("body over the size limit (17 MiB)").await;
    b.rest_with(
        "no API key",
        None,
        Method::POST,
        "/v1/sessions",
        Body::Json(hallway(json!({}))),
        401,
        "unauthenticated",
    )
    .await;
    b.rest_with(
        "a wrong API key",
        Some("not-the-key-but-long-enough"),
        Method::GET,
        "/v1/sessions",
        Body::None,
        401,
        "unauthenticated",
    )
    .await;

    // ------------------------------------------------ observations on a session
    let created = b
        .rest(
            "a legal create",
            Method::POST,
            "/v1/sessions",
            Body::Json(hallway(json!({"seed": 1}))),
            201,
            "",
        )
        .await;
    let id = created["id"].as_str().expect("id").to_string();
    assert!(created["cost"]["bytes"].as_u64().is_some_and(|b| b > 0));
    let obs = format!("/v1/sessions/{id}/observations");
    b.rest(
        "first observation",
        Method::POST,
        &obs,
        Body::Json(json!({"state": 0})),
        200,
        "",
    )
    .await;
    for (name, body, status, code) in [
        (
            "state 10^18",
            json!({"state": 1_000_000_000_000_000_000u64, "stimulus": [0, 0]}),
            400,
            "unknown_state",
        ),
        (
            "state -1",
            json!({"state": -1, "stimulus": [0, 0]}),
            400,
            "bad_request",
        ),
        (
            "state a string",
            json!({"state": "zero", "stimulus": [0, 0]}),
            400,
            "bad_request",
        ),
        (
            "stimulus of 10^6 components",
            json!({"state": 1, "stimulus": vec![0.0; 1_000_000]}),
            400,
            "stimulus_length",
        ),
        (
            "stimulus 1e308",
            json!({"state": 1, "stimulus": [1e308, 0]}),
            400,
            "stimulus_too_large",
        ),
        (
            "stimulus not numbers",
            json!({"state": 1, "stimulus": ["a", "b"]}),
            400,
            "bad_request",
        ),
        (
            "action_taken 10^18",
            json!({"state": 1, "stimulus": [0, 0], "action_taken": 1_000_000_000_000_000_000u64}),
            400,
            "unknown_action",
        ),
        (
            "action_taken name of 200 kB",
            json!({"state": 1, "stimulus": [0, 0], "action_taken": big(200_000)}),
            400,
            "bad_request",
        ),
        (
            "action_taken {}",
            json!({"state": 1, "stimulus": [0, 0], "action_taken": {}}),
            400,
            "bad_request",
        ),
        (
            "signal on a session without a channel",
            json!({"state": 1, "stimulus": [0, 0], "signal": [1.0, 2.0]}),
            400,
            "bad_request",
        ),
        (
            "signal_source without a signal",
            json!({"state": 1, "stimulus": [0, 0], "signal_source": 3}),
            400,
            "bad_request",
        ),
        (
            "unknown field",
            json!({"state": 1, "stimulus": [0, 0], "reward": 1e9}),
            400,
            "bad_request",
        ),
        (
            "batch of 10^5 observations",
            json!({"observations": vec![json!({"state": 1, "stimulus": [0, 0]}); 100_000]}),
            413,
            "limit_exceeded",
        ),
        (
            "empty batch",
            json!({"observations": []}),
            400,
            "bad_request",
        ),
        (
            "batch that is not a list",
            json!({"observations": {"state": 1}}),
            400,
            "bad_request",
        ),
    ] {
        b.rest(name, Method::POST, &obs, Body::Json(body), status, code)
            .await;
    }
    b.rest(
        "observe an unknown session",
        Method::POST,
        "/v1/sessions/s0000.01ARZ3NDEKTSV4RRFFQ69G5FAV/observations",
        Body::Json(json!({"state": 0})),
        404,
        "not_found",
    )
    .await;
    b.rest(
        "a session id of 10 kB",
        Method::GET,
        &format!("/v1/sessions/{}", big(10_000)),
        Body::None,
        404,
        "not_found",
    )
    .await;
    b.rest(
        "values: unknown table",
        Method::GET,
        &format!("/v1/sessions/{id}/values?include=everything"),
        Body::None,
        400,
        "bad_request",
    )
    .await;
    b.rest(
        "values larger than a response may be",
        Method::GET,
        &format!("/v1/sessions/{id}/values?include=all"),
        Body::None,
        413,
        "limit_exceeded",
    )
    .await;
    b.rest(
        "history larger than a response may be",
        Method::GET,
        &format!("/v1/sessions/{id}/history?limit=100000"),
        Body::None,
        413,
        "limit_exceeded",
    )
    .await;
    b.rest(
        "history limit -1",
        Method::GET,
        &format!("/v1/sessions/{id}/history?limit=-1"),
        Body::None,
        400,
        "bad_request",
    )
    .await;
    for limit in ["0", "1000000", "-5", "many"] {
        b.rest(
            &format!("list limit={limit}"),
            Method::GET,
            &format!("/v1/sessions?limit={limit}"),
            Body::None,
            400,
            "bad_request",
        )
        .await;
    }
    b.rest(
        "unknown route",
        Method::GET,
        "/v1/sessions/x/y/z",
        Body::None,
        404,
        "unknown_route",
    )
    .await;
    b.rest(
        "delete an unknown session",
        Method::DELETE,
        "/v1/sessions/s0000.01ARZ3NDEKTSV4RRFFQ69G5FAV",
        Body::None,
        404,
        "not_found",
    )
    .await;
    let curious = b
        .rest(
            "a legal curious create",
            Method::POST,
            "/v1/sessions",
            Body::Json(hallway(json!({"seed": 2, "curiosity": {"signal_dim": 2}}))),
            201,
            "",
        )
        .await;
    let cobs = format!(
        "/v1/sessions/{}/observations",
        curious["id"].as_str().expect("id")
    );
    b.rest(
        "curious first",
        Method::POST,
        &cobs,
        Body::Json(json!({"state": 0})),
        200,
        "",
    )
    .await;
    for (name, body, code) in [
        (
            "signal of 10^6 components",
            json!({"state": 1, "stimulus": [0, 0], "signal": vec![0.0; 1_000_000]}),
            "invalid_parameter",
        ),
        (
            "signal 1e308",
            json!({"state": 1, "stimulus": [0, 0], "signal": [1e308, 0.0]}),
            "invalid_parameter",
        ),
        (
            "signal_source 10^18",
            json!({"state": 1, "stimulus": [0, 0], "signal": [0.0, 0.0], "signal_source": 1_000_000_000_000_000_000u64}),
            "invalid_parameter",
        ),
        (
            "full-length stimulus on a curious session",
            json!({"state": 1, "stimulus": [0, 0, 0]}),
            "stimulus_length",
        ),
    ] {
        b.rest(name, Method::POST, &cobs, Body::Json(body), 400, code)
            .await;
    }

    // ----------------------------------------------------------------- gRPC
    let mut g = b.grpc.clone();
    let r = g
        .create_session(pb::CreateSessionRequest {
            model_json: r#"{"preset": "hallway"}"#.into(),
            model: None,
            agent: None,
        })
        .await;
    b.grpc(
        "gRPC create without a key",
        r,
        Code::Unauthenticated,
        "unauthenticated",
    )
    .await;
    let r = g
        .create_session(authed(pb::CreateSessionRequest {
            model_json: "{".into(),
            model: None,
            agent: None,
        }))
        .await;
    b.grpc(
        "gRPC model_json not JSON",
        r,
        Code::InvalidArgument,
        "bad_request",
    )
    .await;
    let r = g
        .create_session(authed(pb::CreateSessionRequest {
            model_json: r#"{"preset": "hallway"}"#.into(),
            model: None,
            agent: Some(pb::SessionConfig {
                curiosity: Some(pb::CuriosityConfig {
                    signal_dim: 2,
                    params_json: r#"{"tau": 100000000000}"#.into(),
                }),
                ..Default::default()
            }),
        }))
        .await;
    b.grpc(
        "gRPC curiosity tau absurd",
        r,
        Code::ResourceExhausted,
        "limit_exceeded",
    )
    .await;
    let r = g
        .create_session(authed(pb::CreateSessionRequest {
            model_json: r#"{"preset": "hallway"}"#.into(),
            model: None,
            agent: Some(pb::SessionConfig {
                history: Some(u64::MAX),
                ..Default::default()
            }),
        }))
        .await;
    b.grpc(
        "gRPC history u64::MAX",
        r,
        Code::ResourceExhausted,
        "limit_exceeded",
    )
    .await;
    let r = g
        .create_session(authed(pb::CreateSessionRequest {
            model_json: json!({"grid": ["#####", "#.a.#", "#####"], "sources": {"a": u64::MAX}})
                .to_string(),
            model: None,
            agent: None,
        }))
        .await;
    b.grpc(
        "gRPC grid source u64::MAX",
        r,
        Code::ResourceExhausted,
        "limit_exceeded",
    )
    .await;
    let observation = |state: u64, stimulus: Option<Vec<f64>>| pb::Observation {
        session_id: id.clone(),
        state,
        stimulus: stimulus.map(|values| pb::Stimulus { values }),
        ..Default::default()
    };
    let r = g
        .observe(authed(pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![observation(u64::MAX, Some(vec![0.0, 0.0]))],
        }))
        .await;
    b.grpc(
        "gRPC state u64::MAX",
        r,
        Code::InvalidArgument,
        "unknown_state",
    )
    .await;
    let r = g
        .observe(authed(pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![observation(1, Some(vec![f64::NAN, 0.0]))],
        }))
        .await;
    b.grpc(
        "gRPC stimulus NaN",
        r,
        Code::InvalidArgument,
        "non_finite_number",
    )
    .await;
    let r = g
        .observe(authed(pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![observation(1, Some(vec![f64::INFINITY, 0.0]))],
        }))
        .await;
    b.grpc(
        "gRPC stimulus infinite",
        r,
        Code::InvalidArgument,
        "non_finite_number",
    )
    .await;
    let r = g
        .observe(authed(pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![pb::Observation::default(); 200_000],
        }))
        .await;
    b.grpc(
        "gRPC batch of 200,000 empty observations",
        r,
        Code::ResourceExhausted,
        "",
    )
    .await;
    let r = g
        .observe(authed(pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![pb::Observation {
                action_taken: Some(pb::observation::ActionTaken::ActionIndex(u32::MAX)),
                ..observation(1, Some(vec![0.0, 0.0]))
            }],
        }))
        .await;
    b.grpc(
        "gRPC action_index u32::MAX",
        r,
        Code::InvalidArgument,
        "unknown_action",
    )
    .await;
    let r = g
        .observe(authed(pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![pb::Observation {
                signal: vec![1.0; 1000],
                ..observation(1, Some(vec![0.0, 0.0]))
            }],
        }))
        .await;
    b.grpc(
        "gRPC signal on a plain session",
        r,
        Code::InvalidArgument,
        "bad_request",
    )
    .await;
    let r = g
        .observe(authed(pb::ObserveRequest {
            session_id: "s0000.01ARZ3NDEKTSV4RRFFQ69G5FAV".into(),
            observations: vec![pb::Observation {
                session_id: String::new(),
                ..observation(0, None)
            }],
        }))
        .await;
    b.grpc("gRPC unknown session", r, Code::NotFound, "not_found")
        .await;
    let mut mismatched = authed(pb::GetSessionRequest {
        session_id: id.clone(),
    });
    mismatched.metadata_mut().insert(
        SESSION_METADATA,
        "s0000.01ARZ3NDEKTSV4RRFFQ69G5FAV".parse().expect("ascii"),
    );
    let r = g.get_session(mismatched).await;
    b.grpc(
        "gRPC x-mcapi-session that contradicts the message",
        r,
        Code::InvalidArgument,
        "bad_request",
    )
    .await;
    let r = g
        .list_sessions(authed(pb::ListSessionsRequest {
            after: None,
            limit: Some(u32::MAX),
        }))
        .await;
    b.grpc(
        "gRPC list limit u32::MAX",
        r,
        Code::InvalidArgument,
        "bad_request",
    )
    .await;
    let r = g
        .get_values(authed(pb::GetValuesRequest {
            session_id: id.clone(),
            include: vec!["everything".into()],
        }))
        .await;
    b.grpc(
        "gRPC values: unknown table",
        r,
        Code::InvalidArgument,
        "bad_request",
    )
    .await;
    let r = g
        .get_values(authed(pb::GetValuesRequest {
            session_id: id.clone(),
            include: vec!["all".into()],
        }))
        .await;
    b.grpc(
        "gRPC values larger than a response may be",
        r,
        Code::ResourceExhausted,
        "limit_exceeded",
    )
    .await;
    let r = g
        .get_history(authed(pb::GetHistoryRequest {
            session_id: id.clone(),
            limit: Some(u32::MAX),
        }))
        .await;
    b.grpc(
        "gRPC history larger than a response may be",
        r,
        Code::ResourceExhausted,
        "limit_exceeded",
    )
    .await;
    let r = g
        .delete_session(authed(pb::DeleteSessionRequest {
            session_id: big(10_000),
        }))
        .await;
    b.grpc(
        "gRPC delete with a 10 kB id",
        r,
        Code::NotFound,
        "not_found",
    )
    .await;

    // ---------------------------------------------------------------- groups
    let group = b
        .rest(
            "a legal group of two",
            Method::POST,
            "/v1/groups",
            Body::Json(json!({"model": {"preset": "hallway"}, "n": 2, "seed": 1})),
            201,
            "",
        )
        .await;
    let gid = group["id"].as_str().expect("group id").to_string();
    let hallway_group = |extra: Value| {
        let mut body = json!({"model": {"preset": "hallway"}});
        if let (Some(b), Some(e)) = (body.as_object_mut(), extra.as_object()) {
            b.extend(e.clone());
        }
        body
    };
    for (name, body, status, code) in [
        (
            "group of u64::MAX members",
            hallway_group(json!({"n": u64::MAX})),
            413,
            "limit_exceeded",
        ),
        (
            "group of 10001 members",
            hallway_group(json!({"n": 10_001})),
            413,
            "limit_exceeded",
        ),
        (
            "group of 0 members",
            hallway_group(json!({"n": 0})),
            400,
            "bad_request",
        ),
        (
            "group of -1 members",
            hallway_group(json!({"n": -1})),
            400,
            "bad_request",
        ),
        (
            "group of 1e300 members",
            hallway_group(json!({"n": 1e300})),
            400,
            "bad_request",
        ),
        (
            "group without n",
            hallway_group(json!({})),
            400,
            "bad_request",
        ),
        (
            "group with a member's seed",
            hallway_group(json!({"n": 2, "agent": {"seed": 3}})),
            400,
            "bad_request",
        ),
        // Two sessions and the group's two are held: 49 more do not fit 50.
        (
            "group over the key's quota",
            hallway_group(json!({"n": 49})),
            429,
            "quota_exceeded",
        ),
    ] {
        b.rest(
            name,
            Method::POST,
            "/v1/groups",
            Body::Json(body),
            status,
            code,
        )
        .await;
    }
    let steps = format!("/v1/groups/{gid}/steps");
    for (name, body, status, code) in [
        (
            "step: states of another length",
            json!({"states": [1]}),
            400,
            "column_length",
        ),
        (
            "step: a mask of 100000 entries",
            json!({"mask": (0..100_000).collect::<Vec<u32>>(), "states": vec![0; 100_000]}),
            400,
            "invalid_mask",
        ),
        (
            "step: a mask entry u32::MAX",
            json!({"mask": [u32::MAX], "states": [1]}),
            400,
            "invalid_mask",
        ),
        (
            "step: a mask entry beyond u32",
            json!({"mask": [u64::MAX], "states": [1]}),
            400,
            "bad_request",
        ),
        (
            "step: a repeated mask entry",
            json!({"mask": [1, 1], "states": [1, 1]}),
            400,
            "invalid_mask",
        ),
        (
            "step: ragged stimuli",
            json!({"states": [1, 1], "stimuli": [[0, 0], [0]]}),
            400,
            "column_length",
        ),
        (
            "step: 100000 stimulus rows",
            json!({"states": [1, 1], "stimuli": vec![[0, 0]; 100_000]}),
            400,
            "column_length",
        ),
        (
            "step: a state of 1e300",
            json!({"states": [1e300, 1]}),
            400,
            "bad_request",
        ),
        (
            "step: an action u32::MAX",
            json!({"states": [1, 1], "action_taken": [u32::MAX, null]}),
            400,
            "bad_request",
        ),
        ("step: an array body", json!([1, 2]), 400, "bad_request"),
    ] {
        b.rest(name, Method::POST, &steps, Body::Json(body), status, code)
            .await;
    }
    b.rest(
        "step an unknown group",
        Method::POST,
        "/v1/groups/s0000.g01ARZ3NDEKTSV4RRFFQ69G5FAV/steps",
        Body::Json(json!({"states": [1]})),
        404,
        "not_found",
    )
    .await;
    b.rest(
        "a group id of 10 kB",
        Method::GET,
        &format!("/v1/groups/{}", big(10_000)),
        Body::None,
        404,
        "not_found",
    )
    .await;
    b.rest(
        "delete an unknown group",
        Method::DELETE,
        "/v1/groups/s0000.g01ARZ3NDEKTSV4RRFFQ69G5FAV",
        Body::None,
        404,
        "not_found",
    )
    .await;
    let r = g
        .create_group(authed(pb::CreateGroupRequest {
            model: Some(pb::Model::preset("hallway")),
            agent: None,
            n: u32::MAX,
            seed: None,
        }))
        .await;
    b.grpc(
        "gRPC group of u32::MAX members",
        r,
        Code::ResourceExhausted,
        "limit_exceeded",
    )
    .await;
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let mut replies = g
        .step_group(authed(tokio_stream::wrappers::ReceiverStream::new(rx)))
        .await
        .expect("a StepGroup stream opens")
        .into_inner();
    let step = |seq: u64, first: bool| pb::GroupStepRequest {
        group_id: gid.clone(),
        seq,
        states: vec![25, 25],
        stimuli: if first {
            Vec::new()
        } else {
            [0.0f64; 4].iter().flat_map(|x| x.to_le_bytes()).collect()
        },
        ..Default::default()
    };
    tx.send(step(u64::MAX, true)).await.expect("send");
    assert!(replies.message().await.expect("a reply").is_some());
    tx.send(step(0, false)).await.expect("send");
    let r = replies.message().await;
    b.grpc(
        "gRPC StepGroup seq wrapping around",
        r,
        Code::InvalidArgument,
        "sequence_out_of_order",
    )
    .await;
    drop(tx);

    // ----------------------------------------------------- quota of the key
    // Two sessions and the group's two members are held.
    let mut made = 4;
    while made < 50 {
        b.rest(
            "filling the key's quota",
            Method::POST,
            "/v1/sessions",
            Body::Json(hallway(json!({}))),
            201,
            "",
        )
        .await;
        made += 1;
    }
    b.create(
        "one session over the key's quota",
        hallway(json!({})),
        429,
        "quota_exceeded",
    )
    .await;

    // ------------------------------------------------------------- verdict
    assert!(b.cases >= 60, "only {} hostile requests", b.cases);
    let peak = b.rss("VmHWM:");
    let after = b.rss("VmRSS:");
    eprintln!(
        "{} hostile requests; RSS before {} MiB, after {} MiB, peak {} MiB (budget {} MiB)",
        b.cases,
        rss_before >> 20,
        after >> 20,
        peak >> 20,
        RSS_BUDGET_BYTES >> 20
    );
    assert!(
        peak <= RSS_BUDGET_BYTES,
        "peak RSS {peak} bytes exceeds the budget of {RSS_BUDGET_BYTES}"
    );
    let log = server.log_text();
    assert!(
        !log.contains("panicked"),
        "the server logged a panic:\n{log}"
    );
}
