//! Live shard moves (docs/cluster.md, "How a shard moves") while sessions
//! are driven through the router and a replica is killed.

use crate::common;

use std::process::{Command, Output};
use std::time::{Duration, Instant};

use common::{Obs, Reply, check_session, grpc_request, http_client};
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_shards::{ReplicaName, ShardMap, shard_key, shard_of_id};
use serde_json::Value;
use tonic::Code;
use tonic::transport::Channel;

use super::{LocalCluster, Walk, call, create_walks, haproxy_or_skip, owner_of, stderr};

/// What one observation attempt through the router came to.
enum Attempt {
    /// Answered 200: acknowledged.
    Acked(Reply),
    /// A replica said nothing was done (421, or 503 / UNAVAILABLE while
    /// the shard moves): send it again.
    Refused,
    /// No clean answer (a connection cut by a kill or the router's
    /// restart, a router error): it may or may not have been applied.
    Unknown,
}

async fn attempt(
    client: &reqwest::Client,
    base: &str,
    grpc: &mut AgentsClient<Channel>,
    w: &Walk,
    obs: &Obs,
) -> Attempt {
    if w.grpc {
        let answer = grpc
            .observe(grpc_request(
                pb::ObserveRequest {
                    session_id: w.id.clone(),
                    observations: vec![obs.pb(&w.id)],
                },
                None,
                Some(&w.id),
            ))
            .await;
        return match answer {
            Ok(r) => match r.into_inner().steps.first() {
                Some(step) => Attempt::Acked(Reply::from_pb(step)),
                None => panic!("{}: an observe reply without steps", w.id),
            },
            Err(s)
                if s.code() == Code::Unavailable
                    && (s.message().contains("nothing was done")
                        || s.message().contains("retry through the router")) =>
            {
                Attempt::Refused
            }
            Err(_) => Attempt::Unknown,
        };
    }
    let url = format!("{base}/v1/sessions/{}/observations", w.id);
    let Ok(resp) = client.post(&url).json(&obs.json()).send().await else {
        return Attempt::Unknown;
    };
    let status = resp.status().as_u16();
    let Ok(text) = resp.text().await else {
        return Attempt::Unknown;
    };
    let body: Value = serde_json::from_str(&text).unwrap_or(Value::Null);
    match status {
        200 => Attempt::Acked(Reply::from_json(&body)),
        421 => Attempt::Refused,
        503 if body["code"] == "shard_moving" => Attempt::Refused,
        _ => Attempt::Unknown,
    }
}

/// The session's tick through the router, retried until it answers.
async fn tick_of(client: &reqwest::Client, base: &str, id: &str) -> u64 {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if let Ok(resp) = client.get(format!("{base}/v1/sessions/{id}")).send().await
            && resp.status() == 200
            && let Ok(info) = resp.json::<Value>().await
        {
            return info["tick"].as_u64().expect("tick");
        }
        assert!(Instant::now() < deadline, "{id} not readable within 60 s");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

impl Walk {
    /// One more observation through the router, sent until it is
    /// acknowledged; one whose outcome is unknown is settled by the
    /// session's tick (after a pause, so nothing of it is still running):
    /// applied, it counts (its reply unknown), else it is sent again.
    async fn step_retrying(
        &mut self,
        client: &reqwest::Client,
        base: &str,
        grpc: &mut AgentsClient<Channel>,
    ) -> (u32, u32) {
        let obs = self.next();
        let (mut refused, mut unknown) = (0, 0);
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            match attempt(client, base, grpc, self, &obs).await {
                Attempt::Acked(reply) => {
                    self.applied.push((obs, Some(reply)));
                    return (refused, unknown);
                }
                Attempt::Refused => {
                    refused += 1;
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
                Attempt::Unknown => {
                    unknown += 1;
                    tokio::time::sleep(Duration::from_millis(300)).await;
                    // Every observation so far had a stimulus but the first.
                    let acked = self.applied.len() as u64 - 1;
                    let tick = tick_of(client, base, &self.id).await;
                    if tick == acked + 1 {
                        self.applied.push((obs, None));
                        return (refused, unknown);
                    }
                    assert_eq!(
                        tick, acked,
                        "{}: tick {tick}, {acked} acknowledged",
                        self.id
                    );
                }
            }
            assert!(
                Instant::now() < deadline,
                "{}: not acknowledged within 60 s",
                self.id
            );
        }
    }
}

/// Whether a replica of a local cluster answers `/readyz` with 200.
async fn ready(client: &reqwest::Client, cluster: &LocalCluster, name: &str) -> bool {
    let state = cluster.state();
    let Some(http) = state["processes"]
        .as_array()
        .and_then(|ps| ps.iter().find(|p| p["name"] == name))
        .and_then(|p| p["http"].as_str())
    else {
        return false;
    };
    client
        .get(format!("http://{http}/readyz"))
        .send()
        .await
        .is_ok_and(|r| r.status() == 200)
}

/// Runs `mcapi cluster ARGS...`; its output.
fn cluster_cli(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .arg("cluster")
        .args(args)
        .output()
        .expect("mcapi cluster runs")
}

/// The `delta N` of a `cluster move` report line.
fn delta_of(out: &str) -> usize {
    out.split("delta ")
        .nth(1)
        .and_then(|rest| rest.split(',').next())
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or_else(|| panic!("no delta in {out:?}"))
}

/// The test of live moves (docs/cluster.md, "How a shard moves"): 3
/// replicas behind HAProxy, several hundred sessions driven over REST and
/// gRPC through the router while
/// `mcapi cluster rebalance` adds a fourth replica and moves shards to it
/// live and a replica is killed with SIGKILL (and started again by the
/// supervisor) in the middle of it; then single moves of a shard whose
/// session is observed without pause (the delta after the freeze carries
/// its latest observations). Afterwards every session is bit-equal to a
/// core replay of exactly its acknowledged observations, sits on its
/// map's owner, and sessions sit on all four replicas.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shards_move_live_while_sessions_are_driven_and_a_replica_is_killed() {
    if !haproxy_or_skip("shards_move_live_while_sessions_are_driven_and_a_replica_is_killed") {
        return;
    }
    let started = Instant::now();
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut cluster = LocalCluster::start(tmp.path(), &["--replicas", "3"], "moves");
    let data = cluster.dir.to_str().expect("utf-8").to_string();
    let map0 = ShardMap::read(&cluster.dir.join("shards.map")).expect("map");
    let client = http_client();
    let base = cluster.base();
    let grpc_url = format!("http://127.0.0.1:{}", cluster.grpc);
    let mut grpc = AgentsClient::connect(grpc_url.clone())
        .await
        .expect("gRPC through the router");
    let mut walks = create_walks(&client, &base, &mut grpc, 200, 100).await;
    for w in &mut walks {
        w.step(&client, &base, &mut grpc).await;
    }

    // Drivers: four over most sessions, one without pause over the first.
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let hot_walk = walks.remove(0);
    let hot_id = hot_walk.id.clone();
    let mut groups: Vec<Vec<Walk>> = (0..4).map(|_| Vec::new()).collect();
    for (i, w) in walks.into_iter().enumerate() {
        groups[i % 4].push(w);
    }
    groups.push(vec![hot_walk]);
    let mut drivers = Vec::new();
    for mut group in groups {
        let (client, base, stop) = (client.clone(), base.clone(), stop.clone());
        let mut grpc = grpc.clone();
        drivers.push(tokio::spawn(async move {
            let (mut refused, mut unknown) = (0u32, 0u32);
            let deadline = Instant::now() + Duration::from_secs(120);
            while !stop.load(std::sync::atomic::Ordering::Relaxed) && Instant::now() < deadline {
                for w in &mut group {
                    let (r, u) = w.step_retrying(&client, &base, &mut grpc).await;
                    refused += r;
                    unknown += u;
                }
            }
            (group, refused, unknown)
        }));
    }
    tokio::time::sleep(Duration::from_millis(500)).await;

    // The rebalance to 4 replicas, and mcapi-0 killed while shards move.
    let rebalance = {
        let data = data.clone();
        tokio::task::spawn_blocking(move || {
            cluster_cli(&["rebalance", "--data-dir", &data, "--replicas", "4"])
        })
    };
    let victim_pid = cluster.pid("mcapi-0").expect("mcapi-0 runs");
    let kill_deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let epoch = ShardMap::read(&cluster.dir.join("shards.map")).map_or(0, |m| m.epoch());
        if epoch >= map0.epoch() + 40 || rebalance.is_finished() {
            break;
        }
        assert!(
            Instant::now() < kill_deadline,
            "no shard moved within 60 s:\n{}",
            cluster.err()
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let epoch_at_kill = ShardMap::read(&cluster.dir.join("shards.map")).map_or(0, |m| m.epoch());
    common::signal(u32::try_from(victim_pid).expect("pid"), "-KILL");
    let first = rebalance.await.expect("rebalance task");
    let mut attempts = vec![first];
    // A move interrupted by the kill is undone (or, past its commit
    // point, finished by the next run): run it again until it completes.
    while !attempts.last().expect("one").status.success() {
        assert!(
            attempts.len() < 5,
            "rebalance keeps failing:\n{}",
            stderr(attempts.last().expect("one"))
        );
        let deadline = Instant::now() + Duration::from_secs(60);
        while cluster.pid("mcapi-0").is_none_or(|p| p == victim_pid)
            || !ready(&client, &cluster, "mcapi-0").await
        {
            assert!(
                Instant::now() < deadline,
                "mcapi-0 not back:\n{}",
                cluster.err()
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let data = data.clone();
        attempts.push(
            tokio::task::spawn_blocking(move || {
                cluster_cli(&["rebalance", "--data-dir", &data, "--replicas", "4"])
            })
            .await
            .expect("rebalance task"),
        );
    }
    let map = ShardMap::read(&cluster.dir.join("shards.map")).expect("map");
    let names = mcapi_shards::plan::ordinal_names("mcapi", 4).expect("names");
    let planned = mcapi_shards::plan::plan(&names, Some(&map0))
        .expect("plan")
        .map;
    assert_eq!(
        map.owners(),
        planned.owners(),
        "the map is the 4-replica plan"
    );
    let moved = (0..1024u16)
        .filter(|&s| map0.owner(s) != map.owner(s))
        .count();
    assert!((200..=320).contains(&moved), "{moved} shards moved");
    assert!(
        map.epoch() >= map0.epoch() + moved as u64,
        "one epoch per move: {} -> {}",
        map0.epoch(),
        map.epoch()
    );

    // Single moves of the hot session's shard, there and back: the delta
    // after the freeze must carry its observations at least once.
    let hot_shard = shard_of_id(&hot_id).expect("shard");
    let mut deltas = Vec::new();
    for k in 0..6 {
        let now = ShardMap::read(&cluster.dir.join("shards.map")).expect("map");
        let here = now.owner(hot_shard).to_string();
        let to = names
            .iter()
            .map(ReplicaName::as_str)
            .find(|n| *n != here && (k % 2 == 0 || *n != "mcapi-0"))
            .expect("another replica")
            .to_string();
        let out = cluster_cli(&[
            "move",
            "--data-dir",
            &data,
            "--shard",
            &shard_key(hot_shard),
            "--to",
            &to,
        ]);
        assert!(
            out.status.success(),
            "move {}: {}",
            shard_key(hot_shard),
            stderr(&out)
        );
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        deltas.push(delta_of(&text));
        if k >= 1 && deltas.iter().any(|d| *d > 0) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(
        deltas.iter().any(|d| *d > 0),
        "no move of the hot shard had a delta: {deltas:?}"
    );
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let mut walks = Vec::new();
    let (mut refused, mut unknown) = (0, 0);
    for d in drivers {
        let (group, r, u) = d.await.expect("driver");
        walks.extend(group);
        refused += r;
        unknown += u;
    }

    // Every session bit-equal to a replay of its acknowledged
    // observations, served by its map's owner; sessions on every replica.
    let map = ShardMap::read(&cluster.dir.join("shards.map")).expect("map");
    let mut on: std::collections::BTreeMap<String, usize> = Default::default();
    for w in &walks {
        check_session(&client, &base, None, &w.id, &w.params, &w.applied, &w.id).await;
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::GET,
            &format!("{base}/v1/sessions/{}", w.id),
            None,
        )
        .await;
        assert_eq!(status, 200, "{body}");
        let owner = owner_of(&map, &w.id);
        assert_eq!(
            replica.as_deref(),
            Some(owner.as_str()),
            "{} served by its owner",
            w.id
        );
        *on.entry(owner).or_default() += 1;
    }
    assert_eq!(on.len(), 4, "sessions on every replica: {on:?}");
    let steps: usize = walks.iter().map(|w| w.applied.len()).sum();
    // A replica no longer owning a moved shard answers 421 naming the owner.
    let state = cluster.state();
    let moved_walk = walks
        .iter()
        .find(|w| owner_of(&map0, &w.id) != owner_of(&map, &w.id))
        .expect("a session moved");
    let old = owner_of(&map0, &moved_walk.id);
    let old_http = state["processes"]
        .as_array()
        .expect("processes")
        .iter()
        .find(|p| p["name"] == old.as_str())
        .and_then(|p| p["http"].as_str())
        .expect("old owner's address")
        .to_string();
    let (status, _, named, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("http://{old_http}/v1/sessions/{}", moved_walk.id),
        None,
    )
    .await;
    assert_eq!(status, 421, "{body}");
    assert_eq!(
        named.as_deref(),
        Some(owner_of(&map, &moved_walk.id).as_str()),
        "{body}"
    );
    let (status, _) = cluster.terminate();
    assert!(status.success(), "{}", cluster.err());
    eprintln!(
        "moves: {moved} shards to mcapi-3 in {} rebalance run(s), mcapi-0 killed at epoch {epoch_at_kill}; \
         hot shard deltas {deltas:?}; {} sessions, {steps} acknowledged observations, {refused} refused \
         and {unknown} unsettled attempts; {:.1} s",
        attempts.len(),
        walks.len(),
        started.elapsed().as_secs_f64()
    );
}
