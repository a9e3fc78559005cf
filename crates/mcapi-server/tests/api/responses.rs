//! The total memory of value and history responses in flight
//! (`--max-response-bytes-total`): a response holds its estimate until it
//! is sent, one that does not fit gets 503 `responses_busy` with
//! `Retry-After` (gRPC: UNAVAILABLE), and the budget comes back when the
//! response is sent or its client goes away.

use std::sync::Arc;
use std::time::{Duration, Instant};

use mcapi_server::service::auth::Caller;
use mcapi_server::service::budget;
use mcapi_server::service::{Limits, SessionManager, ValueSelection};
use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

const TOTAL: usize = 24 << 20;

async fn start(limits: Limits) -> (Arc<SessionManager>, std::net::SocketAddr) {
    crate::serve_rest(limits).await
}

/// A 200 × 100 open grid, on a one-feature custom basis (cheap to build):
/// about 8.7 MB of JSON for `include=all`, twice that charged.
fn big_grid() -> Value {
    let mut rows = vec!["#".repeat(202)];
    let mut inner = format!("#a{}#", ".".repeat(199));
    rows.push(inner.clone());
    inner = format!("#{}#", ".".repeat(200));
    rows.extend(std::iter::repeat_n(inner, 98));
    rows.push(format!("#{}b#", ".".repeat(199)));
    rows.push("#".repeat(202));
    let features = vec![[1.0]; 200 * 100];
    json!({"grid": rows, "sources": {"a": 0, "b": 1},
           "basis": {"kind": "custom", "state_features": features}})
}

async fn get(client: &reqwest::Client, url: &str) -> (u16, Option<String>, Vec<u8>) {
    let r = client.get(url).send().await.expect("request");
    let status = r.status().as_u16();
    let retry = r
        .headers()
        .get("retry-after")
        .map(|v| v.to_str().expect("ascii").to_string());
    (status, retry, r.bytes().await.expect("body").to_vec())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_reader_holds_its_share_and_the_next_large_response_waits_its_turn() {
    let (manager, addr) = start(Limits {
        max_response_bytes: TOTAL,
        max_response_bytes_total: TOTAL,
        ..Limits::default()
    })
    .await;
    let base = format!("http://{addr}");
    let client = reqwest::Client::new();
    let created: Value = client
        .post(format!("{base}/v1/sessions"))
        .json(&json!({"model": big_grid()}))
        .send()
        .await
        .expect("create")
        .json()
        .await
        .expect("json");
    let id = created["id"]
        .as_str()
        .unwrap_or_else(|| panic!("created: {created}"))
        .to_string();
    let info = manager.get(Caller::Anyone, &id).expect("session");
    let all = ValueSelection::parse(Some("all")).expect("all");
    let estimate = all.check_size(&info.model, usize::MAX).expect("estimate");
    let charge = budget::charge(estimate);
    assert!(
        charge > TOTAL / 2 && charge <= TOTAL,
        "the test needs one `include=all` response to fit the budget and two not to: {estimate} bytes, {charge} charged"
    );

    // A client that asks for every table and reads nothing past the first
    // bytes, on a small receive buffer: the response cannot be sent.
    let socket = tokio::net::TcpSocket::new_v4().expect("socket");
    socket.set_recv_buffer_size(4096).expect("rcvbuf");
    let mut slow = socket.connect(addr).await.expect("connect");
    slow.write_all(
        format!("GET /v1/sessions/{id}/values?include=all HTTP/1.1\r\nhost: x\r\n\r\n").as_bytes(),
    )
    .await
    .expect("send");
    let mut head = [0u8; 12];
    slow.read_exact(&mut head).await.expect("status line");
    assert_eq!(&head, b"HTTP/1.1 200");
    assert!(manager.responses().held_bytes() >= charge);

    // The same response for another client does not fit now: 503 with
    // Retry-After, on both transports, and nothing is built for it.
    let url = format!("{base}/v1/sessions/{id}/values?include=all");
    let (status, retry, body) = get(&client, &url).await;
    assert_eq!(status, 503, "{}", String::from_utf8_lossy(&body));
    assert_eq!(retry.as_deref(), Some("1"));
    let body: Value = serde_json::from_slice(&body).expect("error body");
    assert_eq!(body["code"], "responses_busy");
    assert!(
        body["message"]
            .as_str()
            .is_some_and(|m| m.contains("--max-response-bytes-total")),
        "{body}"
    );
    // A small response still fits beside it.
    let (status, _, _) = get(
        &client,
        &format!("{base}/v1/sessions/{id}/values?include=v"),
    )
    .await;
    assert_eq!(status, 200);
    let (status, _, _) = get(&client, &format!("{base}/v1/sessions/{id}/history")).await;
    assert_eq!(status, 200);

    // The slow client goes away: its share comes back, and the large
    // response is served again.
    drop(slow);
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let (status, _, body) = get(&client, &url).await;
        if status == 200 {
            assert!(body.len() > estimate / 4, "{} bytes", body.len());
            break;
        }
        assert_eq!(status, 503);
        assert!(Instant::now() < deadline, "the budget never came back");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let deadline = Instant::now() + Duration::from_secs(5);
    while manager.responses().held_bytes() != 0 {
        assert!(Instant::now() < deadline, "a sent response kept its share");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_budget_is_unavailable_over_grpc_too() {
    use mcapi_server::api::grpc::pb::{self, agents_client::AgentsClient};

    let manager = Arc::new(
        SessionManager::new(
            Limits {
                max_response_bytes: 1 << 20,
                max_response_bytes_total: 1 << 20,
                ..Limits::default()
            },
            2,
        )
        .expect("manager"),
    );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("addr");
    let served = Arc::clone(&manager);
    tokio::spawn(mcapi_server::api::grpc::serve_on(
        listener,
        served,
        8,
        std::future::pending(),
    ));
    let mut client = AgentsClient::connect(format!("http://{addr}"))
        .await
        .expect("connect");
    let id = client
        .create_session(pb::CreateSessionRequest {
            model: Some(pb::Model::preset("hallway")),
            ..Default::default()
        })
        .await
        .expect("create")
        .into_inner()
        .id;
    let held = manager
        .responses()
        .reserve(1 << 20)
        .expect("the whole budget");
    for result in [
        client
            .get_values(pb::GetValuesRequest {
                session_id: id.clone(),
                ..Default::default()
            })
            .await
            .map(drop),
        client
            .get_history(pb::GetHistoryRequest {
                session_id: id.clone(),
                ..Default::default()
            })
            .await
            .map(drop),
    ] {
        let status = result.expect_err("no room");
        assert_eq!(status.code(), tonic::Code::Unavailable, "{status:?}");
        assert_eq!(
            status
                .metadata()
                .get("x-mcapi-error-code")
                .map(|v| v.to_str().expect("ascii")),
            Some("responses_busy")
        );
        assert_eq!(
            status
                .metadata()
                .get("retry-after")
                .map(|v| v.to_str().expect("ascii")),
            Some("1")
        );
    }
    drop(held);
    client
        .get_values(pb::GetValuesRequest {
            session_id: id,
            ..Default::default()
        })
        .await
        .expect("served once the budget is back");
    assert_eq!(manager.responses().held_bytes(), 0);
}
