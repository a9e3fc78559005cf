//! The partition test's load: each session driven by its own task, every
//! observation numbered (`seq`) and sent again, with the same seq, until
//! it is acknowledged; what each session saw is recorded as it happens,
//! for the phases to wait on and the end to check.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use serde_json::{Value, json};
use tonic::Code;
use tonic::transport::Channel;

use super::HEAL_BOUND;
use crate::cluster::{Walk, meta};
use crate::common::{Obs, Reply, grpc_request};

/// One attempt's time to answer; past it, the observation is sent again.
pub(super) const ATTEMPT_TIMEOUT: Duration = Duration::from_secs(2);
/// Pause between two observations of a session.
pub(super) const PACE: Duration = Duration::from_millis(150);

/// What the drivers saw of one session, as it happened.
#[derive(Debug, Default)]
pub(super) struct Seen {
    /// When each acknowledgement came, in order.
    pub(super) acks: Vec<Instant>,
    /// Who answered each acknowledged seq, and whether it was a replay.
    pub(super) by: Vec<(String, bool)>,
    /// Refusals that did nothing (421, 503 from a replica).
    pub(super) refused: u64,
    /// When it was refused because its shard was frozen.
    pub(super) moving: Vec<Instant>,
    /// Attempts without an answer: a timeout, a cut connection, the
    /// router's own error; the outcome unknown to the client.
    pub(super) unanswered: u64,
    /// The first few of those, for the report.
    pub(super) errors: Vec<String>,
}

pub(super) type Live = Arc<Vec<Mutex<Seen>>>;

pub(super) fn seen(live: &Live, i: usize) -> std::sync::MutexGuard<'_, Seen> {
    live[i].lock().expect("not poisoned")
}

/// One attempt's outcome.
enum Outcome {
    Acked {
        reply: Reply,
        replica: String,
        replayed: bool,
    },
    Refused {
        moving: bool,
    },
    Unanswered(String),
}

async fn attempt_rest(
    client: &reqwest::Client,
    base: &str,
    id: &str,
    obs: &Obs,
    seq: u64,
) -> Outcome {
    let mut body = obs.json();
    body["seq"] = json!(seq);
    let sent = client
        .post(format!("{base}/v1/sessions/{id}/observations"))
        .json(&body)
        .timeout(ATTEMPT_TIMEOUT)
        .send()
        .await;
    let resp = match sent {
        Ok(r) => r,
        Err(e) => return Outcome::Unanswered(format!("REST: {e}")),
    };
    let status = resp.status().as_u16();
    let replica = resp
        .headers()
        .get("x-mcapi-replica")
        .and_then(|v| v.to_str().ok())
        .map(str::to_string);
    let text = match resp.text().await {
        Ok(t) => t,
        Err(e) => return Outcome::Unanswered(format!("REST body: {e}")),
    };
    let v: Value = serde_json::from_str(&text).unwrap_or(Value::Null);
    match (status, v["code"].as_str(), replica) {
        (200, _, Some(replica)) => Outcome::Acked {
            reply: Reply::from_json(&v),
            replica,
            replayed: v["replayed"] == json!(true),
        },
        (421, Some("wrong_replica"), Some(_)) => Outcome::Refused { moving: false },
        (503, Some(code), Some(_)) => Outcome::Refused {
            moving: code == "shard_moving",
        },
        // The router's own answers: no replica reached, or one lost.
        (502..=504, None, None) => Outcome::Unanswered(format!("REST: the router's {status}")),
        _ => panic!("{id}: seq {seq}: {status} {text}"),
    }
}

async fn attempt_grpc(grpc: &mut AgentsClient<Channel>, id: &str, obs: &Obs, seq: u64) -> Outcome {
    let mut o = obs.pb(id);
    o.seq = Some(seq);
    let mut req = grpc_request(
        pb::ObserveRequest {
            session_id: id.to_string(),
            observations: vec![o],
        },
        None,
        Some(id),
    );
    req.set_timeout(ATTEMPT_TIMEOUT);
    let answer =
        tokio::time::timeout(ATTEMPT_TIMEOUT + Duration::from_secs(1), grpc.observe(req)).await;
    match answer {
        Err(_) => Outcome::Unanswered("gRPC: no answer".into()),
        Ok(Ok(r)) => {
            let replica = meta(r.metadata(), "x-mcapi-replica").expect("x-mcapi-replica");
            let step = r.into_inner().steps.into_iter().next().expect("a step");
            Outcome::Acked {
                reply: Reply::from_pb(&step),
                replica,
                replayed: step.replayed,
            }
        }
        Ok(Err(s)) => match (
            s.code(),
            meta(s.metadata(), "x-mcapi-error-code").as_deref(),
        ) {
            (Code::Unavailable, Some("shard_moving")) => Outcome::Refused { moving: true },
            (Code::Unavailable, Some("wrong_replica" | "unavailable")) => {
                Outcome::Refused { moving: false }
            }
            (
                Code::Unavailable
                | Code::DeadlineExceeded
                | Code::Cancelled
                | Code::Unknown
                | Code::Internal,
                None,
            ) => Outcome::Unanswered(format!("gRPC: {:?} {}", s.code(), s.message())),
            _ => panic!("{id}: seq {seq}: {s:?}"),
        },
    }
}

/// Drives one session until `stop`: each observation carries its seq and
/// is sent again, with the same seq, until it is acknowledged; the last
/// one is finished before it returns.
pub(super) async fn drive(
    mut w: Walk,
    i: usize,
    live: Live,
    stop: Arc<AtomicBool>,
    client: reqwest::Client,
    base: String,
    mut grpc: AgentsClient<Channel>,
) -> Walk {
    while !stop.load(Ordering::Relaxed) {
        let obs = w.next();
        let seq = w.applied.len() as u64;
        let first = Instant::now();
        loop {
            let outcome = if w.grpc {
                attempt_grpc(&mut grpc, &w.id, &obs, seq).await
            } else {
                attempt_rest(&client, &base, &w.id, &obs, seq).await
            };
            match outcome {
                Outcome::Acked {
                    reply,
                    replica,
                    replayed,
                } => {
                    let mut s = seen(&live, i);
                    s.acks.push(Instant::now());
                    s.by.push((replica, replayed));
                    drop(s);
                    w.applied.push((obs, Some(reply)));
                    break;
                }
                Outcome::Refused { moving } => {
                    let mut s = seen(&live, i);
                    s.refused += 1;
                    if moving {
                        s.moving.push(Instant::now());
                    }
                }
                Outcome::Unanswered(e) => {
                    let mut s = seen(&live, i);
                    s.unanswered += 1;
                    if s.errors.len() < 3 {
                        s.errors.push(e);
                    }
                }
            }
            assert!(
                first.elapsed() < Duration::from_secs(90),
                "{}: seq {seq} not acknowledged within 90 s",
                w.id
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        tokio::time::sleep(PACE).await;
    }
    w
}

/// Waits until each of `which` has an acknowledgement after `since`;
/// returns the longest wait. Fails past [`HEAL_BOUND`].
pub(super) async fn served_again(
    live: &Live,
    ids: &[String],
    which: &[usize],
    since: Instant,
    what: &str,
) -> Duration {
    loop {
        let firsts: Vec<Option<Duration>> = which
            .iter()
            .map(|&i| {
                seen(live, i)
                    .acks
                    .iter()
                    .find(|a| **a > since)
                    .map(|a| a.duration_since(since))
            })
            .collect();
        if firsts.iter().all(Option::is_some) {
            return firsts.into_iter().flatten().max().unwrap_or_default();
        }
        let waiting: Vec<&str> = which
            .iter()
            .zip(&firsts)
            .filter(|(_, f)| f.is_none())
            .map(|(&i, _)| ids[i].as_str())
            .collect();
        assert!(
            since.elapsed() < HEAL_BOUND,
            "{what}: not served again within {HEAL_BOUND:?} of the heal: {waiting:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Acknowledgements of session `i` within `[from, to]`.
pub(super) fn acks_between(live: &Live, i: usize, from: Instant, to: Instant) -> usize {
    seen(live, i)
        .acks
        .iter()
        .filter(|a| **a >= from && **a <= to)
        .count()
}
