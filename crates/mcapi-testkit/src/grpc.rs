//! gRPC calls with an optional API key and the session metadata, and
//! creating a hallway session over gRPC.

use mcapi_server::api::grpc::SESSION_METADATA;
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use tonic::transport::Channel;

use crate::hallway::ACTIONS;

/// A gRPC request with an optional API key and the session metadata.
pub fn grpc_request<T>(message: T, key: Option<&str>, session: Option<&str>) -> tonic::Request<T> {
    let mut req = tonic::Request::new(message);
    if let Some(k) = key {
        req.metadata_mut().insert(
            "authorization",
            format!("Bearer {k}").parse().expect("ascii key"),
        );
    }
    if let Some(id) = session {
        req.metadata_mut()
            .insert(SESSION_METADATA, id.parse().expect("ascii id"));
    }
    req
}

/// Creates a hallway session over gRPC; returns its id.
pub async fn grpc_create(
    client: &mut AgentsClient<Channel>,
    key: Option<&str>,
    seed: u64,
    lockstep: bool,
    epsilon: Option<f64>,
) -> String {
    let mode = if lockstep {
        pb::UpdateMode::Lockstep
    } else {
        pb::UpdateMode::Async
    };
    let info = client
        .create_session(grpc_request(
            pb::CreateSessionRequest {
                model: Some(pb::Model::preset("hallway")),
                agent: Some(pb::SessionConfig {
                    seed: Some(seed),
                    epsilon,
                    update_mode: mode.into(),
                    ..Default::default()
                }),
                ..Default::default()
            },
            key,
            None,
        ))
        .await
        .expect("create over gRPC")
        .into_inner();
    let model = info.model.expect("model");
    assert_eq!(model.actions, ACTIONS.map(String::from).to_vec());
    info.id
}
