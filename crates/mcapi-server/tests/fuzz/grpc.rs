//! gRPC: raw message bytes over a real socket (a codec that sends bytes as
//! they are), the checks every status must pass, and the fuzzing of
//! `CreateSession` and `Observe`.

use std::time::Instant;

use mcapi_server::api::grpc::pb;
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;
use prost::Message;
use serde_json::Value;

use super::{
    DEFAULT_CASES, case_limit, cases, check_rss, count, env, one_at_a_time, rss_mib, runner,
    summary,
};
use crate::json::{absurd_number, arb_json, body, create_bases};

/// Sends raw bytes as one gRPC message.
#[derive(Clone, Default)]
pub(crate) struct RawCodec;

pub(crate) struct RawEncoder;
pub(crate) struct RawDecoder;

impl tonic::codec::Encoder for RawEncoder {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn encode(
        &mut self,
        item: Vec<u8>,
        dst: &mut tonic::codec::EncodeBuf<'_>,
    ) -> Result<(), tonic::Status> {
        prost::bytes::BufMut::put_slice(dst, &item);
        Ok(())
    }
}

impl tonic::codec::Decoder for RawDecoder {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn decode(
        &mut self,
        src: &mut tonic::codec::DecodeBuf<'_>,
    ) -> Result<Option<Vec<u8>>, tonic::Status> {
        let n = prost::bytes::Buf::remaining(src);
        let mut out = vec![0; n];
        prost::bytes::Buf::copy_to_slice(src, &mut out);
        Ok(Some(out))
    }
}

impl tonic::codec::Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawEncoder;
    type Decoder = RawDecoder;

    fn encoder(&mut self) -> RawEncoder {
        RawEncoder
    }

    fn decoder(&mut self) -> RawDecoder {
        RawDecoder
    }
}

pub(crate) async fn grpc_raw(
    channel: &tonic::transport::Channel,
    method: &str,
    bytes: Vec<u8>,
) -> Result<Vec<u8>, tonic::Status> {
    let mut client = tonic::client::Grpc::new(channel.clone());
    client
        .ready()
        .await
        .map_err(|e| tonic::Status::unavailable(format!("not ready: {e}")))?;
    let path = format!("/mcapi.v1.Agents/{method}")
        .parse::<axum::http::uri::PathAndQuery>()
        .map_err(|e| tonic::Status::internal(format!("path: {e}")))?;
    client
        .unary(tonic::Request::new(bytes), path, RawCodec)
        .await
        .map(tonic::Response::into_inner)
}

/// The gRPC contract: no server error but UNAVAILABLE; INTERNAL only for a
/// request message that does not decode (gRPC's prescribed code, from
/// tonic-prost), never for one that does.
pub(crate) fn check_status(
    method: &str,
    input: &[u8],
    decodes: bool,
    status: &tonic::Status,
) -> Result<(), TestCaseError> {
    use tonic::Code;
    let shown = || format!("{:02x?}", &input[..input.len().min(200)]);
    match status.code() {
        Code::Internal
            if !decodes
                && status
                    .message()
                    .starts_with("failed to decode Protobuf message") =>
        {
            Ok(())
        }
        Code::Internal | Code::Unknown | Code::DataLoss => Err(TestCaseError::fail(format!(
            "{method}: {:?} {:?} for {} bytes {}",
            status.code(),
            status.message(),
            input.len(),
            shown()
        ))),
        _ => Ok(()),
    }
}

fn fuzz_grpc(method: &str, bytes: Vec<u8>) -> Result<(), TestCaseError> {
    let e = env();
    let decodes = match method {
        "CreateSession" => pb::CreateSessionRequest::decode(bytes.as_slice()).is_ok(),
        _ => pb::ObserveRequest::decode(bytes.as_slice()).is_ok(),
    };
    let started = Instant::now();
    let result = e.rt.block_on(grpc_raw(&e.grpc, method, bytes.clone()));
    count(format!(
        "grpc {method} {:?}",
        result
            .as_ref()
            .map_or_else(tonic::Status::code, |_| tonic::Code::Ok)
    ));
    match result {
        Err(status) => check_status(method, &bytes, decodes, &status)?,
        Ok(reply) if method == "CreateSession" => {
            let info = pb::SessionInfo::decode(reply.as_slice());
            prop_assert!(
                info.is_ok(),
                "CreateSession replied with an undecodable message"
            );
            if let Ok(info) = info {
                let del = pb::DeleteSessionRequest {
                    session_id: info.id,
                };
                let deleted =
                    e.rt.block_on(grpc_raw(&e.grpc, "DeleteSession", del.encode_to_vec()));
                prop_assert!(deleted.is_ok(), "{:?}", deleted.err());
            }
        }
        Ok(_) => {}
    }
    prop_assert!(
        started.elapsed() < case_limit(),
        "{method} took {:?}",
        started.elapsed()
    );
    check_rss()
}

/// Byte-level changes to an encoding.
pub(crate) fn mutate_bytes(valid: Vec<u8>) -> impl Strategy<Value = Vec<u8>> {
    let len = valid.len().max(1);
    prop::collection::vec((0..len, any::<u8>(), 0u8..4), 1..6).prop_map(move |edits| {
        let mut b = valid.clone();
        for (at, byte, op) in edits {
            let at = at % (b.len() + 1);
            match op {
                0 if at < b.len() => b[at] = byte,
                1 => b.insert(at, byte),
                2 => b.truncate(at),
                _ => {
                    let tail = b[at..].to_vec();
                    b.extend_from_slice(&tail);
                }
            }
        }
        b
    })
}

fn grpc_create_bodies() -> impl Strategy<Value = Vec<u8>> {
    let valid = pb::CreateSessionRequest {
        model_json: r#"{"preset": "hallway"}"#.into(),
        model: None,
        agent: Some(pb::SessionConfig {
            eta: Some(0.01),
            seed: Some(9),
            history: Some(16),
            curiosity: Some(pb::CuriosityConfig {
                signal_dim: 2,
                params_json: r#"{"gain": 800}"#.into(),
            }),
            ..Default::default()
        }),
    }
    .encode_to_vec();
    let structured = (
        body(create_bases()),
        prop::option::of(absurd_number()),
        prop::option::of(any::<u64>()),
        prop::option::of(0u64..100),
        prop::option::of(arb_json()),
    )
        .prop_map(|(model, x, history, signal_dim, params)| {
            // The REST generator's bodies give the model JSON.
            let model = serde_json::from_slice::<Value>(&model)
                .ok()
                .and_then(|v| v.get("model").cloned())
                .map_or_else(
                    || String::from_utf8_lossy(&model).into_owned(),
                    |m| m.to_string(),
                );
            let f = x.as_ref().and_then(Value::as_f64);
            pb::CreateSessionRequest {
                model_json: model,
                model: None,
                agent: Some(pb::SessionConfig {
                    eta: f,
                    gamma: f,
                    optimistic_sd: f,
                    priorities: f.map(|f| vec![f; 2]).unwrap_or_default(),
                    history,
                    curiosity: signal_dim.map(|d| pb::CuriosityConfig {
                        signal_dim: d,
                        params_json: params.map(|p| p.to_string()).unwrap_or_default(),
                    }),
                    ..Default::default()
                }),
            }
            .encode_to_vec()
        });
    prop_oneof![
        3 => structured,
        2 => mutate_bytes(valid),
        1 => prop::collection::vec(any::<u8>(), 0..256),
    ]
}

fn grpc_observe_bodies(ids: Vec<String>) -> impl Strategy<Value = Vec<u8>> {
    let valid = pb::ObserveRequest {
        session_id: ids[0].clone(),
        observations: vec![pb::Observation {
            state: 25,
            ..Default::default()
        }],
    }
    .encode_to_vec();
    let structured = (
        0..ids.len(),
        prop::collection::vec(
            (
                prop_oneof![4 => 0u64..60, 1 => any::<u64>()],
                prop::option::of(prop_oneof![
                    // The hallway's and the maze's stimulus lengths, mostly.
                    3 => prop::collection::vec(-10.0f64..10.0, 2..=3),
                    1 => prop::collection::vec(any::<f64>(), 0..6),
                ]),
                prop::option::of(prop_oneof![0u32..6, any::<u32>()]),
                prop_oneof![
                    3 => Just(Vec::new()),
                    1 => prop::collection::vec(any::<f64>(), 0..3),
                ],
                prop::option::of(any::<u32>()),
                prop_oneof![
                    2 => Just(Vec::new()),
                    2 => prop::collection::vec(-0.5f64..1.5, 2..=2),
                    1 => prop::collection::vec(any::<f64>(), 0..80),
                ],
                prop::option::of(prop_oneof![3 => 0u64..8, 1 => any::<u64>()]),
            ),
            0..6,
        ),
        prop::bool::weighted(0.1),
    )
        .prop_map(move |(i, obs, foreign)| {
            pb::ObserveRequest {
                session_id: ids[i].clone(),
                observations: obs
                    .into_iter()
                    .map(
                        |(state, stimulus, action, signal, source, observation, seq)| {
                            pb::Observation {
                                session_id: if foreign {
                                    "s0000.x".into()
                                } else {
                                    String::new()
                                },
                                state,
                                stimulus: stimulus.map(|values| pb::Stimulus { values }),
                                action_taken: action.map(pb::observation::ActionTaken::ActionIndex),
                                signal,
                                signal_source: source,
                                observation,
                                seq,
                            }
                        },
                    )
                    .collect(),
            }
            .encode_to_vec()
        });
    prop_oneof![
        4 => structured,
        2 => mutate_bytes(valid),
        1 => prop::collection::vec(any::<u8>(), 0..256),
    ]
}

#[test]
fn grpc_create_and_observe_survive_arbitrary_messages() {
    let _serial = one_at_a_time();
    let e = env();
    let started = Instant::now();
    let create =
        runner(DEFAULT_CASES).run(&grpc_create_bodies(), |b| fuzz_grpc("CreateSession", b));
    let observe = runner(DEFAULT_CASES).run(&grpc_observe_bodies(e.grpc_sessions.clone()), |b| {
        fuzz_grpc("Observe", b)
    });
    eprintln!(
        "grpc: 2 x {} cases in {:.1?} (RSS {} MiB)",
        cases(DEFAULT_CASES),
        started.elapsed(),
        rss_mib()
    );
    eprintln!("responses so far: {}", summary());
    for result in [create, observe] {
        if let Err(err) = result {
            panic!("{err}");
        }
    }
    // The server still serves.
    let again = e.rt.block_on(grpc_raw(
        &e.grpc,
        "GetSession",
        pb::GetSessionRequest {
            session_id: e.grpc_sessions[0].clone(),
        }
        .encode_to_vec(),
    ));
    assert!(again.is_ok(), "{:?}", again.err());
}
