//! The dashboard over a real socket: the page and its assets (content
//! types, caching), the grid layout in the model summary, and the
//! server-sent-events stream of a session (`GET /v1/sessions/{id}/events`):
//! its `session`, `tick`, `values` and `end` events, API keys, bad
//! intervals, and a server shutdown with streams open. The page itself is
//! tested in a browser by `tests/e2e`.

use crate::common;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use mcapi_core::model::{Preset, three_room};
use mcapi_server::api::{AppState, router};
use mcapi_server::service::{ApiKeys, Limits, ManagerOptions, SessionManager};
use serde_json::{Value, json};

const KEY_A: &str = "dashboard-key-a-0123456789";
const KEY_B: &str = "dashboard-key-b-0123456789";

async fn start(keys: &[&str]) -> String {
    let mut options = ManagerOptions::new(Limits::default(), 2);
    options.keys = ApiKeys::new(keys.iter().copied());
    let manager = Arc::new(SessionManager::with_options(options).expect("manager"));
    let state = AppState {
        manager,
        metrics: None,
        serving: None,
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr: SocketAddr = listener.local_addr().expect("addr");
    tokio::spawn(async move { axum::serve(listener, router(state)).await.expect("serve") });
    format!("http://{addr}")
}

fn client() -> reqwest::Client {
    reqwest::Client::builder()
        .timeout(Duration::from_secs(60))
        .build()
        .expect("client")
}

fn with_key(req: reqwest::RequestBuilder, key: Option<&str>) -> reqwest::RequestBuilder {
    match key {
        Some(k) => req.bearer_auth(k),
        None => req,
    }
}

async fn create(client: &reqwest::Client, base: &str, key: Option<&str>, model: Value) -> Value {
    let resp = with_key(client.post(format!("{base}/v1/sessions")), key)
        .json(&json!({"model": model, "agent": {"seed": 3}}))
        .send()
        .await
        .expect("create");
    assert_eq!(resp.status(), 201);
    resp.json().await.expect("json")
}

/// The three-room maze simulated on the client side.
struct Maze {
    preset: Preset,
    state: usize,
    action: Option<usize>,
}

impl Maze {
    fn new() -> Self {
        Self {
            preset: three_room(),
            state: 5,
            action: None,
        }
    }

    /// Sends `n` observations; returns the tick of the last reply.
    async fn drive(
        &mut self,
        client: &reqwest::Client,
        url: &str,
        key: Option<&str>,
        n: usize,
    ) -> u64 {
        let mut tick = 0;
        for _ in 0..n {
            let body = match self.action {
                None => json!({"state": self.state}),
                Some(a) => {
                    let model = &self.preset.model;
                    let pair = model
                        .pair(self.state, a)
                        .expect("advised actions are available");
                    self.state = model.next_state(pair);
                    let mut xi = vec![0.0; 3];
                    for source in &self.preset.sources {
                        if source.state == self.state {
                            xi[source.dim] = 6.0;
                        }
                    }
                    json!({"state": self.state, "stimulus": xi})
                }
            };
            let resp = with_key(client.post(url), key)
                .json(&body)
                .send()
                .await
                .expect("observe");
            assert_eq!(resp.status(), 200);
            let step: Value = resp.json().await.expect("step");
            self.action = Some(step["action_index"].as_u64().expect("action") as usize);
            tick = step["tick"].as_u64().expect("tick");
        }
        tick
    }
}

/// One server-sent event.
#[derive(Debug, Clone)]
struct Sse {
    event: String,
    data: Value,
}

/// Reads server-sent events from a streaming response.
struct EventReader {
    resp: reqwest::Response,
    buf: String,
}

impl EventReader {
    /// The next event, `None` when the stream ended; fails after 20 s.
    async fn next(&mut self) -> Option<Sse> {
        loop {
            if let Some(cut) = self.buf.find("\n\n") {
                let block: String = self.buf.drain(..cut + 2).collect();
                let mut event = "message".to_string();
                let mut data = Vec::new();
                for line in block.lines() {
                    if let Some(v) = line.strip_prefix("event:") {
                        event = v.trim().to_string();
                    } else if let Some(v) = line.strip_prefix("data:") {
                        data.push(v.strip_prefix(' ').unwrap_or(v).to_string());
                    }
                }
                if data.is_empty() {
                    continue; // a keep-alive comment
                }
                let data = serde_json::from_str(&data.join("\n")).expect("event data is JSON");
                return Some(Sse { event, data });
            }
            let chunk = tokio::time::timeout(Duration::from_secs(20), self.resp.chunk())
                .await
                .expect("an event within 20 s")
                .expect("stream readable")?;
            self.buf
                .push_str(std::str::from_utf8(&chunk).expect("UTF-8"));
        }
    }

    /// Events until one of type `event` (returned last).
    async fn until(&mut self, event: &str) -> Vec<Sse> {
        let mut seen = Vec::new();
        loop {
            let e = self.next().await.expect("the stream goes on");
            let done = e.event == event;
            seen.push(e);
            if done {
                return seen;
            }
        }
    }
}

async fn open_events(
    client: &reqwest::Client,
    base: &str,
    id: &str,
    query: &str,
    key: Option<&str>,
) -> reqwest::Response {
    with_key(
        client.get(format!("{base}/v1/sessions/{id}/events{query}")),
        key,
    )
    .send()
    .await
    .expect("events request")
}

fn ticks(events: &[Sse]) -> Vec<u64> {
    events
        .iter()
        .filter(|e| e.event == "tick")
        .map(|e| e.data["tick"].as_u64().expect("tick"))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_and_its_assets_are_served_with_content_types_and_etags() {
    let base = start(&[]).await;
    let client = client();
    let cases = [
        ("/", "text/html; charset=utf-8", "/assets/app.js"),
        (
            "/assets/app.js",
            "text/javascript; charset=utf-8",
            "/events",
        ),
        ("/assets/app.css", "text/css; charset=utf-8", ".charts"),
        (
            "/assets/uplot.iife.min.js",
            "text/javascript; charset=utf-8",
            "uPlot (v1.6.32)",
        ),
        ("/assets/uplot.min.css", "text/css; charset=utf-8", ".uplot"),
        ("/assets/LICENSE-uPlot", "text/plain; charset=utf-8", "MIT"),
    ];
    for (path, content_type, needle) in cases {
        let resp = client
            .get(format!("{base}{path}"))
            .send()
            .await
            .expect("get");
        assert_eq!(resp.status(), 200, "{path}");
        let headers = resp.headers().clone();
        assert_eq!(headers["content-type"], content_type, "{path}");
        assert_eq!(headers["cache-control"], "no-cache", "{path}");
        assert_eq!(headers["x-content-type-options"], "nosniff", "{path}");
        let etag = headers["etag"].to_str().expect("etag").to_string();
        assert!(etag.starts_with('"') && etag.len() == 18, "{path}: {etag}");
        let body = resp.text().await.expect("body");
        assert!(body.contains(needle), "{path} lacks {needle}");
        // Unchanged: 304 without a body.
        let again = client
            .get(format!("{base}{path}"))
            .header("if-none-match", &etag)
            .send()
            .await
            .expect("revalidate");
        assert_eq!(again.status(), 304, "{path}");
        assert_eq!(again.headers()["etag"], etag.as_str());
        assert!(again.bytes().await.expect("body").is_empty());
    }
    // The page needs no key, even when the API does.
    let keyed = start(&[KEY_A]).await;
    let resp = client.get(format!("{keyed}/")).send().await.expect("get");
    assert_eq!(resp.status(), 200);
    assert!(
        resp.headers()["content-security-policy"]
            .to_str()
            .expect("csp")
            .contains("default-src 'self'")
    );
    let resp = client
        .get(format!("{base}/assets/nope.js"))
        .send()
        .await
        .expect("get");
    assert_eq!(resp.status(), 404);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grid_models_carry_their_layout_and_others_none() {
    let base = start(&[]).await;
    let client = client();
    let maze = create(&client, &base, None, json!({"preset": "three_room"})).await;
    let layout = &maze["model"]["layout"];
    assert_eq!(layout["rows"], 11);
    assert_eq!(layout["cols"], 26);
    let cells = layout["cells"].as_array().expect("cells");
    assert_eq!(cells.len(), 200);
    let grid = three_room().grid.expect("a grid preset");
    for (s, cell) in cells.iter().enumerate() {
        let (r, c) = grid.cell_of(s);
        assert_eq!(cell, &json!([r, c]), "state {s}");
    }
    let marks: Vec<&str> = layout["marks"]
        .as_array()
        .expect("marks")
        .iter()
        .map(|m| m["mark"].as_str().expect("mark"))
        .collect();
    assert_eq!(marks, ["c", "a", "b"], "row-major order");
    assert_eq!(
        layout["marks"][1]["state"],
        grid.mark_state('a').expect("a")
    );

    let small = create(
        &client,
        &base,
        None,
        json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1}}),
    )
    .await;
    assert_eq!(
        small["model"]["layout"],
        json!({"rows": 3, "cols": 5, "cells": [[1, 1], [1, 2], [1, 3]],
               "marks": [{"mark": "a", "state": 0}, {"mark": "b", "state": 2}]})
    );
    let hallway = create(&client, &base, None, json!({"preset": "hallway"})).await;
    assert!(hallway["model"].get("layout").is_none(), "{hallway}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_stream_sessions_ticks_values_and_ends_when_deleted() {
    let base = start(&[]).await;
    let client = client();
    let info = create(&client, &base, None, json!({"preset": "three_room"})).await;
    let id = info["id"].as_str().expect("id").to_string();
    let url = format!("{base}/v1/sessions/{id}/observations");
    let mut maze = Maze::new();
    let tick = maze.drive(&client, &url, None, 21).await;
    assert_eq!(tick, 20);

    let resp = open_events(&client, &base, &id, "?interval_ms=50", None).await;
    assert_eq!(resp.status(), 200);
    assert_eq!(resp.headers()["content-type"], "text/event-stream");
    let mut events = EventReader {
        resp,
        buf: String::new(),
    };
    // First the session, then its kept history, then the values.
    let first = events.next().await.expect("session event");
    assert_eq!(first.event, "session");
    assert_eq!(first.data["id"], id.as_str());
    assert_eq!(first.data["tick"], 20);
    assert_eq!(first.data["model"]["layout"]["rows"], 11);
    let backlog = events.until("values").await;
    assert_eq!(ticks(&backlog), (1..=20).collect::<Vec<u64>>());
    let entry = &backlog[0].data;
    for field in [
        "state",
        "action",
        "drive",
        "reward",
        "lstdq_error",
        "stimulus",
    ] {
        assert!(
            entry.get(field).is_some(),
            "tick event lacks {field}: {entry}"
        );
    }
    // The stimulus the page sums: 6 on arrival at a source, else 0.
    for e in backlog.iter().filter(|e| e.event == "tick") {
        let xi = e.data["stimulus"].as_array().expect("stimulus");
        assert_eq!(xi.len(), 3, "{}", e.data);
        assert!(xi.iter().all(|x| x == 0.0 || x == 6.0), "{}", e.data);
    }
    let values = &backlog.last().expect("values").data;
    assert_eq!(values["v"].as_array().expect("v").len(), 200);
    assert_eq!(values["policy"].as_array().expect("policy").len(), 200);
    assert!(values.get("q").is_none(), "only V and the policy");
    let version = values["policy_version"].as_u64().expect("version");
    assert!(version > 0);

    // New observations: one tick event each, in order, and new values.
    let tick = maze.drive(&client, &url, None, 15).await;
    assert_eq!(tick, 35);
    let mut seen = Vec::new();
    let mut newer_values = None;
    while seen.last() != Some(&35) || newer_values.is_none() {
        let e = events.next().await.expect("more events");
        match e.event.as_str() {
            "tick" => seen.push(e.data["tick"].as_u64().expect("tick")),
            "values" => newer_values = Some(e.data["policy_version"].as_u64().expect("v")),
            other => panic!("unexpected {other} event: {:?}", e.data),
        }
    }
    assert_eq!(seen, (21..=35).collect::<Vec<u64>>());
    assert!(newer_values.expect("values") > version);

    // Deleted: an `end` event, then the stream closes.
    let resp = client
        .delete(format!("{base}/v1/sessions/{id}"))
        .send()
        .await
        .expect("delete");
    assert_eq!(resp.status(), 204);
    let rest = events.until("end").await;
    let end = rest.last().expect("end");
    assert_eq!(end.data, json!({"id": id, "reason": "deleted"}));
    assert!(
        events.next().await.is_none(),
        "the stream closes after `end`"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_of_a_session_without_ticks_start_with_session_and_values() {
    let base = start(&[]).await;
    let client = client();
    let info = create(&client, &base, None, json!({"preset": "hallway"})).await;
    let id = info["id"].as_str().expect("id");
    let resp = open_events(&client, &base, id, "", None).await;
    assert_eq!(resp.status(), 200);
    let mut events = EventReader {
        resp,
        buf: String::new(),
    };
    assert_eq!(events.next().await.expect("session").event, "session");
    let values = events.next().await.expect("values");
    assert_eq!(values.event, "values");
    assert_eq!(values.data["tick"], 0);
    assert_eq!(values.data["v"].as_array().expect("v").len(), 50);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_honour_api_keys() {
    let base = start(&[KEY_A, KEY_B]).await;
    let client = client();
    let info = create(&client, &base, Some(KEY_A), json!({"preset": "three_room"})).await;
    let id = info["id"].as_str().expect("id");

    let resp = open_events(&client, &base, id, "", None).await;
    assert_eq!(resp.status(), 401);
    assert_eq!(resp.headers()["www-authenticate"], "Bearer realm=\"mcapi\"");
    let body: Value = resp.json().await.expect("json");
    assert_eq!(body["code"], "unauthenticated");

    let resp = open_events(&client, &base, id, "", Some("not-a-key-of-this-server")).await;
    assert_eq!(resp.status(), 401);

    // Another key's session is exactly a missing one.
    let resp = open_events(&client, &base, id, "", Some(KEY_B)).await;
    assert_eq!(resp.status(), 404);
    let body: Value = resp.json().await.expect("json");
    assert_eq!(body["code"], "not_found");

    let resp = open_events(&client, &base, id, "", Some(KEY_A)).await;
    assert_eq!(resp.status(), 200);
    let mut events = EventReader {
        resp,
        buf: String::new(),
    };
    assert_eq!(events.next().await.expect("session").event, "session");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_queries_and_unknown_sessions_get_precise_errors() {
    let base = start(&[]).await;
    let client = client();
    let info = create(&client, &base, None, json!({"preset": "hallway"})).await;
    let id = info["id"].as_str().expect("id");
    for (query, needle) in [
        (
            "?interval_ms=49",
            "`interval_ms`: is 49; must be between 50 and 10000",
        ),
        (
            "?interval_ms=10001",
            "`interval_ms`: is 10001; must be between 50 and 10000",
        ),
        ("?interval_ms=fast", "bad query string"),
        ("?interval=100", "bad query string"),
    ] {
        let resp = open_events(&client, &base, id, query, None).await;
        assert_eq!(resp.status(), 400, "{query}");
        let body: Value = resp.json().await.expect("json");
        assert_eq!(body["code"], "bad_request", "{query}");
        let message = body["message"].as_str().expect("message");
        assert!(message.contains(needle), "{query}: {message}");
    }
    for ok in ["?interval_ms=50", "?interval_ms=10000"] {
        let resp = open_events(&client, &base, id, ok, None).await;
        assert_eq!(resp.status(), 200, "{ok}");
    }
    let resp = open_events(&client, &base, "s0000.01JDNOSUCHSESSION000000000", "", None).await;
    assert_eq!(resp.status(), 404);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_openapi_document_describes_the_events_stream() {
    let base = start(&[]).await;
    let doc: Value = client()
        .get(format!("{base}/v1/openapi.json"))
        .send()
        .await
        .expect("get")
        .json()
        .await
        .expect("json");
    let op = &doc["paths"]["/v1/sessions/{id}/events"]["get"];
    assert!(op.is_object(), "no events path: {}", doc["paths"]);
    assert!(
        op["responses"]["200"]["content"]["text/event-stream"].is_object(),
        "{op}"
    );
    let params: Vec<&str> = op["parameters"]
        .as_array()
        .expect("parameters")
        .iter()
        .map(|p| p["name"].as_str().expect("name"))
        .collect();
    assert!(params.contains(&"interval_ms"), "{params:?}");
    // The model summary documents the layout.
    assert!(
        doc["components"]["schemas"]["GridLayout"].is_object(),
        "{}",
        doc["components"]["schemas"]
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn open_streams_end_when_the_server_stops() {
    let dir = tempfile::tempdir().expect("tempdir");
    let launch = common::Launch::new(dir.path(), &["--store", "memory"]);
    let mut server = common::Server::start(&launch, dir.path().join("serve.log")).await;
    let base = server.base();
    let client = client();
    let info = create(&client, &base, None, json!({"preset": "hallway"})).await;
    let id = info["id"].as_str().expect("id");
    let resp = open_events(&client, &base, id, "", None).await;
    assert_eq!(resp.status(), 200);
    let mut events = EventReader {
        resp,
        buf: String::new(),
    };
    assert_eq!(events.next().await.expect("session").event, "session");
    // A graceful shutdown waits for in-flight responses; the stream must
    // not hold it up.
    let stopped = tokio::task::spawn_blocking(move || {
        let status = server.terminate();
        (status, server.log_text())
    });
    while let Some(e) = events.next().await {
        assert_eq!(e.event, "values", "only the first values may still come");
    }
    let (status, log) = stopped.await.expect("join");
    assert!(status.success(), "exit {status}; log:\n{log}");
}
