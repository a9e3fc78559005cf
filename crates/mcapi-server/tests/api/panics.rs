//! A request whose handling panics ends with 500 / INTERNAL and the code
//! `internal_panic`, on every path: a REST call, a unary gRPC call, and a
//! gRPC stream (`Interact`, `InteractBatch`) after the replies to the
//! messages before the one that panicked. A stream whose task unwound used
//! to end with status OK, as if the client had been answered in full.
//!
//! The panic is injected with `SessionManager::panic_next_observations`, a
//! hidden call of the library that no request can reach: the next
//! observation panics on the request's task before it touches a session,
//! so the session serves the next observation as if nothing happened.

use std::sync::Arc;

use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_server::service::{Limits, SessionManager};
use serde_json::{Value, json};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

struct Servers {
    manager: Arc<SessionManager>,
    base: String,
    grpc: AgentsClient<Channel>,
}

/// One manager behind both transports.
async fn start() -> Servers {
    let (manager, base, addr) = crate::serve_both(Limits::default()).await;
    let grpc = AgentsClient::connect(addr).await.expect("connect");
    Servers {
        manager,
        base,
        grpc,
    }
}

async fn create(grpc: &mut AgentsClient<Channel>) -> String {
    grpc.create_session(pb::CreateSessionRequest {
        model: Some(pb::Model::preset("hallway")),
        agent: Some(pb::SessionConfig {
            seed: Some(7),
            ..Default::default()
        }),
        ..Default::default()
    })
    .await
    .expect("create")
    .into_inner()
    .id
}

fn observation(id: &str, state: u64, stimulus: Option<Vec<f64>>) -> pb::Observation {
    pb::Observation {
        session_id: id.into(),
        state,
        stimulus: stimulus.map(|values| pb::Stimulus { values }),
        ..Default::default()
    }
}

fn assert_internal_panic(status: &tonic::Status, what: &str) {
    assert_eq!(status.code(), tonic::Code::Internal, "{what}: {status:?}");
    let code = status
        .metadata()
        .get("x-mcapi-error-code")
        .and_then(|v| v.to_str().ok());
    assert_eq!(code, Some("internal_panic"), "{what}: {status:?}");
    assert_eq!(
        status.message(),
        "internal error",
        "{what}: nothing is sent"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panic_mid_interact_ends_the_stream_with_internal() {
    let Servers {
        manager, mut grpc, ..
    } = start().await;
    let id = create(&mut grpc).await;
    let (tx, rx) = mpsc::channel(4);
    let mut stream = grpc
        .interact(ReceiverStream::new(rx))
        .await
        .expect("interact")
        .into_inner();
    tx.send(observation(&id, 25, None)).await.expect("send");
    let first = stream.message().await.expect("a reply").expect("a step");
    assert_eq!(first.tick, 0);
    manager.panic_next_observations(1);
    tx.send(observation(&id, 24, Some(vec![0.0, 0.0])))
        .await
        .expect("send");
    match stream.message().await {
        Err(status) => assert_internal_panic(&status, "Interact"),
        Ok(end) => panic!("the stream ended with {end:?}, not INTERNAL"),
    }
    // The observation that panicked was not applied: the session goes on.
    let mut again = grpc
        .interact(tokio_stream::iter([observation(
            &id,
            24,
            Some(vec![0.0, 0.0]),
        )]))
        .await
        .expect("interact")
        .into_inner();
    let step = again.message().await.expect("a reply").expect("a step");
    assert_eq!(step.tick, 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panic_mid_interact_batch_ends_the_stream_with_internal() {
    let Servers {
        manager, mut grpc, ..
    } = start().await;
    let id = create(&mut grpc).await;
    let (tx, rx) = mpsc::channel(4);
    let mut stream = grpc
        .interact_batch(ReceiverStream::new(rx))
        .await
        .expect("interact batch")
        .into_inner();
    let batch = |o: pb::Observation| pb::ObservationBatch {
        observations: vec![o],
    };
    tx.send(batch(observation(&id, 25, None)))
        .await
        .expect("send");
    let first = stream.message().await.expect("a reply").expect("a batch");
    assert_eq!(first.results.len(), 1);
    manager.panic_next_observations(1);
    tx.send(batch(observation(&id, 24, Some(vec![0.0, 0.0]))))
        .await
        .expect("send");
    match stream.message().await {
        Err(status) => assert_internal_panic(&status, "InteractBatch"),
        Ok(end) => panic!("the stream ended with {end:?}, not INTERNAL"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_unary_call_or_rest_request_answers_internal_panic() {
    let Servers {
        manager,
        base,
        mut grpc,
    } = start().await;
    let id = create(&mut grpc).await;
    manager.panic_next_observations(1);
    let status = grpc
        .observe(pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![observation(&id, 25, None)],
        })
        .await
        .expect_err("the call panicked");
    assert_internal_panic(&status, "Observe");

    manager.panic_next_observations(1);
    let url = format!("{base}/v1/sessions/{id}/observations");
    let client = reqwest::Client::new();
    let resp = client
        .post(&url)
        .json(&json!({"state": 25}))
        .send()
        .await
        .expect("a response, not a dropped connection");
    assert_eq!(resp.status().as_u16(), 500);
    let body: Value = resp.json().await.expect("JSON body");
    assert_eq!(
        body,
        json!({"code": "internal_panic", "message": "internal error"})
    );
    // Neither reached the session.
    let resp = client
        .post(&url)
        .json(&json!({"state": 25}))
        .send()
        .await
        .expect("response");
    assert_eq!(resp.status().as_u16(), 200);
    let step: Value = resp.json().await.expect("JSON body");
    assert_eq!(step["tick"], 0, "{step}");
}
