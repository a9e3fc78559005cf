//! The gRPC transport over a real socket: a client drives a hallway agent
//! over `Interact` and gets the same actions and drives as the core; bad
//! input gets the right codes; streams stop cleanly; health and reflection
//! answer.
// These tests still send the deprecated `model_json` (accepted for one
// more release, docs/grpc.md).
#![allow(deprecated)]

use std::sync::Arc;
use std::time::{Duration, Instant};

use mcapi_core::model::hallway;
use mcapi_core::{Agent, AgentParams, Basis, BasisSpec, Observation, PlanningModel};
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_server::api::grpc::pb::observation::ActionTaken;
use mcapi_server::api::grpc::{SESSION_METADATA, ServeError, pb, serve_on};
use mcapi_server::service::{Limits, SessionManager};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Code, Request, Status};

const SEED: u64 = 20_140_722;
const TICKS: usize = 3000;
const FOOD: usize = 10;
const REST: usize = 40;
const START: usize = 25;

struct Server {
    addr: std::net::SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    task: JoinHandle<Result<(), ServeError>>,
}

impl Server {
    async fn start() -> Self {
        Self::start_with(Limits::default()).await
    }

    async fn start_with(limits: Limits) -> Self {
        let manager = Arc::new(SessionManager::new(limits, 2).expect("session manager"));
        let listener = TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind a free port");
        let addr = listener.local_addr().expect("local address");
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(serve_on(listener, manager, 8, async {
            let _ = stopped.await;
        }));
        Self {
            addr,
            stop: Some(stop),
            task,
        }
    }

    async fn client(&self) -> AgentsClient<Channel> {
        AgentsClient::connect(format!("http://{}", self.addr))
            .await
            .expect("connect")
    }

    async fn channel(&self) -> Channel {
        Channel::from_shared(format!("http://{}", self.addr))
            .expect("uri")
            .connect()
            .await
            .expect("connect")
    }

    /// Shuts down and returns how long serving took to end.
    async fn stop(mut self) -> Duration {
        let t = Instant::now();
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        tokio::time::timeout(Duration::from_secs(10), self.task)
            .await
            .expect("server drains within 10 s")
            .expect("server task")
            .expect("server ends cleanly");
        t.elapsed()
    }
}

/// The hallway as a client simulates it: left, right, stay on a 50-state
/// chain; food ξ = [6, 0] at 10, rest [0, 6] at 40.
fn hallway_move(s: usize, a: u32) -> usize {
    match a {
        0 => s.checked_sub(1).expect("left is not advised in state 0"),
        1 => {
            assert!(s + 1 < 50, "right is not advised in state 49");
            s + 1
        }
        2 => s,
        other => panic!("hallway has no action {other}"),
    }
}

fn hallway_stimulus(s: usize) -> Vec<f64> {
    match s {
        FOOD => vec![6.0, 0.0],
        REST => vec![0.0, 6.0],
        _ => vec![0.0, 0.0],
    }
}

/// The session, asked for by id (in the message and the metadata).
async fn session_info(client: &mut AgentsClient<Channel>, id: &str) -> pb::SessionInfo {
    client
        .get_session(with_session(
            id,
            pb::GetSessionRequest {
                session_id: id.to_string(),
            },
        ))
        .await
        .expect("get")
        .into_inner()
}

fn with_session<T>(id: &str, message: T) -> Request<T> {
    let mut req = Request::new(message);
    req.metadata_mut()
        .insert(SESSION_METADATA, id.parse().expect("ascii id"));
    req
}

async fn create_hallway(
    client: &mut AgentsClient<Channel>,
    mode: pb::UpdateMode,
) -> pb::SessionInfo {
    client
        .create_session(pb::CreateSessionRequest {
            model: Some(pb::Model::preset("hallway")),
            agent: Some(pb::SessionConfig {
                seed: Some(SEED),
                update_mode: mode.into(),
                ..Default::default()
            }),
            ..Default::default()
        })
        .await
        .expect("create hallway session")
        .into_inner()
}

fn observation(id: &str, state: usize, stimulus: Option<Vec<f64>>) -> pb::Observation {
    pb::Observation {
        session_id: id.into(),
        state: state as u64,
        stimulus: stimulus.map(|values| pb::Stimulus { values }),
        action_taken: None,
        ..Default::default()
    }
}

/// The core agent the session should match step for step.
fn core_agent() -> Agent {
    core_agent_seeded(SEED)
}

fn core_agent_seeded(seed: u64) -> Agent {
    let preset = hallway();
    let basis = Basis::build(&BasisSpec::Indicator, &preset.model).expect("indicator basis");
    let ctx = Arc::new(PlanningModel::new(preset.model, basis));
    let params = AgentParams {
        seed: Some(seed),
        ..AgentParams::default()
    }
    .check(2, 0)
    .expect("default parameters");
    Agent::new(ctx, params)
}

fn assert_code<T: std::fmt::Debug>(result: Result<T, Status>, code: Code, needle: &str) -> Status {
    let status = result.expect_err("the call must fail");
    assert_eq!(status.code(), code, "{status:?}");
    assert!(
        status.message().contains(needle),
        "message `{}` should mention `{needle}`",
        status.message()
    );
    status
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hallway_over_interact_alternates_and_matches_the_core() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let info = create_hallway(&mut client, pb::UpdateMode::Lockstep).await;
    let id = info.id.clone();
    assert!(
        id.starts_with('s') && id.as_bytes()[5] == b'.',
        "id `{id}` is s<shard>.<ulid>"
    );
    let agent_cfg = info.agent.expect("effective config");
    assert_eq!(agent_cfg.seed, SEED);
    assert_eq!(agent_cfg.update_mode, pb::UpdateMode::Lockstep as i32);
    let model = info.model.expect("model summary");
    assert_eq!((model.states, model.actions.len()), (50, 3));
    assert_eq!(model.basis.expect("basis").kind, "indicator");

    let (tx, rx) = mpsc::channel(4);
    let mut steps = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    let mut core = core_agent();

    let started = Instant::now();
    let mut s = START;
    let mut last_source = None;
    let mut alternations = 0;
    let mut visits = [0usize; 2];
    let mut last_state = s;
    for t in 0..=TICKS {
        let xi = (t > 0).then(|| hallway_stimulus(s));
        tx.send(observation(&id, s, xi.clone()))
            .await
            .expect("send observation");
        let step = steps.message().await.expect("step").expect("stream open");

        let expected = core
            .step(&Observation {
                state: s,
                stimulus: xi.as_deref(),
                action_taken: None,
            })
            .expect("core step");
        assert_eq!(step.tick, expected.tick, "tick at t={t}");
        assert_eq!(
            step.action_index as usize, expected.action,
            "action at t={t}"
        );
        assert_eq!(step.drive, core.drive().vector().to_vec(), "drive at t={t}");
        assert_eq!(step.reward, expected.reward, "reward at t={t}");
        assert_eq!(
            step.policy_version,
            core.policy_version(),
            "policy version at t={t}"
        );
        assert_eq!(
            step.action,
            ["left", "right", "stay"][step.action_index as usize]
        );

        let source = match s {
            FOOD => Some(0),
            REST => Some(1),
            _ => None,
        };
        if let Some(src) = source {
            visits[src] += 1;
            if last_source.is_some_and(|l| l != src) {
                alternations += 1;
            }
            last_source = Some(src);
        }
        last_state = s;
        s = hallway_move(s, step.action_index);
    }
    drop(tx);
    assert!(
        steps.message().await.expect("clean end").is_none(),
        "stream ends after the client's"
    );
    let elapsed = started.elapsed();
    eprintln!(
        "{TICKS} lockstep ticks over Interact in {elapsed:?} ({:.0} µs/tick); \
         {alternations} alternations, visits {visits:?}",
        elapsed.as_micros() as f64 / TICKS as f64
    );
    assert!(
        alternations >= 10,
        "only {alternations} alternations (visits {visits:?})"
    );

    let info = session_info(&mut client, &id).await;
    assert_eq!(info.tick, TICKS as u64);
    assert_eq!(info.state, Some(last_state as u64));
    assert_eq!(info.drive, core.drive().vector().to_vec());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unary_calls_list_observe_values_delete() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let a = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;
    let b = create_hallway(&mut client, pb::UpdateMode::Async).await.id;

    let page = client
        .list_sessions(pb::ListSessionsRequest {
            after: None,
            limit: Some(1),
        })
        .await
        .expect("list")
        .into_inner();
    assert_eq!(page.sessions.len(), 1);
    let first = page.sessions[0].id.clone();
    assert_eq!(page.next.as_deref(), Some(first.as_str()));
    let rest = client
        .list_sessions(pb::ListSessionsRequest {
            after: page.next,
            limit: None,
        })
        .await
        .expect("list")
        .into_inner();
    assert_eq!(rest.sessions.len(), 1);
    assert_eq!(rest.next, None);
    let mut ids = vec![first, rest.sessions[0].id.clone()];
    ids.sort();
    let mut want = vec![a.clone(), b.clone()];
    want.sort();
    assert_eq!(ids, want);

    // A batch: one step per observation, in order, ids filled from the request.
    let mut batch = vec![observation("", START, None)];
    batch.extend((1..=5).map(|_| pb::Observation {
        action_taken: Some(ActionTaken::ActionName("stay".into())),
        ..observation("", START, Some(vec![0.0, 0.0]))
    }));
    let steps = client
        .observe(pb::ObserveRequest {
            session_id: a.clone(),
            observations: batch,
        })
        .await
        .expect("observe")
        .into_inner()
        .steps;
    assert_eq!(
        steps.iter().map(|s| s.tick).collect::<Vec<_>>(),
        vec![0, 1, 2, 3, 4, 5]
    );

    let values = client
        .get_values(with_session(
            &a,
            pb::GetValuesRequest {
                session_id: a.clone(),
                include: vec!["q".into(), "xi".into(), "policy".into()],
            },
        ))
        .await
        .expect("values")
        .into_inner();
    assert_eq!(values.tick, 5);
    assert!(values.v.is_none() && values.r.is_none());
    // 50 states x 3 actions, less left in 0 and right in 49.
    assert_eq!(values.q.expect("q").pairs.len(), 148);
    let xi = values.xi.expect("xi");
    assert_eq!(xi.pairs.len(), 148);
    assert!(xi.pairs.iter().all(|p| p.values.len() == 2));
    assert_eq!(values.policy.expect("policy").actions.len(), 50);
    let defaults = client
        .get_values(pb::GetValuesRequest {
            session_id: a.clone(),
            include: vec![],
        })
        .await
        .expect("values")
        .into_inner();
    assert_eq!(defaults.v.expect("v by default").values.len(), 50);
    assert!(defaults.policy.is_some() && defaults.q.is_none());

    client
        .delete_session(with_session(
            &a,
            pb::DeleteSessionRequest {
                session_id: a.clone(),
            },
        ))
        .await
        .expect("delete");
    assert_code(
        client
            .get_session(pb::GetSessionRequest {
                session_id: a.clone(),
            })
            .await,
        Code::NotFound,
        &a,
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_inputs_get_the_right_codes() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;

    // Unknown sessions.
    let status = assert_code(
        client
            .get_session(pb::GetSessionRequest {
                session_id: "s0000.nope".into(),
            })
            .await,
        Code::NotFound,
        "s0000.nope",
    );
    assert_eq!(
        status
            .metadata()
            .get("x-mcapi-error-code")
            .and_then(|v| v.to_str().ok()),
        Some("not_found")
    );
    assert_code(
        client
            .observe(pb::ObserveRequest {
                session_id: "s0000.nope".into(),
                observations: vec![observation("", 0, None)],
            })
            .await,
        Code::NotFound,
        "not found",
    );
    assert_code(
        client
            .watch(pb::WatchRequest {
                session_id: "s0000.nope".into(),
                interval_ms: 10,
            })
            .await,
        Code::NotFound,
        "not found",
    );
    let (tx, rx) = mpsc::channel(1);
    tx.send(observation("s0000.nope", 0, None))
        .await
        .expect("send");
    let mut stream = client
        .interact(ReceiverStream::new(rx))
        .await
        .expect("interact")
        .into_inner();
    assert_code(stream.message().await, Code::NotFound, "not found");

    // Bad model JSON, unknown preset, bad configuration.
    let create = |model_json: &str, agent: Option<pb::SessionConfig>| pb::CreateSessionRequest {
        model_json: model_json.into(),
        model: None,
        agent,
    };
    assert_code(
        client.create_session(create("{not json", None)).await,
        Code::InvalidArgument,
        "model_json",
    );
    assert_code(
        client.create_session(create("", None)).await,
        Code::InvalidArgument,
        "model_json",
    );
    assert_code(
        client.create_session(create("[1, 2]", None)).await,
        Code::InvalidArgument,
        "model",
    );
    assert_code(
        client
            .create_session(create(r#"{"preset": "maze"}"#, None))
            .await,
        Code::InvalidArgument,
        "model.preset",
    );
    assert_code(
        client
            .create_session(create(
                r#"{"preset": "hallway"}"#,
                Some(pb::SessionConfig {
                    eta: Some(0.9),
                    ..Default::default()
                }),
            ))
            .await,
        Code::InvalidArgument,
        "eta",
    );
    assert_code(
        client
            .create_session(create(
                r#"{"preset": "hallway"}"#,
                Some(pb::SessionConfig {
                    update_mode: 7,
                    ..Default::default()
                }),
            ))
            .await,
        Code::InvalidArgument,
        "agent.update_mode",
    );

    // Observations: first one with a stimulus, wrong length, unknown action.
    let observe = |obs: pb::Observation| pb::ObserveRequest {
        session_id: id.clone(),
        observations: vec![obs],
    };
    assert_code(
        client
            .observe(observe(observation("", 3, Some(vec![0.0, 0.0]))))
            .await,
        Code::InvalidArgument,
        "stimulus",
    );
    client
        .observe(observe(observation("", 3, None)))
        .await
        .expect("first observation");
    let status = assert_code(
        client
            .observe(observe(observation("", 3, Some(vec![1.0, 2.0, 3.0]))))
            .await,
        Code::InvalidArgument,
        "stimulus",
    );
    assert_eq!(
        status
            .metadata()
            .get("x-mcapi-error-code")
            .and_then(|v| v.to_str().ok()),
        Some("stimulus_length")
    );
    assert_code(
        client.observe(observe(observation("", 3, None))).await,
        Code::InvalidArgument,
        "stimulus",
    );
    assert_code(
        client
            .observe(observe(pb::Observation {
                action_taken: Some(ActionTaken::ActionName("jump".into())),
                ..observation("", 3, Some(vec![0.0, 0.0]))
            }))
            .await,
        Code::InvalidArgument,
        "action_taken",
    );
    assert_code(
        client
            .observe(observe(observation("", 99, Some(vec![0.0, 0.0]))))
            .await,
        Code::InvalidArgument,
        "state 99",
    );
    assert_code(
        client
            .observe(pb::ObserveRequest {
                session_id: id.clone(),
                observations: vec![],
            })
            .await,
        Code::InvalidArgument,
        "observations",
    );
    assert_code(
        client
            .observe(observe(observation("s0000.other", 3, Some(vec![0.0, 0.0]))))
            .await,
        Code::InvalidArgument,
        "observations[0].session_id",
    );

    // Metadata and message must agree; the id is required somewhere.
    assert_code(
        client
            .get_session(with_session(
                "s0000.other",
                pb::GetSessionRequest {
                    session_id: id.clone(),
                },
            ))
            .await,
        Code::InvalidArgument,
        SESSION_METADATA,
    );
    assert_code(
        client
            .get_session(pb::GetSessionRequest {
                session_id: String::new(),
            })
            .await,
        Code::InvalidArgument,
        "session_id",
    );
    let info = client
        .get_session(with_session(
            &id,
            pb::GetSessionRequest {
                session_id: String::new(),
            },
        ))
        .await
        .expect("id from metadata")
        .into_inner();
    assert_eq!(info.id, id);

    // An error inside Interact ends the stream with its status; the earlier
    // observations stay applied.
    let (tx, rx) = mpsc::channel(4);
    let mut stream = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    tx.send(observation(&id, 3, Some(vec![0.0, 0.0])))
        .await
        .expect("send");
    let ok = stream.message().await.expect("step").expect("open");
    assert_eq!(ok.tick, info.tick + 1);
    tx.send(observation(&id, 3, Some(vec![0.0])))
        .await
        .expect("send");
    assert_code(
        stream.message().await,
        Code::InvalidArgument,
        "stimulus has 1 components, expected 2",
    );
    assert!(stream.message().await.expect("ended").is_none());
    // A message naming another session than the metadata.
    let (tx, rx) = mpsc::channel(4);
    let mut stream = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    tx.send(observation("s0000.other", 3, Some(vec![0.0, 0.0])))
        .await
        .expect("send");
    assert_code(
        stream.message().await,
        Code::InvalidArgument,
        SESSION_METADATA,
    );

    // Values: unknown table; Watch: interval below the minimum.
    assert_code(
        client
            .get_values(pb::GetValuesRequest {
                session_id: id.clone(),
                include: vec!["w".into()],
            })
            .await,
        Code::InvalidArgument,
        "include",
    );
    assert_code(
        client
            .watch(pb::WatchRequest {
                session_id: id.clone(),
                interval_ms: 5,
            })
            .await,
        Code::InvalidArgument,
        "interval_ms",
    );
    assert_code(
        client
            .get_history(pb::GetHistoryRequest {
                session_id: id.clone(),
                limit: Some(0),
            })
            .await,
        Code::InvalidArgument,
        "`limit`: must be at least 1",
    );
    assert_code(
        client
            .list_sessions(pb::ListSessionsRequest {
                after: None,
                limit: Some(0),
            })
            .await,
        Code::InvalidArgument,
        "limit",
    );
    server.stop().await;
}

/// The step of one `InteractBatch` result, or the error's code.
fn outcome(result: &pb::StepResult) -> Result<&pb::Step, &str> {
    match result.outcome.as_ref().expect("a step or an error") {
        pb::step_result::Outcome::Step(step) => Ok(step),
        pb::step_result::Outcome::Error(e) => Err(&e.code),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn interact_batch_steps_several_sessions_as_the_core_does() {
    const SESSIONS: usize = 4;
    const BATCH_TICKS: usize = 400;
    let server = Server::start().await;
    let mut client = server.client().await;
    let mut ids = Vec::new();
    let mut cores = Vec::new();
    for i in 0..SESSIONS as u64 {
        let info = client
            .create_session(pb::CreateSessionRequest {
                model: Some(pb::Model::preset("hallway")),
                agent: Some(pb::SessionConfig {
                    seed: Some(SEED + i),
                    update_mode: pb::UpdateMode::Lockstep.into(),
                    ..Default::default()
                }),
                ..Default::default()
            })
            .await
            .expect("create")
            .into_inner();
        ids.push(info.id);
        cores.push(core_agent_seeded(SEED + i));
    }
    let (tx, rx) = mpsc::channel(4);
    let mut replies = client
        .interact_batch(ReceiverStream::new(rx))
        .await
        .expect("interact_batch")
        .into_inner();
    let mut states = [START; SESSIONS];
    let mut started = [false; SESSIONS];
    let mut alternations = [0usize; SESSIONS];
    let mut last_source = [None; SESSIONS];
    for t in 0..BATCH_TICKS {
        // One observation per session, the sessions in a rotating order.
        let order: Vec<usize> = (0..SESSIONS).map(|k| (k + t) % SESSIONS).collect();
        let mut observations: Vec<pb::Observation> = order
            .iter()
            .map(|&i| {
                let xi = started[i].then(|| hallway_stimulus(states[i]));
                observation(&ids[i], states[i], xi)
            })
            .collect();
        // Now and then: a refused observation of session 1 before its good
        // one (the good one is then not applied), one for a session that
        // does not exist, and an empty message.
        let refused_first = t % 50 == 7;
        if refused_first {
            let at = order.iter().position(|&i| i == 1).expect("session 1");
            observations.insert(at, observation(&ids[1], 999, None));
        }
        if t % 50 == 13 {
            observations.push(observation("s0000.01JDXXXXXXXXXXXXXXXXXXXXXX", 3, None));
        }
        let sent = observations.len();
        tx.send(pb::ObservationBatch { observations })
            .await
            .expect("send");
        let reply = replies.message().await.expect("reply").expect("open");
        assert_eq!(reply.results.len(), sent, "one result per observation");
        let mut results = reply.results.iter();
        for &i in &order {
            if refused_first && i == 1 {
                assert_eq!(
                    outcome(results.next().expect("refused")),
                    Err("unknown_state")
                );
                let skipped = results.next().expect("skipped");
                assert_eq!(outcome(skipped), Err("bad_request"), "t={t}");
                let Some(pb::step_result::Outcome::Error(e)) = &skipped.outcome else {
                    unreachable!("checked above");
                };
                assert!(e.message.contains("not applied"), "{e:?}");
                assert_eq!(e.status, Code::InvalidArgument as u32);
                continue;
            }
            let step = outcome(results.next().expect("a result")).expect("a step");
            let xi = started[i].then(|| hallway_stimulus(states[i]));
            let expected = cores[i]
                .step(&Observation {
                    state: states[i],
                    stimulus: xi.as_deref(),
                    action_taken: None,
                })
                .expect("core step");
            assert_eq!(step.tick, expected.tick, "session {i} tick at t={t}");
            assert_eq!(
                step.action_index as usize, expected.action,
                "session {i} at t={t}"
            );
            assert_eq!(
                step.drive,
                cores[i].drive().vector().to_vec(),
                "session {i} at t={t}"
            );
            assert_eq!(step.reward, expected.reward, "session {i} at t={t}");
            let source = match states[i] {
                FOOD => Some(0),
                REST => Some(1),
                _ => None,
            };
            if let Some(src) = source {
                if last_source[i].is_some_and(|l| l != src) {
                    alternations[i] += 1;
                }
                last_source[i] = Some(src);
            }
            started[i] = true;
            states[i] = hallway_move(states[i], step.action_index);
        }
        if t % 50 == 13 {
            assert_eq!(outcome(results.next().expect("unknown")), Err("not_found"));
        }
        assert!(results.next().is_none());
    }
    assert!(
        alternations.iter().all(|&a| a >= 2),
        "every session balances its drives: {alternations:?}"
    );
    // An empty message gets an empty reply.
    tx.send(pb::ObservationBatch::default())
        .await
        .expect("send");
    let reply = replies.message().await.expect("reply").expect("open");
    assert!(reply.results.is_empty());

    // More observations than `--max-batch` in one message end the stream
    // before it is decoded (10,001 empty observations: 20 KB on the wire).
    let flood = pb::ObservationBatch {
        observations: vec![pb::Observation::default(); Limits::default().max_batch + 1],
    };
    tx.send(flood).await.expect("send");
    let status = replies.message().await.expect_err("the stream ends");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(status.message().contains("more than 10000"), "{status:?}");
    drop(tx);

    // Nothing of the refused message was applied.
    for (i, id) in ids.iter().enumerate() {
        let info = session_info(&mut client, id).await;
        assert_eq!(
            info.drive,
            cores[i].drive().vector().to_vec(),
            "session {i}"
        );
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_interact_batch_message_is_bounded_by_its_estimated_cpu_time() {
    let server = Server::start_with(Limits {
        max_batch_ms: 1,
        ..Limits::default()
    })
    .await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;
    let (tx, rx) = mpsc::channel(4);
    let mut replies = client
        .interact_batch(ReceiverStream::new(rx))
        .await
        .expect("interact_batch")
        .into_inner();
    // A few observations fit in a millisecond...
    let first = vec![observation(&id, START, None)];
    tx.send(pb::ObservationBatch {
        observations: first,
    })
    .await
    .expect("send");
    let reply = replies.message().await.expect("reply").expect("open");
    assert!(outcome(&reply.results[0]).is_ok(), "{reply:?}");
    // ... ten thousand lockstep ticks do not: the message is refused whole.
    let many = vec![observation(&id, START, Some(vec![0.0, 0.0])); 10_000];
    tx.send(pb::ObservationBatch { observations: many })
        .await
        .expect("send");
    let status = replies.message().await.expect_err("the stream ends");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(status.message().contains("--max-batch-ms"), "{status:?}");
    let info = session_info(&mut client, &id).await;
    assert_eq!(info.tick, 0, "nothing of the refused message was applied");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dropped_stream_leaves_the_session_usable() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;

    let (tx, rx) = mpsc::channel(4);
    let mut steps = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    let mut s = START;
    for t in 0..20 {
        let xi = (t > 0).then(|| hallway_stimulus(s));
        tx.send(observation(&id, s, xi)).await.expect("send");
        let step = steps.message().await.expect("step").expect("open");
        s = hallway_move(s, step.action_index);
    }
    // Cancel mid-stream: drop the response stream (RST_STREAM) with the
    // request stream still open.
    drop(steps);

    let info = client
        .get_session(pb::GetSessionRequest {
            session_id: id.clone(),
        })
        .await
        .expect("get")
        .into_inner();
    assert_eq!(info.tick, 19);
    drop(tx);
    let steps = client
        .observe(with_session(
            &id,
            pb::ObserveRequest {
                session_id: id.clone(),
                observations: vec![observation("", s, Some(hallway_stimulus(s)))],
            },
        ))
        .await
        .expect("unary observe after the stream was cancelled")
        .into_inner()
        .steps;
    assert_eq!(steps.len(), 1);
    assert_eq!(steps[0].tick, 20);

    // A new stream continues the same session.
    let (tx, rx) = mpsc::channel(4);
    let mut steps2 = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact again")
        .into_inner();
    let s = hallway_move(s, steps[0].action_index);
    tx.send(observation(&id, s, Some(hallway_stimulus(s))))
        .await
        .expect("send");
    assert_eq!(
        steps2.message().await.expect("step").expect("open").tick,
        21
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_sends_snapshots_until_the_session_is_deleted() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;
    let mut snapshots = client
        .watch(with_session(
            &id,
            pb::WatchRequest {
                session_id: id.clone(),
                interval_ms: 10,
            },
        ))
        .await
        .expect("watch")
        .into_inner();
    let first = snapshots.message().await.expect("snapshot").expect("open");
    assert_eq!(
        (first.id.as_str(), first.tick, first.state),
        (id.as_str(), 0, None)
    );
    client
        .observe(pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![observation("", 7, None)],
        })
        .await
        .expect("observe");
    // A later snapshot shows the observation.
    let mut seen = false;
    for _ in 0..50 {
        let snap = snapshots.message().await.expect("snapshot").expect("open");
        if snap.state == Some(7) {
            seen = true;
            break;
        }
    }
    assert!(seen, "no snapshot showed state 7");
    client
        .delete_session(pb::DeleteSessionRequest {
            session_id: id.clone(),
        })
        .await
        .expect("delete");
    // Snapshots already buffered may arrive first; then NOT_FOUND ends it.
    let end = loop {
        match snapshots.message().await {
            Ok(Some(_)) => continue,
            other => break other,
        }
    };
    assert_code(end, Code::NotFound, &id);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_reflection_answer() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

    let server = Server::start().await;
    let channel = server.channel().await;
    let mut health = HealthClient::new(channel.clone());
    for service in ["mcapi.v1.Agents", ""] {
        let status = health
            .check(HealthCheckRequest {
                service: service.into(),
            })
            .await
            .expect("health check")
            .into_inner()
            .status;
        assert_eq!(status, ServingStatus::Serving as i32, "service `{service}`");
    }

    let mut reflection = ServerReflectionClient::new(channel);
    let request = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut replies = reflection
        .server_reflection_info(tokio_stream::iter([request]))
        .await
        .expect("reflection")
        .into_inner();
    let reply = replies.message().await.expect("reply").expect("one reply");
    let Some(MessageResponse::ListServicesResponse(list)) = reply.message_response else {
        panic!("expected a service list, got {reply:?}");
    };
    let names: Vec<_> = list.service.iter().map(|s| s.name.as_str()).collect();
    assert!(names.contains(&"mcapi.v1.Agents"), "{names:?}");
    assert!(names.contains(&"grpc.health.v1.Health"), "{names:?}");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_streams() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;
    let (tx, rx) = mpsc::channel(4);
    let mut interact = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    tx.send(observation(&id, START, None)).await.expect("send");
    interact.message().await.expect("step").expect("open");
    let mut watch = client
        .watch(pb::WatchRequest {
            session_id: id.clone(),
            interval_ms: 1000,
        })
        .await
        .expect("watch")
        .into_inner();
    watch.message().await.expect("snapshot").expect("open");

    let took = server.stop().await;
    assert!(took < Duration::from_secs(5), "shutdown took {took:?}");
    assert_code(interact.message().await, Code::Unavailable, "shutting down");
    assert_code(watch.message().await, Code::Unavailable, "shutting down");
    drop(tx);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grid_models_come_with_their_layout() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let create = |model: &str| pb::CreateSessionRequest {
        model_json: model.into(),
        model: None,
        agent: None,
    };
    let grid = client
        .create_session(create(
            &serde_json::json!({
                "grid": ["#####", "#a.b#", "#.#.#", "#####"],
                "sources": {"a": 0, "b": 1},
            })
            .to_string(),
        ))
        .await
        .expect("grid session")
        .into_inner();
    let layout = grid
        .model
        .and_then(|m| m.layout)
        .expect("a grid model has a layout");
    assert_eq!((layout.rows, layout.cols), (4, 5));
    let cells: Vec<(u64, u64)> = layout.cells.iter().map(|c| (c.row, c.col)).collect();
    assert_eq!(cells, vec![(1, 1), (1, 2), (1, 3), (2, 1), (2, 3)]);
    let marks: Vec<(&str, u64)> = layout
        .marks
        .iter()
        .map(|m| (m.mark.as_str(), m.state))
        .collect();
    assert_eq!(marks, vec![("a", 0), ("b", 2)]);
    let hallway = client
        .create_session(create(r#"{"preset": "hallway"}"#))
        .await
        .expect("hallway session")
        .into_inner();
    assert!(hallway.model.expect("model").layout.is_none());
}
