//! Sessions whose transitions the agent learns (docs/algorithm.md
//! §8), over REST and gRPC: the three-room maze posted
//! as a grid map with `"learn": true` is explored and `known_fraction`
//! rises; absurd learned models are refused with a precise 4xx; and a
//! learned session driven over each transport survives `kill -9` bit-equal
//! to a core replay of exactly its acknowledged observations (the approach
//! of `tests/integration/crash.rs`, with its helpers in `tests/common` and
//! mcapi-testkit).

use crate::common;

use std::collections::BTreeSet;
use std::sync::Arc;

use common::{
    ACTIONS, Launch, Obs, Reply, Server, assert_float_roundtrip, check_replayed, grpc_request,
    http_client, observe_one, replay_on, rest, stimulus,
};
use mcapi_core::model::{THREE_ROOM_MAP, three_room};
use mcapi_core::spec::ModelSpec;
use mcapi_core::{
    Agent, AgentParams, Basis, EnvModel, LearnedParams, Optimism, PlanningModel, Preset,
};
use mcapi_server::api::grpc::pb;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};

// ------------------------------------------------------------ three rooms

/// The client's world: the three-room maze as the map moves (the server
/// never sees this P), ξ = 1 in dimension d on arriving at source d.
struct Maze(Preset);

impl Maze {
    fn new() -> Self {
        Self(three_room())
    }

    fn step(&self, s: usize, a: usize) -> usize {
        let model = &self.0.model;
        let p = model.pair(s, a).expect("every move is available on a map");
        model.successors(p).0[0] as usize
    }

    fn stimulus(&self, s: usize) -> Vec<f64> {
        let mut xi = vec![0.0; self.0.model.n_stimuli()];
        for source in self.0.sources.iter().filter(|src| src.state == s) {
            xi[source.dim] = 1.0;
        }
        xi
    }

    fn source_states(&self) -> BTreeSet<usize> {
        self.0.sources.iter().map(|s| s.state).collect()
    }
}

fn three_room_json(learn: bool) -> Value {
    let lines: Vec<&str> = THREE_ROOM_MAP.lines().collect();
    let mut m = json!({"grid": lines, "sources": {"a": 0, "b": 1, "c": 2}});
    if learn {
        m["learn"] = json!(true);
        m["learning"] = json!({"known_after": 1});
    }
    m
}

/// Ticks driven in each transport's exploration run.
const EXPLORE_TICKS: usize = 2000;
/// Ticks between two readings of `known_fraction`.
const READ_EVERY: usize = 250;

/// What an exploration run saw.
#[derive(Debug)]
struct Explored {
    /// `known_fraction` every READ_EVERY ticks, from tick 0.
    known: Vec<f64>,
    /// Tick at which each source state was first reached.
    found: Vec<(usize, usize)>,
}

impl Explored {
    fn check(&self, maze: &Maze, transport: &str) {
        let known = &self.known;
        assert_eq!(known[0], 0.0, "{transport}: nothing is known at tick 0");
        assert!(
            known.windows(2).all(|w| w[0] <= w[1]),
            "{transport}: known_fraction only grows: {known:?}"
        );
        let last = *known.last().expect("readings");
        assert!(
            last == 1.0,
            "{transport}: the agent comes to know every pair of the maze: {known:?}"
        );
        let found: BTreeSet<usize> = self.found.iter().map(|&(s, _)| s).collect();
        assert_eq!(
            found,
            maze.source_states(),
            "{transport}: every source is found ({:?})",
            self.found
        );
        eprintln!(
            "{transport}: known_fraction every {READ_EVERY} ticks {known:?}; sources found at ticks {:?}",
            self.found
        );
    }
}

/// Drives a learned three-room session over REST, lockstep, one
/// observation per request.
async fn explore_rest(client: &reqwest::Client, base: &str, id: &str, maze: &Maze) -> Explored {
    let url = format!("{base}/v1/sessions/{id}/observations");
    let values = format!("{base}/v1/sessions/{id}/values");
    let sources = maze.source_states();
    let mut out = Explored {
        known: Vec::new(),
        found: Vec::new(),
    };
    let mut s = 0usize;
    let (status, mut reply) = rest(
        client,
        reqwest::Method::POST,
        &url,
        None,
        Some(&json!({"state": s})),
    )
    .await;
    assert_eq!(status, 200, "first observation: {reply}");
    for t in 0..=EXPLORE_TICKS {
        if t % READ_EVERY == 0 {
            let (status, v) = rest(client, reqwest::Method::GET, &values, None, None).await;
            assert_eq!(status, 200, "values: {v}");
            assert_eq!(v["tick"].as_u64(), Some(t as u64));
            out.known.push(
                v["known_fraction"]
                    .as_f64()
                    .expect("a learned session's known_fraction"),
            );
        }
        if t == EXPLORE_TICKS {
            break;
        }
        let a = reply["action_index"].as_u64().expect("action") as usize;
        s = maze.step(s, a);
        if sources.contains(&s) && !out.found.iter().any(|&(f, _)| f == s) {
            out.found.push((s, t + 1));
        }
        let body = json!({"state": s, "stimulus": maze.stimulus(s)});
        let (status, r) = rest(client, reqwest::Method::POST, &url, None, Some(&body)).await;
        assert_eq!(status, 200, "tick {t}: {r}");
        reply = r;
    }
    out
}

/// Drives a learned three-room session over gRPC `Observe`, one
/// observation per call.
async fn explore_grpc(
    client: &mut pb::agents_client::AgentsClient<tonic::transport::Channel>,
    id: &str,
    maze: &Maze,
) -> Explored {
    let sources = maze.source_states();
    let mut out = Explored {
        known: Vec::new(),
        found: Vec::new(),
    };
    let observe = |state: usize, stimulus: Option<Vec<f64>>| {
        grpc_request(
            pb::ObserveRequest {
                session_id: id.to_string(),
                observations: vec![pb::Observation {
                    session_id: id.to_string(),
                    state: state as u64,
                    stimulus: stimulus.map(|values| pb::Stimulus { values }),
                    ..Default::default()
                }],
            },
            None,
            Some(id),
        )
    };
    let mut s = 0usize;
    let mut step = client
        .observe(observe(s, None))
        .await
        .expect("first")
        .into_inner()
        .steps;
    for t in 0..=EXPLORE_TICKS {
        if t % READ_EVERY == 0 {
            let v = client
                .get_values(pb::GetValuesRequest {
                    session_id: id.to_string(),
                    include: vec![],
                })
                .await
                .expect("values")
                .into_inner();
            assert_eq!(v.tick, t as u64);
            out.known.push(
                v.known_fraction
                    .expect("a learned session's known_fraction"),
            );
        }
        if t == EXPLORE_TICKS {
            break;
        }
        s = maze.step(s, step[0].action_index as usize);
        if sources.contains(&s) && !out.found.iter().any(|&(f, _)| f == s) {
            out.found.push((s, t + 1));
        }
        step = client
            .observe(observe(s, Some(maze.stimulus(s))))
            .await
            .unwrap_or_else(|e| panic!("tick {t}: {e:?}"))
            .into_inner()
            .steps;
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn learned_three_room_sessions_explore_over_rest_and_grpc() {
    let data = tempfile::tempdir().expect("data dir");
    let running = common::start_in_process(data.path()).await;
    let base = format!("http://{}", running.http_addr);
    let client = http_client();
    let maze = Maze::new();
    let model = &maze.0.model;

    let create = format!("{base}/v1/sessions");
    let body = json!({"model": three_room_json(true), "agent": {"seed": 17}});
    let (status, info) = rest(&client, reqwest::Method::POST, &create, None, Some(&body)).await;
    assert_eq!(status, 201, "{info}");
    assert_eq!(
        info["model"]["learned"],
        json!({"known_after": 1, "optimism": "absorbing",
               "max_transitions": model.n_pairs() * model.states()}),
        "m as posted, the default optimism (docs/algorithm.md §8)"
    );
    let id = info["id"].as_str().expect("id").to_string();
    let rest_run = explore_rest(&client, &base, &id, &maze).await;

    // The same maze with posted transitions has no known fraction.
    let body = json!({"model": three_room_json(false), "agent": {"seed": 17}});
    let (status, known) = rest(&client, reqwest::Method::POST, &create, None, Some(&body)).await;
    assert_eq!(status, 201, "{known}");
    assert!(known["model"].get("learned").is_none(), "{known}");
    let known_id = known["id"].as_str().expect("id");
    let (status, v) = rest(
        &client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{known_id}/values"),
        None,
        None,
    )
    .await;
    assert_eq!(status, 200);
    assert!(v.get("known_fraction").is_none(), "{v}");

    let mut grpc =
        pb::agents_client::AgentsClient::connect(format!("http://{}", running.grpc_addr))
            .await
            .expect("gRPC connects");
    let lines: Vec<String> = THREE_ROOM_MAP.lines().map(String::from).collect();
    let info = grpc
        .create_session(pb::CreateSessionRequest {
            model: Some(pb::Model {
                form: Some(pb::model::Form::Grid(pb::GridModel {
                    rows: lines,
                    sources: [("a".into(), 0), ("b".into(), 1), ("c".into(), 2)].into(),
                    stimuli: vec![],
                    basis: None,
                    learn: true,
                    learning: Some(pb::LearnedTransitions {
                        known_after: Some(1),
                        optimism: pb::Optimism::Unspecified.into(),
                    }),
                })),
            }),
            agent: Some(pb::SessionConfig {
                seed: Some(17),
                ..Default::default()
            }),
            ..Default::default()
        })
        .await
        .expect("create a learned session over gRPC")
        .into_inner();
    let learned = info.model.and_then(|m| m.learned).expect("learned summary");
    assert_eq!(learned.known_after, 1);
    assert_eq!(learned.optimism, i32::from(pb::Optimism::Absorbing));
    let grpc_run = explore_grpc(&mut grpc, &info.id, &maze).await;

    rest_run.check(&maze, "REST");
    grpc_run.check(&maze, "gRPC");
    // The same seed and observations: both transports drove the same agent.
    assert_eq!(rest_run.known, grpc_run.known, "REST and gRPC agree");
    assert_eq!(rest_run.found, grpc_run.found, "REST and gRPC agree");
    running.shutdown();
    running.wait().await.expect("clean shutdown");
}

// --------------------------------------------------------------- hostile

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn absurd_learned_models_get_a_precise_4xx() {
    let data = tempfile::tempdir().expect("data dir");
    let running = common::start_in_process(data.path()).await;
    let client = http_client();
    let create = format!("http://{}/v1/sessions", running.http_addr);
    let full = |extra: Value| {
        let mut m =
            json!({"states": 3, "actions": ["go"], "stimuli": ["x"], "transitions": "learn"});
        for (k, v) in extra.as_object().expect("object") {
            m[k] = v.clone();
        }
        m
    };
    let grid = json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1}});
    let cases: Vec<(Value, Value, u16, &str, &str)> = vec![
        (
            full(json!({"learning": {"known_after": 5_000_000_000u64}})),
            json!({}),
            400,
            "bad_request",
            "invalid value: integer `5000000000`, expected u32",
        ),
        (
            full(json!({"learning": {"known_after": 1_000_001}})),
            json!({}),
            400,
            "invalid_parameter",
            "`model.learning`: `known_after` 1000001 is not in 1..=1000000",
        ),
        (
            full(json!({"learning": {"known_after": -1}})),
            json!({}),
            400,
            "bad_request",
            "`model`",
        ),
        (
            full(json!({"learning": {"optimism": "hopeful"}})),
            json!({}),
            400,
            "bad_request",
            "unknown variant `hopeful`, expected `absorbing` or `stimulus`",
        ),
        (
            full(json!({"learning": {"m": 3}})),
            json!({}),
            400,
            "bad_request",
            "unknown field `m`",
        ),
        (
            full(json!({"transitions": "guess"})),
            json!({}),
            400,
            "bad_request",
            "unknown variant `guess`, expected `learn`",
        ),
        (
            full(json!({"states": 1_000_000_000_000_000_000u64})),
            json!({}),
            413,
            "limit_exceeded",
            "`model.states` is 1000000000000000000; the limit is 1000000",
        ),
        (
            full(json!({"states": 1_000_000_000_000_000_000u64, "actions": []})),
            json!({}),
            400,
            "bad_request",
            "`model.actions`: must name at least one action",
        ),
        (
            full(json!({"states": 400_000, "actions": ["a", "b", "c"]})),
            json!({}),
            413,
            "limit_exceeded",
            "`model` states x actions is 1200000; the limit is 1000000",
        ),
        (
            full(json!({"states": 0})),
            json!({}),
            400,
            "invalid_model",
            "`states` must be at least 1",
        ),
        (
            full(json!({"basis": {"kind": "proto_value", "k": 2}})),
            json!({}),
            400,
            "bad_request",
            "`model.basis`: proto-value functions come from the transition graph",
        ),
        (
            {
                let mut g = grid.clone();
                g["learn"] = json!(true);
                g["basis"] = json!({"kind": "proto_value", "k": 2});
                g
            },
            json!({}),
            400,
            "invalid_parameter",
            "`absorbing` needs the indicator basis",
        ),
        (
            {
                let mut g = grid.clone();
                g["learning"] = json!({"known_after": 2});
                g
            },
            json!({}),
            400,
            "bad_request",
            "`model.learning`: is only taken with `\"learn\": true`",
        ),
        (
            {
                let mut g = grid.clone();
                g["learn"] = json!("yes");
                g
            },
            json!({}),
            400,
            "bad_request",
            "expected a boolean",
        ),
        (
            {
                let mut g = grid.clone();
                g["learn"] = json!(true);
                g
            },
            json!({"curiosity": {"signal_dim": 2}}),
            400,
            "bad_request",
            "`agent.curiosity`: a curiosity channel needs a model with posted transitions",
        ),
    ];
    for (model, agent, status, code, needle) in cases {
        let body = json!({"model": model, "agent": agent});
        let (got, reply) = rest(&client, reqwest::Method::POST, &create, None, Some(&body)).await;
        assert_eq!(got, status, "{body}: {reply}");
        assert_eq!(reply["code"], json!(code), "{body}: {reply}");
        let message = reply["message"].as_str().expect("message");
        assert!(
            message.contains(needle),
            "{body}: `{message}` lacks `{needle}`"
        );
    }
    running.shutdown();
    running.wait().await.expect("clean shutdown");

    // The cap on stored transitions, on a server whose --max-transitions
    // is 3, so that a session reaches it: a fourth distinct (pair,
    // successor) is refused.
    let logs = tempfile::tempdir().expect("log dir");
    let data = tempfile::tempdir().expect("data dir");
    let launch = Launch::new(data.path(), &["--max-transitions", "3"]);
    let server = Server::start(&launch, logs.path().join("server.log")).await;
    let create = format!("{}/v1/sessions", server.base());
    let body =
        json!({"model": full(json!({"learning": {"known_after": 1}})), "agent": {"seed": 1}});
    let (status, info) = rest(&client, reqwest::Method::POST, &create, None, Some(&body)).await;
    assert_eq!(status, 201, "{info}");
    assert_eq!(info["model"]["learned"]["max_transitions"], json!(3));
    let id = info["id"].as_str().expect("id");
    let url = format!("{}/v1/sessions/{id}/observations", server.base());
    // 0 -go-> 1 -go-> 2 -go-> 0 stores three transitions.
    for (i, s) in [0, 1, 2, 0].into_iter().enumerate() {
        let obs = if i == 0 {
            json!({"state": s})
        } else {
            json!({"state": s, "stimulus": [0.5]})
        };
        let (status, reply) = rest(&client, reqwest::Method::POST, &url, None, Some(&obs)).await;
        assert_eq!(status, 200, "{obs}: {reply}");
    }
    // Seen before from 0: fine. New from 0 (0 -> 2): refused, nothing applied.
    let (status, reply) = rest(
        &client,
        reqwest::Method::POST,
        &url,
        None,
        Some(&json!({"state": 1, "stimulus": [0.5]})),
    )
    .await;
    assert_eq!(status, 200, "{reply}");
    assert_eq!(reply["tick"], json!(4));
    let (status, reply) = rest(
        &client,
        reqwest::Method::POST,
        &url,
        None,
        Some(&json!({"state": 1, "stimulus": [0.5]})),
    )
    .await;
    assert_eq!(status, 413, "1 -> 1 would be a fourth transition: {reply}");
    assert_eq!(reply["code"], json!("limit_exceeded"));
    let message = reply["message"].as_str().expect("message");
    assert!(
        message.contains("already stores 3 transitions"),
        "{message}"
    );
    let (status, info) = common::rest_get(&client, &server.base(), None, id).await;
    assert_eq!(status, 200);
    assert_eq!(
        info["tick"],
        json!(4),
        "the refused observation changed nothing"
    );
    assert_eq!(info["state"], json!(1));
}

// ------------------------------------------------------------ kill -9

/// The learned hallway as posted: 50 states, every action available (a
/// move into an end wall stays put), the hallway's stimuli, m = 2.
fn learned_hallway_json() -> Value {
    json!({"states": 50, "actions": ACTIONS, "stimuli": ["food", "rest"],
           "transitions": "learn", "learning": {"known_after": 2}})
}

/// The client's hallway: the ends are walls.
fn bump(s: usize, a: usize) -> usize {
    match a {
        0 => s.saturating_sub(1),
        1 => (s + 1).min(49),
        _ => s,
    }
}

/// A fresh core agent for the posted learned hallway, built independently
/// of the server: every pair valid, the indicator basis, m = 2, R-max.
fn core_learned_agent(seed: u64) -> Agent {
    let structure = EnvModel::from_spec(&ModelSpec {
        states: 50,
        state_names: None,
        actions: ACTIONS.map(String::from).to_vec(),
        next: Some((0..50).map(|s| vec![Some(s); 3]).collect()),
        transitions: None,
        stimuli: vec!["food".into(), "rest".into()],
        basis: None,
    })
    .expect("structure");
    let ctx = Arc::new(PlanningModel::new(structure, Basis::Indicator));
    let params = AgentParams {
        seed: Some(seed),
        ..AgentParams::default()
    };
    let learned = LearnedParams {
        known_after: Some(2),
        optimism: Some(Optimism::Absorbing),
    };
    Agent::new_learned(
        ctx,
        params.check(2, 0).expect("params"),
        learned.check().expect("learned params"),
    )
    .expect("learned agent")
}

/// A learned session as the client knows it.
struct Tracked {
    id: String,
    seed: u64,
    grpc: bool,
    applied: Vec<(Obs, Option<Reply>)>,
    state: Option<usize>,
    advised: Option<usize>,
    rng: ChaCha8Rng,
}

impl Tracked {
    fn next_obs(&mut self) -> Obs {
        let Some(s) = self.state else {
            return Obs {
                state: self.rng.random_range(0..50),
                stimulus: None,
                taken: None,
                report: None,
                by_name: false,
            };
        };
        let report = self.rng.random_bool(0.15);
        let a = match self.advised {
            Some(a) if !report => a,
            _ => self.rng.random_range(0..ACTIONS.len()),
        };
        let next = bump(s, a);
        Obs {
            state: next,
            stimulus: Some(stimulus(next)),
            taken: Some(a),
            report: report.then_some(a),
            by_name: self.rng.random_bool(0.5),
        }
    }

    /// `n` acknowledged observations, one per request.
    async fn drive(&mut self, server: &Server, n: usize) {
        let client = http_client();
        let mut grpc = server.grpc_client().await;
        for _ in 0..n {
            let obs = self.next_obs();
            let reply = observe_one(
                &client,
                &server.base(),
                &mut grpc,
                self.grpc,
                &self.id,
                &obs,
            )
            .await;
            self.state = Some(obs.state);
            self.advised = Some(reply.action);
            self.applied.push((obs, Some(reply)));
        }
    }

    async fn check(&self, server: &Server, label: &str) {
        let ctx = format!("{label}: session {} (gRPC {})", self.id, self.grpc);
        let (agent, expected) = replay_on(core_learned_agent(self.seed), &self.applied, &ctx);
        check_replayed(
            &http_client(),
            &server.base(),
            None,
            &self.id,
            &agent,
            &expected,
            &ctx,
        )
        .await;
        let known = agent.learned().expect("learned").known_fraction();
        assert!(known > 0.0, "{ctx}: the replay learned something");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn learned_sessions_recover_after_kill9_bit_equal_to_a_core_replay() {
    assert_float_roundtrip();
    let data = tempfile::tempdir().expect("data dir");
    let logs = tempfile::tempdir().expect("log dir");
    // Small, so that recovery reads a learned snapshot and replays the log
    // after it.
    let launch = Launch::new(data.path(), &["--snapshot-every", "37"]);
    let mut server = Server::start(&launch, logs.path().join("run-0.log")).await;
    let client = http_client();
    let mut sessions = Vec::new();
    for (i, grpc) in [false, true].into_iter().enumerate() {
        let seed = 900 + i as u64;
        let body = json!({"model": learned_hallway_json(), "agent": {"seed": seed}});
        let (status, info) = rest(
            &client,
            reqwest::Method::POST,
            &format!("{}/v1/sessions", server.base()),
            None,
            Some(&body),
        )
        .await;
        assert_eq!(status, 201, "{info}");
        assert_eq!(info["model"]["learned"]["known_after"], json!(2));
        sessions.push(Tracked {
            id: info["id"].as_str().expect("id").to_string(),
            seed,
            grpc,
            applied: Vec::new(),
            state: None,
            advised: None,
            rng: ChaCha8Rng::seed_from_u64(seed),
        });
    }
    for (round, ticks) in [(1, 150), (2, 60)] {
        for t in &mut sessions {
            t.drive(&server, ticks).await;
        }
        server.kill9();
        server = Server::start(&launch, logs.path().join(format!("run-{round}.log"))).await;
        for t in &sessions {
            t.check(&server, &format!("after kill -9 number {round}"))
                .await;
        }
        // The recovery's log line may follow readiness by a moment.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        let recovered = loop {
            let lines = common::log_events(&server.log_text(), "sessions recovered");
            if !lines.is_empty() || std::time::Instant::now() > deadline {
                break lines;
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        };
        assert_eq!(recovered.len(), 1, "one recovery line");
        assert_eq!(recovered[0]["sessions"], json!(2));
        // Each session's log after its last snapshot (every 37 entries)
        // was replayed on top of the snapshot.
        let replayed = recovered[0]["replayed"].as_u64().expect("replayed");
        assert!(
            replayed > 0 && replayed < 2 * 37,
            "{replayed} entries replayed"
        );
    }
    // Driving on after the recoveries: the replies follow the replay (the
    // counts and Ξ came back exactly, or ticks, D and rewards would part).
    for t in &mut sessions {
        t.drive(&server, 20).await;
        t.check(&server, "after the recoveries").await;
    }
}
