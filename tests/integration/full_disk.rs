//! A real full disk (docs/operations.md), on the real binary: the data
//! directory is a small tmpfs this test mounts itself, and the test fills it
//! with a file while the server runs. redb latches the first I/O error
//! (ENOSPC), so without a reopen every later commit would fail until a
//! restart. Checked:
//! - observations over REST get 503 `storage_unavailable`, over gRPC
//!   `UNAVAILABLE` with the same code, and `/readyz` answers 503 saying why;
//! - a DELETE while the disk is full gets 503 and the session stays, served
//!   as before; its retry after space is back deletes it;
//! - once the file is removed the server recovers by itself: `/readyz` is
//!   200 again and the observations refused before are retried once each;
//! - nothing acknowledged is lost and nothing is applied twice: every
//!   session equals, bit for bit, an in-memory replay of exactly the
//!   observations that got a 200, live and after a `kill -9` and a restart.
//!
//! Needs permission to mount (root, as here and in CI); without it the test
//! prints why and passes without running.

use crate::common;

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use common::{
    Launch, Obs, Reply, Server, check_session, grpc_create, grpc_request, http_client, log_events,
    params, rest, rest_create, rest_get, rest_list_all,
};
use mcapi_core::AgentParams;
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use reqwest::Method;
use serde_json::{Value, json};
use tonic::transport::Channel;

/// The tmpfs: small, so that filling it is quick.
const TMPFS_SIZE: &str = "2m";
/// Observations tried after filling the disk before the first refusal
/// must have come.
const MAX_UNTIL_FULL: usize = 5000;
/// How long the disk stays full once the first request was refused: long
/// enough for several reopen attempts (backoff 50 ms, doubling).
const HOLD_FULL: Duration = Duration::from_millis(1500);

// ------------------------------------------------------------------ tmpfs

/// A tmpfs mounted on a fresh directory, unmounted when dropped (also when
/// the test fails). Declare it before the server, so the server is stopped
/// first.
struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    /// `None` (with a printed reason) if mounting is not permitted here.
    fn mount(size: &str) -> Option<Self> {
        let dir = tempfile::tempdir().expect("mount point");
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir.path())
            .output();
        match out {
            Ok(o) if o.status.success() => Some(Self { dir }),
            Ok(o) => {
                eprintln!(
                    "SKIPPED: cannot mount a tmpfs ({}): {}",
                    o.status,
                    String::from_utf8_lossy(&o.stderr).trim()
                );
                None
            }
            Err(e) => {
                eprintln!("SKIPPED: cannot run mount: {e}");
                None
            }
        }
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let unmounted = Command::new("umount")
            .arg(self.dir.path())
            .status()
            .is_ok_and(|s| s.success());
        if !unmounted {
            // Busy (a server still running after a failure): detach it.
            let _ = Command::new("umount")
                .arg("-l")
                .arg(self.dir.path())
                .status();
        }
    }
}

/// Writes a file until the filesystem is full; returns its size.
fn fill(path: &Path) -> u64 {
    let mut file = std::fs::File::create(path).expect("filler");
    let mut written = 0u64;
    for size in [64 * 1024, 4096, 512, 1] {
        let block = vec![0xa5u8; size];
        loop {
            match file.write(&block) {
                Ok(0) => break,
                Ok(n) => written += n as u64,
                Err(e) => {
                    assert_eq!(
                        e.raw_os_error(),
                        Some(28),
                        "filling stops at ENOSPC, not at: {e}"
                    );
                    break;
                }
            }
        }
    }
    // Data, not just the size: tmpfs has no lazy allocation to undo this.
    file.sync_all().expect("sync the filler");
    written
}

// ------------------------------------------------------------------ sessions

/// A session driven by this test: what it applied (every observation that
/// got a 200, with its reply) and the observation it must retry (one that
/// was refused: the agent did move in its world, so the client reports it
/// again, exactly once).
struct Driven {
    id: String,
    params: AgentParams,
    applied: Vec<(Obs, Option<Reply>)>,
    state: Option<usize>,
    advised: Option<usize>,
    rng: ChaCha8Rng,
    retry: Option<Obs>,
    refused: usize,
}

impl Driven {
    fn new(id: String, seed: u64) -> Self {
        Self {
            id,
            params: params(seed, None),
            applied: Vec::new(),
            state: None,
            advised: None,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0xf011),
            retry: None,
            refused: 0,
        }
    }

    fn next_obs(&mut self) -> Obs {
        if let Some(obs) = &self.retry {
            return obs.clone();
        }
        common::next_hallway_obs(&mut self.rng, self.state, self.advised, false)
    }

    fn acknowledged(&mut self, obs: Obs, reply: Reply) {
        assert_eq!(
            reply.tick as usize,
            self.applied.len(),
            "{}: the reply's tick counts the acknowledged observations exactly",
            self.id
        );
        self.state = Some(obs.state);
        self.advised = Some(reply.action);
        self.applied.push((obs, Some(reply)));
        self.retry = None;
    }

    fn refuse(&mut self, obs: Obs) {
        self.retry = Some(obs);
        self.refused += 1;
    }

    /// One observation over REST: true if acknowledged, false if refused
    /// with 503 `storage_unavailable` (any other answer fails the test).
    async fn rest_once(&mut self, client: &reqwest::Client, base: &str) -> bool {
        let obs = self.next_obs();
        let (status, body) = rest(
            client,
            Method::POST,
            &format!("{base}/v1/sessions/{}/observations", self.id),
            None,
            Some(&obs.json()),
        )
        .await;
        match status {
            200 => {
                self.acknowledged(obs, Reply::from_json(&body));
                true
            }
            503 => {
                assert_eq!(body["code"], "storage_unavailable", "{}: {body}", self.id);
                self.refuse(obs);
                false
            }
            _ => panic!("{}: observe answered {status}: {body}", self.id),
        }
    }

    /// One observation over gRPC: true if acknowledged, false if refused
    /// with UNAVAILABLE `storage_unavailable`.
    async fn grpc_once(&mut self, client: &mut AgentsClient<Channel>) -> bool {
        let obs = self.next_obs();
        let result = client
            .observe(grpc_request(
                pb::ObserveRequest {
                    session_id: self.id.clone(),
                    observations: vec![obs.pb("")],
                },
                None,
                Some(&self.id),
            ))
            .await;
        match result {
            Ok(resp) => {
                let steps = resp.into_inner().steps;
                assert_eq!(steps.len(), 1);
                self.acknowledged(obs, Reply::from_pb(&steps[0]));
                true
            }
            Err(status) => {
                assert_eq!(status.code(), tonic::Code::Unavailable, "{status:?}");
                assert_eq!(
                    status
                        .metadata()
                        .get("x-mcapi-error-code")
                        .and_then(|v| v.to_str().ok()),
                    Some("storage_unavailable"),
                    "{status:?}"
                );
                self.refuse(obs);
                false
            }
        }
    }

    async fn check(&self, client: &reqwest::Client, base: &str, ctx: &str) {
        check_session(
            client,
            base,
            None,
            &self.id,
            &self.params,
            &self.applied,
            &format!("{ctx}: {}", self.id),
        )
        .await;
    }
}

async fn readyz(client: &reqwest::Client, base: &str) -> (u16, String) {
    let resp = client
        .get(format!("{base}/readyz"))
        .send()
        .await
        .expect("readyz");
    let status = resp.status().as_u16();
    (status, resp.text().await.expect("body"))
}

/// Polls `/readyz` until it answers `want`; returns the body and how long
/// it took.
async fn await_readyz(
    client: &reqwest::Client,
    base: &str,
    want: u16,
    within: Duration,
    log: &dyn Fn() -> String,
) -> (String, Duration) {
    let started = Instant::now();
    loop {
        let (status, body) = readyz(client, base).await;
        if status == want {
            return (body, started.elapsed());
        }
        assert!(
            started.elapsed() < within,
            "/readyz still {status} ({body}) after {within:?}; log:\n{}",
            log()
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

async fn delete(client: &reqwest::Client, base: &str, id: &str) -> (u16, Value) {
    rest(
        client,
        Method::DELETE,
        &format!("{base}/v1/sessions/{id}"),
        None,
        None,
    )
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_is_survived_without_a_restart() {
    let started = Instant::now();
    let Some(tmpfs) = Tmpfs::mount(TMPFS_SIZE) else {
        return;
    };
    let logs = tempfile::tempdir().expect("log dir");
    let data: PathBuf = tmpfs.path().join("data");
    let filler = tmpfs.path().join("filler");
    let launch = Launch::new(&data, &[]);
    let mut server = Server::start(&launch, logs.path().join("first.log")).await;
    let client = http_client();
    let base = server.base();
    let mut grpc = server.grpc_client().await;

    // Four lockstep sessions: a and b driven over REST, c over gRPC, d to
    // be deleted while the disk is full.
    let mut a = Driven::new(
        rest_create(&client, &base, None, json!({"seed": 1201})).await,
        1201,
    );
    let mut b = Driven::new(
        rest_create(&client, &base, None, json!({"seed": 1202})).await,
        1202,
    );
    let mut c = Driven::new(grpc_create(&mut grpc, None, 1203, true, None).await, 1203);
    let mut d = Driven::new(
        rest_create(&client, &base, None, json!({"seed": 1204})).await,
        1204,
    );
    for _ in 0..20 {
        assert!(a.rest_once(&client, &base).await, "before the disk is full");
        assert!(b.rest_once(&client, &base).await, "before the disk is full");
        assert!(c.grpc_once(&mut grpc).await, "before the disk is full");
    }
    for _ in 0..5 {
        assert!(d.rest_once(&client, &base).await, "before the disk is full");
    }

    // The disk fills up under a running server.
    let filled = fill(&filler);
    let mut tried = 0;
    while a.refused + b.refused == 0 {
        assert!(
            tried < MAX_UNTIL_FULL,
            "{tried} observations after filling the disk ({filled} bytes) all committed; log:\n{}",
            server.log_text()
        );
        let s = if tried % 2 == 0 { &mut a } else { &mut b };
        s.rest_once(&client, &base).await;
        tried += 1;
    }
    let log = || server.log_text();
    let (why, _) = await_readyz(&client, &base, 503, Duration::from_secs(5), &log).await;
    assert!(
        why.contains("cannot write"),
        "/readyz says why it is not ready: {why}"
    );
    eprintln!(
        "disk full: filler {filled} bytes, first refusal after {tried} observations; /readyz: {why}"
    );

    // While it stays full: more refusals over both transports.
    let deadline = Instant::now() + Duration::from_secs(30);
    while a.refused + b.refused < 10 || c.refused == 0 {
        assert!(
            Instant::now() < deadline,
            "refusals while the disk is full: REST {}, gRPC {}",
            a.refused + b.refused,
            c.refused
        );
        a.rest_once(&client, &base).await;
        b.rest_once(&client, &base).await;
        c.grpc_once(&mut grpc).await;
    }

    // It stays full for a while: the store keeps probing (reopening with
    // backoff) and stays unavailable, and requests keep being refused.
    let full_until = Instant::now() + HOLD_FULL;
    while Instant::now() < full_until {
        let (status, why) = readyz(&client, &base).await;
        assert_eq!(status, 503, "/readyz while the disk is still full: {why}");
        assert!(!a.rest_once(&client, &base).await, "refused while full");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let failed_reopens = log_events(&server.log_text(), "the store cannot be reopened yet");
    assert!(
        !failed_reopens.is_empty(),
        "the store probed the full disk (reopen attempts) and found it still full; log:\n{}",
        server.log_text()
    );

    // A delete that cannot be committed removes nothing.
    let (_, before) = rest_get(&client, &base, None, &d.id).await;
    let (status, body) = delete(&client, &base, &d.id).await;
    assert_eq!(status, 503, "delete on a full disk: {body}");
    assert_eq!(body["code"], "storage_unavailable", "{body}");
    let (status, after) = rest_get(&client, &base, None, &d.id).await;
    assert_eq!(
        status, 200,
        "the session stays after its delete failed: {after}"
    );
    assert_eq!(after["tick"], before["tick"]);
    assert!(rest_list_all(&client, &base, None).await.contains(&d.id));
    d.check(&client, &base, "after a failed delete").await;

    // Space is back: the server recovers by itself.
    std::fs::remove_file(&filler).expect("remove the filler");
    let (_, took) = await_readyz(&client, &base, 200, Duration::from_secs(20), &log).await;
    eprintln!("ready again {took:?} after the filler was removed");
    assert!(
        !log_events(&server.log_text(), "store reopened after a storage fault").is_empty(),
        "the store was reopened; log:\n{}",
        server.log_text()
    );
    // Every refused observation is retried once, and goes through.
    for s in [&mut a, &mut b] {
        let pending = s.retry.is_some();
        assert!(
            s.rest_once(&client, &base).await,
            "{}: after recovery",
            s.id
        );
        assert!(pending || s.refused == 0, "{}: a retry was due", s.id);
    }
    assert!(c.grpc_once(&mut grpc).await, "gRPC after recovery");
    for _ in 0..10 {
        assert!(a.rest_once(&client, &base).await);
        assert!(b.rest_once(&client, &base).await);
        assert!(c.grpc_once(&mut grpc).await);
    }
    let (status, body) = delete(&client, &base, &d.id).await;
    assert_eq!(status, 204, "the delete's retry: {body}");
    let (status, _) = rest_get(&client, &base, None, &d.id).await;
    assert_eq!(status, 404);
    for s in [&a, &b, &c] {
        s.check(&client, &base, "live, after recovery").await;
    }

    // Nothing acknowledged lost, nothing applied twice: kill -9, restart.
    server.kill9();
    let mut server = Server::start(&launch, logs.path().join("second.log")).await;
    let base = server.base();
    for s in [&a, &b, &c] {
        s.check(&client, &base, "after kill -9").await;
    }
    let (status, _) = rest_get(&client, &base, None, &d.id).await;
    assert_eq!(status, 404, "the deleted session stays deleted");
    let mut listed = rest_list_all(&client, &base, None).await;
    listed.sort();
    let mut want = vec![a.id.clone(), b.id.clone(), c.id.clone()];
    want.sort();
    assert_eq!(listed, want);
    assert!(server.terminate().success());
    drop(server);
    // What redb reported, for the record.
    let first = std::fs::read_to_string(logs.path().join("first.log")).unwrap_or_default();
    let mut errors: Vec<String> = log_events(&first, "store commit failed")
        .iter()
        .chain(&log_events(&first, "the store cannot be reopened yet"))
        .map(|e| e["error"].as_str().unwrap_or_default().to_string())
        .collect();
    errors.sort();
    errors.dedup();
    eprintln!(
        "commit failures {}, failed reopens {}, reopens {}; errors: {errors:#?}",
        log_events(&first, "store commit failed").len(),
        log_events(&first, "the store cannot be reopened yet").len(),
        log_events(&first, "store reopened after a storage fault").len(),
    );
    eprintln!(
        "acknowledged: a {}, b {}, c {}; refused: a {}, b {}, c {}; the test took {:?}",
        a.applied.len(),
        b.applied.len(),
        c.applied.len(),
        a.refused,
        b.refused,
        c.refused,
        started.elapsed()
    );
    drop(tmpfs);
}
