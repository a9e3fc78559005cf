//! The battery's tools: its API key and memory budget, the REST and gRPC
//! calls that check each hostile request's refusal and that the server is
//! still alive after it, and the bodies they send.

use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use reqwest::Method;
use serde_json::{Value, json};
use tonic::transport::Channel;
use tonic::{Code, Request, Status};

/// The battery's API key.
pub(super) const KEY: &str = "hostile-battery-key-000000000001";

/// Peak resident memory the server may reach during the battery: the
/// sessions it holds are bounded by `--max-key-bytes` below; the rest is
/// the runtime, the largest request bodies in flight (16 MiB, and the JSON
/// value parsed from one) and allocator slack.
pub(super) const RSS_BUDGET_BYTES: u64 = 384 << 20;

/// What a REST request carries.
pub(super) enum Body {
    None,
    Json(Value),
    Raw(Vec<u8>, &'static str),
}

pub(super) struct Battery {
    pub(super) client: reqwest::Client,
    pub(super) base: String,
    pub(super) pid: u32,
    pub(super) cases: usize,
    pub(super) grpc: AgentsClient<Channel>,
}

pub(super) fn big(n: usize) -> String {
    "x".repeat(n)
}

impl Battery {
    pub(super) async fn alive(&self, after: &str) {
        let resp = self
            .client
            .get(format!("{}/healthz", self.base))
            .send()
            .await
            .unwrap_or_else(|e| panic!("the server is gone after `{after}`: {e}"));
        assert_eq!(resp.status(), 200, "healthz after `{after}`");
    }

    /// Sends one request with the key (or `key`) and checks the status and
    /// the stable code of its `{"code","message"}` body.
    #[expect(
        clippy::too_many_arguments,
        reason = "a test helper: every part of the request and the expected answer, named at each call"
    )]
    pub(super) async fn rest_with(
        &mut self,
        name: &str,
        key: Option<&str>,
        method: Method,
        path: &str,
        body: Body,
        status: u16,
        code: &str,
    ) -> Value {
        let mut req = self.client.request(method, format!("{}{path}", self.base));
        if let Some(k) = key {
            req = req.bearer_auth(k);
        }
        req = match body {
            Body::None => req,
            Body::Json(v) => req.json(&v),
            Body::Raw(bytes, content_type) => req
                .header(reqwest::header::CONTENT_TYPE, content_type)
                .body(bytes),
        };
        let resp = req
            .send()
            .await
            .unwrap_or_else(|e| panic!("`{name}`: no answer: {e}"));
        let got = resp.status().as_u16();
        let text = resp.text().await.unwrap_or_default();
        let json: Value = serde_json::from_str(&text).unwrap_or(Value::Null);
        let shown: String = text.chars().take(300).collect();
        assert_eq!(got, status, "`{name}`: status; body: {shown}");
        if !code.is_empty() {
            assert_eq!(json["code"], code, "`{name}`: code; body: {shown}");
            assert!(
                json["message"].as_str().is_some_and(|m| !m.is_empty()),
                "`{name}`: a message; body: {shown}"
            );
        }
        if status >= 400 {
            self.cases += 1;
        }
        self.alive(name).await;
        json
    }

    pub(super) async fn rest(
        &mut self,
        name: &str,
        method: Method,
        path: &str,
        body: Body,
        status: u16,
        code: &str,
    ) -> Value {
        self.rest_with(name, Some(KEY), method, path, body, status, code)
            .await
    }

    /// A create with `body` must be refused with `status` and `code`.
    pub(super) async fn create(&mut self, name: &str, body: Value, status: u16, code: &str) {
        self.rest(
            name,
            Method::POST,
            "/v1/sessions",
            Body::Json(body),
            status,
            code,
        )
        .await;
    }

    /// A gRPC result must be this status, with this stable code.
    pub(super) async fn grpc<T: std::fmt::Debug>(
        &mut self,
        name: &str,
        result: Result<T, Status>,
        code: Code,
        stable: &str,
    ) {
        let status = match result {
            Ok(v) => panic!("`{name}`: expected {code:?}, got {v:?}"),
            Err(s) => s,
        };
        assert_eq!(status.code(), code, "`{name}`: {status:?}");
        if !stable.is_empty() {
            let got = status
                .metadata()
                .get("x-mcapi-error-code")
                .and_then(|v| v.to_str().ok());
            assert_eq!(got, Some(stable), "`{name}`: stable code of {status:?}");
        }
        self.cases += 1;
        self.alive(name).await;
    }

    pub(super) fn rss(&self, field: &str) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.pid))
            .expect("the server's /proc status");
        status
            .lines()
            .find_map(|l| l.strip_prefix(field))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            .map_or(0, |kb| kb * 1024)
    }
}

pub(super) fn authed<T>(message: T) -> Request<T> {
    let mut req = Request::new(message);
    req.metadata_mut().insert(
        "authorization",
        format!("Bearer {KEY}").parse().expect("ascii"),
    );
    req
}

pub(super) fn chain(states: usize) -> Value {
    let next: Vec<[usize; 2]> = (0..states)
        .map(|s| [s.saturating_sub(1), (s + 1).min(states - 1)])
        .collect();
    json!({"states": states, "actions": ["left", "right"], "stimuli": ["a", "b"], "next": next})
}
