//! A mover that dies mid-move (docs/cluster.md, "When a mover dies"): a
//! shard frozen without a commit is served again once its lease ends, and
//! `mcapi cluster status` shows it meanwhile; a move that died past its
//! commit point is shown half-moved and finished by running `move` again.
//! The dead mover is played by the test, calling the replicas' admin
//! routes itself and stopping where a mover would have died.

use std::process::Command;
use std::time::{Duration, Instant};

use common::http_client;
use mcapi_shards::{shard_key, shard_of_id};
use serde_json::{Value, json};

use super::{LocalCluster, call, haproxy_or_skip};
use crate::common;

/// `mcapi cluster ARGS...`: stdout, and stderr on failure.
fn cli(args: &[&str]) -> String {
    let (ok, stdout, stderr) = cli_status(args);
    assert!(ok, "mcapi cluster {args:?}: {stderr}");
    stdout
}

/// `mcapi cluster ARGS`: whether it exited 0, its stdout and its stderr.
fn cli_status(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .arg("cluster")
        .args(args)
        .output()
        .expect("mcapi cluster runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `mcapi cluster status` of a cluster with a shard that needs attention:
/// it lists what it found and exits non-zero, saying how many.
fn status_needing_attention(data: &str) -> String {
    let (ok, stdout, stderr) = cli_status(&["status", "--data-dir", data]);
    assert!(
        !ok,
        "status exits non-zero while a shard needs attention: {stdout}"
    );
    assert!(stderr.contains("shard(s) frozen, half-moved"), "{stderr}");
    stdout
}

/// An admin call on a replica: status and body bytes.
async fn admin(
    client: &reqwest::Client,
    cluster: &LocalCluster,
    replica: &str,
    method: reqwest::Method,
    path: &str,
    body: Vec<u8>,
) -> (u16, Vec<u8>) {
    let state = cluster.state();
    let http = state["processes"]
        .as_array()
        .expect("processes")
        .iter()
        .find(|p| p["name"] == replica)
        .and_then(|p| p["http"].as_str())
        .expect("the replica's address")
        .to_string();
    let key = std::fs::read_to_string(cluster.dir.join("admin.key")).expect("admin key");
    let resp = client
        .request(method, format!("http://{http}{path}"))
        .bearer_auth(key.trim())
        .body(body)
        .send()
        .await
        .expect("admin call");
    let status = resp.status().as_u16();
    (status, resp.bytes().await.expect("body").to_vec())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_movers_freeze_ends_with_its_lease_and_a_half_move_is_finished() {
    if !haproxy_or_skip("a_dead_movers_freeze_ends_with_its_lease_and_a_half_move_is_finished") {
        return;
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut cluster = LocalCluster::start(tmp.path(), &["--replicas", "2"], "leases");
    let data = cluster.dir.to_str().expect("utf-8").to_string();
    let client = http_client();
    let base = cluster.base();
    let (code, replica, _, body) = call(
        &client,
        reqwest::Method::POST,
        &format!("{base}/v1/sessions"),
        Some(json!({"model": {"preset": "hallway"}})),
    )
    .await;
    assert_eq!(code, 201, "{body}");
    let id = body["id"].as_str().expect("id").to_string();
    let from = replica.expect("x-mcapi-replica");
    let to = if from == "mcapi-0" {
        "mcapi-1"
    } else {
        "mcapi-0"
    };
    let shard = shard_key(shard_of_id(&id).expect("shard"));
    let observe = format!("{base}/v1/sessions/{id}/observations");
    let (code, _, _, body) = call(
        &client,
        reqwest::Method::POST,
        &observe,
        Some(json!({"state": 25})),
    )
    .await;
    assert_eq!(code, 200, "{body}");
    let later = json!({"state": 26, "stimulus": [0.5, 0.25], "action_taken": 1});
    assert!(
        cli(&["status", "--data-dir", &data]).contains("none is frozen or half-moved"),
        "a quiet cluster"
    );

    // A mover froze the shard for 1.5 s and died: writes are refused, the
    // status shows the lease; after it the shard takes writes again.
    let (code, frozen) = admin(
        &client,
        &cluster,
        &from,
        reqwest::Method::POST,
        &format!("/admin/shards/{shard}/freeze?lease_ms=1500"),
        Vec::new(),
    )
    .await;
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&frozen));
    let frozen_at = Instant::now();
    let (code, _, _, body) = call(
        &client,
        reqwest::Method::POST,
        &observe,
        Some(later.clone()),
    )
    .await;
    assert_eq!(code, 503, "{body}");
    assert_eq!(body["code"], "shard_moving");
    let status = status_needing_attention(&data);
    assert!(
        status.contains(&format!("{shard} frozen on {from}, its lease ends in")),
        "{status}"
    );
    let acked = loop {
        let (code, _, _, body) = call(
            &client,
            reqwest::Method::POST,
            &observe,
            Some(later.clone()),
        )
        .await;
        if code == 200 {
            break body;
        }
        assert_eq!(body["code"], "shard_moving", "{body}");
        assert!(
            frozen_at.elapsed() < Duration::from_secs(10),
            "still frozen 10 s after a 1.5 s lease"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let thawed_after = frozen_at.elapsed();
    assert!(
        thawed_after >= Duration::from_millis(1400),
        "thawed after {thawed_after:?}, before its lease"
    );
    assert_eq!(acked["tick"], 1, "{acked}");
    assert!(cli(&["status", "--data-dir", &data]).contains("none is frozen or half-moved"));

    // A mover that died right after the source's commit, before writing
    // the map: the shard is half-moved; `move` run again finishes it.
    let empty = Vec::new();
    let (code, snapshot) = admin(
        &client,
        &cluster,
        &from,
        reqwest::Method::POST,
        &format!("/admin/shards/{shard}/export"),
        empty.clone(),
    )
    .await;
    assert_eq!(code, 200);
    let (code, body) = admin(
        &client,
        &cluster,
        to,
        reqwest::Method::POST,
        &format!("/admin/shards/{shard}/import?begin=true"),
        snapshot,
    )
    .await;
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
    let (code, frozen) = admin(
        &client,
        &cluster,
        &from,
        reqwest::Method::POST,
        &format!("/admin/shards/{shard}/freeze?lease_ms=2000"),
        empty.clone(),
    )
    .await;
    assert_eq!(code, 200);
    let frozen: Value = serde_json::from_slice(&frozen).expect("json");
    let token = frozen["freeze_token"].as_u64().expect("token");
    let epoch = frozen["epoch"].as_u64().expect("epoch") + 1;
    let (code, body) = admin(
        &client,
        &cluster,
        &from,
        reqwest::Method::POST,
        &format!("/admin/shards/{shard}/commit?epoch={epoch}&owner={to}&token={token}"),
        empty.clone(),
    )
    .await;
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
    let status = status_needing_attention(&data);
    assert!(
        status.contains(&format!(
            "{shard} half-moved: {from} gave it to {to} but the map still names {from}"
        )),
        "{status}"
    );
    // Past the lease, the committed shard stays given away: no thaw.
    tokio::time::sleep(Duration::from_millis(2200)).await;
    let (code, _, _, body) = call(
        &client,
        reqwest::Method::POST,
        &observe,
        Some(later.clone()),
    )
    .await;
    assert_ne!(
        code, 200,
        "a committed source never serves the shard again: {body}"
    );
    let out = cli(&["move", "--data-dir", &data, "--shard", &shard, "--to", to]);
    assert!(out.contains("already"), "{out}");
    assert!(cli(&["status", "--data-dir", &data]).contains("none is frozen or half-moved"));
    let (code, replica, _, body) = call(
        &client,
        reqwest::Method::POST,
        &observe,
        Some(later.clone()),
    )
    .await;
    assert_eq!(code, 200, "{body}");
    assert_eq!(replica.as_deref(), Some(to), "served by its new owner");
    assert_eq!(body["tick"], 2, "nothing lost: {body}");
    let (status, _) = cluster.terminate();
    assert!(status.success(), "{}", cluster.err());
}
