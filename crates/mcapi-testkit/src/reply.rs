//! One acknowledged observation over REST or gRPC, and what its reply
//! said (the parts a replay can check).

use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use serde_json::Value;
use tonic::transport::Channel;

use crate::floats::floats;
use crate::grpc::grpc_request;
use crate::hallway::{ACTIONS, Obs};
use crate::rest::rest;

/// What a reply said (the parts a replay can check).
#[derive(Debug, Clone, PartialEq)]
pub struct Reply {
    /// Tick.
    pub tick: u64,
    /// Advised action.
    pub action: usize,
    /// D after the tick.
    pub drive: Vec<f64>,
    /// |r|.
    pub reward: f64,
}

impl Reply {
    /// From a REST step.
    pub fn from_json(v: &Value) -> Self {
        let action = v["action_index"].as_u64().expect("action_index") as usize;
        assert_eq!(v["action"].as_str(), Some(ACTIONS[action]), "{v}");
        Self {
            tick: v["tick"].as_u64().expect("tick"),
            action,
            drive: floats(&v["drive"]),
            reward: v["reward"].as_f64().expect("reward"),
        }
    }

    /// From a gRPC step.
    pub fn from_pb(s: &pb::Step) -> Self {
        assert_eq!(s.action, ACTIONS[s.action_index as usize]);
        Self {
            tick: s.tick,
            action: s.action_index as usize,
            drive: s.drive.clone(),
            reward: s.reward,
        }
    }
}

/// One observation of session `id`, acknowledged: over gRPC (`Observe`,
/// the session in the metadata too) or REST. Panics unless it is applied.
pub async fn observe_one(
    client: &reqwest::Client,
    base: &str,
    grpc: &mut AgentsClient<Channel>,
    over_grpc: bool,
    id: &str,
    obs: &Obs,
) -> Reply {
    if over_grpc {
        let steps = grpc
            .observe(grpc_request(
                pb::ObserveRequest {
                    session_id: id.to_string(),
                    observations: vec![obs.pb(id)],
                },
                None,
                Some(id),
            ))
            .await
            .unwrap_or_else(|s| panic!("gRPC observe {id}: {s:?}"))
            .into_inner()
            .steps;
        Reply::from_pb(&steps[0])
    } else {
        let url = format!("{base}/v1/sessions/{id}/observations");
        let (status, body) =
            rest(client, reqwest::Method::POST, &url, None, Some(&obs.json())).await;
        assert_eq!(status, 200, "observe {id}: {body}");
        Reply::from_json(&body)
    }
}
