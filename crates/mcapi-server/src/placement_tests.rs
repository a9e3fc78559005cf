//! A clustered replica's REST answers in process (no socket): its replica
//! header, 421 naming the owner, 503 with `Retry-After` for a frozen
//! shard, creates only in owned shards; a single node's answers unchanged.

use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use http_body_util::BodyExt;
use serde_json::Value;
use tower::ServiceExt;

use crate::api::error::to_status;
use crate::api::{AppState, router};
use crate::service::{Limits, ManagerOptions, ServiceError, SessionManager};
use mcapi_shards::plan::{ordinal_names, plan};
use mcapi_shards::{Placement, ReplicaName, ShardMap, ShardState, shard_key, shard_of_id};

fn replica(map: &ShardMap, name: &str) -> (axum::Router, Arc<Placement>) {
    let placement = Arc::new(
        Placement::new(map.clone(), ReplicaName::parse(name).expect("name")).expect("placement"),
    );
    let manager = SessionManager::with_options(ManagerOptions {
        placement: Some(Arc::clone(&placement)),
        ..ManagerOptions::new(Limits::default(), 1)
    })
    .expect("manager");
    let app = router(AppState {
        manager: Arc::new(manager),
        metrics: None,
        serving: None,
    });
    (app, placement)
}

async fn send(
    app: &axum::Router,
    method: &str,
    uri: &str,
    body: Option<&str>,
) -> (StatusCode, axum::http::HeaderMap, Value) {
    let req = Request::builder()
        .method(method)
        .uri(uri)
        .header("content-type", "application/json")
        .body(body.map_or_else(Body::empty, |b| Body::from(b.to_string())))
        .expect("request");
    let resp = app.clone().oneshot(req).await.expect("response");
    let (parts, body) = resp.into_parts();
    let bytes = body.collect().await.expect("body").to_bytes();
    (
        parts.status,
        parts.headers,
        serde_json::from_slice(&bytes).unwrap_or(Value::Null),
    )
}

const HALLWAY: &str = r#"{"model": {"preset": "hallway"}}"#;

#[tokio::test]
async fn a_replica_serves_its_shards_and_refuses_the_others() {
    let names = ordinal_names("mcapi", 2).expect("names");
    let map = plan(&names, None).expect("plan").map;
    let (app, placement) = replica(&map, "mcapi-1");

    let mut ids = Vec::new();
    for _ in 0..20 {
        let (status, headers, body) = send(&app, "POST", "/v1/sessions", Some(HALLWAY)).await;
        assert_eq!(status, StatusCode::CREATED, "{body}");
        assert_eq!(headers["x-mcapi-replica"], "mcapi-1");
        let id = body["id"].as_str().expect("id").to_string();
        assert_eq!(
            map.owner(shard_of_id(&id).expect("shard")).as_str(),
            "mcapi-1"
        );
        ids.push(id);
    }

    // A foreign shard: 421 naming its owner, before any lookup.
    let foreign = format!(
        "{}.01JDX4AAAAAAAAAAAAAAAAAAAA",
        shard_key(map.shards_of(&names[0])[0])
    );
    let (status, headers, body) = send(&app, "GET", &format!("/v1/sessions/{foreign}"), None).await;
    assert_eq!(status, StatusCode::MISDIRECTED_REQUEST, "{body}");
    assert_eq!(body["code"], "wrong_replica");
    assert_eq!(headers["x-mcapi-owner"], "mcapi-0");
    assert_eq!(headers["x-mcapi-replica"], "mcapi-1");
    let (status, _, _) = send(
        &app,
        "POST",
        &format!("/v1/sessions/{foreign}/observations"),
        Some(r#"{"state": 1}"#),
    )
    .await;
    assert_eq!(status, StatusCode::MISDIRECTED_REQUEST);
    let (status, _, _) = send(&app, "DELETE", &format!("/v1/sessions/{foreign}"), None).await;
    assert_eq!(status, StatusCode::MISDIRECTED_REQUEST);

    // A well-formed id beyond the shard count is no shard at all: 404 on
    // every route, as on a single node (it once indexed the map out of
    // bounds: a 500 and a backtrace per request).
    for beyond in ["s0400", "sffff"] {
        let id = format!("{beyond}.01JDX4AAAAAAAAAAAAAAAAAAAA");
        for (method, uri, body) in [
            ("GET", format!("/v1/sessions/{id}"), None),
            ("GET", format!("/v1/sessions/{id}/values"), None),
            (
                "POST",
                format!("/v1/sessions/{id}/observations"),
                Some(r#"{"state": 1}"#),
            ),
            ("DELETE", format!("/v1/sessions/{id}"), None),
        ] {
            let (status, _, reply) = send(&app, method, &uri, body).await;
            assert_eq!(status, StatusCode::NOT_FOUND, "{method} {uri}: {reply}");
            assert_eq!(reply["code"], "not_found");
        }
    }

    // A frozen shard: 503 with Retry-After; nothing is minted there.
    let shard = shard_of_id(&ids[0]).expect("shard");
    placement.set_state(shard, ShardState::Frozen);
    let (status, headers, body) =
        send(&app, "GET", &format!("/v1/sessions/{}", ids[0]), None).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(body["code"], "shard_moving");
    assert_eq!(headers["retry-after"], "1");
    for _ in 0..20 {
        let (status, _, body) = send(&app, "POST", "/v1/sessions", Some(HALLWAY)).await;
        assert_eq!(status, StatusCode::CREATED);
        assert_ne!(shard_of_id(body["id"].as_str().expect("id")), Some(shard));
    }
    placement.set_state(shard, ShardState::Owned);
    let (status, _, body) = send(&app, "GET", &format!("/v1/sessions/{}", ids[0]), None).await;
    assert_eq!(status, StatusCode::OK, "{body}");

    // No shard left to mint in: creates are refused, retryably.
    for s in map.shards_of(&names[1]) {
        placement.set_state(s, ShardState::Frozen);
    }
    let (status, _, body) = send(&app, "POST", "/v1/sessions", Some(HALLWAY)).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(body["code"], "unavailable");
}

#[tokio::test]
async fn a_single_node_sends_no_replica_header_and_owns_every_shard() {
    let manager = SessionManager::new(Limits::default(), 1).expect("manager");
    let app = router(AppState {
        manager: Arc::new(manager),
        metrics: None,
        serving: None,
    });
    let (status, headers, body) = send(&app, "POST", "/v1/sessions", Some(HALLWAY)).await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    assert!(headers.get("x-mcapi-replica").is_none());
    let (status, _, _) = send(
        &app,
        "GET",
        "/v1/sessions/s03ff.01JDX4AAAAAAAAAAAAAAAAAAAA",
        None,
    )
    .await;
    assert_eq!(status, StatusCode::NOT_FOUND);
}

#[test]
fn grpc_refusals_carry_the_owner() {
    let status = to_status(ServiceError::WrongReplica(mcapi_shards::WrongReplica {
        id: "s0001.x".into(),
        shard: "s0001".into(),
        owner: "mcapi-2".into(),
        replica: "mcapi-0".into(),
        epoch: 4,
    }));
    assert_eq!(status.code(), tonic::Code::Unavailable);
    assert_eq!(
        status
            .metadata()
            .get("x-mcapi-owner")
            .map(|v| v.to_str().ok()),
        Some(Some("mcapi-2"))
    );
    assert!(status.message().contains("epoch 4"), "{}", status.message());
    let frozen = to_status(ServiceError::ShardFrozen(mcapi_shards::ShardFrozen {
        shard: "s0001".into(),
        retry_after_secs: 1,
    }));
    assert_eq!(frozen.code(), tonic::Code::Unavailable);
    assert_eq!(
        frozen
            .metadata()
            .get("x-mcapi-error-code")
            .map(|v| v.to_str().ok()),
        Some(Some("shard_moving"))
    );
}
