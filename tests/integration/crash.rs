//! The crash test of durable sessions (docs/sessions.md, "Durability and
//! recovery"), on the real binary: several sessions are
//! driven concurrently over REST (lockstep, async, batches) and gRPC
//! (`Interact` streams), the server is `kill -9`ed at a random moment while
//! requests are in flight, and restarted on the same data directory on
//! fresh ports. Then every session must exist exactly once (for its own
//! key only), and its tick, D (with λ₁'s running moment), Ξ and history
//! must equal an in-memory replay of the acknowledged observations, plus
//! the in-flight ones only where the recovered tick shows they committed
//! (a request in flight at the kill may or may not have been committed,
//! never half of an observation). Driving then continues, is killed again,
//! recovered again; finally every session takes more ticks (which checks
//! the recovered visit counts and advised action too) and the server stops
//! cleanly. Three seeds with three crashes each at 200-1500 ms, one more
//! under `--durability os`, and one that kills within milliseconds, while
//! first observations are in flight.

use crate::common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use common::{
    Launch, Obs, Reply, Server, assert_float_roundtrip, check_session, free_ports, grpc_create,
    grpc_request, http_client, log_events, params, rest, rest_create, rest_get, rest_list_all,
};
use mcapi_core::AgentParams;
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

const KEY_A: &str = "crash-test-key-alpha-0123456789";
const KEY_B: &str = "crash-test-key-bravo-9876543210";
/// Small, so that snapshots and log trimming happen many times per run.
const SNAPSHOT_EVERY: u64 = 50;
/// How a round ends.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Stop {
    /// `kill -9`.
    Kill,
    /// SIGTERM under load: in-flight requests finish or fail, every session
    /// is snapshotted.
    Term,
}

/// One round: drive, stop the server this way after a random time in `when`
/// (ms), restart, check.
struct Round {
    when: std::ops::Range<u64>,
    stop: Stop,
}

const ROUNDS: [Round; 3] = [
    Round {
        when: 200..1500,
        stop: Stop::Kill,
    },
    Round {
        when: 200..1500,
        stop: Stop::Term,
    },
    Round {
        when: 200..1500,
        stop: Stop::Kill,
    },
];
/// Ticks per session after the last recovery.
const AFTER: usize = 8;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Transport {
    Rest,
    Grpc,
}

#[derive(Debug, Clone, Copy)]
struct Spec {
    transport: Transport,
    lockstep: bool,
    epsilon: Option<f64>,
    /// Sometimes sends 2-4 observations in one REST request.
    batches: bool,
}

const fn spec(transport: Transport, lockstep: bool) -> Spec {
    Spec {
        transport,
        lockstep,
        epsilon: None,
        batches: false,
    }
}

/// 3 REST lockstep (one with batches), 2 REST async (one exploring),
/// 3 gRPC `Interact` (2 lockstep, 1 async).
const SPECS: [Spec; 8] = [
    spec(Transport::Rest, true),
    spec(Transport::Rest, true),
    Spec {
        batches: true,
        ..spec(Transport::Rest, true)
    },
    spec(Transport::Rest, false),
    Spec {
        epsilon: Some(0.2),
        ..spec(Transport::Rest, false)
    },
    spec(Transport::Grpc, true),
    spec(Transport::Grpc, true),
    spec(Transport::Grpc, false),
];

/// A session as the client knows it.
#[derive(Debug)]
struct Tracked {
    spec: Spec,
    id: String,
    key: &'static str,
    params: AgentParams,
    /// Observations the server has applied: acknowledged ones with their
    /// reply, and in-flight ones the recovery showed were committed.
    applied: Vec<(Obs, Option<Reply>)>,
    /// The state of the last applied observation.
    state: Option<usize>,
    /// The action the server will take as done if none is reported: the
    /// last reply's, or unknown after an in-flight observation committed.
    advised: Option<usize>,
    /// Sent, but the reply never came (the kill).
    in_flight: Vec<Obs>,
    /// Acknowledged / in-flight-committed / in-flight-lost counts.
    acked: usize,
    committed: usize,
    lost: usize,
    rng: ChaCha8Rng,
}

impl Tracked {
    fn ctx(&self) -> String {
        format!(
            "session {} ({:?}, lockstep {})",
            self.id, self.spec.transport, self.spec.lockstep
        )
    }

    fn ticks(&self) -> u64 {
        self.applied
            .iter()
            .filter(|(o, _)| o.stimulus.is_some())
            .count() as u64
    }

    /// The next observation from `state` when the server advised
    /// `advised`: usually takes the advice, sometimes (and always when the
    /// advice is unknown) reports another available action.
    fn next_obs(&mut self, state: Option<usize>, advised: Option<usize>) -> Obs {
        common::next_hallway_obs(&mut self.rng, state, advised, true)
    }

    fn acknowledged(&mut self, batch: Vec<Obs>, replies: Vec<Reply>) {
        assert_eq!(batch.len(), replies.len(), "{}: one reply each", self.ctx());
        for (obs, reply) in batch.into_iter().zip(replies) {
            self.state = Some(obs.state);
            self.advised = Some(reply.action);
            self.applied.push((obs, Some(reply)));
            self.acked += 1;
        }
    }

    /// A request failed: fine once the kill is under way (the batch was in
    /// flight), a failure of the test before.
    fn lost_in_flight(&mut self, batch: Vec<Obs>, killed: &AtomicBool, error: &str) {
        assert!(
            killed.load(Ordering::SeqCst),
            "{}: a request failed before the kill: {error}",
            self.ctx()
        );
        self.in_flight = batch;
    }
}

/// Drives one session until a request fails after the kill (`limit` None)
/// or for `limit` exchanges that must all succeed.
async fn drive(
    mut t: Tracked,
    base: String,
    grpc_url: String,
    killed: Arc<AtomicBool>,
    limit: Option<usize>,
) -> Tracked {
    assert!(
        t.in_flight.is_empty(),
        "in-flight observations are resolved"
    );
    match t.spec.transport {
        Transport::Rest => drive_rest(&mut t, &base, &killed, limit).await,
        Transport::Grpc => drive_grpc(&mut t, grpc_url, &killed, limit).await,
    }
    t
}

async fn drive_rest(t: &mut Tracked, base: &str, killed: &AtomicBool, limit: Option<usize>) {
    let client = http_client();
    let url = format!("{base}/v1/sessions/{}/observations", t.id);
    let mut n = 0;
    while limit.is_none_or(|l| n < l) {
        n += 1;
        let len = if t.spec.batches && t.state.is_some() && t.rng.random_bool(0.5) {
            t.rng.random_range(2..=4)
        } else {
            1
        };
        let mut batch = Vec::with_capacity(len);
        let (mut state, mut advised) = (t.state, t.advised);
        for _ in 0..len {
            // Later observations of a batch report their action: the
            // advice for them is in replies not yet received.
            let obs = t.next_obs(state, advised);
            state = Some(obs.state);
            advised = None;
            batch.push(obs);
        }
        let body = if len == 1 {
            batch[0].json()
        } else {
            json!({"observations": batch.iter().map(Obs::json).collect::<Vec<_>>()})
        };
        let sent = client
            .post(&url)
            .bearer_auth(t.key)
            .json(&body)
            .send()
            .await;
        let resp = match sent {
            Ok(r) => r,
            Err(e) => return t.lost_in_flight(batch, killed, &e.to_string()),
        };
        let status = resp.status().as_u16();
        let text = match resp.text().await {
            Ok(text) => text,
            Err(e) => return t.lost_in_flight(batch, killed, &e.to_string()),
        };
        assert_eq!(status, 200, "{}: observe {body}: {text}", t.ctx());
        let reply: Value = serde_json::from_str(&text).expect("JSON reply");
        let replies = if len == 1 {
            vec![Reply::from_json(&reply)]
        } else {
            reply["steps"]
                .as_array()
                .expect("steps")
                .iter()
                .map(Reply::from_json)
                .collect()
        };
        t.acknowledged(batch, replies);
    }
}

async fn drive_grpc(t: &mut Tracked, url: String, killed: &AtomicBool, limit: Option<usize>) {
    let mut client = match AgentsClient::connect(url).await {
        Ok(c) => c,
        Err(e) => return t.lost_in_flight(Vec::new(), killed, &e.to_string()),
    };
    let (tx, rx) = mpsc::channel::<pb::Observation>(1);
    let request = grpc_request(ReceiverStream::new(rx), Some(t.key), Some(&t.id));
    let mut steps = match client.interact(request).await {
        Ok(r) => r.into_inner(),
        Err(e) => return t.lost_in_flight(Vec::new(), killed, &e.to_string()),
    };
    let mut n = 0;
    while limit.is_none_or(|l| n < l) {
        n += 1;
        let obs = t.next_obs(t.state, t.advised);
        if let Err(e) = tx.send(obs.pb(&t.id)).await {
            return t.lost_in_flight(vec![obs], killed, &e.to_string());
        }
        match steps.message().await {
            Ok(Some(step)) => t.acknowledged(vec![obs], vec![Reply::from_pb(&step)]),
            Ok(None) => return t.lost_in_flight(vec![obs], killed, "the stream ended"),
            Err(status) => return t.lost_in_flight(vec![obs], killed, &status.to_string()),
        }
    }
    drop(tx);
    let end = steps.message().await;
    assert!(
        matches!(end, Ok(None)),
        "{}: the stream ends after the client's: {end:?}",
        t.ctx()
    );
}

/// Runs every session's driver at once; returns them in order.
async fn drive_all(
    tracked: Vec<Tracked>,
    server: &Server,
    killed: &Arc<AtomicBool>,
    limit: Option<usize>,
) -> Vec<tokio::task::JoinHandle<Tracked>> {
    tracked
        .into_iter()
        .map(|t| {
            tokio::spawn(drive(
                t,
                server.base(),
                server.grpc_url(),
                Arc::clone(killed),
                limit,
            ))
        })
        .collect()
}

async fn join_all(handles: Vec<tokio::task::JoinHandle<Tracked>>) -> Vec<Tracked> {
    let mut out = Vec::with_capacity(handles.len());
    for h in handles {
        let t = tokio::time::timeout(Duration::from_secs(60), h)
            .await
            .expect("a driver hung")
            .expect("a driver failed");
        out.push(t);
    }
    out
}

/// After a restart: the sessions are all there, once, each visible to its
/// own key only; in-flight observations are resolved by the recovered tick;
/// each session equals the replay of what it applied.
async fn verify(server: &Server, tracked: &mut [Tracked], label: &str) {
    let client = http_client();
    let base = server.base();
    for key in [KEY_A, KEY_B] {
        let listed = rest_list_all(&client, &base, Some(key)).await;
        let mut want: Vec<&str> = tracked
            .iter()
            .filter(|t| t.key == key)
            .map(|t| t.id.as_str())
            .collect();
        want.sort_unstable();
        assert_eq!(
            listed, want,
            "{label}: each session listed exactly once, for its own key"
        );
    }
    for t in tracked.iter_mut() {
        let ctx = format!("{label}: {}", t.ctx());
        let (status, info) = rest_get(&client, &base, Some(t.key), &t.id).await;
        assert_eq!(status, 200, "{ctx}: {info}");
        let other = if t.key == KEY_A { KEY_B } else { KEY_A };
        let (status, _) = rest_get(&client, &base, Some(other), &t.id).await;
        assert_eq!(status, 404, "{ctx}: the other key must not see it");
        let tick = info["tick"].as_u64().expect("tick");
        let acked = t.ticks();
        let in_flight = std::mem::take(&mut t.in_flight);
        let extra = tick.checked_sub(acked).unwrap_or_else(|| {
            panic!("{ctx}: acknowledged observations were lost: tick {tick} < {acked} acknowledged")
        });
        let committed = match in_flight.first() {
            None => 0,
            // A first observation (state only, never batched) moves no tick.
            Some(first) if first.stimulus.is_none() => usize::from(info["state"].is_u64()),
            Some(_) => usize::try_from(extra).expect("small"),
        };
        assert!(
            committed <= in_flight.len(),
            "{ctx}: tick {tick} is {extra} past the {acked} acknowledged, \
             but only {} observations were in flight",
            in_flight.len()
        );
        t.lost += in_flight.len() - committed;
        for obs in in_flight.into_iter().take(committed) {
            t.state = Some(obs.state);
            // The reply advising the next action never arrived.
            t.advised = None;
            t.applied.push((obs, None));
            t.committed += 1;
        }
        assert_eq!(tick, t.ticks(), "{ctx}: tick");
        check_session(
            &client,
            &base,
            Some(t.key),
            &t.id,
            &t.params,
            &t.applied,
            &ctx,
        )
        .await;
    }
    let (status, body) = rest(
        &client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions"),
        None,
        None,
    )
    .await;
    assert_eq!(status, 401, "{label}: keys still required: {body}");
}

async fn create_sessions(server: &Server, seed: u64) -> Vec<Tracked> {
    let client = http_client();
    let mut grpc = server.grpc_client().await;
    let mut out = Vec::new();
    for (i, spec) in SPECS.iter().enumerate() {
        let session_seed = seed * 1000 + i as u64;
        let (id, key) = match spec.transport {
            Transport::Rest => {
                let mut agent = json!({
                    "seed": session_seed,
                    "update_mode": if spec.lockstep { "lockstep" } else { "async" },
                });
                if let Some(e) = spec.epsilon {
                    agent["epsilon"] = json!(e);
                }
                (
                    rest_create(&client, &server.base(), Some(KEY_A), agent).await,
                    KEY_A,
                )
            }
            Transport::Grpc => (
                grpc_create(
                    &mut grpc,
                    Some(KEY_B),
                    session_seed,
                    spec.lockstep,
                    spec.epsilon,
                )
                .await,
                KEY_B,
            ),
        };
        out.push(Tracked {
            spec: *spec,
            id,
            key,
            params: params(session_seed, spec.epsilon),
            applied: Vec::new(),
            state: None,
            advised: None,
            in_flight: Vec::new(),
            acked: 0,
            committed: 0,
            lost: 0,
            rng: ChaCha8Rng::seed_from_u64(session_seed ^ 0x5eed),
        });
    }
    out
}

async fn crash_run(seed: u64, rounds: &[Round]) {
    crash_run_with(seed, rounds, &[]).await;
}

/// [`crash_run`] with more `mcapi serve` flags.
async fn crash_run_with(seed: u64, rounds: &[Round], flags: &[&str]) {
    let started = Instant::now();
    assert_float_roundtrip();
    let data = tempfile::tempdir().expect("data dir");
    let logs = tempfile::tempdir().expect("log dir");
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let every = SNAPSHOT_EVERY.to_string();
    let mut args = vec![
        "--snapshot-every",
        &every,
        "--api-key",
        KEY_A,
        "--api-key",
        KEY_B,
    ];
    args.extend_from_slice(flags);
    let launch = Launch::new(data.path(), &args);
    let mut server = Server::start(&launch, logs.path().join("run-0.log")).await;
    let mut tracked = create_sessions(&server, seed).await;

    for (round, Round { when, stop }) in (1..).zip(rounds) {
        let killed = Arc::new(AtomicBool::new(false));
        let handles = drive_all(tracked, &server, &killed, None).await;
        let delay = rng.random_range(when.clone());
        tokio::time::sleep(Duration::from_millis(delay)).await;
        killed.store(true, Ordering::SeqCst);
        match stop {
            Stop::Kill => server.kill9(),
            Stop::Term => {
                let status = tokio::task::block_in_place(|| server.terminate());
                assert!(
                    status.success(),
                    "seed {seed}: clean exit on SIGTERM under load: {status}; log:\n{}",
                    server.log_text()
                );
            }
        }
        tracked = join_all(handles).await;
        let in_flight: usize = tracked.iter().map(|t| t.in_flight.len()).sum();

        // A crash during recovery (the store's integrity check and repair,
        // or the replay) changes nothing either.
        let (http, grpc) = free_ports();
        let mut interrupted = common::spawn(
            &launch,
            http,
            grpc,
            &logs.path().join(format!("run-{round}-interrupted.log")),
        );
        tokio::time::sleep(Duration::from_millis(rng.random_range(0..40))).await;
        interrupted.kill().expect("SIGKILL");
        interrupted.wait().expect("wait");

        server = Server::start(&launch, logs.path().join(format!("run-{round}.log"))).await;
        let label = format!("seed {seed}, {stop:?} {round} at {delay} ms");
        verify(&server, &mut tracked, &label).await;

        // The log is trimmed at every snapshot: at most SNAPSHOT_EVERY - 1
        // entries per session are left to replay.
        let log = server.log_text();
        let recovered = log_events(&log, "sessions recovered");
        assert_eq!(recovered.len(), 1, "{label}: one recovery line in\n{log}");
        assert_eq!(recovered[0]["sessions"], json!(SPECS.len()), "{label}");
        let replayed = recovered[0]["replayed"].as_u64().expect("replayed");
        let total: usize = tracked.iter().map(|t| t.applied.len()).sum();
        assert!(
            replayed <= SPECS.len() as u64 * (SNAPSHOT_EVERY - 1),
            "{label}: {replayed} log entries replayed: the log is not trimmed at snapshots"
        );
        if *stop == Stop::Term {
            assert_eq!(
                replayed, 0,
                "{label}: a clean stop snapshots every session; nothing is left to replay"
            );
        }
        eprintln!(
            "{label}: {total} observations applied so far, {in_flight} in flight at the kill, \
             {replayed} replayed at recovery"
        );
    }

    // Every session keeps going: a few more ticks each, then the same checks.
    let never = Arc::new(AtomicBool::new(false));
    let handles = drive_all(tracked, &server, &never, Some(AFTER)).await;
    tracked = join_all(handles).await;
    verify(
        &server,
        &mut tracked,
        &format!("seed {seed}, after the crashes"),
    )
    .await;
    let status = server.terminate();
    assert!(
        status.success(),
        "clean exit: {status}; log:\n{}",
        server.log_text()
    );

    let (acked, committed, lost) = tracked.iter().fold((0, 0, 0), |(a, c, l), t| {
        (a + t.acked, c + t.committed, l + t.lost)
    });
    assert!(acked > 0);
    eprintln!(
        "seed {seed}: {acked} acknowledged, {committed} in-flight committed, {lost} in-flight lost; \
         {:.1} s",
        started.elapsed().as_secs_f64()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn kill_9_loses_no_acknowledged_observation_seed_1() {
    crash_run(1, &ROUNDS).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn kill_9_loses_no_acknowledged_observation_seed_2() {
    crash_run(2, &ROUNDS).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn kill_9_loses_no_acknowledged_observation_seed_3() {
    crash_run(3, &ROUNDS).await;
}

/// `--durability os` acknowledges once the log frame is in the kernel: a
/// killed process loses nothing acknowledged either (a power cut could).
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn kill_9_with_durability_os_loses_no_acknowledged_observation() {
    crash_run_with(5, &ROUNDS, &["--durability", "os"]).await;
}

/// Kills within milliseconds of the start, when sessions' first
/// observations (a state, no tick) are in flight.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn kill_9_during_the_first_observations() {
    let round = |when| Round {
        when,
        stop: Stop::Kill,
    };
    crash_run(4, &[round(0..3), round(0..30)]).await;
}
