//! A basis build is priced before it starts and stopped when it runs past
//! `--max-build-ms` or its request is abandoned: a proto-value basis that
//! could not finish in time is refused at once with 413 (it used to run
//! for minutes after its request had timed out), every check that costs
//! nothing comes first, and the build of a request whose client went away
//! stops instead of holding its thread and its creation slot.

use std::time::Duration;

use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_server::service::{Limits, SessionManager};
use serde_json::{Value, json};

/// A ring of `n` states, one action, with `k` proto-value functions: a
/// graph whose eigenvalues crowd together, so its sparse build is slow.
fn ring(n: usize, k: usize) -> Value {
    let next: Vec<Vec<usize>> = (0..n).map(|s| vec![(s + 1) % n]).collect();
    json!({"states": n, "actions": ["go"], "next": next, "stimuli": ["x"],
           "basis": {"kind": "proto_value", "k": k}})
}

async fn post(base: &str, body: &Value) -> (u16, Value) {
    crate::post_json(base, "/v1/sessions", body).await
}

/// Sends `body` to `base` + `path` with a client that gives up after
/// 200 ms on a build of seconds, then waits (bounded) for the server to
/// stop that build: a build that ran to its end would leave the count at
/// 0. Asserts that exactly one build was stopped and nothing was created.
async fn abandon_and_wait(manager: &SessionManager, base: &str, path: &str, body: &Value) {
    let gave_up = reqwest::Client::new()
        .post(format!("{base}{path}"))
        .timeout(Duration::from_millis(200))
        .json(body)
        .send()
        .await;
    assert!(gave_up.is_err(), "the client timed out: {gave_up:?}");
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    while manager.builds_stopped() == 0 && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(
        manager.builds_stopped(),
        1,
        "the abandoned build was stopped"
    );
    assert!(manager.is_empty());
}

#[tokio::test]
async fn a_build_estimated_over_the_budget_is_refused_before_it_starts() {
    let (manager, base, addr) = crate::serve_both(Limits::default()).await;
    // 550 PVFs of a 10,000-state ring: inside every size limit, but about
    // 155 s of eigensolver (estimated at least 56 s; the budget is 30 s).
    let body = json!({"model": ring(10_000, 550)});
    let (status, reply) = post(&base, &body).await;
    assert_eq!(status, 413, "{reply}");
    assert_eq!(reply["code"], "limit_exceeded", "{reply}");
    let message = reply["message"].as_str().unwrap_or_default();
    assert!(message.contains("--max-build-ms"), "{message}");
    assert!(message.contains("fewer proto-value functions"), "{message}");
    assert_eq!(manager.builds_stopped(), 0, "refused, not started");
    // gRPC alike: RESOURCE_EXHAUSTED.
    let mut client = AgentsClient::connect(addr).await.expect("connect");
    #[allow(deprecated)]
    let status = client
        .create_session(pb::CreateSessionRequest {
            model_json: body["model"].to_string(),
            ..Default::default()
        })
        .await
        .expect_err("refused");
    assert_eq!(status.code(), tonic::Code::ResourceExhausted, "{status:?}");
    assert!(status.message().contains("--max-build-ms"), "{status:?}");
    assert!(manager.is_empty());
}

#[tokio::test]
async fn cheap_checks_come_before_the_build() {
    // A wrong agent parameter on a model whose build would cost seconds,
    // on a server that stops builds after 1 s: refused for the parameter,
    // not for the build (which, run first, would be stopped: 413).
    let (manager, base, _) = crate::serve_both(Limits {
        max_build_ms: 1000,
        ..Limits::default()
    })
    .await;
    let (status, reply) = post(
        &base,
        &json!({"model": ring(2000, 150), "agent": {"eta": -1.0}}),
    )
    .await;
    assert_eq!(status, 400, "{reply}");
    assert!(
        reply["message"]
            .as_str()
            .unwrap_or_default()
            .contains("eta"),
        "{reply}"
    );
    let (status, reply) = post(
        &base,
        &json!({"model": ring(2000, 150), "agent": {"priorities": [1.0, 1.0, 1.0]}}),
    )
    .await;
    assert_eq!(status, 400, "{reply}");
    // A session over the per-session tick budget: 413 for its cost, before
    // its basis is built.
    let (tight, tight_base, _) = crate::serve_both(Limits {
        max_tick_us: 1,
        max_build_ms: 1000,
        ..Limits::default()
    })
    .await;
    let (status, reply) = post(&tight_base, &json!({"model": ring(2000, 150)})).await;
    assert_eq!(status, 413, "{reply}");
    assert!(
        reply["message"]
            .as_str()
            .unwrap_or_default()
            .contains("--max-tick-us"),
        "{reply}"
    );
    assert_eq!(manager.builds_stopped() + tight.builds_stopped(), 0);
}

#[tokio::test]
async fn a_custom_basis_out_of_range_is_refused_without_waiting_for_a_build() {
    // Both build places taken by builds of seconds; a custom basis with an
    // entry beyond ±10⁶ is refused while they run, not after one of them.
    let (manager, base, _) = crate::serve_both(Limits {
        max_build_ms: 120_000,
        ..Limits::default()
    })
    .await;
    let long: Vec<_> = (0..2)
        .map(|_| {
            let base = base.clone();
            tokio::spawn(async move { post(&base, &json!({"model": ring(2000, 150)})).await })
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let custom = json!({"states": 2, "actions": ["go", "stay"], "stimuli": ["x"],
                        "next": [[1, 0], [0, 1]],
                        "basis": {"kind": "custom", "state_features": [[1e200, 0], [0, 1]]}});
    let (status, reply) = post(&base, &json!({ "model": custom })).await;
    assert_eq!(status, 400, "{reply}");
    assert!(
        reply["message"]
            .as_str()
            .unwrap_or_default()
            .contains("exceeds the limit"),
        "{reply}"
    );
    assert!(
        long.iter().all(|h| !h.is_finished()),
        "the refusal waited for a build to end"
    );
    for h in long {
        h.abort();
    }
    // The abandoned builds stop.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    while manager.builds_stopped() < 2 && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(manager.builds_stopped(), 2);
}

#[tokio::test]
async fn a_build_past_its_deadline_is_stopped() {
    // 150 PVFs of a 2000-state ring: estimated at about 0.9 s, so it
    // starts under a 1 s budget, and takes seconds, so it is stopped.
    let (manager, base, _) = crate::serve_both(Limits {
        max_build_ms: 1000,
        ..Limits::default()
    })
    .await;
    let (status, reply) = post(&base, &json!({"model": ring(2000, 150)})).await;
    assert_eq!(status, 413, "{reply}");
    let message = reply["message"].as_str().unwrap_or_default();
    assert!(message.contains("ran past its time budget"), "{message}");
    assert_eq!(manager.builds_stopped(), 1);
    assert!(manager.is_empty());
    // The slot is free again: a model that builds at once is served.
    let (status, reply) = post(&base, &json!({"model": ring(50, 5)})).await;
    assert_eq!(status, 201, "{reply}");
}

#[tokio::test]
async fn the_build_of_an_abandoned_request_stops() {
    let (manager, base, _) = crate::serve_both(Limits::default()).await;
    let body = json!({"model": ring(2000, 150)});
    abandon_and_wait(&manager, &base, "/v1/sessions", &body).await;
    // The slot is free again.
    let (status, reply) = post(&base, &json!({"model": ring(50, 5)})).await;
    assert_eq!(status, 201, "{reply}");
}

#[tokio::test]
async fn the_build_of_an_abandoned_group_stops() {
    let (manager, base, _) = crate::serve_both(Limits::default()).await;
    let body = json!({"model": ring(2000, 150), "n": 3});
    abandon_and_wait(&manager, &base, "/v1/groups", &body).await;
}
