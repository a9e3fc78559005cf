//! Connections are bounded (docs/limits.md), over real sockets against the
//! real binary: slow-loris connections are closed after the header-read
//! timeout, connections beyond `--max-connections` wait for a slot, slow
//! requests get `request_timeout`, watch streams per key are limited over
//! both transports, an unauthenticated 16 MiB `Observe` is refused without
//! the server's memory growing, oversized `Observe` batches and `Interact`
//! messages are refused before decoding, the request metric's labels stay
//! bounded; and (in process) a panicking handler answers 500 / INTERNAL
//! for its own request alone.

use crate::common;

use std::collections::BTreeSet;
use std::convert::Infallible;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use common::{Launch, Server, grpc_request, rest, rest_create};
use mcapi_server::api::grpc::pb;
use mcapi_testkit::time_to_close;
use prost::bytes::{Buf, BufMut, Bytes};
use serde_json::{Value, json};
use tonic::Code;
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::codegen::http::uri::PathAndQuery;

const KEY_A: &str = "connections-key-a-0123456789";
const KEY_B: &str = "connections-key-b-0123456789";

async fn start(args: &[&str]) -> (Server, tempfile::TempDir) {
    let data = tempfile::tempdir().expect("data dir");
    let mut all = vec!["--store", "memory"];
    all.extend_from_slice(args);
    let log = data.path().join("server.log");
    let server = Server::start(&Launch::new(data.path(), &all), log).await;
    (server, data)
}

/// The bytes a raw HTTP/1.1 exchange got back until the server closed or
/// `limit` passed.
fn read_for(stream: &mut TcpStream, limit: Duration) -> String {
    let started = Instant::now();
    stream
        .set_read_timeout(Some(Duration::from_millis(100)))
        .expect("read timeout");
    let mut out = Vec::new();
    let mut buf = [0u8; 4096];
    while started.elapsed() < limit {
        match stream.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => out.extend_from_slice(&buf[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => break,
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_loris_and_idle_connections_are_closed_after_the_header_timeout() {
    let (server, _data) = start(&["--header-read-timeout-ms", "1000"]).await;
    let addr = format!("127.0.0.1:{}", server.http);

    // A request head that never ends.
    let mut loris = TcpStream::connect(&addr).expect("connect");
    loris
        .write_all(b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nX-Slow: ")
        .expect("partial head");
    let closed = time_to_close(&mut loris, Duration::from_secs(10))
        .expect("the server closes a connection whose head never completes");
    eprintln!("slow-loris REST connection closed after {closed:?}");
    assert!(
        closed >= Duration::from_millis(800) && closed < Duration::from_secs(3),
        "closed after {closed:?}, expected about 1 s"
    );

    // Nothing sent at all.
    let mut silent = TcpStream::connect(&addr).expect("connect");
    let closed = time_to_close(&mut silent, Duration::from_secs(10)).expect("closed");
    assert!(closed < Duration::from_secs(3), "silent: {closed:?}");

    // A kept-alive connection idle after its response.
    let mut idle = TcpStream::connect(&addr).expect("connect");
    idle.write_all(b"GET /healthz HTTP/1.1\r\nHost: localhost\r\n\r\n")
        .expect("request");
    let started = Instant::now();
    let got = read_for(&mut idle, Duration::from_secs(10));
    assert!(got.starts_with("HTTP/1.1 200"), "{got}");
    assert!(got.ends_with("ok"), "{got}");
    let idle_for = started.elapsed();
    assert!(
        idle_for < Duration::from_secs(3),
        "an idle kept-alive connection is closed after the timeout, not {idle_for:?}"
    );

    // gRPC: a connection that never sends the HTTP/2 preface.
    let mut grpc = TcpStream::connect(format!("127.0.0.1:{}", server.grpc)).expect("connect");
    grpc.write_all(b"PRI * HTTP/2.0\r\n")
        .expect("half a preface");
    let closed = time_to_close(&mut grpc, Duration::from_secs(10))
        .expect("the gRPC port closes a connection without a preface");
    eprintln!("gRPC connection without a preface closed after {closed:?}");
    assert!(
        closed >= Duration::from_millis(800) && closed < Duration::from_secs(3),
        "gRPC: {closed:?}"
    );
    // A real client is served as usual.
    let mut client = server.grpc_client().await;
    let list = client
        .list_sessions(pb::ListSessionsRequest::default())
        .await
        .expect("list over gRPC");
    assert!(list.into_inner().sessions.is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_beyond_the_limit_wait_for_a_slot() {
    let (server, _data) =
        start(&["--max-connections", "3", "--header-read-timeout-ms", "1500"]).await;
    let addr = format!("127.0.0.1:{}", server.http);
    let url = format!("{}/healthz", server.base());
    // With slots free, a request is answered at once.
    let started = Instant::now();
    let resp = reqwest::Client::new()
        .get(&url)
        .send()
        .await
        .expect("healthz");
    assert_eq!(resp.status(), 200);
    assert!(started.elapsed() < Duration::from_millis(1000));
    // Give the client's connection time to be closed and its slot freed.
    tokio::time::sleep(Duration::from_millis(300)).await;

    // Three idle connections take every slot; a fourth client waits in the
    // backlog until the header timeout frees one.
    let idle: Vec<TcpStream> = (0..3)
        .map(|_| TcpStream::connect(&addr).expect("connect"))
        .collect();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let started = Instant::now();
    let resp = reqwest::Client::new()
        .get(&url)
        .timeout(Duration::from_secs(10))
        .send()
        .await
        .expect("served once a slot is free");
    let waited = started.elapsed();
    eprintln!("a client beyond --max-connections waited {waited:?}");
    assert_eq!(resp.status(), 200);
    assert!(
        waited >= Duration::from_millis(900),
        "the fourth connection was served after {waited:?}, before a slot was free"
    );
    drop(idle);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_that_does_not_finish_gets_request_timeout() {
    let (server, _data) = start(&["--request-timeout-ms", "800"]).await;
    let mut slow = TcpStream::connect(format!("127.0.0.1:{}", server.http)).expect("connect");
    slow.write_all(
        b"POST /v1/sessions HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n\
          Content-Length: 1000\r\n\r\n{\"model\": ",
    )
    .expect("head and part of the body");
    let started = Instant::now();
    let got = read_for(&mut slow, Duration::from_secs(5));
    let took = started.elapsed();
    assert!(got.starts_with("HTTP/1.1 503"), "{got}");
    let body = got.split("\r\n\r\n").nth(1).unwrap_or_default();
    let body: Value = serde_json::from_str(body).expect("JSON error body");
    assert_eq!(body["code"], "request_timeout", "{body}");
    assert!(took < Duration::from_secs(3), "{took:?}");
}

/// Opens an event stream; the response (kept open) or the status and body.
async fn open_events(
    client: &reqwest::Client,
    base: &str,
    id: &str,
    key: &str,
) -> Result<reqwest::Response, (u16, Value)> {
    let resp = client
        .get(format!("{base}/v1/sessions/{id}/events?interval_ms=50"))
        .bearer_auth(key)
        .send()
        .await
        .expect("events request");
    if resp.status() == 200 {
        Ok(resp)
    } else {
        let status = resp.status().as_u16();
        let body = resp.json().await.unwrap_or(Value::Null);
        Err((status, body))
    }
}

async fn open_watch(
    server: &Server,
    key: &str,
    id: &str,
) -> Result<tonic::Streaming<pb::SessionInfo>, tonic::Status> {
    let mut client = server.grpc_client().await;
    let req = grpc_request(
        pb::WatchRequest {
            session_id: id.to_string(),
            interval_ms: 50,
        },
        Some(key),
        None,
    );
    client.watch(req).await.map(tonic::Response::into_inner)
}

fn error_code(status: &tonic::Status) -> String {
    status
        .metadata()
        .get("x-mcapi-error-code")
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default()
        .to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_streams_per_key_are_limited_over_both_transports() {
    let (server, _data) = start(&[
        "--api-key",
        KEY_A,
        "--api-key",
        KEY_B,
        "--max-streams-per-key",
        "2",
        // Streams outlive the request timeout.
        "--request-timeout-ms",
        "500",
    ])
    .await;
    let base = server.base();
    let client = common::http_client();
    let id_a = rest_create(&client, &base, Some(KEY_A), json!({"seed": 1})).await;
    let id_b = rest_create(&client, &base, Some(KEY_B), json!({"seed": 2})).await;

    let mut first = open_events(&client, &base, &id_a, KEY_A)
        .await
        .expect("first stream");
    let second = open_events(&client, &base, &id_a, KEY_A)
        .await
        .expect("second stream");
    let (status, body) = open_events(&client, &base, &id_a, KEY_A)
        .await
        .expect_err("a third stream is refused");
    assert_eq!(status, 429, "{body}");
    assert_eq!(body["code"], "too_many_streams", "{body}");
    // The budget is the key's, over both transports.
    let refused = open_watch(&server, KEY_A, &id_a)
        .await
        .expect_err("Watch counts against the same budget");
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert_eq!(error_code(&refused), "too_many_streams");
    // Another key has its own budget.
    let mut watch_b = open_watch(&server, KEY_B, &id_b)
        .await
        .expect("another key watches");
    assert!(watch_b.message().await.expect("snapshot").is_some());

    // An open stream is not cut by the request timeout.
    tokio::time::sleep(Duration::from_millis(1200)).await;
    let mut data = 0;
    let until = Instant::now() + Duration::from_secs(2);
    while data == 0 && Instant::now() < until {
        if let Some(chunk) = first.chunk().await.expect("stream still open") {
            data += chunk.len();
        }
    }
    assert!(
        data > 0,
        "the first stream goes on past the request timeout"
    );

    // Closing a stream gives its slot back.
    drop(second);
    let until = Instant::now() + Duration::from_secs(10);
    let third = loop {
        match open_events(&client, &base, &id_a, KEY_A).await {
            Ok(resp) => break resp,
            Err((429, _)) if Instant::now() < until => {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(other) => panic!("the freed slot was not given back: {other:?}"),
        }
    };
    drop((first, third));

    // gRPC Watch: the same for key B (one open already).
    let _watch_b2 = open_watch(&server, KEY_B, &id_b).await.expect("second");
    let refused = open_watch(&server, KEY_B, &id_b)
        .await
        .expect_err("third refused");
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert_eq!(error_code(&refused), "too_many_streams");
    drop(watch_b);
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        match open_watch(&server, KEY_B, &id_b).await {
            Ok(_) => break,
            Err(s) if s.code() == Code::ResourceExhausted && Instant::now() < until => {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(s) => panic!("the Watch slot was not given back: {s:?}"),
        }
    }
}

/// Sends prepared `ObserveRequest` bytes as they are and reads the reply as
/// bytes: the test builds 16 MiB messages without decoding them itself.
#[derive(Debug, Clone, Copy, Default)]
struct RawCodec;

impl Codec for RawCodec {
    type Encode = Bytes;
    type Decode = Bytes;
    type Encoder = RawCodec;
    type Decoder = RawCodec;

    fn encoder(&mut self) -> Self::Encoder {
        RawCodec
    }

    fn decoder(&mut self) -> Self::Decoder {
        RawCodec
    }
}

impl Encoder for RawCodec {
    type Item = Bytes;
    type Error = tonic::Status;

    fn encode(&mut self, item: Bytes, dst: &mut EncodeBuf<'_>) -> Result<(), tonic::Status> {
        dst.put(item);
        Ok(())
    }
}

impl Decoder for RawCodec {
    type Item = Bytes;
    type Error = tonic::Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<Bytes>, tonic::Status> {
        Ok(Some(src.copy_to_bytes(src.remaining())))
    }
}

/// An `ObserveRequest` of `n` empty observations: 2 bytes each on the wire.
fn empty_observations(n: usize) -> Bytes {
    let mut out = Vec::with_capacity(2 * n);
    for _ in 0..n {
        out.extend_from_slice(&[0x12, 0x00]);
    }
    Bytes::from(out)
}

async fn raw_observe(server: &Server, message: Bytes, key: Option<&str>) -> tonic::Status {
    let channel = tonic::transport::Channel::from_shared(server.grpc_url())
        .expect("uri")
        .connect()
        .await
        .expect("connect");
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.expect("ready");
    let req = grpc_request(message, key, None);
    let path = PathAndQuery::from_static("/mcapi.v1.Agents/Observe");
    grpc.unary::<Bytes, Bytes, _>(req, path, RawCodec)
        .await
        .expect_err("refused")
}

/// A `/proc/<pid>/status` field in KiB: `VmHWM` is the peak resident set
/// (what a decoded message costs even after it is freed), `VmRSS` the
/// current one.
fn proc_kib(pid: u32, field: &str) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("proc status");
    status
        .lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("a /proc status field")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_observe_is_refused_before_decoding() {
    let (server, _data) = start(&["--api-key", KEY_A]).await;
    let pid = server.pid();
    // The largest message the body limit lets through: 16 MiB of empty
    // observations (8 Mi entries), which used to decode to ~930 MB.
    let message = empty_observations((16 << 20) / 2 - 16);
    // Warm up the connection machinery before measuring.
    let status = raw_observe(&server, empty_observations(1), None).await;
    assert_eq!(status.code(), Code::Unauthenticated);
    let (rss0, peak0) = (proc_kib(pid, "VmRSS"), proc_kib(pid, "VmHWM"));

    // Without a key: refused before the body is read.
    let status = raw_observe(&server, message.clone(), None).await;
    assert_eq!(status.code(), Code::Unauthenticated, "{status:?}");
    assert_eq!(error_code(&status), "unauthenticated");
    let (rss1, peak1) = (proc_kib(pid, "VmRSS"), proc_kib(pid, "VmHWM"));
    eprintln!(
        "unauthenticated 16 MiB Observe: server RSS {rss0} -> {rss1} KiB, peak RSS {peak0} -> {peak1} KiB ({:+} KiB)",
        peak1 as i64 - peak0 as i64
    );
    assert!(
        peak1.saturating_sub(peak0) < 64 << 10,
        "peak RSS grew from {peak0} KiB to {peak1} KiB"
    );

    // With a key: counted before decoding, refused as too long a batch.
    let status = raw_observe(&server, message, Some(KEY_A)).await;
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert_eq!(error_code(&status), "limit_exceeded");
    assert!(status.message().contains("observations"), "{status:?}");
    let (rss2, peak2) = (proc_kib(pid, "VmRSS"), proc_kib(pid, "VmHWM"));
    eprintln!(
        "authenticated 16 MiB Observe: server RSS {rss1} -> {rss2} KiB, peak RSS {peak1} -> {peak2} KiB ({:+} KiB)",
        peak2 as i64 - peak1 as i64
    );
    // The body is buffered (16 MiB, and once more contiguous), never decoded.
    assert!(
        peak2.saturating_sub(peak1) < 128 << 10,
        "peak RSS grew from {peak1} KiB to {peak2} KiB"
    );

    // A batch within the limit is decoded and served as before.
    let mut client = server.grpc_client().await;
    let id = common::grpc_create(&mut client, Some(KEY_A), 3, true, None).await;
    let req = grpc_request(
        pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![pb::Observation {
                state: 25,
                ..Default::default()
            }],
        },
        Some(KEY_A),
        None,
    );
    let steps = client.observe(req).await.expect("observe").into_inner();
    assert_eq!(steps.steps.len(), 1);

    // An Interact message above its per-message limit ends the stream.
    let huge = pb::Observation {
        session_id: "x".repeat(1 << 20),
        state: 25,
        ..Default::default()
    };
    let req = grpc_request(tokio_stream::iter(vec![huge]), Some(KEY_A), None);
    let status = match client.interact(req).await {
        Err(status) => status,
        Ok(resp) => {
            let mut stream = resp.into_inner();
            stream
                .message()
                .await
                .expect_err("the oversized message is refused")
        }
    };
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(status.message().contains("Interact message"), "{status:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn request_metric_labels_stay_bounded() {
    let (server, _data) = start(&[]).await;
    let base = server.base();
    let client = common::http_client();
    for i in 0..50 {
        let method = reqwest::Method::from_bytes(format!("X{i}CUSTOM").as_bytes()).expect("method");
        let resp = client
            .request(method, format!("{base}/no/such/route/{i}"))
            .send()
            .await
            .expect("custom method");
        assert_eq!(resp.status(), 404);
    }
    let (status, _) = rest(
        &client,
        reqwest::Method::GET,
        &format!("{base}/healthz"),
        None,
        None,
    )
    .await;
    assert_eq!(status, 200);
    let text = client
        .get(format!("{base}/metrics"))
        .send()
        .await
        .expect("metrics")
        .text()
        .await
        .expect("text");
    let label = |line: &str, name: &str| -> Option<String> {
        let start = line.find(&format!("{name}=\""))? + name.len() + 2;
        let end = line[start..].find('"')? + start;
        Some(line[start..end].to_string())
    };
    let lines: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("mcapi_http_request_duration_seconds"))
        .collect();
    let methods: BTreeSet<String> = lines.iter().filter_map(|l| label(l, "method")).collect();
    let routes: BTreeSet<String> = lines.iter().filter_map(|l| label(l, "route")).collect();
    let allowed = [
        "GET", "POST", "DELETE", "PUT", "PATCH", "HEAD", "OPTIONS", "other",
    ];
    assert!(methods.contains("other"), "{methods:?}");
    assert!(
        methods.iter().all(|m| allowed.contains(&m.as_str())),
        "{methods:?}"
    );
    assert!(routes.contains("unmatched"), "{routes:?}");
    assert!(
        routes
            .iter()
            .all(|r| r == "unmatched" || r.starts_with('/')),
        "{routes:?}"
    );
    assert!(routes.len() <= 3, "{routes:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zero_connection_limits_are_refused_before_binding() {
    for (flag, env) in [
        ("--max-connections", "MCAPI_MAX_CONNECTIONS"),
        ("--header-read-timeout-ms", "MCAPI_HEADER_READ_TIMEOUT_MS"),
        ("--request-timeout-ms", "MCAPI_REQUEST_TIMEOUT_MS"),
        ("--max-streams-per-key", "MCAPI_MAX_STREAMS_PER_KEY"),
        ("--http2-max-streams", "MCAPI_HTTP2_MAX_STREAMS"),
        ("--http2-keepalive-ms", "MCAPI_HTTP2_KEEPALIVE_MS"),
        (
            "--http2-keepalive-timeout-ms",
            "MCAPI_HTTP2_KEEPALIVE_TIMEOUT_MS",
        ),
        ("--tcp-keepalive-secs", "MCAPI_TCP_KEEPALIVE_SECS"),
    ] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_mcapi"))
            .args(["serve", "--store", "memory", "--http", "127.0.0.1:0"])
            .args(["--grpc", "127.0.0.1:0"])
            .env(env, "0")
            .output()
            .expect("mcapi runs");
        assert!(!out.status.success(), "{env}=0 accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains(&format!("{flag} must be at least 1")),
            "{env}: {err}"
        );
    }
}

// ------------------------------------------------- panics, in process

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_rest_handler_answers_500_for_its_request_alone() {
    use axum::routing::get;
    let app = axum::Router::new()
        .route(
            "/boom",
            get(|| async {
                if std::hint::black_box(true) {
                    panic!("a handler bug");
                }
                "unreachable"
            }),
        )
        .route("/ok", get(|| async { "ok" }))
        .layer(mcapi_server::api::conn::rest_panic_layer());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("addr");
    let limits = mcapi_server::api::conn::ConnLimits::default();
    tokio::spawn(async move {
        mcapi_server::api::conn::serve_http(listener, app, &limits, std::future::pending()).await;
    });
    // One client: the same kept-alive connection serves the next request.
    let client = reqwest::Client::new();
    for _ in 0..2 {
        let resp = client
            .get(format!("http://{addr}/boom"))
            .send()
            .await
            .expect("a response, not a dropped connection");
        assert_eq!(resp.status(), 500);
        let body: Value = resp.json().await.expect("JSON body");
        assert_eq!(body["code"], "internal_panic", "{body}");
        assert_eq!(body["message"], "internal error", "the panic is not sent");
        let ok = client
            .get(format!("http://{addr}/ok"))
            .send()
            .await
            .expect("ok");
        assert_eq!(ok.status(), 200);
        assert_eq!(ok.text().await.expect("text"), "ok");
    }
}

/// A stand-in for the `Agents` service whose every method panics.
#[derive(Debug, Clone)]
struct Panicking;

impl tonic::server::NamedService for Panicking {
    const NAME: &'static str = "mcapi.v1.Agents";
}

impl tower::Service<tonic::codegen::http::Request<tonic::body::Body>> for Panicking {
    type Response = tonic::codegen::http::Response<tonic::body::Body>;
    type Error = Infallible;
    type Future = std::pin::Pin<
        Box<dyn std::future::Future<Output = Result<Self::Response, Infallible>> + Send>,
    >;

    fn poll_ready(
        &mut self,
        _cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Result<(), Infallible>> {
        std::task::Poll::Ready(Ok(()))
    }

    fn call(&mut self, _req: tonic::codegen::http::Request<tonic::body::Body>) -> Self::Future {
        Box::pin(async {
            if std::hint::black_box(true) {
                panic!("a method bug");
            }
            Ok(tonic::Status::ok("").into_http())
        })
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_grpc_method_answers_internal_for_its_call_alone() {
    let (_, health) = tonic_health::server::health_reporter();
    let routes = tonic::service::Routes::new(Panicking).add_service(health);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("addr");
    tokio::spawn(
        tonic::transport::Server::builder()
            .layer(mcapi_server::api::conn::grpc_panic_layer())
            .add_routes(routes)
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)),
    );
    let channel = tonic::transport::Channel::from_shared(format!("http://{addr}"))
        .expect("uri")
        .connect()
        .await
        .expect("connect");
    let mut agents = pb::agents_client::AgentsClient::new(channel.clone());
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    for _ in 0..2 {
        let status = agents
            .get_session(pb::GetSessionRequest {
                session_id: "x".into(),
            })
            .await
            .expect_err("the panicking method fails");
        assert_eq!(status.code(), Code::Internal, "{status:?}");
        assert_eq!(error_code(&status), "internal_panic");
        assert_eq!(status.message(), "internal error");
        // The connection and the other calls on it go on.
        let reply = health
            .check(tonic_health::pb::HealthCheckRequest::default())
            .await
            .expect("health answers on the same connection");
        assert_eq!(
            reply.into_inner().status(),
            tonic_health::pb::health_check_response::ServingStatus::Serving
        );
    }
}
