//! Sessions with a curiosity channel on the real binary (the server
//! part of docs/algorithm.md §7):
//! - over REST, every reply of a lockstep curious session equals a core
//!   `CuriousAgent` stepped alongside, bit for bit (action, D, |r|, ξ_cur,
//!   ε), through a module freeze; history and values expose ξ_cur, ε, the
//!   full stimulus and the module library;
//! - the same session over gRPC (Observe, GetHistory, GetValues,
//!   GetSession) says the same;
//! - after kill -9 (log replay over a snapshot) the session comes back with
//!   its channel, library, D and history exactly, and its Ξ, D, ξ_cur and ε
//!   go on exactly as the core agent's that never stopped (the policy is
//!   recomputed once at recovery, not replayed update by update, so the
//!   advised action may differ from then on);
//! - bad curiosity input gets a 400 / INVALID_ARGUMENT naming the field.
// These tests still send the deprecated `model_json` (accepted for one
// more release, docs/grpc.md).
#![allow(deprecated)]

use crate::common;

use std::sync::Arc;

use common::{Launch, Server, http_client, rest};
use mcapi_core::model::hallway;
use mcapi_core::{
    AgentParams, Basis, CuriosityParams, CuriousAgent, CuriousObservation, CuriousStep, Eq6Source,
    PlanningModel, Signals,
};
use mcapi_server::api::grpc::pb;
use reqwest::Method;
use serde_json::{Value, json};
use tonic::Code;

const SEED: u64 = 77;
/// The hallway's book is at state 25, its music at 30.
const BOOK: usize = 25;
const MUSIC: usize = 30;

fn core() -> CuriousAgent {
    let model = hallway()
        .model
        .with_stimulus("curiosity")
        .expect("a third dimension");
    let params = AgentParams {
        seed: Some(SEED),
        ..AgentParams::default()
    }
    .check(3, 0)
    .expect("params");
    let curiosity = CuriosityParams::default().check().expect("defaults");
    CuriousAgent::new(
        Arc::new(PlanningModel::new(model, Basis::Indicator)),
        params,
        curiosity,
        2,
    )
    .expect("curious agent")
}

/// One observation of the drive schedule: state, extrinsic stimulus, the
/// action taken to get there, and the signal sample with its source.
#[derive(Debug, Clone)]
struct Tick {
    state: usize,
    stimulus: Option<[f64; 2]>,
    taken: Option<usize>,
    signal: Option<(usize, [f64; 2])>,
}

impl Tick {
    fn json(&self) -> Value {
        let mut v = json!({"state": self.state});
        if let Some(x) = self.stimulus {
            v["stimulus"] = json!(x);
        }
        if let Some(a) = self.taken {
            v["action_taken"] = json!(a);
        }
        if let Some((source, x)) = self.signal {
            v["signal"] = json!(x);
            v["signal_source"] = json!(source);
        }
        v
    }

    fn pb(&self) -> pb::Observation {
        pb::Observation {
            state: self.state as u64,
            stimulus: self.stimulus.map(|x| pb::Stimulus { values: x.to_vec() }),
            action_taken: self
                .taken
                .map(|a| pb::observation::ActionTaken::ActionIndex(a as u32)),
            signal: self.signal.map(|(_, x)| x.to_vec()).unwrap_or_default(),
            signal_source: self.signal.map(|(s, _)| s as u32),
            ..Default::default()
        }
    }

    fn step(&self, agent: &mut CuriousAgent) -> CuriousStep {
        let signal = self.signal.as_ref().map(|(s, x)| (*s, &x[..]));
        agent
            .step(&CuriousObservation {
                state: self.state,
                stimulus: self.stimulus.as_ref().map(|x| &x[..]),
                signal,
                action_taken: self.taken,
            })
            .expect("core step")
    }
}

/// The client's schedule: from state 20 walk to the book and stay there for
/// `book` ticks (one book sample per tick), walk to the music and stay for
/// `music` ticks, then walk to the food and back. Actions are reported, so
/// the schedule does not depend on the advice.
fn schedule(book: usize, music: usize) -> Vec<Tick> {
    let mut signals = Signals::new(0.08);
    let mut out = vec![Tick {
        state: 20,
        stimulus: None,
        taken: None,
        signal: None,
    }];
    let mut state = 20;
    let mut go = |out: &mut Vec<Tick>, to: usize, stay: usize, signals: &mut Signals| {
        let mut moves: Vec<usize> = Vec::new();
        while state != to {
            let a = if to < state { 0 } else { 1 };
            state = if a == 0 { state - 1 } else { state + 1 };
            moves.push(a);
        }
        moves.extend(std::iter::repeat_n(2, stay));
        for a in moves {
            let signal = match state {
                BOOK => Some((0, signals.next(Eq6Source::Book))),
                MUSIC => Some((1, signals.next(Eq6Source::Music))),
                _ => None,
            };
            out.push(Tick {
                state,
                stimulus: Some(common::stimulus(state)),
                taken: Some(a),
                signal,
            });
        }
    };
    go(&mut out, BOOK, book, &mut signals);
    go(&mut out, MUSIC, music, &mut signals);
    go(&mut out, 10, 3, &mut signals);
    go(&mut out, BOOK, 40, &mut signals);
    out
}

fn bits(v: &Value) -> Vec<u64> {
    v.as_array()
        .expect("array")
        .iter()
        .map(|x| x.as_f64().expect("number").to_bits())
        .collect()
}

fn f64_bits(x: &Value) -> u64 {
    x.as_f64().expect("number").to_bits()
}

/// Checks a REST step reply against the core agent's step.
fn check_reply(reply: &Value, want: &CuriousStep, agent: &CuriousAgent, at: usize, action: bool) {
    if action {
        assert_eq!(
            reply["action_index"].as_u64(),
            Some(want.step.action as u64),
            "action at observation {at}"
        );
    }
    assert_eq!(
        bits(&reply["drive"]),
        agent
            .agent()
            .drive()
            .vector()
            .iter()
            .map(|x| x.to_bits())
            .collect::<Vec<_>>(),
        "D at observation {at}"
    );
    assert_eq!(f64_bits(&reply["reward"]), want.step.reward.to_bits());
    let c = &reply["curiosity"];
    assert_eq!(
        f64_bits(&c["xi_cur"]),
        want.xi_cur.to_bits(),
        "ξ_cur at {at}"
    );
    assert_eq!(
        f64_bits(&c["epsilon"]),
        agent.channel().epsilon().to_bits(),
        "ε at {at}"
    );
    assert_eq!(
        c["modules"].as_u64(),
        Some(agent.channel().module_count() as u64)
    );
}

async fn create(client: &reqwest::Client, base: &str) -> (String, Value) {
    let (status, body) = rest(
        client,
        Method::POST,
        &format!("{base}/v1/sessions"),
        None,
        Some(&json!({
            "model": {"preset": "hallway"},
            "agent": {"seed": SEED, "curiosity": {"signal_dim": 2}},
        })),
    )
    .await;
    assert_eq!(status, 201, "create: {body}");
    (body["id"].as_str().expect("id").to_string(), body)
}

/// Sends `ticks` one request each, checking every reply against `agent`.
async fn drive(
    client: &reqwest::Client,
    base: &str,
    id: &str,
    ticks: &[Tick],
    agent: &mut CuriousAgent,
    offset: usize,
    action: bool,
) {
    for (i, t) in ticks.iter().enumerate() {
        let (status, reply) = rest(
            client,
            Method::POST,
            &format!("{base}/v1/sessions/{id}/observations"),
            None,
            Some(&t.json()),
        )
        .await;
        assert_eq!(status, 200, "observation {}: {reply}", offset + i);
        let want = t.step(agent);
        check_reply(&reply, &want, agent, offset + i, action);
    }
}

async fn get(client: &reqwest::Client, url: &str) -> Value {
    let (status, body) = rest(client, Method::GET, url, None, None).await;
    assert_eq!(status, 200, "{url}: {body}");
    body
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_curious_session_matches_the_core_and_survives_kill_9() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = tempfile::tempdir().expect("logs");
    // Snapshots every 700 observations: the kill below leaves a snapshot
    // and a log after it to replay.
    let launch = Launch::new(data.path(), &["--snapshot-every", "700"]);
    let mut server = Server::start(&launch, logs.path().join("first.log")).await;
    let client = http_client();
    let base = server.base();
    let (id, created) = create(&client, &base).await;
    assert_eq!(
        created["model"]["stimuli"],
        json!(["food", "rest", "curiosity"])
    );
    assert_eq!(created["agent"]["curiosity"]["signal_dim"], json!(2));
    assert_eq!(
        created["agent"]["curiosity"]["params"]["gain"],
        json!(800.0)
    );

    let mut agent = core();
    let ticks = schedule(1500, 300);
    let (before, after) = ticks.split_at(ticks.len() - 60);
    drive(&client, &base, &id, before, &mut agent, 0, true).await;

    // The book was learned: a module froze while the client stayed there.
    let session = get(&client, &format!("{base}/v1/sessions/{id}")).await;
    let c = &session["curiosity"];
    let modules = c["modules"].as_array().expect("modules");
    assert!(!modules.is_empty(), "no module froze: {c}");
    assert_eq!(modules[0]["source"], json!(0));
    let frozen_tick = modules[0]["frozen_tick"].as_u64().expect("frozen tick");
    assert_eq!(
        agent.frozen_ticks()[0],
        frozen_tick,
        "the freeze tick is the core's"
    );
    assert_eq!(c["samples"].as_u64(), Some(agent.channel().samples()));
    let values = get(&client, &format!("{base}/v1/sessions/{id}/values")).await;
    assert_eq!(values["curiosity"], session["curiosity"]);

    // History: the full stimulus with ξ_cur last, and the channel per tick.
    let history = get(&client, &format!("{base}/v1/sessions/{id}/history")).await;
    let entries = history.as_array().expect("entries");
    assert_eq!(entries.len(), 256);
    for e in entries {
        let stimulus = e["stimulus"].as_array().expect("stimulus");
        assert_eq!(stimulus.len(), 3, "{e}");
        assert_eq!(stimulus[2], e["curiosity"]["xi_cur"], "{e}");
    }
    let positive = before
        .iter()
        .take(1500)
        .filter(|t| t.signal.is_some())
        .count();
    assert!(positive > 1000, "the schedule delivers book samples");

    // kill -9: the session comes back from its snapshot and log exactly.
    server.kill9();
    let mut server = Server::start(&launch, logs.path().join("second.log")).await;
    let base = server.base();
    let client = http_client();
    let recovered = get(&client, &format!("{base}/v1/sessions/{id}")).await;
    for key in ["tick", "drive", "state", "curiosity"] {
        assert_eq!(recovered[key], session[key], "`{key}` after kill -9");
    }
    let version = |v: &Value| v["policy_version"].as_u64().expect("version");
    assert!(version(&recovered) >= version(&session));
    let replayed = get(&client, &format!("{base}/v1/sessions/{id}/history")).await;
    assert_eq!(replayed, history, "history after kill -9");
    // And its learning goes on as the core agent's that never stopped.
    drive(&client, &base, &id, after, &mut agent, before.len(), false).await;
    let xi = get(
        &client,
        &format!("{base}/v1/sessions/{id}/values?include=xi"),
    )
    .await;
    let rows: Vec<f64> = xi["xi"]
        .as_array()
        .expect("rows")
        .iter()
        .flat_map(|row| row.as_array().expect("row").clone())
        .filter(|pair| !pair.is_null())
        .flat_map(|pair| pair.as_array().expect("pair").clone())
        .map(|x| x.as_f64().expect("number"))
        .collect();
    let model = agent.agent().planning_model().model();
    let want: Vec<f64> = (0..model.states())
        .flat_map(|s| (0..model.n_actions()).filter_map(move |a| model.pair(s, a)))
        .flat_map(|p| agent.agent().stimulus().row(p).to_vec())
        .collect();
    assert_eq!(
        rows.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
        want.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
        "Ξ after the restart and more ticks"
    );
    server.terminate();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_says_what_rest_says() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = tempfile::tempdir().expect("logs");
    let server = Server::start(
        &Launch::new(data.path(), &["--store", "memory"]),
        logs.path().join("serve.log"),
    )
    .await;
    let client = http_client();
    let base = server.base();
    let mut grpc = server.grpc_client().await;
    let (rest_id, _) = create(&client, &base).await;
    let info = grpc
        .create_session(pb::CreateSessionRequest {
            model_json: r#"{"preset": "hallway"}"#.into(),
            model: None,
            agent: Some(pb::SessionConfig {
                seed: Some(SEED),
                curiosity: Some(pb::CuriosityConfig {
                    signal_dim: 2,
                    params_json: String::new(),
                }),
                ..Default::default()
            }),
        })
        .await
        .expect("create over gRPC")
        .into_inner();
    let cfg = info.agent.and_then(|a| a.curiosity).expect("curiosity");
    assert_eq!(cfg.signal_dim, 2);
    let params: Value = serde_json::from_str(&cfg.params_json).expect("params JSON");
    assert_eq!(params["gain"], json!(800.0));
    let grpc_id = info.id;

    let ticks = schedule(200, 50);
    let mut agent = core();
    drive(&client, &base, &rest_id, &ticks, &mut agent, 0, true).await;
    let mut xi_cur = Vec::new();
    for chunk in ticks.chunks(64) {
        let steps = grpc
            .observe(pb::ObserveRequest {
                session_id: grpc_id.clone(),
                observations: chunk.iter().map(Tick::pb).collect(),
            })
            .await
            .expect("observe over gRPC")
            .into_inner()
            .steps;
        xi_cur.extend(steps.iter().map(|s| s.curiosity.expect("curiosity").xi_cur));
    }
    assert!(xi_cur.iter().any(|&x| x > 0.0), "ξ_cur while learning");

    let rest_history = get(&client, &format!("{base}/v1/sessions/{rest_id}/history")).await;
    let history = grpc
        .get_history(pb::GetHistoryRequest {
            session_id: grpc_id.clone(),
            limit: None,
        })
        .await
        .expect("history over gRPC")
        .into_inner()
        .entries;
    let rest_entries = rest_history.as_array().expect("entries");
    assert_eq!(history.len(), rest_entries.len());
    for (g, r) in history.iter().zip(rest_entries) {
        let stimulus = g.stimulus.as_ref().expect("stimulus").values.clone();
        assert_eq!(json!(stimulus), r["stimulus"]);
        let c = g.curiosity.expect("curiosity");
        assert_eq!(json!(c.xi_cur), r["curiosity"]["xi_cur"]);
        assert_eq!(json!(c.epsilon), r["curiosity"]["epsilon"]);
        assert_eq!(json!(g.drive), r["drive"]);
    }
    let tail: Vec<f64> = rest_entries
        .iter()
        .map(|e| e["curiosity"]["xi_cur"].as_f64().expect("xi_cur"))
        .collect();
    assert_eq!(tail, xi_cur[xi_cur.len() - tail.len()..]);

    let values = grpc
        .get_values(pb::GetValuesRequest {
            session_id: grpc_id.clone(),
            include: vec![],
        })
        .await
        .expect("values over gRPC")
        .into_inner();
    let c = values.curiosity.expect("curiosity");
    let rest_values = get(&client, &format!("{base}/v1/sessions/{rest_id}/values")).await;
    assert_eq!(json!(c.epsilon), rest_values["curiosity"]["epsilon"]);
    assert_eq!(json!(c.samples), rest_values["curiosity"]["samples"]);
    assert_eq!(
        c.active_source,
        Some(agent.channel().active().source().map_or(99, |s| s as u64))
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_curiosity_input_is_a_precise_client_error() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = tempfile::tempdir().expect("logs");
    let server = Server::start(
        &Launch::new(data.path(), &["--store", "memory"]),
        logs.path().join("serve.log"),
    )
    .await;
    let client = http_client();
    let base = server.base();
    let post = |url: String, body: Value| {
        let client = client.clone();
        async move { rest(&client, Method::POST, &url, None, Some(&body)).await }
    };
    let sessions = format!("{base}/v1/sessions");
    for (agent, field) in [
        (json!({"curiosity": {"signal_dim": 0}}), "agent.curiosity"),
        (
            json!({"curiosity": {"signal_dim": 2, "params": {"gain": -1.0}}}),
            "agent.curiosity.params",
        ),
        (
            json!({"curiosity": {"signal_dim": 2, "params": {"gian": 1.0}}}),
            "gian",
        ),
        (
            json!({"curiosity": {"signal_dim": 2}, "priorities": [1.0, 1.0]}),
            "priorities",
        ),
    ] {
        let (status, body) = post(
            sessions.clone(),
            json!({"model": {"preset": "hallway"}, "agent": agent}),
        )
        .await;
        assert!((400..500).contains(&status), "{agent}: {status} {body}");
        let message = body["message"].as_str().unwrap_or_default();
        assert!(message.contains(field), "{agent}: {message}");
    }
    // A model that already names a dimension `curiosity`.
    let (status, body) = post(
        sessions.clone(),
        json!({
            "model": {"grid": ["#####", "#F..#", "#####"], "sources": {"F": 0},
                      "stimuli": ["curiosity"]},
            "agent": {"curiosity": {"signal_dim": 2}},
        }),
    )
    .await;
    assert_eq!(status, 400, "{body}");
    assert!(
        body["message"]
            .as_str()
            .unwrap_or_default()
            .contains("curiosity"),
        "{body}"
    );

    let (curious, _) = create(&client, &base).await;
    let (status, plain) = post(
        sessions.clone(),
        json!({"model": {"preset": "hallway"}, "agent": {"seed": 1}}),
    )
    .await;
    assert_eq!(status, 201);
    let plain = plain["id"].as_str().expect("id").to_string();
    let observe = |id: &str| format!("{base}/v1/sessions/{id}/observations");
    // The first observation carries a state only.
    let (status, body) = post(observe(&curious), json!({"state": 3, "signal": [0.0, 1.0]})).await;
    assert_eq!(status, 400, "{body}");
    for id in [&curious, &plain] {
        let (status, _) = post(observe(id), json!({"state": 3})).await;
        assert_eq!(status, 200);
    }
    for (id, obs, needle) in [
        (
            &plain,
            json!({"state": 3, "stimulus": [0.0, 0.0], "signal": [0.0, 1.0]}),
            "no curiosity channel",
        ),
        (
            &curious,
            json!({"state": 3, "stimulus": [0.0, 0.0, 0.0]}),
            "2 extrinsic",
        ),
        (
            &curious,
            json!({"state": 3, "stimulus": [0.0, 0.0], "signal": [0.0, 1.0, 2.0]}),
            "signal",
        ),
        (
            &curious,
            json!({"state": 3, "stimulus": [0.0, 0.0], "signal_source": 1}),
            "signal_source",
        ),
        (
            &curious,
            json!({"state": 3, "stimulus": [0.0, 0.0], "signal": [0.0, 1.0], "signal_source": 1000}),
            "source",
        ),
        (
            &curious,
            json!({"state": 3, "stimulus": [0.0, 0.0], "signal": [0.0, 1e300]}),
            "signal",
        ),
    ] {
        let (status, body) = post(observe(id), obs.clone()).await;
        assert_eq!(status, 400, "{obs}: {body}");
        let message = body["message"].as_str().unwrap_or_default();
        assert!(message.contains(needle), "{obs}: {message}");
    }
    let (_, body) = post(
        observe(&curious),
        json!({"state": 3, "stimulus": [0.0, 0.0, 0.0]}),
    )
    .await;
    assert_eq!(body["code"], json!("stimulus_length"), "{body}");
    // Nothing above was applied.
    let session = get(&client, &format!("{base}/v1/sessions/{curious}")).await;
    assert_eq!(session["tick"], json!(0));
    assert_eq!(session["curiosity"]["samples"], json!(0));

    // gRPC: the same mistakes are INVALID_ARGUMENT.
    let mut grpc = server.grpc_client().await;
    let status = grpc
        .observe(pb::ObserveRequest {
            session_id: plain.clone(),
            observations: vec![pb::Observation {
                state: 3,
                stimulus: Some(pb::Stimulus {
                    values: vec![0.0, 0.0],
                }),
                signal: vec![0.0, 1.0],
                ..Default::default()
            }],
        })
        .await
        .expect_err("a signal without a channel");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    let status = grpc
        .create_session(pb::CreateSessionRequest {
            model_json: r#"{"preset": "hallway"}"#.into(),
            model: None,
            agent: Some(pb::SessionConfig {
                curiosity: Some(pb::CuriosityConfig {
                    signal_dim: 2,
                    params_json: "{not json".into(),
                }),
                ..Default::default()
            }),
        })
        .await
        .expect_err("bad params JSON");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status.message().contains("params_json"), "{status:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_async_curious_session_learns_as_a_lockstep_one() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = tempfile::tempdir().expect("logs");
    let server = Server::start(
        &Launch::new(data.path(), &[]),
        logs.path().join("serve.log"),
    )
    .await;
    let client = http_client();
    let base = server.base();
    let (status, body) = rest(
        &client,
        Method::POST,
        &format!("{base}/v1/sessions"),
        None,
        Some(&json!({
            "model": {"preset": "hallway"},
            "agent": {"seed": SEED, "update_mode": "async", "curiosity": {"signal_dim": 2}},
        })),
    )
    .await;
    assert_eq!(status, 201, "{body}");
    let id = body["id"].as_str().expect("id");
    // Batches: the channel, Ξ and D do not depend on when the policy is
    // updated, since the schedule reports its actions.
    let ticks = schedule(300, 30);
    let mut agent = core();
    let mut want = Vec::new();
    for t in &ticks {
        let s = t.step(&mut agent);
        want.push(s.xi_cur.to_bits());
    }
    let mut got = Vec::new();
    for chunk in ticks.chunks(100) {
        let (status, reply) = rest(
            &client,
            Method::POST,
            &format!("{base}/v1/sessions/{id}/observations"),
            None,
            Some(&json!({"observations": chunk.iter().map(Tick::json).collect::<Vec<_>>()})),
        )
        .await;
        assert_eq!(status, 200, "{reply}");
        got.extend(
            reply["steps"]
                .as_array()
                .expect("steps")
                .iter()
                .map(|s| f64_bits(&s["curiosity"]["xi_cur"])),
        );
    }
    assert_eq!(got, want, "ξ_cur of every tick");
    let session = get(&client, &format!("{base}/v1/sessions/{id}")).await;
    assert_eq!(
        bits(&session["drive"]),
        agent
            .agent()
            .drive()
            .vector()
            .iter()
            .map(|x| x.to_bits())
            .collect::<Vec<_>>()
    );
}
