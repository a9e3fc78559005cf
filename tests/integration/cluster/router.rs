//! The router while the cluster changes (docs/cluster.md, "Adding
//! replicas", "Removing replicas"): load runs through HAProxy over REST
//! and gRPC while `mcapi cluster local` takes new replicas, shards move and
//! a replica leaves, and every request must get an answer. A request without one (a connection closed
//! before the response, a connection refused) is what restarting HAProxy
//! did to every request in flight.

use crate::common;

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use common::{grpc_request, http_client, rest_create};
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_shards::{shard_key, shard_of_id};
use serde_json::json;

use super::{LocalCluster, call, haproxy_or_skip, process_exists};

/// What the drivers saw.
#[derive(Debug, Default)]
struct Tally {
    sent: u64,
    /// Answered, by status (REST) or gRPC code.
    answered: BTreeMap<String, u64>,
    /// No answer: the error of the first few.
    unanswered: u64,
    errors: Vec<String>,
}

impl Tally {
    fn add(&mut self, other: Tally) {
        self.sent += other.sent;
        for (k, v) in other.answered {
            *self.answered.entry(k).or_default() += v;
        }
        self.unanswered += other.unanswered;
        for e in other.errors {
            if self.errors.len() < 5 {
                self.errors.push(e);
            }
        }
    }

    fn miss(&mut self, e: String) {
        self.unanswered += 1;
        if self.errors.len() < 5 {
            self.errors.push(e);
        }
    }
}

/// One GET over a kept-alive HTTP/1.1 connection, opened if there is
/// none, with no retry of any kind (as Python's `http.client` does, unlike
/// reqwest, which sends a request again on a pooled connection that
/// closed before it was written). `Err` when no answer came; the
/// connection is then dropped.
async fn raw_get(
    conn: &mut Option<tokio::io::BufReader<tokio::net::TcpStream>>,
    addr: &str,
    path: &str,
) -> Result<u16, String> {
    use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt};
    let result = async {
        if conn.is_none() {
            let stream = tokio::net::TcpStream::connect(addr)
                .await
                .map_err(|e| format!("connect: {e}"))?;
            *conn = Some(tokio::io::BufReader::new(stream));
        }
        let c = conn.as_mut().ok_or("no connection")?;
        c.get_mut()
            .write_all(format!("GET {path} HTTP/1.1\r\nHost: mcapi\r\n\r\n").as_bytes())
            .await
            .map_err(|e| format!("write: {e}"))?;
        let mut status = 0u16;
        let mut length = 0usize;
        let mut keep = true;
        loop {
            let mut line = String::new();
            let n = c
                .read_line(&mut line)
                .await
                .map_err(|e| format!("read: {e}"))?;
            if n == 0 {
                return Err("the connection closed without a response".to_string());
            }
            let l = line.trim_end().to_ascii_lowercase();
            if status == 0 {
                status = l
                    .split_whitespace()
                    .nth(1)
                    .and_then(|s| s.parse().ok())
                    .ok_or(format!("a bad status line {line:?}"))?;
            } else if l.is_empty() {
                break;
            } else if let Some(v) = l.strip_prefix("content-length:") {
                length = v.trim().parse().map_err(|_| "a bad length".to_string())?;
            } else if l == "connection: close" {
                keep = false;
            }
        }
        let mut body = vec![0u8; length];
        c.read_exact(&mut body)
            .await
            .map_err(|e| format!("body: {e}"))?;
        Ok((status, keep))
    }
    .await;
    match result {
        Ok((status, keep)) => {
            if !keep {
                *conn = None;
            }
            Ok(status)
        }
        Err(e) => {
            *conn = None;
            Err(e)
        }
    }
}

/// Asks the supervisor for `n` replicas as `rebalance` does (its request
/// file, then SIGHUP), without moving shards, and waits until it says they
/// run behind the router.
fn grow(cluster: &LocalCluster, n: usize) {
    std::fs::write(
        cluster.dir.join("rebalance.json"),
        format!("{{\"replicas\": {n}}}\n"),
    )
    .expect("request file");
    let supervisor = cluster.state()["supervisor"].as_u64().expect("pid");
    common::signal(u32::try_from(supervisor).expect("pid"), "-HUP");
    let deadline = Instant::now() + Duration::from_secs(60);
    while cluster.state()["replicas"].as_u64() != Some(n as u64) {
        assert!(
            Instant::now() < deadline,
            "the supervisor did not run {n} replicas within 60 s:\n{}",
            cluster.err()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Load through the router while replicas join and shards move, with the
/// router updated the way `how` says; returns the tally and checks what
/// does not depend on `how` (the new replicas serve their shards).
async fn load_while_replicas_join(how: &str) -> Tally {
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut cluster = LocalCluster::start(
        tmp.path(),
        &["--replicas", "2", "--router-update", how],
        "router",
    );
    let data = cluster.dir.to_str().expect("utf-8").to_string();
    let client = http_client();
    let base = cluster.base();
    let grpc_url = format!("http://127.0.0.1:{}", cluster.grpc);
    let grpc = AgentsClient::connect(grpc_url)
        .await
        .expect("gRPC through the router");
    let mut ids = Vec::new();
    for seed in 0..24u64 {
        ids.push(
            rest_create(
                &client,
                &base,
                None,
                json!({"seed": seed, "update_mode": "lockstep"}),
            )
            .await,
        );
    }
    let haproxy_pid = cluster.pid("haproxy").expect("haproxy runs");

    // Six drivers, each reading its sessions in turn without pause: two
    // over REST with reqwest, two over raw kept-alive HTTP/1.1 connections
    // without retries, two over gRPC.
    let stop = Arc::new(AtomicBool::new(false));
    let mut drivers = Vec::new();
    let router_addr = format!("127.0.0.1:{}", cluster.http);
    for d in 0..6usize {
        let router_addr = router_addr.clone();
        let mine: Vec<String> = ids.iter().skip(d).step_by(6).cloned().collect();
        let (client, base, stop) = (client.clone(), base.clone(), stop.clone());
        let mut grpc = grpc.clone();
        drivers.push(tokio::spawn(async move {
            let mut t = Tally::default();
            let mut raw = None;
            let deadline = Instant::now() + Duration::from_secs(60);
            while !stop.load(Ordering::Relaxed) && Instant::now() < deadline {
                for id in &mine {
                    t.sent += 1;
                    if (2..4).contains(&d) {
                        match raw_get(&mut raw, &router_addr, &format!("/v1/sessions/{id}")).await {
                            Ok(status) => *t.answered.entry(status.to_string()).or_default() += 1,
                            Err(e) => t.miss(format!("raw HTTP/1.1: {e}")),
                        }
                    } else if d < 2 {
                        let url = format!("{base}/v1/sessions/{id}");
                        match client.get(&url).send().await {
                            Ok(r) => {
                                let status = r.status().as_u16().to_string();
                                match r.bytes().await {
                                    Ok(_) => *t.answered.entry(status).or_default() += 1,
                                    Err(e) => t.miss(format!("REST body: {e:?}")),
                                }
                            }
                            Err(e) => t.miss(format!("REST: {e:?}")),
                        }
                    } else {
                        let req = grpc_request(
                            pb::GetSessionRequest {
                                session_id: id.clone(),
                            },
                            None,
                            Some(id),
                        );
                        match grpc.get_session(req).await {
                            Ok(_) => *t.answered.entry("grpc ok".into()).or_default() += 1,
                            // A status from a replica or the router is an
                            // answer; a broken transport is not.
                            Err(s)
                                if matches!(
                                    s.code(),
                                    tonic::Code::Unknown | tonic::Code::Cancelled
                                ) || (s.code() == tonic::Code::Unavailable
                                    && s.metadata().get("x-mcapi-error-code").is_none()) =>
                            {
                                t.miss(format!("gRPC: {s:?}"));
                            }
                            Err(s) => {
                                *t.answered
                                    .entry(format!("grpc {:?}", s.code()))
                                    .or_default() += 1;
                            }
                        }
                    }
                }
            }
            t
        }));
    }
    tokio::time::sleep(Duration::from_millis(500)).await;

    // Two replicas join, one at a time, while the load runs.
    for n in [3usize, 4] {
        let c = &cluster;
        tokio::task::block_in_place(|| grow(c, n));
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    // Map changes under load: a session's shard moved to each new replica,
    // and served there through the router at once.
    for (k, to) in ["mcapi-2", "mcapi-3"].into_iter().enumerate() {
        let id = ids[k].clone();
        let shard = shard_key(shard_of_id(&id).expect("shard"));
        let data = data.clone();
        let out = tokio::task::spawn_blocking(move || {
            std::process::Command::new(env!("CARGO_BIN_EXE_mcapi"))
                .args(["cluster", "move", "--data-dir", &data, "--shard", &shard])
                .args(["--to", to])
                .output()
                .expect("mcapi cluster move runs")
        })
        .await
        .expect("move task");
        assert!(
            out.status.success(),
            "move: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::GET,
            &format!("{base}/v1/sessions/{id}"),
            None,
        )
        .await;
        assert_eq!(status, 200, "{body}");
        assert_eq!(replica.as_deref(), Some(to), "served by its new replica");
    }
    // One replica leaves under the same load: `rebalance --replicas 3`
    // moves every shard off mcapi-3 (and what the plan for three gives
    // mcapi-2), takes it out of the router and stops it.
    let leaving_pid = cluster.pid("mcapi-3").expect("mcapi-3 runs");
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new(env!("CARGO_BIN_EXE_mcapi"))
            .args([
                "cluster",
                "rebalance",
                "--data-dir",
                &data,
                "--replicas",
                "3",
            ])
            .output()
            .expect("mcapi cluster rebalance runs")
    })
    .await
    .expect("rebalance task");
    assert!(
        out.status.success(),
        "rebalance --replicas 3: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        cluster.err()
    );
    assert_eq!(cluster.state()["replicas"], 3, "{}", cluster.err());
    assert_eq!(cluster.pid("mcapi-3"), None, "mcapi-3 is no longer run");
    assert!(!process_exists(leaving_pid), "mcapi-3 stopped");
    let (status, replica, _, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{}", ids[1]),
        None,
    )
    .await;
    assert_eq!(status, 200, "the session mcapi-3 held is served: {body}");
    assert_ne!(replica.as_deref(), Some("mcapi-3"));
    tokio::time::sleep(Duration::from_millis(500)).await;
    stop.store(true, Ordering::Relaxed);
    let mut tally = Tally::default();
    for d in drivers {
        tally.add(d.await.expect("driver"));
    }
    if how == "runtime" {
        assert_eq!(
            cluster.pid("haproxy"),
            Some(haproxy_pid),
            "the router was not restarted"
        );
        for said in [
            "added to the running router",
            "deleted from the running router",
        ] {
            assert!(cluster.err().contains(said), "{}", cluster.err());
        }
    }
    let (status, _) = cluster.terminate();
    assert!(status.success(), "{}", cluster.err());
    eprintln!(
        "router update `{how}`: {} requests sent while 2 replicas joined, 2 shards moved and \
         1 replica left, {} unanswered, answers {:?}; first errors: {:?}",
        tally.sent, tally.unanswered, tally.answered, tally.errors
    );
    tally
}

/// Replicas added through HAProxy's Runtime API: HAProxy keeps running,
/// and no request through it goes without an answer.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_join_and_shards_move_without_a_request_left_unanswered() {
    if !haproxy_or_skip("replicas_join_and_shards_move_without_a_request_left_unanswered") {
        return;
    }
    let tally = load_while_replicas_join("runtime").await;
    assert!(tally.sent > 1000, "too little load: {tally:?}");
    assert_eq!(
        tally.unanswered, 0,
        "requests left without an answer: {tally:?}"
    );
}

/// The same load with a master-worker reload of HAProxy instead: a
/// measurement, not a check (`-- --ignored` runs it), kept to compare the
/// ways (docs/cluster.md gives the numbers).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement of a reload, which the Runtime API replaced"]
async fn measure_a_reloaded_router() {
    if !haproxy_or_skip("measure_a_reloaded_router") {
        return;
    }
    load_while_replicas_join("reload").await;
}

/// The same load with HAProxy stopped and started again, as `cluster
/// local` did before: requests go unanswered (the measurement shows the
/// test can see what it guards against).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement of the restart that the Runtime API replaced"]
async fn measure_a_restarted_router() {
    if !haproxy_or_skip("measure_a_restarted_router") {
        return;
    }
    let tally = load_while_replicas_join("restart").await;
    assert!(tally.unanswered > 0, "a restart cut nothing? {tally:?}");
}
