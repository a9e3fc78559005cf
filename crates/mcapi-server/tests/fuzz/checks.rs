//! The fuzzer's own checks: they catch what they look for, a long quoted
//! input still gets its status, structs are objects only.

use mcapi_server::api::grpc::pb;
use prost::Message;
use serde_json::json;

use super::env;
use crate::grpc::{check_status, grpc_raw};
use crate::rest::{check_response, rest_call};

/// The checks can fail: a 500 and a bare-text error are caught.
#[test]
fn the_checks_catch_what_they_look_for() {
    assert!(
        check_response(
            "x",
            b"{}",
            500,
            &json!({"code": "internal", "message": "m"})
        )
        .is_err()
    );
    assert!(
        check_response(
            "x",
            b"{}",
            503,
            &json!({"code": "unavailable", "message": "m"})
        )
        .is_ok()
    );
    assert!(check_response("x", b"{}", 400, &json!("text")).is_err());
    assert!(
        check_response(
            "x",
            b"{}",
            400,
            &json!({"code": "c", "message": "m", "x": 1})
        )
        .is_err()
    );
    let internal = tonic::Status::internal("boom");
    assert!(check_status("m", b"", true, &internal).is_err());
    let undecodable =
        tonic::Status::internal("failed to decode Protobuf message: buffer underflow");
    assert!(check_status("m", b"", false, &undecodable).is_ok());
    assert!(check_status("m", b"", true, &undecodable).is_err());
    // A numerical failure is a server error like any other: numbers the
    // session cannot compute with are refused when it is created.
    assert!(
        check_response(
            "x",
            b"{}",
            500,
            &json!({"code": "numerical_failure", "message": "m"})
        )
        .is_err()
    );
}

/// Found by this fuzzer: an error message quoting a long input (here a
/// 20 kB `params_json` string) went into the `grpc-message` trailer whole,
/// beyond the client's header-list limit, and the call failed with an
/// HTTP/2 protocol error (INTERNAL) instead of INVALID_ARGUMENT. Messages
/// are now capped (`api::error::MAX_MESSAGE_BYTES`), on both transports.
#[test]
fn a_long_quoted_input_still_gets_its_status() {
    let e = env();
    let req = pb::CreateSessionRequest {
        model_json: r#"{"preset": "hallway"}"#.into(),
        model: None,
        agent: Some(pb::SessionConfig {
            curiosity: Some(pb::CuriosityConfig {
                signal_dim: 2,
                params_json: format!("\"{}\"", "x".repeat(20_000)),
            }),
            ..Default::default()
        }),
    };
    let status =
        e.rt.block_on(grpc_raw(&e.grpc, "CreateSession", req.encode_to_vec()))
            .expect_err("refused");
    assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
    assert!(status.message().len() < 1200, "{}", status.message().len());
    // (A long preset name is refused by its length limit before it is
    // quoted; an unknown basis kind is quoted back by serde.)
    let body = json!({"model": {"preset": "hallway", "basis": {"kind": "x".repeat(20_000)}}});
    let (status, reply) = e.rt.block_on(rest_call(
        &e.rest,
        "POST",
        "/v1/sessions",
        body.to_string().into_bytes(),
    ));
    assert_eq!(status, 400, "{reply}");
    assert!(
        reply["message"]
            .as_str()
            .is_some_and(|m| m.len() < 1200 && m.ends_with("more bytes)")),
        "{reply}"
    );
}

/// Found by this fuzzer: serde reads a struct from an array of its fields
/// in order, so `"params": [557733413844816262]` was `max_centres` =
/// 557733413844816262 and the server aborted allocating ROC centres, and
/// `[25]` was the observation `{"state": 25}`. Neither form is in the
/// document; both are refused now, before the body is typed.
#[test]
fn structs_are_objects_only() {
    let e = env();
    let (id, _, _) = &e.sessions[0];
    for (uri, body) in [
        (
            "/v1/sessions".to_string(),
            json!({"model": {"preset": "hallway"}, "agent": {"curiosity": {"signal_dim": 2, "params": [557_733_413_844_816_262_u64]}}}),
        ),
        (
            "/v1/sessions".to_string(),
            json!({"model": {"preset": "hallway"}, "agent": {"curiosity": {"signal_dim": 2, "params": []}}}),
        ),
        ("/v1/sessions".to_string(), json!([{"preset": "hallway"}])),
        (
            "/v1/sessions".to_string(),
            json!({"model": {"preset": "hallway", "basis": ["proto_value", 5]}}),
        ),
        (format!("/v1/sessions/{id}/observations"), json!([25])),
        (
            format!("/v1/sessions/{id}/observations"),
            json!({"observations": [[25]]}),
        ),
    ] {
        let (status, reply) = e.rt.block_on(rest_call(
            &e.rest,
            "POST",
            &uri,
            body.to_string().into_bytes(),
        ));
        assert_eq!(status, 400, "{body}: {reply}");
        assert!(
            reply["message"]
                .as_str()
                .is_some_and(|m| m.contains("must be a JSON object")),
            "{body}: {reply}"
        );
    }
}
