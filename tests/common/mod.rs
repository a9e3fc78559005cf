//! Shared helpers of the tests that run the real `mcapi` binary
//! (`tests/integration/crash.rs`, `tests/integration/durability.rs`) or the full server in-process
//! (`tests/integration/parity.rs`, `tests/grpc_model.rs`): starting, killing and stopping
//! a server, REST and gRPC calls with an API key, the client-side hallway
//! and the exact in-memory replay a recovered session is compared with.

// Each test binary uses a different part of this module.
#![allow(dead_code)]

use std::ffi::OsString;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use mcapi_core::model::hallway;
use mcapi_core::{Agent, AgentParams, Basis, Observation, PlanningModel};
use mcapi_server::api::grpc::SESSION_METADATA;
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use rand::RngExt as _;
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use tonic::transport::Channel;

/// Hallway actions, in the preset's order.
pub const ACTIONS: [&str; 3] = ["left", "right", "stay"];
/// States of the hallway.
pub const STATES: usize = 50;

/// `mcapi serve`'s options, parsed as the binary parses them.
#[derive(clap::Parser)]
struct ServeCli {
    #[command(flatten)]
    serve: mcapi_server::config::ServeConfig,
}

/// The full server in this process (`server::start`: both ports on
/// loopback port 0, 2 tick workers, the durable store in `data`).
pub async fn start_in_process(data: &Path) -> mcapi_server::server::Running {
    use clap::Parser;
    let cfg = ServeCli::parse_from([
        "mcapi",
        "--http",
        "127.0.0.1:0",
        "--grpc",
        "127.0.0.1:0",
        "--workers",
        "2",
        "--data-dir",
        data.to_str().expect("utf-8 path"),
    ])
    .serve;
    mcapi_server::server::start(&cfg)
        .await
        .expect("server starts")
}

/// Two distinct ports nothing listens on right now (HTTP, gRPC). Both
/// listeners are held until both ports are known: binding port 0 twice,
/// releasing the first before the second, may return the same port.
pub fn free_ports() -> (u16, u16) {
    let a = TcpListener::bind("127.0.0.1:0").expect("bind");
    let b = TcpListener::bind("127.0.0.1:0").expect("bind");
    let port = |l: &TcpListener| l.local_addr().expect("addr").port();
    (port(&a), port(&b))
}

/// How to start `mcapi serve`.
#[derive(Debug, Clone, Default)]
pub struct Launch {
    /// `--data-dir`.
    pub data_dir: Option<PathBuf>,
    /// Extra flags.
    pub args: Vec<String>,
    /// Environment variables.
    pub env: Vec<(String, String)>,
}

impl Launch {
    /// `--data-dir dir --workers 2 --log-format json` and the given flags.
    pub fn new(data_dir: &Path, args: &[&str]) -> Self {
        Self {
            data_dir: Some(data_dir.to_path_buf()),
            args: args.iter().map(|s| s.to_string()).collect(),
            env: Vec::new(),
        }
    }

    /// Adds an environment variable.
    pub fn env(mut self, key: &str, value: &str) -> Self {
        self.env.push((key.into(), value.into()));
        self
    }
}

/// A running `mcapi serve` child, killed when dropped (a failing test
/// leaves no server behind).
pub struct Server {
    child: Option<Child>,
    /// REST port.
    pub http: u16,
    /// gRPC port.
    pub grpc: u16,
    /// The file its stderr (the log) goes to.
    pub log: PathBuf,
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Spawns `mcapi serve` on the given ports with its log in `log`.
pub fn spawn(launch: &Launch, http: u16, grpc: u16, log: &Path) -> Child {
    let log_file = std::fs::File::create(log).expect("log file");
    let mut args: Vec<OsString> = vec![
        "serve".into(),
        "--http".into(),
        format!("127.0.0.1:{http}").into(),
        "--grpc".into(),
        format!("127.0.0.1:{grpc}").into(),
        "--workers".into(),
        "2".into(),
        "--log-format".into(),
        "json".into(),
    ];
    if let Some(dir) = &launch.data_dir {
        args.push("--data-dir".into());
        args.push(dir.into());
    }
    args.extend(launch.args.iter().map(OsString::from));
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mcapi"));
    cmd.args(&args)
        .env_remove("MCAPI_API_KEYS")
        .env("RUST_LOG", "info")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::from(log_file));
    for (k, v) in &launch.env {
        cmd.env(k, v);
    }
    cmd.spawn().expect("mcapi serve starts")
}

/// A fresh HTTP client (no connections pooled from an earlier server).
pub fn http_client() -> reqwest::Client {
    reqwest::Client::builder()
        .timeout(Duration::from_secs(30))
        .build()
        .expect("http client")
}

impl Server {
    /// Starts the server on fresh ports and waits until `/readyz` answers
    /// 200 (recovery done); `log` names its log file.
    pub async fn start(launch: &Launch, log: PathBuf) -> Self {
        let (http, grpc) = free_ports();
        let child = spawn(launch, http, grpc, &log);
        let mut server = Self {
            child: Some(child),
            http,
            grpc,
            log,
        };
        server.wait_ready(Duration::from_secs(60)).await;
        server
    }

    /// Polls `/readyz` until 200; fails if the process exits first.
    pub async fn wait_ready(&mut self, timeout: Duration) {
        let client = reqwest::Client::builder()
            .timeout(Duration::from_secs(2))
            .build()
            .expect("client");
        let url = format!("{}/readyz", self.base());
        let started = Instant::now();
        loop {
            if let Some(status) = self.child_mut().try_wait().expect("try_wait") {
                panic!(
                    "mcapi serve exited with {status} before becoming ready; log:\n{}",
                    self.log_text()
                );
            }
            if let Ok(resp) = client.get(&url).send().await
                && resp.status() == 200
            {
                return;
            }
            assert!(
                started.elapsed() < timeout,
                "mcapi serve not ready after {timeout:?}; log:\n{}",
                self.log_text()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    fn child_mut(&mut self) -> &mut Child {
        self.child.as_mut().expect("the server is running")
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.as_ref().expect("the server is running").id()
    }

    /// `http://127.0.0.1:<http>`.
    pub fn base(&self) -> String {
        format!("http://127.0.0.1:{}", self.http)
    }

    /// `http://127.0.0.1:<grpc>`.
    pub fn grpc_url(&self) -> String {
        format!("http://127.0.0.1:{}", self.grpc)
    }

    /// A gRPC client.
    pub async fn grpc_client(&self) -> AgentsClient<Channel> {
        AgentsClient::connect(self.grpc_url())
            .await
            .expect("gRPC connects")
    }

    /// The log so far.
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// `kill -9`: no shutdown, no snapshot, nothing flushed by the server.
    pub fn kill9(&mut self) {
        if let Some(mut child) = self.child.take() {
            // `Child::kill` is SIGKILL on unix.
            child.kill().expect("SIGKILL");
            let status = child.wait().expect("wait");
            assert!(!status.success(), "a killed server cannot exit cleanly");
        }
    }

    /// SIGTERM, then waits (at most 30 s) for the exit status.
    pub fn terminate(&mut self) -> ExitStatus {
        let mut child = self.child.take().expect("the server is running");
        terminate(&mut child, Duration::from_secs(30), &|| self.log_text())
    }
}

/// `kill <signal> <pid>`, e.g. `signal(pid, "-TERM")` (std sends SIGKILL only).
pub fn signal(pid: u32, signal: &str) {
    let ok = Command::new("kill")
        .args([signal, &pid.to_string()])
        .status()
        .expect("kill runs")
        .success();
    assert!(ok, "kill {signal} {pid} failed");
}

/// SIGTERM to a child, then its exit status within `timeout`; past it, the
/// child is killed and the test fails with `log()`.
pub fn terminate(child: &mut Child, timeout: Duration, log: &dyn Fn() -> String) -> ExitStatus {
    signal(child.id(), "-TERM");
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            return status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "{} did not stop within {timeout:?} of SIGTERM; log:\n{}",
                child.id(),
                log()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Parsed JSON log lines whose `fields.message` is `message`.
pub fn log_events(log: &str, message: &str) -> Vec<Value> {
    log.lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v["fields"]["message"].as_str() == Some(message))
        .map(|v| v["fields"].clone())
        .collect()
}

// ------------------------------------------------------------------ REST

/// A REST request with an optional API key; returns status and JSON body
/// (Null when the body is not JSON).
pub async fn rest(
    client: &reqwest::Client,
    method: reqwest::Method,
    url: &str,
    key: Option<&str>,
    body: Option<&Value>,
) -> (u16, Value) {
    let mut req = client.request(method, url);
    if let Some(k) = key {
        req = req.bearer_auth(k);
    }
    if let Some(b) = body {
        req = req.json(b);
    }
    let resp = req.send().await.expect("request");
    let status = resp.status().as_u16();
    let text = resp.text().await.expect("body");
    (status, serde_json::from_str(&text).unwrap_or(Value::Null))
}

/// Creates a hallway session over REST; returns its id.
pub async fn rest_create(
    client: &reqwest::Client,
    base: &str,
    key: Option<&str>,
    agent: Value,
) -> String {
    let (status, body) = rest(
        client,
        reqwest::Method::POST,
        &format!("{base}/v1/sessions"),
        key,
        Some(&json!({"model": {"preset": "hallway"}, "agent": agent})),
    )
    .await;
    assert_eq!(status, 201, "create: {body}");
    assert_eq!(body["model"]["actions"], json!(ACTIONS), "hallway actions");
    body["id"].as_str().expect("id").to_string()
}

/// GET a session: (status, body).
pub async fn rest_get(
    client: &reqwest::Client,
    base: &str,
    key: Option<&str>,
    id: &str,
) -> (u16, Value) {
    rest(
        client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{id}"),
        key,
        None,
    )
    .await
}

/// Every session id the key lists, following `next` (pages of 3, so paging
/// is exercised).
pub async fn rest_list_all(client: &reqwest::Client, base: &str, key: Option<&str>) -> Vec<String> {
    let mut ids = Vec::new();
    let mut after: Option<String> = None;
    loop {
        let url = match &after {
            Some(a) => format!("{base}/v1/sessions?limit=3&after={a}"),
            None => format!("{base}/v1/sessions?limit=3"),
        };
        let (status, body) = rest(client, reqwest::Method::GET, &url, key, None).await;
        assert_eq!(status, 200, "list: {body}");
        for s in body["sessions"].as_array().expect("sessions") {
            ids.push(s["id"].as_str().expect("id").to_string());
        }
        match body["next"].as_str() {
            Some(n) => after = Some(n.to_string()),
            None => return ids,
        }
    }
}

// ------------------------------------------------------------------ gRPC

/// A gRPC request with an optional API key and the session metadata.
pub fn grpc_request<T>(message: T, key: Option<&str>, session: Option<&str>) -> tonic::Request<T> {
    let mut req = tonic::Request::new(message);
    if let Some(k) = key {
        req.metadata_mut().insert(
            "authorization",
            format!("Bearer {k}").parse().expect("ascii key"),
        );
    }
    if let Some(id) = session {
        req.metadata_mut()
            .insert(SESSION_METADATA, id.parse().expect("ascii id"));
    }
    req
}

/// Creates a hallway session over gRPC; returns its id.
pub async fn grpc_create(
    client: &mut AgentsClient<Channel>,
    key: Option<&str>,
    seed: u64,
    lockstep: bool,
    epsilon: Option<f64>,
) -> String {
    let mode = if lockstep {
        pb::UpdateMode::Lockstep
    } else {
        pb::UpdateMode::Async
    };
    let info = client
        .create_session(grpc_request(
            pb::CreateSessionRequest {
                model: Some(pb::Model::preset("hallway")),
                agent: Some(pb::SessionConfig {
                    seed: Some(seed),
                    epsilon,
                    update_mode: mode.into(),
                    ..Default::default()
                }),
                ..Default::default()
            },
            key,
            None,
        ))
        .await
        .expect("create over gRPC")
        .into_inner();
    let model = info.model.expect("model");
    assert_eq!(model.actions, ACTIONS.map(String::from).to_vec());
    info.id
}

// ------------------------------------------------------------------ hallway

/// ξ on arrival in `s`: food at 10, rest at 40.
pub fn stimulus(s: usize) -> [f64; 2] {
    match s {
        10 => [6.0, 0.0],
        40 => [0.0, 6.0],
        _ => [0.0, 0.0],
    }
}

/// Whether action `a` is available in `s` (no left at 0, no right at 49).
pub fn available(s: usize, a: usize) -> bool {
    match a {
        0 => s > 0,
        1 => s + 1 < STATES,
        2 => true,
        _ => false,
    }
}

/// The state after taking `a` in `s`.
pub fn step_state(s: usize, a: usize) -> usize {
    assert!(available(s, a), "action {a} is not available in {s}");
    match a {
        0 => s - 1,
        1 => s + 1,
        _ => s,
    }
}

/// A simulated hallway client's next observation from `state` when the
/// server advised `advised`: usually takes the advice, sometimes (and
/// always when the advice is unknown) reports another available action.
/// The first observation (no state yet) lands in a random state. With
/// `names`, the action is reported by name half the time (one more draw).
pub fn next_hallway_obs(
    rng: &mut ChaCha8Rng,
    state: Option<usize>,
    advised: Option<usize>,
    names: bool,
) -> Obs {
    let Some(s) = state else {
        return Obs {
            state: rng.random_range(0..STATES),
            stimulus: None,
            taken: None,
            report: None,
            by_name: false,
        };
    };
    let report = advised.is_none() || rng.random_bool(0.1);
    let a = match advised {
        Some(a) if !report => a,
        _ => loop {
            let a = rng.random_range(0..ACTIONS.len());
            if available(s, a) {
                break a;
            }
        },
    };
    let next = step_state(s, a);
    Obs {
        state: next,
        stimulus: Some(stimulus(next)),
        taken: Some(a),
        report: report.then_some(a),
        by_name: names && rng.random_bool(0.5),
    }
}

/// One observation as the client sent it, resolved: `taken` is the action
/// whose pair its stimulus updates (the advised one unless `report`ed).
#[derive(Debug, Clone, PartialEq)]
pub struct Obs {
    /// The state arrived in.
    pub state: usize,
    /// Its stimulus (None on a session's first observation).
    pub stimulus: Option<[f64; 2]>,
    /// The action taken (None on the first observation).
    pub taken: Option<usize>,
    /// Reported as `action_taken` (by index or, if `by_name`, by name).
    pub report: Option<usize>,
    /// Report by name rather than index.
    pub by_name: bool,
}

impl Obs {
    /// The REST JSON of this observation.
    pub fn json(&self) -> Value {
        let mut v = json!({"state": self.state});
        if let Some(x) = self.stimulus {
            v["stimulus"] = json!(x);
        }
        if let Some(a) = self.report {
            v["action_taken"] = if self.by_name {
                json!(ACTIONS[a])
            } else {
                json!(a)
            };
        }
        v
    }

    /// The gRPC message of this observation.
    pub fn pb(&self, id: &str) -> pb::Observation {
        use pb::observation::ActionTaken;
        pb::Observation {
            session_id: id.into(),
            state: self.state as u64,
            stimulus: self.stimulus.map(|x| pb::Stimulus { values: x.to_vec() }),
            action_taken: self.report.map(|a| {
                if self.by_name {
                    ActionTaken::ActionName(ACTIONS[a].into())
                } else {
                    ActionTaken::ActionIndex(a as u32)
                }
            }),
            ..Default::default()
        }
    }
}

/// What a reply said (the parts a replay can check).
#[derive(Debug, Clone, PartialEq)]
pub struct Reply {
    /// Tick.
    pub tick: u64,
    /// Advised action.
    pub action: usize,
    /// D after the tick.
    pub drive: Vec<f64>,
    /// |r|.
    pub reward: f64,
}

impl Reply {
    /// From a REST step.
    pub fn from_json(v: &Value) -> Self {
        let action = v["action_index"].as_u64().expect("action_index") as usize;
        assert_eq!(v["action"].as_str(), Some(ACTIONS[action]), "{v}");
        Self {
            tick: v["tick"].as_u64().expect("tick"),
            action,
            drive: floats(&v["drive"]),
            reward: v["reward"].as_f64().expect("reward"),
        }
    }

    /// From a gRPC step.
    pub fn from_pb(s: &pb::Step) -> Self {
        assert_eq!(s.action, ACTIONS[s.action_index as usize]);
        Self {
            tick: s.tick,
            action: s.action_index as usize,
            drive: s.drive.clone(),
            reward: s.reward,
        }
    }
}

/// A JSON array of numbers.
/// One observation of session `id`, acknowledged: over gRPC (`Observe`,
/// the session in the metadata too) or REST. Panics unless it is applied.
pub async fn observe_one(
    client: &reqwest::Client,
    base: &str,
    grpc: &mut AgentsClient<Channel>,
    over_grpc: bool,
    id: &str,
    obs: &Obs,
) -> Reply {
    if over_grpc {
        let steps = grpc
            .observe(grpc_request(
                pb::ObserveRequest {
                    session_id: id.to_string(),
                    observations: vec![obs.pb(id)],
                },
                None,
                Some(id),
            ))
            .await
            .unwrap_or_else(|s| panic!("gRPC observe {id}: {s:?}"))
            .into_inner()
            .steps;
        Reply::from_pb(&steps[0])
    } else {
        let url = format!("{base}/v1/sessions/{id}/observations");
        let (status, body) =
            rest(client, reqwest::Method::POST, &url, None, Some(&obs.json())).await;
        assert_eq!(status, 200, "observe {id}: {body}");
        Reply::from_json(&body)
    }
}

pub fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap_or_else(|| panic!("not an array: {v}"))
        .iter()
        .map(|x| x.as_f64().unwrap_or_else(|| panic!("not a number: {x}")))
        .collect()
}

/// Bit-for-bit equality of float slices (NaN-safe, -0 ≠ +0).
pub fn assert_bits_eq(got: &[f64], want: &[f64], what: &str) {
    let g: Vec<u64> = got.iter().map(|x| x.to_bits()).collect();
    let w: Vec<u64> = want.iter().map(|x| x.to_bits()).collect();
    assert_eq!(g, w, "{what}: got {got:?}, want {want:?}");
}

/// The agent parameters a session with this seed and ε has.
pub fn params(seed: u64, epsilon: Option<f64>) -> AgentParams {
    AgentParams {
        seed: Some(seed),
        epsilon,
        ..AgentParams::default()
    }
}

/// A fresh core agent on the hallway, as the server builds it.
pub fn core_agent(params: &AgentParams) -> Agent {
    let preset = hallway();
    let ctx = Arc::new(PlanningModel::new(preset.model, Basis::Indicator));
    Agent::new(ctx, params.check(2, 0).expect("parameters"))
}

/// One tick of the expected history.
#[derive(Debug, Clone, PartialEq)]
pub struct Expected {
    /// Tick.
    pub tick: u64,
    /// State arrived in.
    pub state: usize,
    /// D after the tick.
    pub drive: Vec<f64>,
    /// |r|.
    pub reward: f64,
    /// The advised action, if the reply was seen.
    pub action: Option<usize>,
    /// The known fraction after the tick, for an agent that learns its
    /// transitions.
    pub known_fraction: Option<f64>,
}

/// Replays `applied` observations through a core agent (observe only: Ξ,
/// visits, D and the tick are pure functions of them), checking every
/// reply that was seen against it; returns the agent and the history.
pub fn replay(
    params: &AgentParams,
    applied: &[(Obs, Option<Reply>)],
    ctx: &str,
) -> (Agent, Vec<Expected>) {
    replay_on(core_agent(params), applied, ctx)
}

/// [`replay`] through a given fresh agent (one that learns its
/// transitions, say): the counts N(s, a, s′) are pure functions of the
/// observations too.
pub fn replay_on(
    mut agent: Agent,
    applied: &[(Obs, Option<Reply>)],
    ctx: &str,
) -> (Agent, Vec<Expected>) {
    let mut history = Vec::new();
    for (i, (obs, reply)) in applied.iter().enumerate() {
        let out = agent
            .observe(&Observation {
                state: obs.state,
                stimulus: obs.stimulus.as_ref().map(|x| &x[..]),
                action_taken: obs.taken,
            })
            .unwrap_or_else(|e| panic!("{ctx}: replay of observation {i} {obs:?}: {e}"));
        if let Some(r) = reply {
            assert_eq!(r.tick, out.tick, "{ctx}: tick of reply {i}");
            assert_bits_eq(
                &r.drive,
                agent.drive().vector(),
                &format!("{ctx}: drive of reply {i}"),
            );
            assert_eq!(
                r.reward.to_bits(),
                out.reward.to_bits(),
                "{ctx}: reward of reply {i}"
            );
        }
        if obs.stimulus.is_some() {
            history.push(Expected {
                tick: out.tick,
                state: obs.state,
                drive: agent.drive().vector().to_vec(),
                reward: out.reward,
                action: reply.as_ref().map(|r| r.action),
                known_fraction: agent.learned().map(|l| l.known_fraction()),
            });
        }
    }
    (agent, history)
}

/// Checks a session's GET body, its Ξ table (`values?include=xi`) and its
/// history against a replayed core agent, bit for bit.
pub fn assert_session_matches(
    agent: &Agent,
    expected_history: &[Expected],
    info: &Value,
    values: &Value,
    history: &Value,
    ctx: &str,
) {
    assert_eq!(info["tick"].as_u64(), Some(agent.tick()), "{ctx}: tick");
    assert_eq!(values["tick"].as_u64(), Some(agent.tick()), "{ctx}: tick");
    assert_eq!(
        info["state"].as_u64().map(|s| s as usize),
        agent.state(),
        "{ctx}: state"
    );
    assert_bits_eq(
        &floats(&info["drive"]),
        agent.drive().vector(),
        &format!("{ctx}: D"),
    );
    assert_eq!(
        info["stats"]["lambda1_estimate"].as_f64().map(f64::to_bits),
        Some(agent.drive().lambda1_estimate().to_bits()),
        "{ctx}: λ₁ estimate (D's running second moment)"
    );
    let constant: Vec<usize> = info["stats"]["constant_stimuli"]
        .as_array()
        .expect("constant_stimuli")
        .iter()
        .map(|v| v.as_u64().expect("index") as usize)
        .collect();
    assert_eq!(
        constant,
        agent.stimulus().constant_columns(),
        "{ctx}: constant stimuli"
    );
    match agent.learned() {
        Some(l) => assert_eq!(
            values["known_fraction"].as_f64().map(f64::to_bits),
            Some(l.known_fraction().to_bits()),
            "{ctx}: known fraction of the learned model"
        ),
        None => assert!(
            values.get("known_fraction").is_none(),
            "{ctx}: a session with posted transitions has no known fraction: {values}"
        ),
    }
    let model = agent.planning_model().model();
    let xi = values["xi"].as_array().expect("xi");
    assert_eq!(xi.len(), model.states(), "{ctx}: Ξ rows");
    for (s, row) in xi.iter().enumerate() {
        let row = row.as_array().expect("Ξ row");
        assert_eq!(row.len(), model.n_actions(), "{ctx}: Ξ[{s}]");
        for (a, cell) in row.iter().enumerate() {
            match model.pair(s, a) {
                None => assert!(cell.is_null(), "{ctx}: Ξ[{s}][{a}] should be null"),
                Some(p) => assert_bits_eq(
                    &floats(cell),
                    agent.stimulus().row(p),
                    &format!("{ctx}: Ξ[{s}][{a}]"),
                ),
            }
        }
    }
    let history = history.as_array().expect("history");
    let keep = expected_history
        .len()
        .min(mcapi_server::service::agent_config::DEFAULT_HISTORY);
    let want = &expected_history[expected_history.len() - keep..];
    assert_eq!(history.len(), want.len(), "{ctx}: history length");
    for (got, want) in history.iter().zip(want) {
        let t = want.tick;
        assert_eq!(got["tick"].as_u64(), Some(t), "{ctx}: history tick");
        assert_eq!(
            got["state"].as_u64(),
            Some(want.state as u64),
            "{ctx}: history state at tick {t}"
        );
        assert_bits_eq(
            &floats(&got["drive"]),
            &want.drive,
            &format!("{ctx}: history drive at tick {t}"),
        );
        assert_eq!(
            got["reward"].as_f64().map(f64::to_bits),
            Some(want.reward.to_bits()),
            "{ctx}: history reward at tick {t}"
        );
        assert_eq!(
            got["known_fraction"].as_f64().map(f64::to_bits),
            want.known_fraction.map(f64::to_bits),
            "{ctx}: history known fraction at tick {t}"
        );
        if let Some(a) = want.action {
            assert_eq!(
                got["action"].as_u64(),
                Some(a as u64),
                "{ctx}: history action at tick {t}"
            );
        }
    }
}

/// GETs a session, its Ξ table and its history and checks them against a
/// replay of `applied`.
pub async fn check_session(
    client: &reqwest::Client,
    base: &str,
    key: Option<&str>,
    id: &str,
    params: &AgentParams,
    applied: &[(Obs, Option<Reply>)],
    ctx: &str,
) {
    let (agent, expected) = replay(params, applied, ctx);
    check_replayed(client, base, key, id, &agent, &expected, ctx).await;
}

/// GETs a session, its Ξ table and its history and checks them against an
/// agent that replayed its observations (and the history it gave).
pub async fn check_replayed(
    client: &reqwest::Client,
    base: &str,
    key: Option<&str>,
    id: &str,
    agent: &Agent,
    expected: &[Expected],
    ctx: &str,
) {
    let (status, info) = rest_get(client, base, key, id).await;
    assert_eq!(status, 200, "{ctx}: get: {info}");
    let (status, values) = rest(
        client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{id}/values?include=xi"),
        key,
        None,
    )
    .await;
    assert_eq!(status, 200, "{ctx}: values: {values}");
    let (status, history) = rest(
        client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{id}/history"),
        key,
        None,
    )
    .await;
    assert_eq!(status, 200, "{ctx}: history: {history}");
    assert_session_matches(agent, expected, &info, &values, &history, ctx);
}

/// serde_json in this test build reads back every f64 it writes exactly
/// (the `float_roundtrip` feature), or bit-equality checks would be moot.
pub fn assert_float_roundtrip() {
    let mut x = 0.1f64;
    for i in 0..10_000 {
        x = (x * 1.618_033_988_749_895 + 0.3).fract() * 10f64.powi(i % 40 - 20);
        let text = serde_json::to_string(&x).expect("to_string");
        let back: f64 = serde_json::from_str(&text).expect("from_str");
        assert_eq!(back.to_bits(), x.to_bits(), "{x} → {text} → {back}");
    }
}
