//! REST calls with an optional API key: the raw request, and creating,
//! getting and listing hallway sessions.

use std::time::Duration;

use serde_json::{Value, json};

use crate::hallway::ACTIONS;

/// A fresh HTTP client (no connections pooled from an earlier server).
pub fn http_client() -> reqwest::Client {
    reqwest::Client::builder()
        .timeout(Duration::from_secs(30))
        .build()
        .expect("http client")
}

/// A REST request with an optional API key; returns status and JSON body
/// (Null when the body is not JSON).
pub async fn rest(
    client: &reqwest::Client,
    method: reqwest::Method,
    url: &str,
    key: Option<&str>,
    body: Option<&Value>,
) -> (u16, Value) {
    let mut req = client.request(method, url);
    if let Some(k) = key {
        req = req.bearer_auth(k);
    }
    if let Some(b) = body {
        req = req.json(b);
    }
    let resp = req.send().await.expect("request");
    let status = resp.status().as_u16();
    let text = resp.text().await.expect("body");
    (status, serde_json::from_str(&text).unwrap_or(Value::Null))
}

/// Creates a hallway session over REST; returns its id.
pub async fn rest_create(
    client: &reqwest::Client,
    base: &str,
    key: Option<&str>,
    agent: Value,
) -> String {
    let (status, body) = rest(
        client,
        reqwest::Method::POST,
        &format!("{base}/v1/sessions"),
        key,
        Some(&json!({"model": {"preset": "hallway"}, "agent": agent})),
    )
    .await;
    assert_eq!(status, 201, "create: {body}");
    assert_eq!(body["model"]["actions"], json!(ACTIONS), "hallway actions");
    body["id"].as_str().expect("id").to_string()
}

/// GET a session: (status, body).
pub async fn rest_get(
    client: &reqwest::Client,
    base: &str,
    key: Option<&str>,
    id: &str,
) -> (u16, Value) {
    rest(
        client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{id}"),
        key,
        None,
    )
    .await
}

/// Every session id the key lists, following `next` (pages of 3, so paging
/// is exercised).
pub async fn rest_list_all(client: &reqwest::Client, base: &str, key: Option<&str>) -> Vec<String> {
    let mut ids = Vec::new();
    let mut after: Option<String> = None;
    loop {
        let url = match &after {
            Some(a) => format!("{base}/v1/sessions?limit=3&after={a}"),
            None => format!("{base}/v1/sessions?limit=3"),
        };
        let (status, body) = rest(client, reqwest::Method::GET, &url, key, None).await;
        assert_eq!(status, 200, "list: {body}");
        for s in body["sessions"].as_array().expect("sessions") {
            ids.push(s["id"].as_str().expect("id").to_string());
        }
        match body["next"].as_str() {
            Some(n) => after = Some(n.to_string()),
            None => return ids,
        }
    }
}
