//! A cluster over real sockets (docs/cluster.md): three replicas of the
//! debug binary with a shard map from `mcapi cluster plan`, behind a real
//! HAProxy configured by `mcapi cluster haproxy-config`. Sessions go
//! through the router over REST and gRPC and land on their shard's owner;
//! a replica hit directly for a foreign shard answers 421 / UNAVAILABLE
//! naming the owner; a shard flipped live through HAProxy's Runtime API
//! (`set map`) is routed to its new replica at once. Also: what a replica
//! restarted with a different map serves, and the shard maps a replica
//! refuses before it opens a port.
//!
//! `mcapi cluster local` is tested whole as well: three replicas and HAProxy
//! started by one command, sessions driven through the router over REST and
//! gRPC, one replica killed with SIGKILL and started again by the
//! supervisor with every session bit-equal to a replay of its acknowledged
//! observations, SIGTERM leaving no process behind, and a second start on
//! the same directory serving the same sessions.
//!
//! Needs `haproxy` (Debian's package; `.ci/run` installs it): without it on
//! PATH these tests fail, unless `MCAPI_SKIP_HAPROXY` is set, when they say
//! so and return.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::{
    Launch, Obs, Reply, Server, available, check_session, free_ports, grpc_create, grpc_request,
    http_client, observe_one, params, rest_create, step_state, stimulus,
};
use mcapi_cluster::haproxy::{find_haproxy, runtime_command, set_owner};
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_shards::{ReplicaName, ShardMap, shard_key, shard_of_id};
use serde_json::{Value, json};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::transport::Channel;

fn mcapi(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args(args)
        .env_remove("MCAPI_SHARD_MAP")
        .env_remove("MCAPI_REPLICA")
        .output()
        .expect("mcapi runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Whether a test that needs `haproxy` can run. Missing, it fails the
/// test, unless `MCAPI_SKIP_HAPROXY` is set: then the test says it skips
/// and returns (CI installs haproxy, so there it always runs).
fn haproxy_or_skip(test: &str) -> bool {
    if find_haproxy().is_some() {
        return true;
    }
    assert!(
        std::env::var_os("MCAPI_SKIP_HAPROXY").is_some(),
        "{test}: `haproxy` is not on PATH (apt-get install haproxy); set MCAPI_SKIP_HAPROXY=1 to skip this test"
    );
    eprintln!("SKIPPED {test}: `haproxy` is not on PATH and MCAPI_SKIP_HAPROXY is set");
    false
}

/// A running HAProxy, killed when dropped.
struct Router {
    child: Child,
    rest: u16,
    grpc: u16,
    socket: PathBuf,
    map_path: PathBuf,
    log: PathBuf,
}

impl Drop for Router {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Router {
    fn base(&self) -> String {
        format!("http://127.0.0.1:{}", self.rest)
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    async fn grpc(&self) -> AgentsClient<Channel> {
        AgentsClient::connect(format!("http://127.0.0.1:{}", self.grpc))
            .await
            .expect("gRPC through the router")
    }
}

/// A REST call: status, the `x-mcapi-replica` and `x-mcapi-owner` headers, the JSON body.
async fn call(
    client: &reqwest::Client,
    method: reqwest::Method,
    url: &str,
    body: Option<Value>,
) -> (u16, Option<String>, Option<String>, Value) {
    let mut req = client.request(method, url);
    if let Some(b) = body {
        req = req.json(&b);
    }
    let resp = req.send().await.expect("request");
    let header = |name: &str| {
        resp.headers()
            .get(name)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string)
    };
    let (replica, owner) = (header("x-mcapi-replica"), header("x-mcapi-owner"));
    let status = resp.status().as_u16();
    let text = resp.text().await.expect("body");
    (
        status,
        replica,
        owner,
        serde_json::from_str(&text).unwrap_or(Value::Null),
    )
}

fn meta(map: &tonic::metadata::MetadataMap, key: &str) -> Option<String> {
    map.get(key)
        .and_then(|v| v.to_str().ok())
        .map(str::to_string)
}

fn owner_of(map: &ShardMap, id: &str) -> String {
    map.owner(shard_of_id(id).expect("id has a shard"))
        .to_string()
}

/// A later hallway observation: the agent stayed in state 25.
fn stay(id: &str) -> pb::Observation {
    pb::Observation {
        session_id: id.to_string(),
        state: 25,
        stimulus: Some(pb::Stimulus {
            values: vec![0.0, 0.0],
        }),
        action_taken: Some(pb::observation::ActionTaken::ActionName("stay".into())),
        ..Default::default()
    }
}

/// Plans a map of `n` replicas with the CLI into `path`.
fn plan(path: &Path, n: usize) -> ShardMap {
    let out = mcapi(&[
        "cluster",
        "plan",
        "--replicas",
        &n.to_string(),
        "--out",
        path.to_str().expect("utf-8"),
    ]);
    assert!(out.status.success(), "plan: {}", stderr(&out));
    assert!(
        stderr(&out).contains(&format!("epoch 1: {n} replicas")),
        "{}",
        stderr(&out)
    );
    ShardMap::read(path).expect("the planned map reads back")
}

async fn start_replica(dir: &Path, map: &Path, name: &str, extra: &[&str]) -> Server {
    let data = dir.join(format!("data-{name}"));
    let mut args = vec![
        "--shard-map",
        map.to_str().expect("utf-8"),
        "--replica",
        name,
    ];
    args.extend_from_slice(extra);
    Server::start(&Launch::new(&data, &args), dir.join(format!("{name}.log"))).await
}

async fn start_router(dir: &Path, map: &Path, replicas: &[(&str, &Server)]) -> Router {
    let haproxy = find_haproxy().expect("checked by the caller");
    let (rest, grpc) = free_ports();
    let out_dir = dir.join("router");
    let mut args: Vec<String> = [
        "cluster",
        "haproxy-config",
        "--map",
        map.to_str().expect("utf-8"),
        "--out-dir",
        out_dir.to_str().expect("utf-8"),
        "--rest-bind",
        &format!("127.0.0.1:{rest}"),
        "--grpc-bind",
        &format!("127.0.0.1:{grpc}"),
    ]
    .map(String::from)
    .to_vec();
    for (name, s) in replicas {
        args.push("--backend".into());
        args.push(format!("{name}=127.0.0.1:{},127.0.0.1:{}", s.http, s.grpc));
    }
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    let out = mcapi(&refs);
    assert!(out.status.success(), "haproxy-config: {}", stderr(&out));
    let cfg = out_dir.join("haproxy.cfg");
    let check = Command::new(&haproxy)
        .args(["-c", "-f"])
        .arg(&cfg)
        .output()
        .expect("haproxy -c");
    assert!(
        check.status.success(),
        "haproxy refuses the generated config: {}{}",
        String::from_utf8_lossy(&check.stdout),
        stderr(&check)
    );
    let log = dir.join("haproxy.log");
    let child = Command::new(&haproxy)
        .arg("-db")
        .arg("-f")
        .arg(&cfg)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::from(std::fs::File::create(&log).expect("log")))
        .spawn()
        .expect("haproxy starts");
    let router = Router {
        child,
        rest,
        grpc,
        socket: out_dir.join("admin.sock"),
        map_path: out_dir.join("shards.map"),
        log,
    };
    // Up once every replica answers /readyz through it (each in turn).
    let client = http_client();
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut seen = std::collections::HashSet::new();
    while seen.len() < replicas.len() {
        assert!(
            Instant::now() < deadline,
            "the router did not reach every replica: {seen:?}; log:\n{}",
            router.log_text()
        );
        if let Ok(r) = client
            .get(format!("{}/v1/sessions", router.base()))
            .send()
            .await
            && r.status() == 200
            && let Some(v) = r.headers().get("x-mcapi-replica")
        {
            seen.insert(v.to_str().unwrap_or_default().to_string());
            continue;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    router
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_replicas_behind_haproxy_route_by_shard() {
    if !haproxy_or_skip("three_replicas_behind_haproxy_route_by_shard") {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let map_path = dir.path().join("shards.map");
    let map = plan(&map_path, 3);
    let names = ["mcapi-0", "mcapi-1", "mcapi-2"];
    let mut replicas = Vec::new();
    for name in names {
        replicas.push(start_replica(dir.path(), &map_path, name, &["--store", "memory"]).await);
    }
    let pairs: Vec<(&str, &Server)> = names.iter().copied().zip(replicas.iter()).collect();
    let router = start_router(dir.path(), &map_path, &pairs).await;
    let client = http_client();
    let by_name = |n: &str| &replicas[names.iter().position(|x| *x == n).expect("known")];

    // REST creates go round-robin; each replica mints in a shard it owns.
    let mut ids = Vec::new();
    let mut created_on = std::collections::BTreeMap::<String, usize>::new();
    for _ in 0..12 {
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::POST,
            &format!("{}/v1/sessions", router.base()),
            Some(json!({"model": {"preset": "hallway"}})),
        )
        .await;
        assert_eq!(status, 201, "{body}");
        let id = body["id"].as_str().expect("id").to_string();
        let replica = replica.expect("x-mcapi-replica on a create");
        assert_eq!(
            owner_of(&map, &id),
            replica,
            "{id} minted outside its replica's shards"
        );
        *created_on.entry(replica).or_default() += 1;
        ids.push(id);
    }
    assert_eq!(
        created_on.len(),
        3,
        "creates reach every replica: {created_on:?}"
    );

    // gRPC creates too, without session metadata: round-robin.
    let mut grpc = router.grpc().await;
    let mut grpc_on = std::collections::BTreeSet::new();
    for _ in 0..6 {
        let reply = grpc
            .create_session(grpc_request(
                pb::CreateSessionRequest {
                    model: Some(pb::Model::preset("hallway")),
                    ..Default::default()
                },
                None,
                None,
            ))
            .await
            .expect("gRPC create through the router");
        let replica = meta(reply.metadata(), "x-mcapi-replica").expect("replica metadata");
        let id = reply.into_inner().id;
        assert_eq!(owner_of(&map, &id), replica);
        grpc_on.insert(replica);
        ids.push(id);
    }
    assert!(grpc_on.len() >= 2, "gRPC creates spread: {grpc_on:?}");

    // Every session, over both transports through the router, reaches its owner.
    for (k, id) in ids.iter().enumerate() {
        let owner = owner_of(&map, id);
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::POST,
            &format!("{}/v1/sessions/{id}/observations", router.base()),
            Some(json!({"state": 25})),
        )
        .await;
        assert_eq!(
            (status, replica.as_deref()),
            (200, Some(owner.as_str())),
            "{id}: {body}"
        );
        // Two requests in a row for one session: round-robin would send
        // them to two different replicas, so both reaching the owner shows
        // the routing by shard (the creates above ran in the same rotation,
        // which one request per session could match by chance).
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::GET,
            &format!("{}/v1/sessions/{id}/history?limit=1", router.base()),
            None,
        )
        .await;
        assert_eq!(
            (status, replica.as_deref()),
            (200, Some(owner.as_str())),
            "{id}: {body}"
        );
        let reply = grpc
            .observe(grpc_request(
                pb::ObserveRequest {
                    session_id: id.clone(),
                    observations: vec![stay("")],
                },
                None,
                Some(id),
            ))
            .await
            .unwrap_or_else(|s| panic!("gRPC observe {id} (#{k}): {s:?}"));
        assert_eq!(
            meta(reply.metadata(), "x-mcapi-replica").as_deref(),
            Some(owner.as_str())
        );
        assert_eq!(reply.into_inner().steps[0].tick, 1);
        // Again right after: the routing is by metadata, not the rotation.
        let reply = grpc
            .get_history(grpc_request(
                pb::GetHistoryRequest {
                    session_id: id.clone(),
                    limit: Some(1),
                },
                None,
                Some(id),
            ))
            .await
            .unwrap_or_else(|s| panic!("gRPC history {id} (#{k}): {s:?}"));
        assert_eq!(meta(reply.metadata(), "x-mcapi-replica"), Some(owner));
    }

    // A bidirectional stream through the router, on its session's owner.
    let id = &ids[0];
    let (tx, rx) = mpsc::channel(4);
    let mut req = tonic::Request::new(ReceiverStream::new(rx));
    req.metadata_mut()
        .insert("x-mcapi-session", id.parse().expect("ascii"));
    let mut steps = grpc.interact(req).await.expect("interact").into_inner();
    for tick in 2..=4 {
        tx.send(stay(id)).await.expect("send");
        let step = steps.message().await.expect("step").expect("a step");
        assert_eq!(step.tick, tick);
    }
    drop(tx);

    // Metadata naming another session than the message: INVALID_ARGUMENT.
    let e = grpc
        .get_session(grpc_request(
            pb::GetSessionRequest {
                session_id: ids[0].clone(),
            },
            None,
            Some(&ids[1]),
        ))
        .await
        .expect_err("mismatch");
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");

    // A replica asked directly for a shard it does not own: 421 / UNAVAILABLE naming the owner.
    let owner = owner_of(&map, id);
    let other = names.iter().find(|n| **n != owner).expect("another");
    let wrong = by_name(other);
    let (status, replica, owner_header, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{id}", wrong.base()),
        None,
    )
    .await;
    assert_eq!(status, 421, "{body}");
    assert_eq!(body["code"], "wrong_replica");
    assert!(
        body["message"]
            .as_str()
            .expect("message")
            .contains(&format!("`{owner}`")),
        "{body}"
    );
    assert_eq!(owner_header.as_deref(), Some(owner.as_str()));
    assert_eq!(replica.as_deref(), Some(*other));
    let e = wrong
        .grpc_client()
        .await
        .get_session(grpc_request(
            pb::GetSessionRequest {
                session_id: id.clone(),
            },
            None,
            Some(id),
        ))
        .await
        .expect_err("misdirected");
    assert_eq!(e.code(), Code::Unavailable, "{e:?}");
    assert_eq!(meta(e.metadata(), "x-mcapi-owner"), Some(owner.clone()));
    assert_eq!(
        meta(e.metadata(), "x-mcapi-error-code").as_deref(),
        Some("wrong_replica")
    );

    // Flip the session's shard to another replica live (Runtime API, no
    // reload): the router sends it there at once, and that replica, the
    // authority, refuses with 421 naming the owner of its map.
    let shard = shard_of_id(id).expect("shard");
    let to = ReplicaName::parse(other).expect("name");
    set_owner(&router.socket, &router.map_path, shard, &to).expect("set map");
    let shown = runtime_command(
        &router.socket,
        &format!("show map {}", router.map_path.display()),
    )
    .expect("show map");
    assert!(
        shown.contains(&format!("{} {other}", shard_key(shard))),
        "the live map has the flip: {}",
        shown.lines().take(3).collect::<Vec<_>>().join(" | ")
    );
    let (status, replica, owner_header, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{id}", router.base()),
        None,
    )
    .await;
    assert_eq!((status, replica.as_deref()), (421, Some(*other)), "{body}");
    assert_eq!(owner_header.as_deref(), Some(owner.as_str()));
    let e = grpc
        .get_session(grpc_request(
            pb::GetSessionRequest {
                session_id: id.clone(),
            },
            None,
            Some(id),
        ))
        .await
        .expect_err("flipped");
    assert_eq!(e.code(), Code::Unavailable);
    assert_eq!(
        meta(e.metadata(), "x-mcapi-replica").as_deref(),
        Some(*other)
    );
    // Only that shard moved: a session of another shard still reaches its owner.
    let steady = ids
        .iter()
        .find(|i| shard_of_id(i) != Some(shard))
        .expect("another session");
    let (status, replica, _, _) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{steady}", router.base()),
        None,
    )
    .await;
    assert_eq!((status, replica), (200, Some(owner_of(&map, steady))));
    // Flipped back, the session is served again by its owner.
    set_owner(
        &router.socket,
        &router.map_path,
        shard,
        &ReplicaName::parse(&owner).expect("name"),
    )
    .expect("set map back");
    let (status, replica, _, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{id}", router.base()),
        None,
    )
    .await;
    assert_eq!(
        (status, replica.as_deref()),
        (200, Some(owner.as_str())),
        "{body}"
    );
    assert_eq!(body["tick"], 4);
    // The Runtime API refuses a key the map does not have.
    assert!(
        set_owner(&router.socket, Path::new("/nonexistent.map"), 0, &to).is_err(),
        "an unknown map is refused"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_replica_keeps_but_does_not_serve_shards_it_lost() {
    let dir = tempfile::tempdir().expect("tempdir");
    let v1 = dir.path().join("v1.map");
    let map = plan(&v1, 2);
    let mut server = start_replica(dir.path(), &v1, "mcapi-0", &[]).await;
    let client = http_client();
    let mut ids = Vec::new();
    for _ in 0..6 {
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::POST,
            &format!("{}/v1/sessions", server.base()),
            Some(json!({"model": {"preset": "hallway"}})),
        )
        .await;
        assert_eq!(
            (status, replica.as_deref()),
            (201, Some("mcapi-0")),
            "{body}"
        );
        ids.push(body["id"].as_str().expect("id").to_string());
    }
    assert!(ids.iter().all(|id| owner_of(&map, id) == "mcapi-0"));
    server.terminate();

    // Epoch 2 gives the first session's shard to mcapi-1.
    let lost = shard_of_id(&ids[0]).expect("shard");
    let mut owners = map.owners();
    owners[usize::from(lost)] = ReplicaName::parse("mcapi-1").expect("name");
    let v2 = dir.path().join("v2.map");
    std::fs::write(
        &v2,
        ShardMap::from_owners(2, &owners).expect("map").to_text(),
    )
    .expect("write");
    let mut server = start_replica(dir.path(), &v2, "mcapi-0", &[]).await;
    let (status, _, owner, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{}", server.base(), ids[0]),
        None,
    )
    .await;
    assert_eq!((status, owner.as_deref()), (421, Some("mcapi-1")), "{body}");
    assert!(
        body["message"]
            .as_str()
            .expect("message")
            .contains("epoch 2"),
        "{body}"
    );
    for id in ids.iter().filter(|i| shard_of_id(i) != Some(lost)) {
        let (status, _, _, body) = call(
            &client,
            reqwest::Method::GET,
            &format!("{}/v1/sessions/{id}", server.base()),
            None,
        )
        .await;
        assert_eq!(status, 200, "{body}");
    }
    let (_, _, _, page) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions", server.base()),
        None,
    )
    .await;
    let listed: Vec<&str> = page["sessions"]
        .as_array()
        .expect("sessions")
        .iter()
        .filter_map(|s| s["id"].as_str())
        .collect();
    assert!(
        !listed.contains(&ids[0].as_str()),
        "a lost shard's session is not listed"
    );
    let events = common::log_events(
        &server.log_text(),
        "stored sessions of shards this replica does not own are kept in the store, not served",
    );
    let kept = ids.iter().filter(|i| shard_of_id(i) == Some(lost)).count();
    assert_eq!(events.len(), 1, "{}", server.log_text());
    assert_eq!(events[0]["sessions"], kept);
    server.terminate();

    // Back on the epoch-1 map, the kept session is served again, intact.
    let server = start_replica(dir.path(), &v1, "mcapi-0", &[]).await;
    let (status, _, _, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{}", server.base(), ids[0]),
        None,
    )
    .await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["id"], ids[0].as_str());
}

#[test]
fn absurd_shard_maps_and_cluster_flags_are_refused_before_any_port_opens() {
    let dir = tempfile::tempdir().expect("tempdir");
    let good = dir.path().join("good.map");
    let map = plan(&good, 2);
    let text = map.to_text();
    let write = |name: &str, body: &[u8]| {
        let p = dir.path().join(name);
        std::fs::write(&p, body).expect("write");
        p
    };
    let dup = write("dup.map", format!("{text}s0002 mcapi-0\n").as_bytes());
    let missing = write(
        "missing.map",
        text.lines()
            .filter(|l| !l.starts_with("s01"))
            .collect::<Vec<_>>()
            .join("\n")
            .as_bytes(),
    );
    let epoch = write(
        "epoch.map",
        text.replace("epoch 1", "epoch zero").as_bytes(),
    );
    let huge = write("huge.map", &vec![b'#'; 8 << 20]);
    let binary = write("binary.map", &[0xff; 64]);
    let (http, grpc) = free_ports();
    let serve = |extra: &[&str]| {
        let mut args = vec![
            "serve".to_string(),
            "--store".into(),
            "memory".into(),
            "--http".into(),
            format!("127.0.0.1:{http}"),
            "--grpc".into(),
            format!("127.0.0.1:{grpc}"),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let started = Instant::now();
        let out = mcapi(&refs);
        assert!(!out.status.success(), "{extra:?} was accepted");
        assert!(started.elapsed() < Duration::from_secs(20));
        stderr(&out)
    };
    let p = |p: &PathBuf| p.to_str().expect("utf-8").to_string();
    for (file, want) in [
        (
            &dup,
            "line 1027: shard s0002 is assigned again (first on line 5)",
        ),
        (
            &missing,
            "256 of the 1024 shards have no owner: s0100, s0101",
        ),
        (&epoch, "line 2: the epoch `zero` is not a whole number"),
        (&huge, "larger than 262144 bytes"),
        (&binary, "not UTF-8"),
        (&dir.path().join("absent.map"), "absent.map"),
    ] {
        let e = serve(&["--shard-map", &p(file), "--replica", "mcapi-0"]);
        assert!(e.contains(want), "{}: want {want:?} in {e}", file.display());
        assert!(!e.contains("binding"), "refused before binding: {e}");
    }
    let e = serve(&["--shard-map", &p(&good), "--replica", "mcapi-7"]);
    assert!(
        e.contains("`mcapi-7` owns no shard") && e.contains("mcapi-0, mcapi-1"),
        "{e}"
    );
    let e = serve(&["--shard-map", &p(&good), "--replica", "Not_A_Name"]);
    assert!(e.contains("only a-z, 0-9 and `-`"), "{e}");
    let e = serve(&["--shard-map", &p(&good)]);
    assert!(e.contains("--replica"), "{e}");
    let e = serve(&["--replica", "mcapi-0"]);
    assert!(e.contains("--shard-map"), "{e}");

    // plan --from: 2 -> 3 replicas moves a third, all to the new one.
    let out = mcapi(&["cluster", "plan", "--replicas", "3", "--from", &p(&good)]);
    assert!(out.status.success(), "{}", stderr(&out));
    let next = ShardMap::parse(&String::from_utf8_lossy(&out.stdout)).expect("a map on stdout");
    assert_eq!(next.epoch(), 2);
    let moved = (0..1024u16)
        .filter(|&s| next.owner(s) != map.owner(s))
        .count();
    assert!(
        stderr(&out).contains(&format!("{moved} of 1024 shards move"))
            && stderr(&out).contains(&format!("{moved} to mcapi-2")),
        "{}",
        stderr(&out)
    );
    assert!((330..=345).contains(&moved), "{moved}");
}

// ------------------------------------------------------- mcapi cluster local

/// A running `mcapi cluster local`, killed (SIGKILL) when dropped; its
/// children then get SIGTERM from the kernel (PR_SET_PDEATHSIG).
struct LocalCluster {
    child: Child,
    dir: PathBuf,
    http: u16,
    grpc: u16,
    stdout: PathBuf,
    stderr: PathBuf,
}

impl Drop for LocalCluster {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl LocalCluster {
    /// Starts it on fresh router ports and waits for its banner (every
    /// replica and the router ready).
    fn start(dir: &Path, extra: &[&str], run: &str) -> Self {
        let (http, grpc) = free_ports();
        let stdout = dir.join(format!("local-{run}.out"));
        let stderr = dir.join(format!("local-{run}.err"));
        let data = dir.join("cluster");
        let mut args: Vec<String> = [
            "cluster",
            "local",
            "--http",
            &format!("127.0.0.1:{http}"),
            "--grpc",
            &format!("127.0.0.1:{grpc}"),
            "--data-dir",
            data.to_str().expect("utf-8"),
        ]
        .map(String::from)
        .to_vec();
        args.extend(extra.iter().map(|s| s.to_string()));
        args.extend(["--", "--workers", "2"].map(String::from));
        let child = Command::new(env!("CARGO_BIN_EXE_mcapi"))
            .args(&args)
            .env_remove("MCAPI_SHARD_MAP")
            .env_remove("MCAPI_REPLICA")
            .stdin(Stdio::null())
            .stdout(Stdio::from(std::fs::File::create(&stdout).expect("stdout")))
            .stderr(Stdio::from(std::fs::File::create(&stderr).expect("stderr")))
            .spawn()
            .expect("mcapi cluster local starts");
        let mut cluster = Self {
            child,
            dir: data,
            http,
            grpc,
            stdout,
            stderr,
        };
        let deadline = Instant::now() + Duration::from_secs(120);
        while !cluster
            .out()
            .contains("Ctrl-C or SIGTERM stops everything.")
        {
            if let Some(status) = cluster.child.try_wait().expect("try_wait") {
                panic!(
                    "cluster local exited ({status}) before it was up:\n{}",
                    cluster.err()
                );
            }
            assert!(
                Instant::now() < deadline,
                "cluster local not up after 120 s:\n{}",
                cluster.err()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        cluster
    }

    fn out(&self) -> String {
        std::fs::read_to_string(&self.stdout).unwrap_or_default()
    }

    fn err(&self) -> String {
        std::fs::read_to_string(&self.stderr).unwrap_or_default()
    }

    fn base(&self) -> String {
        format!("http://127.0.0.1:{}", self.http)
    }

    /// `cluster.json`.
    fn state(&self) -> Value {
        let text = std::fs::read_to_string(self.dir.join("cluster.json")).expect("cluster.json");
        serde_json::from_str(&text).expect("cluster.json is JSON")
    }

    /// The pid of a process named in `cluster.json` (None while it waits to restart).
    fn pid(&self, name: &str) -> Option<u64> {
        self.state()["processes"]
            .as_array()
            .expect("processes")
            .iter()
            .find(|p| p["name"] == name)
            .and_then(|p| p["pid"].as_u64())
    }

    /// SIGTERM; returns the exit status and how long it took.
    fn terminate(&mut self) -> (std::process::ExitStatus, Duration) {
        let started = Instant::now();
        let stderr = self.stderr.clone();
        let log = move || std::fs::read_to_string(&stderr).unwrap_or_default();
        let status = common::terminate(&mut self.child, Duration::from_secs(60), &log);
        (status, started.elapsed())
    }
}

fn process_exists(pid: u64) -> bool {
    Path::new(&format!("/proc/{pid}")).exists()
}

/// A session as its client knows it: the observations acknowledged, with
/// their replies, for the replay `check_session` compares with.
struct Walk {
    id: String,
    params: mcapi_core::AgentParams,
    grpc: bool,
    applied: Vec<(Obs, Option<Reply>)>,
}

impl Walk {
    /// The next observation: the first puts the agent in state 25; then it
    /// walks right (left at the end), reporting the action it took.
    fn next(&self) -> Obs {
        let Some((last, _)) = self.applied.last() else {
            return Obs {
                state: 25,
                stimulus: None,
                taken: None,
                report: None,
                by_name: false,
            };
        };
        let a = if available(last.state, 1) { 1 } else { 0 };
        let next = step_state(last.state, a);
        Obs {
            state: next,
            stimulus: Some(stimulus(next)),
            taken: Some(a),
            report: Some(a),
            by_name: self.applied.len() % 2 == 0,
        }
    }

    /// One observation through the router, over the session's transport.
    async fn step(
        &mut self,
        client: &reqwest::Client,
        base: &str,
        grpc: &mut AgentsClient<Channel>,
    ) {
        let obs = self.next();
        let reply = observe_one(client, base, grpc, self.grpc, &self.id, &obs).await;
        self.applied.push((obs, Some(reply)));
    }
}

/// Creates `rest` sessions over REST and `grpc` over gRPC through the router.
async fn create_walks(
    client: &reqwest::Client,
    base: &str,
    grpc: &mut AgentsClient<Channel>,
    rest_n: u64,
    grpc_n: u64,
) -> Vec<Walk> {
    let mut walks = Vec::new();
    for seed in 0..rest_n + grpc_n {
        let is_grpc = seed >= rest_n;
        let id = if is_grpc {
            grpc_create(grpc, None, seed, true, None).await
        } else {
            rest_create(
                client,
                base,
                None,
                json!({"seed": seed, "update_mode": "lockstep"}),
            )
            .await
        };
        walks.push(Walk {
            id,
            params: params(seed, None),
            grpc: is_grpc,
            applied: Vec::new(),
        });
    }
    walks
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cluster_local_restarts_a_killed_replica_and_stops_everything() {
    if !haproxy_or_skip("cluster_local_restarts_a_killed_replica_and_stops_everything") {
        return;
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let started = Instant::now();
    let mut cluster = LocalCluster::start(tmp.path(), &["--replicas", "3"], "first");
    let up_in = started.elapsed();
    let state = cluster.state();
    let names: Vec<String> = state["processes"]
        .as_array()
        .expect("processes")
        .iter()
        .map(|p| p["name"].as_str().expect("name").to_string())
        .collect();
    assert_eq!(
        names,
        ["mcapi-0", "mcapi-1", "mcapi-2", "haproxy"],
        "{state}"
    );
    assert_eq!(
        state["supervisor"].as_u64(),
        Some(u64::from(cluster.child.id()))
    );
    let map = ShardMap::read(&cluster.dir.join("shards.map")).expect("the cluster's map");
    for want in [
        format!("REST  http://127.0.0.1:{}", cluster.http),
        format!("gRPC  http://127.0.0.1:{}", cluster.grpc),
        "mcapi-2".to_string(),
    ] {
        assert!(
            cluster.out().contains(&want),
            "banner lacks {want:?}:\n{}",
            cluster.out()
        );
    }

    // Sessions created and driven through the router, over both transports.
    let client = http_client();
    let base = cluster.base();
    let mut grpc = AgentsClient::connect(format!("http://127.0.0.1:{}", cluster.grpc))
        .await
        .expect("gRPC through the router");
    let mut walks = create_walks(&client, &base, &mut grpc, 18, 6).await;
    for w in &mut walks {
        for _ in 0..5 {
            w.step(&client, &base, &mut grpc).await;
        }
    }
    let mut on: std::collections::BTreeMap<String, usize> = Default::default();
    for w in &walks {
        *on.entry(owner_of(&map, &w.id)).or_default() += 1;
    }
    assert_eq!(on.len(), 3, "sessions on every replica: {on:?}");

    // SIGKILL the replica of the first session; the supervisor starts it again.
    let victim = owner_of(&map, &walks[0].id);
    let old_pid = cluster.pid(&victim).expect("the victim runs");
    let killed_at = Instant::now();
    common::signal(u32::try_from(old_pid).expect("a pid"), "-KILL");
    let deadline = killed_at + Duration::from_secs(60);
    let new_pid = loop {
        if let Some(pid) = cluster.pid(&victim)
            && pid != old_pid
        {
            break pid;
        }
        assert!(
            Instant::now() < deadline,
            "{victim} not started again within 60 s:\n{}",
            cluster.err()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let restarted_in = killed_at.elapsed();
    let entry = cluster.state()["processes"]
        .as_array()
        .expect("processes")
        .iter()
        .find(|p| p["name"] == victim.as_str())
        .cloned()
        .expect("victim entry");
    assert_eq!(entry["restarts"], 1, "{entry}");
    assert!(!process_exists(old_pid), "the killed replica is reaped");
    // Served again through the router, over both transports, once it has
    // recovered (the router may answer 503 meanwhile, as it does to any
    // client, which retries).
    let probe = &walks[0].id;
    let (mut attempts, mut rest_back, mut grpc_back) = (0, None, None);
    loop {
        attempts += 1;
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::GET,
            &format!("{base}/v1/sessions/{probe}"),
            None,
        )
        .await;
        let grpc_ok = grpc
            .get_session(grpc_request(
                pb::GetSessionRequest {
                    session_id: probe.clone(),
                },
                None,
                Some(probe),
            ))
            .await;
        let grpc_replica = grpc_ok
            .as_ref()
            .ok()
            .and_then(|r| meta(r.metadata(), "x-mcapi-replica"));
        if status == 200 && rest_back.is_none() {
            rest_back = Some(killed_at.elapsed());
        }
        if grpc_ok.is_ok() && grpc_back.is_none() {
            grpc_back = Some(killed_at.elapsed());
        }
        if status == 200 && grpc_ok.is_ok() {
            assert_eq!(replica.as_deref(), Some(victim.as_str()));
            assert_eq!(grpc_replica.as_deref(), Some(victim.as_str()));
            break;
        }
        assert!(
            Instant::now() < deadline,
            "{probe} not served again within 60 s of the kill: REST {status} {body}; gRPC {:?}",
            grpc_ok.err()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let served_in = killed_at.elapsed();
    let log = cluster.err();
    let logged = |event: &str| {
        log.lines()
            .any(|l| l.contains(event) && l.contains(victim.as_str()))
    };
    assert!(
        logged("exited; starting it again after a backoff") && logged("started again"),
        "the restart is logged:\n{log}"
    );
    // Every session bit-equal to a replay of its acknowledged observations,
    // and writable: the killed replica's through its new process.
    for w in &mut walks {
        check_session(&client, &base, None, &w.id, &w.params, &w.applied, &w.id).await;
        w.step(&client, &base, &mut grpc).await;
    }
    drop(grpc);

    // SIGTERM: replicas drained, then the router; no process left.
    let mut pids: Vec<u64> = names.iter().filter_map(|n| cluster.pid(n)).collect();
    assert_eq!(pids.len(), 4);
    assert!(pids.contains(&new_pid));
    pids.push(u64::from(cluster.child.id()));
    let (status, stop_in) = cluster.terminate();
    assert!(status.success(), "exit {status}:\n{}", cluster.err());
    for pid in &pids {
        assert!(
            !process_exists(*pid),
            "pid {pid} still exists after shutdown"
        );
    }
    assert!(
        std::net::TcpStream::connect(("127.0.0.1", cluster.http)).is_err(),
        "the router's port is closed"
    );
    assert!(
        !cluster.dir.join("cluster.json").exists(),
        "the state file goes with the cluster"
    );
    let log = cluster.err();
    assert!(log.contains("every process stopped"), "{log}");
    drop(cluster);

    // Started again on the same directory (its map, no --replicas): the
    // sessions are all there.
    let cluster = LocalCluster::start(tmp.path(), &[], "second");
    assert_eq!(
        ShardMap::read(&cluster.dir.join("shards.map"))
            .expect("map")
            .to_text(),
        map.to_text(),
        "the map is reused"
    );
    let base = cluster.base();
    for w in &walks {
        check_session(&client, &base, None, &w.id, &w.params, &w.applied, &w.id).await;
    }
    let mut cluster = cluster;
    let (status, _) = cluster.terminate();
    assert!(status.success(), "{}", cluster.err());
    eprintln!(
        "cluster local: up in {:.1} s; killed replica started again in {:.2} s, served through the router in {:.2} s ({attempts} attempts; REST from {:.2} s, gRPC from {:.2} s); stopped in {:.2} s",
        up_in.as_secs_f64(),
        restarted_in.as_secs_f64(),
        served_in.as_secs_f64(),
        rest_back.unwrap_or_default().as_secs_f64(),
        grpc_back.unwrap_or_default().as_secs_f64(),
        stop_in.as_secs_f64()
    );
}

#[test]
fn cluster_local_refuses_bad_flags_before_starting_anything() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("c");
    let data_s = data.to_str().expect("utf-8").to_string();
    let (http, grpc) = free_ports();
    let local = |extra: &[&str]| {
        let mut args = vec![
            "cluster".to_string(),
            "local".into(),
            "--data-dir".into(),
            data_s.clone(),
            "--grpc".into(),
            format!("127.0.0.1:{grpc}"),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let started = Instant::now();
        let out = mcapi(&refs);
        assert!(!out.status.success(), "{extra:?} was accepted");
        assert!(started.elapsed() < Duration::from_secs(20));
        assert!(
            !data.join("cluster.json").exists() && !data.join("logs").exists(),
            "{extra:?}: nothing started"
        );
        stderr(&out)
    };
    let http_flag = format!("127.0.0.1:{http}");
    for n in ["0", "65", "-1", "three"] {
        let e = local(&[&format!("--replicas={n}"), "--http", &http_flag]);
        assert!(e.contains("--replicas"), "{n}: {e}");
    }
    let e = local(&["--replicas", "0", "--http", &http_flag]);
    assert!(e.contains("1..=64"), "{e}");
    let busy = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let busy_addr = busy.local_addr().expect("addr").to_string();
    let e = local(&["--http", &busy_addr]);
    assert!(
        e.contains(&format!("--http {busy_addr} is not free")),
        "{e}"
    );
    let e = local(&["--http", &format!("127.0.0.1:{grpc}")]);
    assert!(e.contains("--http and --grpc must differ"), "{e}");
    let e = local(&["--http", &http_flag, "--haproxy", "/nonexistent/haproxy"]);
    assert!(
        e.contains("--haproxy /nonexistent/haproxy: no such file"),
        "{e}"
    );
    let e = local(&["--http", &http_flag, "--", "--replica", "x"]);
    assert!(e.contains("`--replica` is set by `cluster local`"), "{e}");
    for (flag, arg) in [
        ("--ready-timeout-secs", "0"),
        ("--drain-timeout-secs", "301"),
    ] {
        let e = local(&["--http", &http_flag, flag, arg]);
        assert!(e.contains(flag), "{e}");
    }
    // A directory whose map has 2 replicas is not started with 3 (the
    // haproxy given is any file: the map is checked before it runs).
    std::fs::create_dir_all(&data).expect("mkdir");
    plan(&data.join("shards.map"), 2);
    let e = local(&[
        "--http",
        &http_flag,
        "--replicas",
        "3",
        "--haproxy",
        "/bin/true",
    ]);
    assert!(
        e.contains("has 2 replicas (mcapi-0, mcapi-1), not 3"),
        "{e}"
    );
}

// ------------------------------------------------------------- Kubernetes

/// The text of `key: |` in a generated ConfigMap, de-indented.
fn configmap_block(yaml: &str, key: &str) -> String {
    let head = format!("\n  {key}: |\n");
    let start = yaml
        .find(&head)
        .unwrap_or_else(|| panic!("no {key} in the ConfigMap"))
        + head.len();
    let mut out = String::new();
    for line in yaml[start..].lines() {
        if line.is_empty() {
            out.push('\n');
        } else if let Some(l) = line.strip_prefix("    ") {
            out.push_str(l);
            out.push('\n');
        } else {
            break;
        }
    }
    out
}

#[test]
fn the_committed_kubernetes_configmap_is_what_the_command_writes() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("configmap.yaml");
    let run = Command::new("bash")
        .arg(root.join("tools/k8s-configmap.sh"))
        .arg(&out)
        .env("MCAPI_BIN", env!("CARGO_BIN_EXE_mcapi"))
        .env_remove("REPLICAS")
        .env_remove("MAP")
        .output()
        .expect("bash runs");
    assert!(run.status.success(), "k8s-configmap.sh: {}", stderr(&run));
    let generated = std::fs::read_to_string(&out).expect("generated");
    let committed = std::fs::read_to_string(root.join("deploy/k8s/10-mcapi-cluster.yaml"))
        .expect("deploy/k8s/10-mcapi-cluster.yaml");
    assert!(
        generated == committed,
        "deploy/k8s/10-mcapi-cluster.yaml differs from what `bash tools/k8s-configmap.sh` writes now: run it (make k8s-configmap)"
    );

    // The StatefulSet runs exactly the map's replicas.
    let map = ShardMap::parse(&configmap_block(&committed, "mcapi-shards.map")).expect("the map");
    let sts = std::fs::read_to_string(root.join("deploy/k8s/20-replicas.yaml")).expect("sts");
    let replicas: Vec<&str> = sts
        .lines()
        .filter_map(|l| l.strip_prefix("  replicas: "))
        .collect();
    assert_eq!(
        replicas,
        [map.replicas().len().to_string()],
        "StatefulSet replicas"
    );
    for (k, name) in map.replicas().iter().enumerate() {
        assert_eq!(
            name.as_str(),
            format!("mcapi-{k}"),
            "pod names are the replica names"
        );
    }

    // HAProxy accepts the configuration (with its two paths moved here).
    let cfg = configmap_block(&committed, "haproxy.cfg");
    assert!(cfg.contains("resolvers dns init-addr none"), "{cfg}");
    if !haproxy_or_skip("the_committed_kubernetes_configmap_is_what_the_command_writes") {
        return;
    }
    let map_path = dir.path().join("shards.map");
    std::fs::write(&map_path, configmap_block(&committed, "shards.map")).expect("map");
    let local = cfg
        .replace(
            "/usr/local/etc/haproxy/shards.map",
            map_path.to_str().expect("utf-8"),
        )
        .replace(
            "/var/run/haproxy/admin.sock",
            dir.path().join("admin.sock").to_str().expect("utf-8"),
        );
    let cfg_path = dir.path().join("haproxy.cfg");
    std::fs::write(&cfg_path, local).expect("cfg");
    let check = Command::new(find_haproxy().expect("checked"))
        .args(["-c", "-f"])
        .arg(&cfg_path)
        .output()
        .expect("haproxy -c");
    assert!(
        check.status.success(),
        "haproxy refuses the Kubernetes configuration: {}{}",
        String::from_utf8_lossy(&check.stdout),
        stderr(&check)
    );
}

// ------------------------------------------------------ live shard moves

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

/// Issue 16's test of live moves: 3 replicas behind HAProxy, several
/// hundred sessions driven over REST and gRPC through the router while
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
