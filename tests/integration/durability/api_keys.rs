//! API keys over REST and gRPC: missing, wrong or malformed keys, another
//! key's sessions, health and metrics without a key, keys never logged or
//! echoed, and `--store memory` with keys from `MCAPI_API_KEYS`.

use crate::common;

use std::path::Path;
use std::process::Command;

use common::{
    Launch, Server, grpc_create, grpc_request, http_client, params, rest, rest_create, rest_get,
    rest_list_all,
};
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use reqwest::Method;
use serde_json::{Value, json};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Code, Status};

use super::{KEY_A, KEY_B, KEY_WRONG, MISSING, Sim, log_path, logs};

fn keyed(dir: &Path) -> Launch {
    Launch::new(dir, &["--api-key", KEY_A, "--api-key", KEY_B])
}

/// Replaces `id` by a placeholder everywhere in a JSON value's text.
fn without_id(v: &Value, id: &str) -> String {
    v.to_string().replace(id, "<id>")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_keys_over_rest() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    let mut server = Server::start(&keyed(data.path()), log_path(&logs, "rest")).await;
    let client = http_client();
    let base = server.base();

    // Health, readiness and metrics need no key.
    for path in ["/healthz", "/readyz", "/metrics"] {
        let resp = client
            .get(format!("{base}{path}"))
            .send()
            .await
            .expect("request");
        assert_eq!(resp.status(), 200, "{path} without a key");
    }

    let a_id = rest_create(&client, &base, Some(KEY_A), json!({"seed": 501})).await;
    let mut a = Sim::new(a_id.clone(), Some(KEY_A), params(501, None), true);
    a.rest_ticks(&client, &base, 5).await;
    let b_id = rest_create(&client, &base, Some(KEY_B), json!({"seed": 502})).await;

    // Metrics need no key, so they must not name sessions.
    let metrics = client
        .get(format!("{base}/metrics"))
        .send()
        .await
        .expect("metrics")
        .text()
        .await
        .expect("text");
    assert!(
        !metrics.contains(&a_id) && !metrics.contains(&b_id),
        "metrics name no session"
    );

    let observation = json!({"state": 3, "stimulus": [0.0, 0.0]});
    let create = json!({"model": {"preset": "hallway"}});
    let calls = |id: &str| {
        vec![
            (Method::GET, format!("{base}/v1/sessions"), None),
            (
                Method::POST,
                format!("{base}/v1/sessions"),
                Some(create.clone()),
            ),
            (Method::GET, format!("{base}/v1/sessions/{id}"), None),
            (
                Method::POST,
                format!("{base}/v1/sessions/{id}/observations"),
                Some(observation.clone()),
            ),
            (
                Method::GET,
                format!("{base}/v1/sessions/{id}/values?include=all"),
                None,
            ),
            (
                Method::GET,
                format!("{base}/v1/sessions/{id}/history"),
                None,
            ),
            (Method::DELETE, format!("{base}/v1/sessions/{id}"), None),
        ]
    };

    // No key, a wrong key, a malformed header: 401 on every route, for an
    // existing session and a missing one alike (no existence leak).
    let bad_headers: Vec<(&str, Option<reqwest::header::HeaderValue>)> = vec![
        ("no key", None),
        (
            "a wrong key",
            Some(format!("Bearer {KEY_WRONG}").parse().expect("header")),
        ),
        (
            "another scheme",
            Some(format!("Basic {KEY_A}").parse().expect("header")),
        ),
        ("an empty key", Some("Bearer ".parse().expect("header"))),
        ("a bare key", Some(KEY_A.parse().expect("header"))),
        (
            "non-ASCII",
            Some(reqwest::header::HeaderValue::from_bytes(b"Bearer \xff\xfe").expect("header")),
        ),
    ];
    for (what, header) in &bad_headers {
        for id in [a_id.as_str(), MISSING] {
            for (method, url, body) in calls(id) {
                let mut req = client.request(method.clone(), &url);
                if let Some(h) = header {
                    req = req.header(reqwest::header::AUTHORIZATION, h.clone());
                }
                if let Some(b) = &body {
                    req = req.json(b);
                }
                let resp = req.send().await.expect("request");
                let status = resp.status().as_u16();
                let challenge = resp
                    .headers()
                    .get(reqwest::header::WWW_AUTHENTICATE)
                    .map(|v| v.to_str().expect("ascii").to_string());
                let body: Value = resp.json().await.unwrap_or(Value::Null);
                let ctx = format!("{what}: {method} {url}");
                assert_eq!(status, 401, "{ctx}: {body}");
                assert_eq!(body["code"], "unauthenticated", "{ctx}: {body}");
                assert!(
                    challenge
                        .as_deref()
                        .is_some_and(|c| c.starts_with("Bearer")),
                    "{ctx}: WWW-Authenticate: {challenge:?}"
                );
                let message = body["message"].as_str().expect("message");
                assert!(
                    !message.contains(KEY_A) && !message.contains(KEY_WRONG),
                    "{ctx}: the key is echoed: {message}"
                );
            }
        }
    }

    // Key B on A's session: 404, exactly as for a missing session.
    for ((method, url, body), (_, missing_url, _)) in calls(&a_id).into_iter().zip(calls(MISSING)) {
        if !url.contains(&a_id) {
            continue;
        }
        let got = rest(&client, method.clone(), &url, Some(KEY_B), body.as_ref()).await;
        let missing = rest(
            &client,
            method.clone(),
            &missing_url,
            Some(KEY_B),
            body.as_ref(),
        )
        .await;
        let ctx = format!("key B: {method} {url}");
        assert_eq!(got.0, 404, "{ctx}: {}", got.1);
        assert_eq!(got.1["code"], "not_found", "{ctx}");
        assert_eq!(missing.0, 404, "{ctx}");
        assert_eq!(
            without_id(&got.1, &a_id),
            without_id(&missing.1, MISSING),
            "{ctx}: indistinguishable from a missing session"
        );
    }
    assert_eq!(
        rest_list_all(&client, &base, Some(KEY_B)).await,
        vec![b_id.clone()],
        "key B lists only its own"
    );
    assert_eq!(
        rest_list_all(&client, &base, Some(KEY_A)).await,
        vec![a_id.clone()],
        "key A lists only its own"
    );
    // B's attempts changed nothing; A still does everything.
    a.check(&client, &base, "after key B's attempts").await;
    a.rest_ticks(&client, &base, 3).await;
    a.check(&client, &base, "key A").await;
    // Keys are accepted with a lower-case scheme too.
    let resp = client
        .get(format!("{base}/v1/sessions/{a_id}"))
        .header(reqwest::header::AUTHORIZATION, format!("bearer {KEY_A}"))
        .send()
        .await
        .expect("request");
    assert_eq!(resp.status(), 200);
    // Ownership survives a restart.
    assert!(server.terminate().success());
    let mut server = Server::start(&keyed(data.path()), log_path(&logs, "rest-2")).await;
    let base = server.base();
    let (status, _) = rest_get(&client, &base, Some(KEY_B), &a_id).await;
    assert_eq!(status, 404, "key B after a restart");
    a.check(&client, &base, "key A after a restart").await;
    let (status, _) = rest(
        &client,
        Method::DELETE,
        &format!("{base}/v1/sessions/{a_id}"),
        Some(KEY_A),
        None,
    )
    .await;
    assert_eq!(status, 204);
    let (status, _) = rest_get(&client, &base, Some(KEY_A), &a_id).await;
    assert_eq!(status, 404);
    assert_eq!(rest_list_all(&client, &base, Some(KEY_B)).await, vec![b_id]);
    assert!(server.terminate().success());
    assert!(
        [KEY_A, KEY_B, KEY_WRONG]
            .iter()
            .all(|k| !server.log_text().contains(k)),
        "keys, right or wrong, are never logged"
    );
}

/// The status a streaming call ends with: at the call, or as its first
/// message.
async fn interact_status(
    client: &mut AgentsClient<Channel>,
    key: Option<&str>,
    id: &str,
) -> Result<pb::Step, Status> {
    let (tx, rx) = mpsc::channel(1);
    tx.send(pb::Observation {
        session_id: id.into(),
        state: 3,
        stimulus: Some(pb::Stimulus {
            values: vec![0.0, 0.0],
        }),
        action_taken: None,
        ..Default::default()
    })
    .await
    .expect("queued");
    let mut steps = client
        .interact(grpc_request(ReceiverStream::new(rx), key, Some(id)))
        .await?
        .into_inner();
    let first = steps.message().await?;
    first.ok_or_else(|| Status::unknown("the stream ended without a step"))
}

async fn watch_status(
    client: &mut AgentsClient<Channel>,
    key: Option<&str>,
    id: &str,
) -> Result<pb::SessionInfo, Status> {
    let mut stream = client
        .watch(grpc_request(
            pb::WatchRequest {
                session_id: id.into(),
                interval_ms: 50,
            },
            key,
            Some(id),
        ))
        .await?
        .into_inner();
    let first = stream.message().await?;
    first.ok_or_else(|| Status::unknown("the stream ended without a message"))
}

/// Every `Agents` method on session `id` with `key`: (name, outcome).
async fn every_grpc_call(
    client: &mut AgentsClient<Channel>,
    key: Option<&str>,
    id: &str,
) -> Vec<(&'static str, Result<(), Status>)> {
    let s = Some(id);
    let mut out = Vec::new();
    let r = client
        .get_session(grpc_request(
            pb::GetSessionRequest {
                session_id: id.into(),
            },
            key,
            s,
        ))
        .await;
    out.push(("GetSession", r.map(drop)));
    let r = client
        .observe(grpc_request(
            pb::ObserveRequest {
                session_id: id.into(),
                observations: vec![pb::Observation {
                    session_id: String::new(),
                    state: 3,
                    stimulus: Some(pb::Stimulus {
                        values: vec![0.0, 0.0],
                    }),
                    action_taken: None,
                    ..Default::default()
                }],
            },
            key,
            s,
        ))
        .await;
    out.push(("Observe", r.map(drop)));
    let r = client
        .get_values(grpc_request(
            pb::GetValuesRequest {
                session_id: id.into(),
                include: vec!["xi".into()],
            },
            key,
            s,
        ))
        .await;
    out.push(("GetValues", r.map(drop)));
    out.push(("Watch", watch_status(client, key, id).await.map(drop)));
    out.push(("Interact", interact_status(client, key, id).await.map(drop)));
    let r = client
        .delete_session(grpc_request(
            pb::DeleteSessionRequest {
                session_id: id.into(),
            },
            key,
            s,
        ))
        .await;
    out.push(("DeleteSession", r.map(drop)));
    out
}

async fn grpc_list(client: &AgentsClient<Channel>, key: &str) -> Vec<String> {
    client
        .clone()
        .list_sessions(grpc_request(
            pb::ListSessionsRequest {
                after: None,
                limit: None,
            },
            Some(key),
            None,
        ))
        .await
        .expect("list")
        .into_inner()
        .sessions
        .into_iter()
        .map(|s| s.id)
        .collect()
}

fn error_code(status: &Status) -> Option<String> {
    status
        .metadata()
        .get("x-mcapi-error-code")
        .map(|v| v.to_str().expect("ascii").to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_keys_over_grpc() {
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};

    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    let mut server = Server::start(&keyed(data.path()), log_path(&logs, "grpc")).await;
    let mut client = server.grpc_client().await;

    // gRPC health needs no key.
    let channel = Channel::from_shared(server.grpc_url())
        .expect("uri")
        .connect()
        .await
        .expect("connect");
    let health = HealthClient::new(channel)
        .check(HealthCheckRequest {
            service: String::new(),
        })
        .await
        .expect("health without a key")
        .into_inner();
    assert_eq!(
        health.status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );

    let a_id = grpc_create(&mut client, Some(KEY_A), 601, true, None).await;
    let b_id = grpc_create(&mut client, Some(KEY_B), 602, false, None).await;
    let mut a = Sim::new(a_id.clone(), Some(KEY_A), params(601, None), true);
    a.grpc_ticks(&mut client, 5).await;

    // No key or a wrong one: UNAUTHENTICATED everywhere, code in metadata.
    for key in [None, Some(KEY_WRONG)] {
        let what = if key.is_none() {
            "no key"
        } else {
            "a wrong key"
        };
        let create = client
            .create_session(grpc_request(
                pb::CreateSessionRequest {
                    model_json: r#"{"preset": "hallway"}"#.into(),
                    model: None,
                    agent: None,
                },
                key,
                None,
            ))
            .await
            .map(drop);
        let list = client
            .list_sessions(grpc_request(
                pb::ListSessionsRequest {
                    after: None,
                    limit: None,
                },
                key,
                None,
            ))
            .await
            .map(drop);
        let mut calls = vec![("CreateSession", create), ("ListSessions", list)];
        for id in [a_id.as_str(), MISSING] {
            calls.extend(every_grpc_call(&mut client, key, id).await);
        }
        for (name, r) in calls {
            let status = r.expect_err(&format!("{what}: {name} must fail"));
            assert_eq!(
                status.code(),
                Code::Unauthenticated,
                "{what}: {name}: {status:?}"
            );
            assert_eq!(
                error_code(&status).as_deref(),
                Some("unauthenticated"),
                "{what}: {name}: x-mcapi-error-code"
            );
            assert!(!status.message().contains(KEY_WRONG), "{name}: key echoed");
        }
    }

    // Key B on A's session: NOT_FOUND, as for a missing session.
    let on_a = every_grpc_call(&mut client, Some(KEY_B), &a_id).await;
    let on_missing = every_grpc_call(&mut client, Some(KEY_B), MISSING).await;
    for ((name, got), (_, missing)) in on_a.into_iter().zip(on_missing) {
        let got = got.expect_err(&format!("key B: {name} on A's session must fail"));
        let missing = missing.expect_err("missing session");
        assert_eq!(got.code(), Code::NotFound, "key B: {name}: {got:?}");
        assert_eq!(error_code(&got).as_deref(), Some("not_found"), "{name}");
        assert_eq!(
            (
                missing.code(),
                missing.message().replace(MISSING, "<id>"),
                error_code(&missing)
            ),
            (
                got.code(),
                got.message().replace(&a_id, "<id>"),
                error_code(&got)
            ),
            "key B: {name}: indistinguishable from a missing session"
        );
    }
    assert_eq!(grpc_list(&client, KEY_B).await, vec![b_id.clone()]);
    assert_eq!(grpc_list(&client, KEY_A).await, vec![a_id.clone()]);

    // A's session is untouched, and A can use every call on it.
    let http = http_client();
    a.check(&http, &server.base(), "after key B's attempts")
        .await;
    for (name, r) in every_grpc_call(&mut client, Some(KEY_A), &a_id).await {
        // Observe and Interact each took one tick (state 3, no stimulus
        // change matters here); DeleteSession comes last.
        r.unwrap_or_else(|e| panic!("key A: {name}: {e:?}"));
    }
    assert_eq!(
        grpc_list(&client, KEY_A).await,
        Vec::<String>::new(),
        "deleted by A"
    );
    assert_eq!(grpc_list(&client, KEY_B).await, vec![b_id]);
    assert!(server.terminate().success());
    assert!(
        [KEY_A, KEY_B, KEY_WRONG]
            .iter()
            .all(|k| !server.log_text().contains(k)),
        "keys, right or wrong, are never logged"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn memory_store_with_keys_from_the_environment() {
    let root = tempfile::tempdir().expect("root");
    let data = root.path().join("never-created");
    let logs = logs();
    let launch = Launch::new(&data, &["--store", "memory"])
        .env("MCAPI_API_KEYS", &format!("{KEY_A},{KEY_B}"));
    let mut server = Server::start(&launch, log_path(&logs, "memory")).await;
    let client = http_client();
    let base = server.base();
    let (status, body) = rest(
        &client,
        Method::GET,
        &format!("{base}/v1/sessions"),
        None,
        None,
    )
    .await;
    assert_eq!(status, 401, "{body}");
    let id = rest_create(&client, &base, Some(KEY_A), json!({"seed": 701})).await;
    let mut sim = Sim::new(id.clone(), Some(KEY_A), params(701, None), true);
    sim.rest_ticks(&client, &base, 20).await;
    sim.check(&client, &base, "memory store").await;
    let (status, _) = rest_get(&client, &base, Some(KEY_B), &id).await;
    assert_eq!(status, 404);
    assert!(rest_list_all(&client, &base, Some(KEY_B)).await.is_empty());
    assert!(server.terminate().success());
    assert!(
        !data.exists(),
        "--store memory creates no data directory or file"
    );
    // Nothing survives a restart in memory.
    let mut server = Server::start(&launch, log_path(&logs, "memory-2")).await;
    assert!(
        rest_list_all(&client, &server.base(), Some(KEY_A))
            .await
            .is_empty()
    );
    assert!(server.terminate().success());
    assert!(!data.exists());
}

#[test]
fn short_or_empty_keys_are_refused_and_never_echoed() {
    for (args, env, needle) in [
        (
            vec!["--api-key", "short-key-12"],
            None,
            "at least 16 characters",
        ),
        (
            vec![],
            Some(format!("{KEY_A},short-key-12")),
            "at least 16 characters",
        ),
        (vec![], Some(format!("{KEY_A},,{KEY_B}")), "a key is empty"),
    ] {
        let root = tempfile::tempdir().expect("root");
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_mcapi"));
        cmd.args(["serve", "--http", "127.0.0.1:0", "--grpc", "127.0.0.1:0"])
            .arg("--data-dir")
            .arg(root.path().join("data"))
            .args(&args)
            .env_remove("MCAPI_API_KEYS");
        if let Some(e) = &env {
            cmd.env("MCAPI_API_KEYS", e);
        }
        let out = cmd.output().expect("mcapi runs");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} {env:?}: {err}");
        assert!(err.contains(needle), "{args:?} {env:?}: {err}");
        assert!(
            !err.contains("short-key-12") && !err.contains(KEY_A),
            "keys are not echoed: {err}"
        );
        assert!(
            !root.path().join("data").exists(),
            "refused before the store"
        );
    }
}
