//! Session groups: `POST /v1/groups` with mutated create bodies (every
//! group accepted is stepped once and deleted), `POST /v1/groups/{id}/steps`
//! with mutated columns and seqs against a standing group, and `StepGroup`
//! messages (mutated encodings, absurd columns and seqs, raw bytes) as the
//! first message of a stream. Every answer must pass the REST and gRPC contracts of the
//! other fuzz tests; no case may take long or grow memory past the budget.

use std::sync::OnceLock;
use std::time::Instant;

use mcapi_server::api::grpc::pb;
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;
use prost::Message;
use serde_json::{Value, json};

use super::{
    DEFAULT_CASES, case_limit, cases, check_rss, count, env, one_at_a_time, rss_mib, runner,
    summary,
};
use crate::grpc::{RawCodec, check_status, grpc_raw, mutate_bytes};
use crate::json::body;
use crate::rest::{check_response, rest_call};

/// Members of the standing groups.
const MEMBERS: usize = 4;

fn create_bases() -> Vec<Value> {
    vec![
        json!({"model": {"preset": "hallway"}, "n": 3, "seed": 7}),
        json!({"model": {"preset": "hallway"}, "agent": {"update_mode": "lockstep", "history": 8}, "n": 2}),
        json!({"model": {"preset": "three_room"}, "agent": {"update_mode": "async"}, "n": 2, "seed": 1}),
        json!({"model": {"observation_space": {"low": [0, 0], "high": [1, 1]},
            "actions": ["n", "s", "e", "w"], "stimuli": ["food", "rest"],
            "samples": {"max": 64}}, "n": 2, "seed": 3}),
    ]
}

fn step_bases() -> Vec<Value> {
    vec![
        json!({"states": [25, 25, 25, 25]}),
        json!({"states": [26, 24, 26, 25], "stimuli": [[0, 0], [0, 0], [0, 0], [0, 0]]}),
        json!({"mask": [0, 2], "states": [27, 27], "stimuli": [[0, 0], [6, 0]]}),
        json!({"mask": [1], "states": [23], "stimuli": [[0, 0]], "action_taken": [0]}),
        json!({"states": [25, 25, 25, 25], "stimuli": [[0, 0], [0, 0], [0, 0], [0, 0]],
            "action_taken": [null, 1, 2, null]}),
        json!({"states": [25, 25, 25, 25], "stimuli": [[0, 0], [0, 0], [0, 0], [0, 0]],
            "seqs": [0, 1, 2, 18_446_744_073_709_551_615u64]}),
        json!({"mask": [0, 3], "states": [24, 26], "seqs": [5, 1]}),
    ]
}

/// The standing REST group every step case is sent to.
fn rest_group() -> &'static str {
    static GROUP: OnceLock<String> = OnceLock::new();
    GROUP.get_or_init(|| {
        let e = env();
        let body = json!({"model": {"preset": "hallway"}, "n": MEMBERS, "seed": 11});
        let (status, info) = e.rt.block_on(rest_call(
            &e.rest,
            "POST",
            "/v1/groups",
            body.to_string().into_bytes(),
        ));
        assert_eq!(status, 201, "{info}");
        info["id"].as_str().expect("group id").to_string()
    })
}

/// The standing gRPC group every `StepGroup` case is sent to.
fn grpc_group() -> &'static str {
    static GROUP: OnceLock<String> = OnceLock::new();
    GROUP.get_or_init(|| {
        let e = env();
        let req = pb::CreateGroupRequest {
            model: Some(pb::Model::preset("hallway")),
            agent: None,
            n: MEMBERS as u32,
            seed: Some(12),
        };
        let reply =
            e.rt.block_on(grpc_raw(&e.grpc, "CreateGroup", req.encode_to_vec()))
                .expect("a valid CreateGroup");
        pb::GroupInfo::decode(reply.as_slice())
            .expect("GroupInfo")
            .group_id
    })
}

fn fuzz_create(body: Vec<u8>) -> Result<(), TestCaseError> {
    let e = env();
    let started = Instant::now();
    let (status, info) =
        e.rt.block_on(rest_call(&e.rest, "POST", "/v1/groups", body.clone()));
    count(format!(
        "create group {status} {}",
        info["code"].as_str().unwrap_or("")
    ));
    check_response("POST /v1/groups", &body, status, &info)?;
    if status == 201 {
        let id = info["id"].as_str().unwrap_or_default().to_string();
        let n = info["size"].as_u64().unwrap_or(0) as usize;
        // One step of every member: a continuous group takes vectors.
        let step = match info["observation_dim"].as_u64() {
            Some(d) if d > 0 => json!({"observations": vec![vec![0.5; d as usize]; n]}),
            _ => json!({"states": vec![0; n]}),
        };
        let bytes = step.to_string().into_bytes();
        let uri = format!("/v1/groups/{id}/steps");
        let (status, reply) = e.rt.block_on(rest_call(&e.rest, "POST", &uri, bytes));
        check_response(
            &format!("a first step {step} of a group created from"),
            &body,
            status,
            &reply,
        )?;
        let (status, reply) = e.rt.block_on(rest_call(
            &e.rest,
            "DELETE",
            &format!("/v1/groups/{id}"),
            Vec::new(),
        ));
        prop_assert_eq!(status, 204, "{}", reply);
    }
    prop_assert!(
        started.elapsed() < case_limit(),
        "a group create took {:?}: {}",
        started.elapsed(),
        String::from_utf8_lossy(&body[..body.len().min(600)])
    );
    check_rss()
}

fn fuzz_step(body: Vec<u8>) -> Result<(), TestCaseError> {
    let e = env();
    let started = Instant::now();
    let uri = format!("/v1/groups/{}/steps", rest_group());
    let (status, reply) =
        e.rt.block_on(rest_call(&e.rest, "POST", &uri, body.clone()));
    count(format!(
        "step group {status} {}",
        reply["code"].as_str().unwrap_or("")
    ));
    check_response(&format!("POST {uri}"), &body, status, &reply)?;
    if status == 200 {
        // Per-member refusals keep the contract too.
        for err in reply["errors"].as_array().into_iter().flatten() {
            prop_assert!(
                err["code"].is_string() && err["message"].is_string() && err["index"].is_u64(),
                "a member's refusal {err} is not {{\"index\",\"code\",\"message\"}}"
            );
        }
    }
    prop_assert!(
        started.elapsed() < case_limit(),
        "a group step took {:?}",
        started.elapsed()
    );
    check_rss()
}

/// Sends `bytes` as the one message of a `StepGroup` stream and reads its
/// reply or its status.
async fn step_group_raw(
    channel: &tonic::transport::Channel,
    bytes: Vec<u8>,
) -> Result<Option<Vec<u8>>, tonic::Status> {
    let mut client = tonic::client::Grpc::new(channel.clone());
    client
        .ready()
        .await
        .map_err(|e| tonic::Status::unavailable(format!("not ready: {e}")))?;
    let path = axum::http::uri::PathAndQuery::from_static("/mcapi.v1.Agents/StepGroup");
    let messages = tokio_stream::iter([bytes]);
    let mut replies = client
        .streaming(tonic::Request::new(messages), path, RawCodec)
        .await?
        .into_inner();
    replies.message().await
}

fn fuzz_grpc_step(bytes: Vec<u8>) -> Result<(), TestCaseError> {
    let e = env();
    let decodes = pb::GroupStepRequest::decode(bytes.as_slice()).is_ok();
    let started = Instant::now();
    let result = e.rt.block_on(step_group_raw(&e.grpc, bytes.clone()));
    count(format!(
        "grpc StepGroup {:?}",
        result
            .as_ref()
            .map_or_else(tonic::Status::code, |_| tonic::Code::Ok)
    ));
    match result {
        Err(status) => check_status("StepGroup", &bytes, decodes, &status)?,
        Ok(Some(reply)) => prop_assert!(
            pb::GroupStepReply::decode(reply.as_slice()).is_ok(),
            "StepGroup replied with an undecodable message"
        ),
        Ok(None) => {}
    }
    prop_assert!(
        started.elapsed() < case_limit(),
        "a StepGroup message took {:?}",
        started.elapsed()
    );
    check_rss()
}

fn le(xs: &[f64]) -> Vec<u8> {
    xs.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn grpc_step_bodies(group: String) -> impl Strategy<Value = Vec<u8>> {
    let valid = pb::GroupStepRequest {
        group_id: group.clone(),
        seq: 0,
        states: vec![25; MEMBERS],
        ..Default::default()
    }
    .encode_to_vec();
    let structured = (
        prop_oneof![3 => Just(group), 1 => "[a-z0-9.]{0,40}"],
        any::<u64>(),
        prop::collection::vec(prop_oneof![4 => 0u32..60, 1 => any::<u32>()], 0..9),
        prop_oneof![
            2 => prop::collection::vec(-10.0f64..10.0, 0..12),
            1 => prop::collection::vec(any::<f64>(), 0..12),
        ],
        prop::collection::vec(any::<u8>(), 0..20),
        prop::collection::vec(prop_oneof![4 => 0u32..4, 1 => any::<u32>()], 0..6),
        prop::collection::vec(prop_oneof![4 => 0u32..5, 1 => any::<u32>()], 0..6),
        prop::collection::vec(prop_oneof![4 => 0u64..8, 1 => any::<u64>()], 0..6),
    )
        .prop_map(
            |(group_id, seq, states, stimuli, observations, action_taken, mask, seqs)| {
                pb::GroupStepRequest {
                    group_id,
                    seq,
                    states,
                    observations,
                    stimuli: le(&stimuli),
                    action_taken,
                    mask,
                    seqs,
                }
                .encode_to_vec()
            },
        );
    prop_oneof![
        3 => structured,
        2 => mutate_bytes(valid),
        1 => prop::collection::vec(any::<u8>(), 0..256),
    ]
}

#[test]
fn groups_survive_arbitrary_bodies_and_messages() {
    let _serial = one_at_a_time();
    let e = env();
    let started = Instant::now();
    let create = runner(DEFAULT_CASES / 5).run(&body(create_bases()), fuzz_create);
    let step = runner(DEFAULT_CASES / 2).run(&body(step_bases()), fuzz_step);
    let grpc =
        runner(DEFAULT_CASES / 2).run(&grpc_step_bodies(grpc_group().to_string()), fuzz_grpc_step);
    eprintln!(
        "groups: {} + {} + {} cases in {:.1?} (RSS {} MiB)",
        cases(DEFAULT_CASES / 5),
        cases(DEFAULT_CASES / 2),
        cases(DEFAULT_CASES / 2),
        started.elapsed(),
        rss_mib()
    );
    eprintln!("responses so far: {}", summary());
    for result in [create, step, grpc] {
        if let Err(err) = result {
            panic!("{err}");
        }
    }
    // Both servers still step their groups.
    let uri = format!("/v1/groups/{}", rest_group());
    let (status, info) = e.rt.block_on(rest_call(&e.rest, "GET", &uri, Vec::new()));
    assert_eq!(status, 200, "{info}");
    let info = pb::GetGroupRequest {
        group_id: grpc_group().to_string(),
    };
    let again =
        e.rt.block_on(grpc_raw(&e.grpc, "GetGroup", info.encode_to_vec()));
    assert!(again.is_ok(), "{:?}", again.err());
}
