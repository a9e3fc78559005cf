//! The gRPC transport over a real socket: a client drives a hallway agent
//! over `Interact` and gets the same actions and drives as the core; bad
//! input gets the right codes; streams stop cleanly; health and reflection
//! answer.
//!
//! One module per concern: [`sessions`], [`bad_inputs`], [`batch`]
//! (`InteractBatch`), [`streams`], [`health`]; the in-process server and
//! the helpers they share are here.
// These tests still send the deprecated `model_json` (accepted for one
// more release, docs/grpc.md).
#![allow(deprecated)]

use std::sync::Arc;
use std::time::{Duration, Instant};

use mcapi_core::model::hallway;
use mcapi_core::{Agent, AgentParams, Basis, BasisSpec, PlanningModel};
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_server::api::grpc::{SESSION_METADATA, ServeError, pb, serve_on};
use mcapi_server::service::{Limits, SessionManager};
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tonic::transport::Channel;
use tonic::{Code, Request, Status};

mod bad_inputs;
mod batch;
mod groups;
mod health;
mod seq;
mod sessions;
mod streams;

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
