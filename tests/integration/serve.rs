//! The real binary: `mcapi serve` starts on given ports, answers, refuses a
//! bad configuration before binding, and shuts down cleanly on SIGTERM.

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::{Launch, Server, free_ports};

fn healthcheck(url: &str) -> bool {
    Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args(["healthcheck", "--url", url, "--timeout-ms", "500"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

#[test]
fn serve_answers_and_stops_on_sigterm() {
    let (http, grpc) = free_ports();
    let data = tempfile::tempdir().expect("data dir");
    let mut child = Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args([
            "serve",
            "--http",
            &format!("127.0.0.1:{http}"),
            "--grpc",
            &format!("127.0.0.1:{grpc}"),
        ])
        .args(["--workers", "2", "--log-format", "json"])
        .arg("--data-dir")
        .arg(data.path())
        .env(
            "MCAPI_API_KEYS",
            "a-secret-key-0123456789,another-key-abcdefghij",
        )
        .stderr(Stdio::piped())
        .spawn()
        .expect("mcapi serve starts");
    let url = format!("http://127.0.0.1:{http}/healthz");
    let started = Instant::now();
    while !healthcheck(&url) {
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "server never became healthy"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let status = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .expect("kill runs");
    assert!(status.success());
    let deadline = Instant::now() + Duration::from_secs(15);
    let exit = loop {
        if let Some(exit) = child.try_wait().expect("wait") {
            break exit;
        }
        assert!(
            Instant::now() < deadline,
            "server did not stop after SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(exit.success(), "clean exit after SIGTERM: {exit:?}");
    let mut log = String::new();
    child
        .stderr
        .take()
        .expect("stderr")
        .read_to_string(&mut log)
        .expect("log");
    assert!(
        log.contains("\"mcapi stopped\""),
        "JSON log with the stop line: {log}"
    );
    assert!(
        log.contains("\"api_keys\":2"),
        "the key count is logged: {log}"
    );
    assert!(
        !log.contains("a-secret-key") && !log.contains("another-key"),
        "API keys must never be logged: {log}"
    );
    assert!(
        data.path().join("mcapi.redb").exists(),
        "the store file is in --data-dir"
    );
    assert!(!healthcheck(&url), "port closed after shutdown");
}

/// A `--grpc-socket` path of 4,097 bytes, past any socket's and any path's limit.
static LONG_SOCKET_PATH: std::sync::LazyLock<String> =
    std::sync::LazyLock::new(|| format!("/{}", "s".repeat(4096)));

#[test]
fn bad_configuration_is_refused_before_binding() {
    let out = Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args([
            "serve",
            "--workers",
            "0",
            "--http",
            "127.0.0.1:1",
            "--grpc",
            "127.0.0.1:2",
        ])
        .output()
        .expect("mcapi runs");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--workers must be between 1 and 1024"),
        "{err}"
    );
    for (args, want) in [
        (
            &["--evict-idle-secs", "99999999999999"][..],
            "--evict-idle-secs must be at most 2592000 (30 days), not 99999999999999",
        ),
        (
            &["--evict-idle-secs", "60", "--store", "memory"][..],
            "--evict-idle-secs needs the durable store",
        ),
        (
            &["--store-cache-mib", "18446744073709551615"][..],
            "--store-cache-mib must be between 1 and 65536, not 18446744073709551615",
        ),
        (
            &["--store-cache-mib", "0"][..],
            "--store-cache-mib must be between 1 and 65536, not 0",
        ),
        (
            &["--grpc-socket", &LONG_SOCKET_PATH][..],
            "--grpc-socket must be at most 107 bytes (the limit of a Unix socket's path), not 4097",
        ),
        (
            &["--grpc-socket", "/tmp/mcapi/"][..],
            "--grpc-socket /tmp/mcapi/ names a directory, not a file",
        ),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_mcapi"))
            .args(["serve", "--http", "127.0.0.1:1", "--grpc", "127.0.0.1:2"])
            .args(args)
            .output()
            .expect("mcapi runs");
        assert!(!out.status.success(), "{args:?} accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(want), "{args:?}: {err}");
    }
    let out = Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args(["serve", "--http", "127.0.0.1:9", "--grpc", "127.0.0.1:9"])
        .output()
        .expect("mcapi runs");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("both use 127.0.0.1:9"));
}

#[test]
fn dockerfile_uses_only_flags_the_binary_knows() {
    let dockerfile = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/Dockerfile"))
        .expect("Dockerfile");
    let help = Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args(["serve", "--help"])
        .output()
        .expect("mcapi runs");
    let help = String::from_utf8_lossy(&help.stdout);
    let vars: Vec<&str> = dockerfile
        .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .filter(|w| w.starts_with("MCAPI_"))
        .collect();
    assert!(
        vars.len() >= 3,
        "the Dockerfile configures the server by env: {vars:?}"
    );
    for var in vars {
        assert!(
            help.contains(&format!("env: {var}=")),
            "{var} is not an env var of `mcapi serve`"
        );
    }
    assert!(
        dockerfile.contains("\"healthcheck\""),
        "HEALTHCHECK uses `mcapi healthcheck`"
    );
    let out = Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args(["healthcheck", "--help"])
        .output()
        .expect("mcapi runs");
    assert!(out.status.success());
}

/// The memory of deleted sessions goes back to the system within seconds,
/// with nothing else for the server to do: `mcapi-loadgen --scenario
/// memory` creates sessions, observes each once, deletes them all and reads
/// the server's RSS. Before the allocator's purger thread and the 1 s
/// keep-alive of blocking threads (src/main.rs), an idle server kept all of
/// it at this size (0% returned) and 60-75% at 50,000 sessions.
#[tokio::test]
async fn deleted_sessions_give_their_memory_back() {
    let out_dir = tempfile::tempdir().expect("dir");
    let launch = Launch {
        args: [
            "--store",
            "memory",
            "--max-sessions",
            "20000",
            "--max-key-sessions",
            "20000",
        ]
        .map(String::from)
        .to_vec(),
        ..Launch::default()
    };
    let server = Server::start(&launch, out_dir.path().join("serve.log")).await;
    let json = out_dir.path().join("memory.json");
    let out = Command::new(loadgen_bin())
        .args(["--scenario", "memory", "--threads", "1"])
        .args(["--http", &server.base()])
        .args(["--grpc", &server.grpc_url()])
        .args(["--memory-sessions", "5000", "--settle-secs", "4"])
        .args(["--server-pid", &server.pid().to_string()])
        .arg("--json")
        .arg(&json)
        .output()
        .expect("mcapi-loadgen runs");
    drop(server);
    assert!(
        out.status.success(),
        "loadgen failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&json).expect("loadgen's JSON")).expect("JSON");
    let memory = report.get("memory").unwrap_or(&report);
    let mib = |k: &str| memory[k].as_f64().unwrap_or(f64::NAN) / 1048576.0;
    let returned = memory["returned_after_settle"].as_f64().unwrap_or(0.0);
    let summary = format!(
        "fresh {:.0} MiB, with sessions {:.0} MiB, deleted {:.0} MiB, 4 s later {:.0} MiB",
        mib("baseline_rss_bytes"),
        mib("observed_rss_bytes"),
        mib("deleted_rss_bytes"),
        mib("settled_rss_bytes"),
    );
    assert!(
        mib("observed_rss_bytes") - mib("baseline_rss_bytes") > 15.0,
        "5,000 sessions should take tens of MiB: {summary}"
    );
    assert!(
        returned >= 0.8,
        "only {:.0}% of the sessions' memory came back: {summary}",
        100.0 * returned
    );
}

/// The `mcapi-loadgen` binary: another package of the workspace, so Cargo
/// gives its path to no test of this one; it is built next to `mcapi` in the
/// same target directory (`cargo test --workspace` builds it for
/// mcapi-loadgen's own tests; a run of this package's tests alone needs
/// `cargo build -p mcapi-loadgen` first).
fn loadgen_bin() -> std::path::PathBuf {
    let mcapi = std::path::Path::new(env!("CARGO_BIN_EXE_mcapi"));
    let bin = mcapi.with_file_name(format!("mcapi-loadgen{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.exists(),
        "{} is missing: build it with `cargo build -p mcapi-loadgen` \
         (`cargo test --workspace` does)",
        bin.display()
    );
    bin
}

/// SIGTERM is a drain: a request the server accepted before it (here, one
/// whose body is still arriving) is answered in full, and only then does
/// the server exit, cleanly; connections made after it are refused, since
/// the listeners close first. What a replica leaving a cluster relies on:
/// the router stops sending it requests, and those it has get answers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_answers_the_request_in_flight_before_exiting() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let data = tempfile::tempdir().expect("data dir");
    let logs = tempfile::tempdir().expect("log dir");
    let mut server = Server::start(&Launch::new(data.path(), &[]), logs.path().join("s.log")).await;
    let client = crate::common::http_client();
    let created: serde_json::Value = client
        .post(format!("{}/v1/sessions", server.base()))
        .json(&serde_json::json!({"model": {"preset": "hallway"}}))
        .send()
        .await
        .expect("create")
        .json()
        .await
        .expect("json");
    let id = created["id"].as_str().expect("id").to_string();

    // Headers and half the body, then SIGTERM, then the rest.
    let body = br#"{"state": 25}"#;
    let mut conn = tokio::net::TcpStream::connect(("127.0.0.1", server.http))
        .await
        .expect("connect");
    let head = format!(
        "POST /v1/sessions/{id}/observations HTTP/1.1\r\nHost: mcapi\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    conn.write_all(head.as_bytes()).await.expect("head");
    conn.write_all(&body[..5]).await.expect("half the body");
    tokio::time::sleep(Duration::from_millis(200)).await;
    crate::common::signal(server.pid(), "-TERM");
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert!(
        tokio::net::TcpStream::connect(("127.0.0.1", server.http))
            .await
            .is_err(),
        "a connection after SIGTERM is refused"
    );
    conn.write_all(&body[5..])
        .await
        .expect("the rest of the body");
    let mut answer = Vec::new();
    tokio::time::timeout(Duration::from_secs(10), conn.read_to_end(&mut answer))
        .await
        .expect("answered within 10 s")
        .expect("read");
    let answer = String::from_utf8_lossy(&answer);
    assert!(
        answer.starts_with("HTTP/1.1 200"),
        "the request in flight at SIGTERM is answered: {answer}"
    );
    assert!(answer.contains("\"tick\":0"), "{answer}");
    // Exited already, or about to: a second SIGTERM changes nothing.
    let status = tokio::task::block_in_place(|| server.terminate());
    assert!(
        status.success(),
        "clean exit: {status}; log:\n{}",
        server.log_text()
    );
}
