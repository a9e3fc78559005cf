//! Continuous worlds on the real binary: sessions created and driven over
//! REST and gRPC with observation vectors, `kill -9`ed, and recovered from
//! their logs bit for bit. A lockstep session's every reply, before and
//! after the kill, is the one a core `ContinuousAgent` fed the same
//! observations gives; an async session's values at every grid point are
//! the same bits before the kill and after the recovery (its plans, made
//! by the tick loop whenever it ran, are replayed where they were made).
//! Snapshots are taken every 120 observations, so a recovery restores one
//! and replays the log after it, through basis rebuilds on both sides; a
//! session on the grid planner is restored from its own snapshot form.

use crate::common;

use common::{
    Launch, Server, assert_bits_eq, grpc_request, http_client, log_events, rest, rest_get,
};
use mcapi_core::continuous::{ContinuousAgent, ContinuousObservation, ContinuousSpec};
use mcapi_server::api::grpc::pb;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use reqwest::Method;
use serde_json::{Value, json};

use super::{log_path, logs, settled};

/// A point robot in the unit square: four moves of 0.03 with a little
/// noise; food in a disc at (0.15, 0.15), rest in one at (0.85, 0.85).
struct Point {
    x: [f64; 2],
    rng: ChaCha8Rng,
}

impl Point {
    fn new(seed: u64) -> Self {
        Self {
            x: [0.5, 0.5],
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// Moves by `action`; the stimulus received on arrival.
    fn step(&mut self, action: usize) -> Vec<f64> {
        let (dx, dy) = [(0.0, 0.03), (0.0, -0.03), (0.03, 0.0), (-0.03, 0.0)][action];
        let noise = |rng: &mut ChaCha8Rng| (rng.random::<f64>() - 0.5) * 0.01;
        self.x[0] = (self.x[0] + dx + noise(&mut self.rng)).clamp(0.0, 1.0);
        self.x[1] = (self.x[1] + dy + noise(&mut self.rng)).clamp(0.0, 1.0);
        let near =
            |c: [f64; 2]| ((self.x[0] - c[0]).powi(2) + (self.x[1] - c[1]).powi(2)).sqrt() < 0.1;
        vec![
            f64::from(u8::from(near([0.15, 0.15]))),
            f64::from(u8::from(near([0.85, 0.85]))),
        ]
    }
}

fn model() -> Value {
    json!({"observation_space": {"low": [0, 0], "high": [1, 1]},
           "actions": ["north", "south", "east", "west"],
           "stimuli": ["food", "rest"],
           "basis": {"kind": "fourier", "order": 4},
           "samples": {"max": 512}})
}

/// A reply: the action, the tick and the bits of D and |r|.
#[derive(Debug, Clone, PartialEq)]
struct Step {
    action: usize,
    tick: u64,
    drive: Vec<u64>,
    reward: u64,
}

impl Step {
    fn of(v: &Value) -> Self {
        Self {
            action: v["action_index"].as_u64().expect("action_index") as usize,
            tick: v["tick"].as_u64().expect("tick"),
            drive: v["drive"]
                .as_array()
                .expect("drive")
                .iter()
                .map(|x| x.as_f64().expect("number").to_bits())
                .collect(),
            reward: v["reward"].as_f64().expect("reward").to_bits(),
        }
    }
}

/// One driven session: what it was sent and what it answered.
struct Driven {
    id: String,
    world: Point,
    sent: Vec<(Vec<f64>, Option<Vec<f64>>)>,
    replies: Vec<Step>,
    grpc: bool,
    /// The model it was created with.
    model: Value,
}

impl Driven {
    async fn ticks(
        &mut self,
        client: &reqwest::Client,
        base: &str,
        grpc: &mut pb::agents_client::AgentsClient<tonic::transport::Channel>,
        n: usize,
    ) {
        for _ in 0..n {
            let stimulus = match self.replies.last() {
                Some(last) => Some(self.world.step(last.action)),
                None => None,
            };
            let x = self.world.x.to_vec();
            let reply = if self.grpc {
                let step = grpc
                    .observe(grpc_request(
                        pb::ObserveRequest {
                            session_id: self.id.clone(),
                            observations: vec![pb::Observation {
                                observation: x.clone(),
                                stimulus: stimulus.clone().map(|values| pb::Stimulus { values }),
                                ..Default::default()
                            }],
                        },
                        None,
                        None,
                    ))
                    .await
                    .expect("Observe")
                    .into_inner()
                    .steps
                    .remove(0);
                json!({"action_index": step.action_index, "tick": step.tick,
                       "drive": step.drive, "reward": step.reward})
            } else {
                let mut body = json!({"observation": x});
                if let Some(s) = &stimulus {
                    body["stimulus"] = json!(s);
                }
                let (status, reply) = rest(
                    client,
                    Method::POST,
                    &format!("{base}/v1/sessions/{}/observations", self.id),
                    None,
                    Some(&body),
                )
                .await;
                assert_eq!(status, 200, "{reply}");
                reply
            };
            self.sent.push((x, stimulus));
            self.replies.push(Step::of(&reply));
        }
    }

    /// The replies a core agent gives to the same observations.
    fn core_replies(&self, seed: u64) -> Vec<Step> {
        let spec: ContinuousSpec = serde_json::from_value(self.model.clone()).expect("spec");
        let params = common::params(seed, None).check(2, seed).expect("params");
        let mut agent = ContinuousAgent::new(spec.build().expect("model"), params);
        self.sent
            .iter()
            .map(|(x, stimulus)| {
                let step = agent
                    .step(&ContinuousObservation {
                        observation: x,
                        stimulus: stimulus.as_deref(),
                        action_taken: None,
                    })
                    .expect("step");
                Step {
                    action: step.action,
                    tick: step.tick,
                    drive: agent.drive().vector().iter().map(|d| d.to_bits()).collect(),
                    reward: step.reward.to_bits(),
                }
            })
            .collect()
    }
}

async fn values(client: &reqwest::Client, base: &str, id: &str) -> Value {
    let (status, v) = rest(
        client,
        Method::GET,
        &format!("{base}/v1/sessions/{id}/values?include=v,q,policy"),
        None,
        None,
    )
    .await;
    assert_eq!(status, 200, "{v}");
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn continuous_sessions_survive_kill_9_bit_for_bit() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    let launch = Launch::new(data.path(), &["--snapshot-every", "120"]);
    let mut server = Server::start(&launch, log_path(&logs, "continuous-first")).await;
    let client = http_client();
    let base = server.base();
    let mut grpc = server.grpc_client().await;

    let rest_create = |seed: u64, mode: &'static str, model: Value| {
        let client = client.clone();
        let base = base.clone();
        async move {
            let (status, info) = rest(
                &client,
                Method::POST,
                &format!("{base}/v1/sessions"),
                None,
                Some(&json!({"model": model, "agent": {"seed": seed, "update_mode": mode}})),
            )
            .await;
            assert_eq!(status, 201, "{info}");
            assert_eq!(
                info["model"]["continuous"]["basis"]["kind"], model["basis"]["kind"],
                "{info}"
            );
            info["id"].as_str().expect("id").to_string()
        }
    };
    // The paper's own basis carried to continuous spaces, rebuilt as its
    // graph grows: before the kill and after it.
    let mut pvf_model = model();
    pvf_model["basis"] = json!({"kind": "pvf", "k": 16, "nodes": 200, "neighbours": 8});
    // The typed gRPC form of the same model.
    let typed = pb::Model {
        form: Some(pb::model::Form::Continuous(pb::ContinuousModel {
            low: vec![0.0, 0.0],
            high: vec![1.0, 1.0],
            actions: ["north", "south", "east", "west"]
                .map(String::from)
                .to_vec(),
            stimuli: vec!["food".into(), "rest".into()],
            basis: Some(pb::ContinuousBasis {
                kind: Some(pb::continuous_basis::Kind::Fourier(pb::FourierBasis {
                    order: 4,
                    max_coupling: None,
                })),
            }),
            out_of_bounds: pb::OutOfBounds::Unspecified.into(),
            samples: Some(pb::SampleParams {
                max: Some(512),
                ..Default::default()
            }),
        })),
    };
    let info = grpc
        .create_session(grpc_request(
            pb::CreateSessionRequest {
                model: Some(typed),
                agent: Some(pb::SessionConfig {
                    seed: Some(33),
                    ..Default::default()
                }),
                ..Default::default()
            },
            None,
            None,
        ))
        .await
        .expect("CreateSession")
        .into_inner();
    let summary = info.model.expect("model").continuous.expect("continuous");
    assert_eq!(summary.samples.and_then(|s| s.max), Some(512));

    let mut lockstep = Driven {
        id: rest_create(31, "lockstep", model()).await,
        world: Point::new(1),
        sent: Vec::new(),
        replies: Vec::new(),
        grpc: false,
        model: model(),
    };
    let mut async_ = Driven {
        id: rest_create(32, "async", model()).await,
        world: Point::new(2),
        sent: Vec::new(),
        replies: Vec::new(),
        grpc: false,
        model: model(),
    };
    let mut pvf = Driven {
        id: rest_create(34, "lockstep", pvf_model.clone()).await,
        world: Point::new(4),
        sent: Vec::new(),
        replies: Vec::new(),
        grpc: false,
        model: pvf_model,
    };
    // The grid planner (docs/algorithm.md §9.8): its own snapshot form.
    let mut grid_model = model();
    grid_model["basis"] = json!({"kind": "grid", "cells_per_dim": 32});
    let mut grid = Driven {
        id: rest_create(35, "lockstep", grid_model.clone()).await,
        world: Point::new(5),
        sent: Vec::new(),
        replies: Vec::new(),
        grpc: false,
        model: grid_model,
    };
    let mut typed = Driven {
        id: info.id,
        world: Point::new(3),
        sent: Vec::new(),
        replies: Vec::new(),
        grpc: true,
        model: model(),
    };
    for d in [&mut lockstep, &mut async_, &mut typed, &mut pvf, &mut grid] {
        d.ticks(&client, &base, &mut grpc, 300).await;
    }
    let grid_before = values(&client, &base, &grid.id).await;
    let builds = |info: &Value| info["stats"]["continuous"]["basis_builds"].as_u64();
    let (_, info) = rest_get(&client, &base, None, &pvf.id).await;
    let builds_before = builds(&info).expect("basis_builds");
    eprintln!("pvf basis builds before the kill: {builds_before}");
    // The async session's queued updates land, then its tables are read.
    settled(&client, &base, None, &async_.id).await;
    let before = values(&client, &base, &async_.id).await;
    let (_, info) = rest_get(&client, &base, None, &lockstep.id).await;
    assert!(
        info["stats"]["continuous"]["samples"].as_u64().unwrap_or(0) > 50,
        "the sample store fills: {info}"
    );
    let (_, history) = rest(
        &client,
        Method::GET,
        &format!("{base}/v1/sessions/{}/history?limit=1", lockstep.id),
        None,
        None,
    )
    .await;
    let last = &lockstep.sent.last().expect("sent").0;
    assert_eq!(history[0]["observation"], json!(last), "{history}");

    server.kill9();
    let server = Server::start(&launch, log_path(&logs, "continuous-second")).await;
    // Each session's 301 logged observations: a snapshot (after 240 of
    // them) restored, and only the ones after it replayed.
    let recovered = log_events(&server.log_text(), "sessions recovered");
    assert_eq!(recovered.len(), 1, "{recovered:?}");
    assert_eq!(recovered[0]["sessions"], json!(5), "{recovered:?}");
    let replayed = recovered[0]["replayed"].as_u64().expect("replayed");
    assert!(
        replayed > 0 && replayed <= 5 * 120,
        "a snapshot, then the log after it: {replayed} entries replayed"
    );
    let base = server.base();
    let mut grpc = server.grpc_client().await;
    let after = values(&client, &base, &async_.id).await;
    assert_eq!(before["points"], after["points"]);
    for table in ["v", "q", "policy"] {
        assert_eq!(before[table], after[table], "{table} after kill -9");
    }
    assert_bits_eq(
        &common::floats(&after["v"]),
        &common::floats(&before["v"]),
        "V at every grid point",
    );
    let grid_after = values(&client, &base, &grid.id).await;
    for table in ["v", "q", "policy"] {
        assert_eq!(
            grid_before[table], grid_after[table],
            "grid {table} after kill -9"
        );
    }
    for d in [&mut lockstep, &mut async_, &mut typed, &mut pvf, &mut grid] {
        d.ticks(&client, &base, &mut grpc, 200).await;
    }
    let (_, info) = rest_get(&client, &base, None, &pvf.id).await;
    let builds_after = builds(&info).expect("basis_builds");
    eprintln!("pvf basis builds after: {builds_after}");
    assert!(
        builds_before >= 2,
        "the pvf basis was rebuilt before the kill: {builds_before}"
    );
    assert!(builds_after > builds_before, "and after it: {builds_after}");
    for (d, seed) in [(&lockstep, 31), (&typed, 33), (&pvf, 34), (&grid, 35)] {
        let want = d.core_replies(seed);
        assert_eq!(want.len(), 500);
        for (i, (got, want)) in d.replies.iter().zip(&want).enumerate() {
            assert_eq!(got, want, "reply {i} of {} (kill -9 after 300)", d.id);
        }
    }
    // Async: D and |r| do not depend on when plans ran.
    let want = async_.core_replies(32);
    for (i, (got, want)) in async_.replies.iter().zip(&want).enumerate() {
        assert_eq!(
            (got.tick, &got.drive, got.reward),
            (want.tick, &want.drive, want.reward),
            "async reply {i}"
        );
    }
}
