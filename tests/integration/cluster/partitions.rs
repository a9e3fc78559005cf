//! Network partitions (docs/cluster.md, "Partitions and stale routers"):
//! `mcapi cluster local` with its router and each of its three replicas
//! in a network namespace of its own (`--netns`), the supervisor and this
//! test's client in a fourth and the mover in a fifth, all linked through
//! a bridge ([`super::netns`]). Under a steady load of numbered
//! observations (each with its `seq`, sent again with the same seq until
//! it is answered), links are cut by iptables rules that drop packets, as
//! a real partition loses them:
//!
//! 1. **The router from a replica**: first only the replica's answers
//!    vanish (observations are applied and their replies lost), then the
//!    link is cut both ways; then it heals.
//! 2. **The mover from a move's source**, right after the freeze: the
//!    source serves the shard again by itself when the freeze's lease
//!    ends, while the mover is still cut off; the move is undone.
//! 3. **A move's target from its source and from the mover**, right after
//!    the source's commit: the shard is half-moved and no replica serves
//!    it (the source refuses it, past its lease too, naming the target)
//!    until the links heal and `cluster move` is run again. Replicas never
//!    call each other (the mover relays a shard's data), so the cut
//!    between source and target alone changes nothing: the mover losing
//!    the target is what leaves the move half done.
//! 4. **A commit's answer**, and the source with it, from the mover, from
//!    the moment the commit is sent: the source commits, the mover cannot
//!    know it and undoes nothing (the target keeps its copy); after the
//!    heal, `cluster rebalance` finishes the move.
//!
//! Asserted: no acknowledged observation is lost and none is applied
//! twice (every session's `next_seq` equals the observations acknowledged
//! to it, and the session equals, bit for bit, a core replay of exactly
//! those); no shard is owned by two replicas (checked on every replica at
//! each quiet point), the router's map names one owner, a replica that
//! gave a shard away refuses it with 421, and each session's observations
//! were applied by one replica and then another, never back and forth;
//! after each heal every session is served again within [`HEAL_BOUND`].
//!
//! Needs root, `ip netns` and iptables with the `string` and `recent`
//! matches; without them it says so and skips.

use std::collections::BTreeMap;
use std::process::Output;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::{check_session, http_client};
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_shards::moves::ReplicaShards;
use mcapi_shards::{ShardMap, shard_key, shard_of_id};

use super::netns::{self, Net, exec_in};
use super::{LocalCluster, create_walks, haproxy_or_skip, owner_of};
use crate::common;
use load::{Live, Seen, acks_between, drive, seen, served_again};

mod load;

/// After a heal, every session is served again within this.
const HEAL_BOUND: Duration = Duration::from_secs(20);
/// The freeze's lease the mover asks for (ms).
const LEASE_MS: u64 = 3000;
/// The members of the network: role and last octet of its address.
const MEMBERS: [(&str, u8); 6] = [
    ("ctl", 2),
    ("mover", 3),
    ("router", 4),
    ("r0", 10),
    ("r1", 11),
    ("r2", 12),
];
/// The router's ports, in its own namespace.
const ROUTER_REST: u16 = 8080;
const ROUTER_GRPC: u16 = 50051;

/// The replicas' REST addresses, by name, from `cluster.json`.
fn replica_addrs(cluster: &LocalCluster) -> BTreeMap<String, String> {
    cluster.state()["processes"]
        .as_array()
        .expect("processes")
        .iter()
        .filter_map(|p| {
            Some((
                p["name"].as_str()?.to_string(),
                p["http"].as_str()?.to_string(),
            ))
        })
        .collect()
}

/// Every replica's shards (`GET /admin/shards`), asked directly.
async fn listings(client: &reqwest::Client, cluster: &LocalCluster) -> Vec<ReplicaShards> {
    let key = std::fs::read_to_string(cluster.dir.join("admin.key")).expect("admin key");
    let mut out = Vec::new();
    for (name, addr) in replica_addrs(cluster) {
        let resp = client
            .get(format!("http://{addr}/admin/shards"))
            .bearer_auth(key.trim())
            .send()
            .await
            .unwrap_or_else(|e| panic!("{name}'s shards: {e}"));
        assert_eq!(resp.status(), 200, "{name}'s shards");
        out.push(resp.json().await.expect("a shard listing"));
    }
    out
}

/// No shard is owned (served, or frozen) by two replicas; each shard not
/// in `unsettled` is owned by exactly its map's owner.
fn assert_one_owner(listings: &[ReplicaShards], map: &ShardMap, unsettled: &[u16], ctx: &str) {
    for shard in 0..mcapi_shards::SHARDS as u16 {
        let owners: Vec<&str> = listings
            .iter()
            .filter(|l| {
                matches!(
                    l.shards[usize::from(shard)].state.as_str(),
                    "owned" | "frozen"
                )
            })
            .map(|l| l.replica.as_str())
            .collect();
        assert!(
            owners.len() <= 1,
            "{ctx}: {} owned by {owners:?} at once",
            shard_key(shard)
        );
        if !unsettled.contains(&shard) {
            assert_eq!(
                owners,
                [map.owner(shard).as_str()],
                "{ctx}: {} is owned by its map's owner alone",
                shard_key(shard)
            );
        }
    }
}

/// A replica's epoch in its listing.
fn epoch_of(listings: &[ReplicaShards], replica: &str) -> u64 {
    listings
        .iter()
        .find(|l| l.replica == replica)
        .map(|l| l.epoch)
        .expect("the replica's listing")
}

/// The owners the running router's map names for `shard` (HAProxy's
/// `show map` on its Runtime API).
fn router_owners(cluster: &LocalCluster, shard: u16) -> Vec<String> {
    let dir = std::fs::canonicalize(&cluster.dir).expect("data dir");
    let socket = dir.join("router").join("admin.sock");
    let map = dir.join("router").join("shards.map");
    let answer =
        mcapi_cluster::haproxy::runtime_command(&socket, &format!("show map {}", map.display()))
            .expect("show map");
    let key = shard_key(shard);
    answer
        .lines()
        .filter_map(|l| {
            let mut f = l.split_whitespace().skip(1);
            (f.next()? == key).then(|| f.next().map(str::to_string))?
        })
        .collect()
}

/// Session `id` asked for directly on every replica: each one's status
/// and the owner a 421 names.
async fn probe(
    client: &reqwest::Client,
    cluster: &LocalCluster,
    id: &str,
) -> BTreeMap<String, (u16, Option<String>)> {
    let mut out = BTreeMap::new();
    for (name, addr) in replica_addrs(cluster) {
        let resp = client
            .get(format!("http://{addr}/v1/sessions/{id}"))
            .send()
            .await
            .unwrap_or_else(|e| panic!("{id} on {name}: {e}"));
        let owner = resp
            .headers()
            .get("x-mcapi-owner")
            .and_then(|v| v.to_str().ok())
            .map(str::to_string);
        out.insert(name, (resp.status().as_u16(), owner));
    }
    out
}

/// `mcapi cluster ARGS` in the mover's namespace.
async fn mover(net: &Arc<Net>, args: Vec<String>) -> Output {
    let ns = net.ns("mover").to_string();
    tokio::task::spawn_blocking(move || {
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let mut all = vec!["cluster"];
        all.extend(refs);
        exec_in(&ns, env!("CARGO_BIN_EXE_mcapi"), &all)
    })
    .await
    .expect("the mover's task")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn map_of(cluster: &LocalCluster) -> ShardMap {
    ShardMap::read(&cluster.dir.join("shards.map")).expect("the shard map")
}

/// What the run measured, for the report.
struct Report {
    heal_router: Duration,
    heal_mover: Duration,
    heal_target: Duration,
    heal_commit: Duration,
    thawed_by_lease: Duration,
    sessions: usize,
    acked: usize,
    replayed: usize,
    refused: u64,
    unanswered: u64,
    errors: Vec<String>,
}

async fn partitioned(net: Arc<Net>, tmp: std::path::PathBuf) -> Report {
    let router_ip = net.member("router").ip.to_string();
    let mut extra: Vec<String> = vec![
        "--replicas".into(),
        "3".into(),
        "--netns".into(),
        format!("haproxy={}", net.ns("router")),
    ];
    for k in 0..3 {
        let m = net.member(&format!("r{k}"));
        extra.push("--netns".into());
        extra.push(format!("mcapi-{k}={}@{}", m.ns, m.ip));
    }
    let refs: Vec<&str> = extra.iter().map(String::as_str).collect();
    // Started from this thread, in the client's namespace: the supervisor
    // runs there, and puts each replica and the router in its own.
    let mut cluster = LocalCluster::start_at(
        &tmp,
        &refs,
        "partitions",
        &router_ip,
        ROUTER_REST,
        ROUTER_GRPC,
    );
    let data = cluster.dir.to_str().expect("utf-8").to_string();
    let map0 = map_of(&cluster);
    let client = http_client();
    let base = cluster.base();
    let mut grpc = AgentsClient::connect(format!("http://{router_ip}:{ROUTER_GRPC}"))
        .await
        .expect("gRPC through the router");
    let walks = create_walks(&client, &base, &mut grpc, 16, 8).await;
    let ids: Vec<String> = walks.iter().map(|w| w.id.clone()).collect();
    let owner0: Vec<String> = ids.iter().map(|id| owner_of(&map0, id)).collect();
    for k in 0..3 {
        assert!(
            owner0.iter().any(|o| *o == format!("mcapi-{k}")),
            "sessions on every replica: {owner0:?}"
        );
    }
    let all: Vec<usize> = (0..ids.len()).collect();
    let on = |replica: &str| -> Vec<usize> {
        all.iter()
            .copied()
            .filter(|&i| owner0[i] == replica)
            .collect()
    };
    let shard = |i: usize| shard_of_id(&ids[i]).expect("shard");
    // The move that the mover's cut undoes, and the one the target's cut
    // leaves half done.
    let b = on("mcapi-0")[0];
    let c = *on("mcapi-1")
        .iter()
        .find(|&&i| shard(i) != shard(b))
        .expect("a session of mcapi-1");
    let (shard_b, shard_c) = (shard(b), shard(c));

    let live: Live = Arc::new(ids.iter().map(|_| Mutex::new(Seen::default())).collect());
    let stop = Arc::new(AtomicBool::new(false));
    let drivers: Vec<_> = walks
        .into_iter()
        .enumerate()
        .map(|(i, w)| {
            tokio::spawn(drive(
                w,
                i,
                live.clone(),
                stop.clone(),
                client.clone(),
                base.clone(),
                grpc.clone(),
            ))
        })
        .collect();
    let warm = Instant::now();
    while all.iter().any(|&i| seen(&live, i).acks.len() < 3) {
        assert!(
            warm.elapsed() < Duration::from_secs(30),
            "the load did not start within 30 s"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_one_owner(
        &listings(&client, &cluster).await,
        &map0,
        &[],
        "before any cut",
    );

    // 1. The router from mcapi-2: its answers vanish first (observations
    // applied, replies lost), then the link is cut both ways.
    net.cut_one_way("r2", "router");
    tokio::time::sleep(Duration::from_secs(3)).await;
    net.cut_one_way("router", "r2");
    tokio::time::sleep(Duration::from_secs(1)).await;
    let window = Instant::now();
    tokio::time::sleep(Duration::from_secs(3)).await;
    let now = Instant::now();
    for &i in &all {
        let n = acks_between(&live, i, window, now);
        if owner0[i] == "mcapi-2" {
            assert_eq!(
                n, 0,
                "{} answered through a router cut from its replica",
                ids[i]
            );
        } else {
            assert!(
                n > 0,
                "{} not served while another replica was cut off",
                ids[i]
            );
        }
    }
    // Cut off from the router, mcapi-2 still serves its shards alone.
    let cut_off = on("mcapi-2")[0];
    let seen_there = probe(&client, &cluster, &ids[cut_off]).await;
    assert_eq!(seen_there["mcapi-2"].0, 200, "{seen_there:?}");
    assert_one_owner(
        &listings(&client, &cluster).await,
        &map0,
        &[],
        "router cut from mcapi-2",
    );
    net.heal();
    let healed = Instant::now();
    let heal_router = served_again(&live, &ids, &all, healed, "router cut from mcapi-2").await;

    // 2. The mover from the source (mcapi-0), right after it froze the
    // shard: the source serves it again when the lease ends, the mover
    // gives up and undoes what it can.
    net.cut_after("mover", "r0", "/freeze?", "r0");
    let started = Instant::now();
    let out = mover(
        &net,
        [
            "move",
            "--data-dir",
            &data,
            "--shard",
            &shard_key(shard_b),
            "--to",
            "mcapi-1",
            "--freeze-lease-ms",
            &LEASE_MS.to_string(),
        ]
        .map(String::from)
        .to_vec(),
    )
    .await;
    let gave_up = Instant::now();
    assert!(
        !out.status.success(),
        "the move had to fail: {}",
        text(&out.stdout)
    );
    assert!(
        text(&out.stderr).contains("failed; undone"),
        "{}",
        text(&out.stderr)
    );
    let (frozen_at, thawed_at) = {
        let s = seen(&live, b);
        let frozen_at = *s
            .moving
            .iter()
            .find(|t| **t > started)
            .expect("the frozen shard refused an observation");
        let thawed_at = *s
            .acks
            .iter()
            .find(|t| **t > frozen_at)
            .expect("the shard served again");
        (frozen_at, thawed_at)
    };
    assert!(
        thawed_at < gave_up,
        "served again only after the mover gave up ({:?} after the freeze)",
        thawed_at - frozen_at
    );
    let thawed_by_lease = thawed_at - frozen_at;
    assert!(
        thawed_by_lease < Duration::from_millis(LEASE_MS) + Duration::from_secs(3),
        "frozen for {thawed_by_lease:?} with a {LEASE_MS} ms lease"
    );
    assert_eq!(map_of(&cluster).owners(), map0.owners(), "nothing moved");
    assert_one_owner(
        &listings(&client, &cluster).await,
        &map0,
        &[],
        "mover cut from mcapi-0",
    );
    net.heal();
    let healed = Instant::now();
    let heal_mover = served_again(&live, &ids, &all, healed, "mover cut from mcapi-0").await;
    let status = mover(
        &net,
        ["status", "--data-dir", &data].map(String::from).to_vec(),
    )
    .await;
    assert!(
        status.status.success(),
        "{}{}",
        text(&status.stdout),
        text(&status.stderr)
    );

    // 3. The target (mcapi-2) cut from the source (mcapi-1) and, right
    // after the source's commit, from the mover: half-moved.
    net.cut("r1", "r2");
    net.cut_after("mover", "r1", "/commit?", "r2");
    let out = mover(
        &net,
        [
            "move",
            "--data-dir",
            &data,
            "--shard",
            &shard_key(shard_c),
            "--to",
            "mcapi-2",
            "--freeze-lease-ms",
            &LEASE_MS.to_string(),
        ]
        .map(String::from)
        .to_vec(),
    )
    .await;
    assert!(
        !out.status.success(),
        "the move had to stop: {}",
        text(&out.stdout)
    );
    assert!(
        text(&out.stderr).contains("mcapi-2"),
        "{}",
        text(&out.stderr)
    );
    let map1 = map_of(&cluster);
    assert_eq!(
        map1.owner(shard_c).as_str(),
        "mcapi-2",
        "the commit point was passed"
    );
    assert_eq!(map1.epoch(), map0.epoch() + 1);
    // Past the freeze's lease, no replica serves the shard: the source gave
    // it away (421 naming the target) and the target has not activated it.
    let probed = probe(&client, &cluster, &ids[c]).await;
    assert!(probed.values().all(|(s, _)| *s == 421), "{probed:?}");
    assert_eq!(
        probed["mcapi-1"].1.as_deref(),
        Some("mcapi-2"),
        "{probed:?}"
    );
    assert_eq!(
        router_owners(&cluster, shard_c),
        ["mcapi-1"],
        "the router's one owner"
    );
    let half = listings(&client, &cluster).await;
    assert_one_owner(&half, &map1, &[shard_c], "half-moved");
    // Fenced by the epoch: the source gave the shard away at the new
    // epoch, the target has not taken it.
    assert_eq!(
        epoch_of(&half, "mcapi-1"),
        map1.epoch(),
        "the source's epoch"
    );
    assert!(
        epoch_of(&half, "mcapi-2") < map1.epoch(),
        "the target's epoch"
    );
    assert!(
        half.iter().all(|l| !matches!(
            l.shards[usize::from(shard_c)].state.as_str(),
            "owned" | "frozen"
        )),
        "a half-moved shard is served by nobody"
    );
    let before_heal = seen(&live, c).acks.len();
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(
        seen(&live, c).acks.len(),
        before_heal,
        "a half-moved shard answered"
    );
    net.heal();
    let healed = Instant::now();
    let out = mover(
        &net,
        [
            "move",
            "--data-dir",
            &data,
            "--shard",
            &shard_key(shard_c),
            "--to",
            "mcapi-2",
        ]
        .map(String::from)
        .to_vec(),
    )
    .await;
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        text(&out.stdout).contains("already"),
        "{}",
        text(&out.stdout)
    );
    let heal_target = served_again(&live, &ids, &all, healed, "mcapi-2 cut after the commit").await;
    assert_eq!(
        router_owners(&cluster, shard_c),
        ["mcapi-2"],
        "the router's one owner"
    );
    let status = mover(
        &net,
        ["status", "--data-dir", &data].map(String::from).to_vec(),
    )
    .await;
    assert!(
        status.status.success(),
        "{}{}",
        text(&status.stdout),
        text(&status.stderr)
    );

    // 4. The source (mcapi-2) answers its commit into the void, and stays
    // cut from the mover: the mover cannot know whether the commit was
    // made, so it undoes nothing; after the heal, `rebalance` finishes
    // the commit. (Moving to mcapi-1 leaves every replica's share as it
    // was: the rebalance has nothing else to move.)
    let d = on("mcapi-2")[0];
    let shard_d = shard(d);
    let map_c = map_of(&cluster);
    net.cut_answers_after("mover", "r2", "/commit?");
    let out = mover(
        &net,
        [
            "move",
            "--data-dir",
            &data,
            "--shard",
            &shard_key(shard_d),
            "--to",
            "mcapi-1",
            "--freeze-lease-ms",
            &LEASE_MS.to_string(),
            "--call-timeout-secs",
            "3",
        ]
        .map(String::from)
        .to_vec(),
    )
    .await;
    assert!(
        !out.status.success(),
        "the move had to stop: {}",
        text(&out.stdout)
    );
    assert!(
        text(&out.stderr).contains("nothing undone"),
        "{}",
        text(&out.stderr)
    );
    let unknown = listings(&client, &cluster).await;
    let line = |r: &str| {
        let l = unknown.iter().find(|l| l.replica == r).expect("a listing");
        let line = &l.shards[usize::from(shard_d)];
        (line.state.clone(), line.owner.clone())
    };
    assert_eq!(
        line("mcapi-2"),
        ("foreign".into(), "mcapi-1".into()),
        "the source committed"
    );
    assert_eq!(line("mcapi-1").0, "importing", "the target's copy is kept");
    assert_eq!(
        map_of(&cluster).owners(),
        map_c.owners(),
        "the map was not written"
    );
    assert_one_owner(&unknown, &map_c, &[shard_d], "commit unanswered");
    let probed = probe(&client, &cluster, &ids[d]).await;
    assert!(probed.values().all(|(s, _)| *s == 421), "{probed:?}");
    net.heal();
    let healed = Instant::now();
    let out = mover(
        &net,
        ["rebalance", "--data-dir", &data, "--replicas", "3"]
            .map(String::from)
            .to_vec(),
    )
    .await;
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        text(&out.stderr).contains("repaired 1 shards"),
        "{}",
        text(&out.stderr)
    );
    assert!(
        text(&out.stdout).contains(": 0 shards moved"),
        "{}",
        text(&out.stdout)
    );
    let heal_commit = served_again(&live, &ids, &all, healed, "a commit's answer lost").await;
    assert_eq!(
        router_owners(&cluster, shard_d),
        ["mcapi-1"],
        "the router's one owner"
    );

    stop.store(true, Ordering::Relaxed);
    let mut walks = Vec::new();
    for d in drivers {
        walks.push(d.await.expect("a driver"));
    }

    // Nothing lost, nothing applied twice, one replica at a time.
    let map = map_of(&cluster);
    let after = listings(&client, &cluster).await;
    assert_one_owner(&after, &map, &[], "after the heals");
    for r in ["mcapi-1", "mcapi-2"] {
        assert_eq!(epoch_of(&after, r), map.epoch(), "{r}'s epoch");
    }
    let mut report = Report {
        heal_router,
        heal_mover,
        heal_target,
        heal_commit,
        thawed_by_lease,
        sessions: walks.len(),
        acked: 0,
        replayed: 0,
        refused: 0,
        unanswered: 0,
        errors: Vec::new(),
    };
    for (i, w) in walks.iter().enumerate() {
        let (code, info) = common::rest_get(&client, &base, None, &w.id).await;
        assert_eq!(code, 200, "{info}");
        assert_eq!(
            info["next_seq"].as_u64(),
            Some(w.applied.len() as u64),
            "{}: applied as often as acknowledged",
            w.id
        );
        check_session(&client, &base, None, &w.id, &w.params, &w.applied, &w.id).await;
        let owner = owner_of(&map, &w.id);
        let answers = probe(&client, &cluster, &w.id).await;
        let serving: Vec<&String> = answers
            .iter()
            .filter(|(_, (s, _))| *s == 200)
            .map(|(n, _)| n)
            .collect();
        assert_eq!(serving, [&owner], "{}: {answers:?}", w.id);
        let s = seen(&live, i);
        let mut replicas: Vec<&str> = s.by.iter().map(|(r, _)| r.as_str()).collect();
        replicas.dedup();
        let moves = usize::from(shard(i) == shard_c || shard(i) == shard_d);
        assert!(
            replicas.len() <= 1 + moves && replicas.last() == Some(&owner.as_str()),
            "{}: answered by {replicas:?} in turn",
            w.id
        );
        report.acked += s.by.len();
        report.replayed += s.by.iter().filter(|(_, r)| *r).count();
        report.refused += s.refused;
        report.unanswered += s.unanswered;
        for e in &s.errors {
            if report.errors.len() < 5 {
                report.errors.push(e.clone());
            }
        }
    }
    assert!(
        report.replayed > 0,
        "no observation was replayed: no answer was lost, so exactly-once was not put to the test"
    );
    let (status, _) = cluster.terminate();
    assert!(status.success(), "{}", cluster.err());
    report
}

#[test]
fn partitions_lose_nothing_apply_nothing_twice_and_heal() {
    let name = "partitions_lose_nothing_apply_nothing_twice_and_heal";
    if !haproxy_or_skip(name) {
        return;
    }
    if let Err(why) = netns::usable() {
        eprintln!("SKIPPED {name}: network namespaces unusable here: {why}");
        return;
    }
    netns::remove_stale();
    let started = Instant::now();
    let net = Arc::new(Net::create(&MEMBERS));
    let tmp = tempfile::tempdir().expect("tempdir");
    let (inner, dir) = (net.clone(), tmp.path().to_path_buf());
    // The test's client lives in the `ctl` namespace: this thread enters
    // it, and the runtime's threads, started from it, are there too.
    let outcome = std::thread::spawn(move || {
        inner.enter("ctl");
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("runtime");
        runtime.block_on(partitioned(inner, dir))
    })
    .join();
    let r = match outcome {
        Ok(r) => r,
        Err(panic) => {
            eprintln!("partitions: namespaces {:?} (removed now)", net.names());
            std::panic::resume_unwind(panic)
        }
    };
    eprintln!(
        "partitions: {} sessions, {} acknowledged observations ({} replayed after a lost answer), \
         {} refused and {} unanswered attempts; served again after the heal within {:.1} s (router \
         cut from a replica), {:.1} s (mover cut from a source), {:.1} s (target cut after the \
         commit, `move` run again), {:.1} s (a commit's answer lost, `rebalance` run); a frozen \
         shard thawed by its lease after {:.1} s; {:.1} s in all; first errors: {:?}",
        r.sessions,
        r.acked,
        r.replayed,
        r.refused,
        r.unanswered,
        r.heal_router.as_secs_f64(),
        r.heal_mover.as_secs_f64(),
        r.heal_target.as_secs_f64(),
        r.heal_commit.as_secs_f64(),
        r.thawed_by_lease.as_secs_f64(),
        started.elapsed().as_secs_f64(),
        r.errors
    );
}
