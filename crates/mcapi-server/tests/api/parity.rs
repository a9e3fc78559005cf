//! REST-vs-gRPC parity on the full server (`server::start`, both ports on
//! real sockets): the same seed and the same observations give identical
//! actions and drives over both transports in lockstep mode.
// These tests still send the deprecated `model_json` (accepted for one
// more release, docs/grpc.md).
#![allow(deprecated)]

use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_testkit::start_in_process;
use serde_json::{Value, json};

const SEED: u64 = 2024;

fn stimulus(state: usize) -> Vec<f64> {
    match state {
        10 => vec![6.0, 0.0],
        40 => vec![0.0, 6.0],
        _ => vec![0.0, 0.0],
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rest_and_grpc_give_identical_trajectories() {
    // On the durable store: parity must hold with group commit in the path.
    let data = tempfile::tempdir().expect("data dir");
    let running = start_in_process(data.path()).await;
    let base = format!("http://{}", running.http_addr);
    let http = reqwest::Client::new();
    let mut grpc = AgentsClient::connect(format!("http://{}", running.grpc_addr))
        .await
        .expect("grpc connects");

    let created: Value = http
        .post(format!("{base}/v1/sessions"))
        .json(&json!({"model": {"preset": "hallway"}, "agent": {"seed": SEED, "update_mode": "lockstep"}}))
        .send()
        .await
        .expect("create over REST")
        .json()
        .await
        .expect("json");
    let rest_id = created["id"].as_str().expect("id").to_string();
    let grpc_id = grpc
        .create_session(pb::CreateSessionRequest {
            model_json: r#"{"preset": "hallway"}"#.into(),
            model: None,
            agent: Some(pb::SessionConfig {
                seed: Some(SEED),
                update_mode: pb::UpdateMode::Lockstep as i32,
                ..Default::default()
            }),
        })
        .await
        .expect("create over gRPC")
        .into_inner()
        .id;

    let mut state = 33usize;
    for t in 0..1500 {
        let xi = (t > 0).then(|| stimulus(state));
        let body = match &xi {
            Some(x) => json!({"state": state, "stimulus": x}),
            None => json!({"state": state}),
        };
        let rest: Value = http
            .post(format!("{base}/v1/sessions/{rest_id}/observations"))
            .json(&body)
            .send()
            .await
            .expect("observe over REST")
            .json()
            .await
            .expect("json");
        let grpc_step = grpc
            .observe(pb::ObserveRequest {
                session_id: grpc_id.clone(),
                observations: vec![pb::Observation {
                    session_id: grpc_id.clone(),
                    state: state as u64,
                    stimulus: xi.map(|values| pb::Stimulus { values }),
                    action_taken: None,
                    ..Default::default()
                }],
            })
            .await
            .expect("observe over gRPC")
            .into_inner()
            .steps
            .remove(0);
        let rest_drive: Vec<f64> = serde_json::from_value(rest["drive"].clone()).expect("drive");
        assert_eq!(
            rest["action_index"].as_u64(),
            Some(u64::from(grpc_step.action_index)),
            "tick {t}"
        );
        assert_eq!(rest_drive, grpc_step.drive, "tick {t}: drives differ");
        assert_eq!(
            rest["policy_version"].as_u64(),
            Some(grpc_step.policy_version),
            "tick {t}"
        );
        state = match grpc_step.action_index {
            0 => state - 1,
            1 => state + 1,
            _ => state,
        };
    }
    running.shutdown();
    running.wait().await.expect("clean shutdown");
}

/// gRPC's JSON text fields (`model_json`, a curiosity channel's
/// `params_json`) are read as REST reads the same parts of its body: a
/// struct written as an array is refused with REST's message (serde alone
/// reads a struct from an array of its fields), and a count written as an
/// integral float (`20.0`) is the integer it equals, as JSON Schema reads
/// it. Each case is sent over both transports and must get the same
/// answer: created, or refused with the same code and message.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_reads_its_json_text_as_rest_reads_its_body() {
    let data = tempfile::tempdir().expect("data dir");
    let running = start_in_process(data.path()).await;
    let base = format!("http://{}", running.http_addr);
    let http = reqwest::Client::new();
    let mut grpc = AgentsClient::connect(format!("http://{}", running.grpc_addr))
        .await
        .expect("grpc connects");
    let hallway = json!({"preset": "hallway"});
    let posted = |transitions: Value| json!({"states": 2, "actions": ["go"], "stimuli": ["x"], "transitions": transitions});
    let all_constants = json!([
        3, 0.01, 20, 20, 0.03, 800, 12, 0.3, 100, 0.3, 20, 0.08, 0.001, 1e-8, 1.0, 64
    ]);
    // (model, curiosity params, refused with this message, or created)
    let cases = [
        (
            posted(json!([[0, "go", [[1, 1.0]]], [1, "go", [[0, 1.0]]]])),
            None,
            Some("`model.transitions.0`: must be a JSON object"),
        ),
        (
            hallway.clone(),
            Some(all_constants),
            Some("`agent.curiosity.params`: must be a JSON object"),
        ),
        (
            posted(json!([{"state": 0.0, "action": 0.0, "next": [[1.0, 1.0]]},
                          {"state": 1, "action": "go", "next": [[0, 1.0]]}])),
            None,
            None,
        ),
        (
            hallway.clone(),
            Some(json!({"tau": 20.0, "lag": 1e1})),
            None,
        ),
    ];
    for (model, params, refused) in cases {
        let mut agent = json!({"seed": SEED});
        if let Some(p) = &params {
            agent["curiosity"] = json!({"signal_dim": 2, "params": p});
        }
        let body = json!({"model": model, "agent": agent});
        let resp = http
            .post(format!("{base}/v1/sessions"))
            .json(&body)
            .send()
            .await
            .expect("create over REST");
        let status = resp.status().as_u16();
        let reply: Value = resp.json().await.expect("json");
        let grpc_reply = grpc
            .create_session(pb::CreateSessionRequest {
                model_json: model.to_string(),
                model: None,
                agent: Some(pb::SessionConfig {
                    seed: Some(SEED),
                    curiosity: params.as_ref().map(|p| pb::CuriosityConfig {
                        signal_dim: 2,
                        params_json: p.to_string(),
                    }),
                    ..Default::default()
                }),
            })
            .await;
        match refused {
            Some(message) => {
                assert_eq!(
                    (status, reply["code"].as_str()),
                    (400, Some("bad_request")),
                    "REST {body}: {reply}"
                );
                assert_eq!(reply["message"], message, "REST {body}");
                let grpc_status = grpc_reply.expect_err("refused over gRPC");
                assert_eq!(
                    grpc_status.code(),
                    tonic::Code::InvalidArgument,
                    "gRPC {body}: {grpc_status:?}"
                );
                assert_eq!(grpc_status.message(), message, "gRPC {body}");
            }
            None => {
                assert_eq!(status, 201, "REST {body}: {reply}");
                let info = grpc_reply.expect("created over gRPC").into_inner();
                assert_eq!(
                    info.agent.and_then(|a| a.curiosity).map(|c| c.signal_dim),
                    params.map(|_| 2),
                    "gRPC {body}"
                );
            }
        }
    }
}
