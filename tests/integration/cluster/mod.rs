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
//!
//! One module per concern: [`replicas`] (behind HAProxy, and the maps they
//! refuse), [`local`] (`mcapi cluster local`), [`kubernetes`] (the committed
//! ConfigMap), [`shard_moves`] (live moves), [`router`] (no request left
//! unanswered while replicas join), [`leases`] (a dead mover's freeze and
//! half-done move), [`partitions`] (replicas and the router in network
//! namespaces of their own, links cut with iptables under load); the
//! helpers they share (the
//! router, replicas, a local cluster, a driven session) are here.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::{
    Launch, Obs, Reply, Server, available, free_ports, grpc_create, http_client, observe_one,
    params, rest_create, step_state, stimulus,
};
use mcapi_cluster::haproxy::find_haproxy;
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_shards::{ShardMap, shard_of_id};
use serde_json::{Value, json};
use tonic::transport::Channel;

mod kubernetes;
mod leases;
mod local;
mod netns;
mod partitions;
mod replicas;
mod router;
mod shard_moves;

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

// ------------------------------------------------------- mcapi cluster local

/// A running `mcapi cluster local`, killed (SIGKILL) when dropped; its
/// children then get SIGTERM from the kernel (PR_SET_PDEATHSIG).
struct LocalCluster {
    child: Child,
    dir: PathBuf,
    /// The router's address (127.0.0.1 unless it runs in a namespace).
    host: String,
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
        Self::start_at(dir, extra, run, "127.0.0.1", http, grpc)
    }

    /// Starts it with its router on `host`, as [`LocalCluster::start`].
    fn start_at(dir: &Path, extra: &[&str], run: &str, host: &str, http: u16, grpc: u16) -> Self {
        let stdout = dir.join(format!("local-{run}.out"));
        let stderr = dir.join(format!("local-{run}.err"));
        let data = dir.join("cluster");
        let mut args: Vec<String> = [
            "cluster",
            "local",
            "--http",
            &format!("{host}:{http}"),
            "--grpc",
            &format!("{host}:{grpc}"),
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
            host: host.to_string(),
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
        format!("http://{}:{}", self.host, self.http)
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
