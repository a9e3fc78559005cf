//! The REST driver: a [`Workload`] (`GET /healthz`, or a connection's
//! share of the sessions' observations) run request after request on each
//! keep-alive connection through a phase, closed loop, or open loop at a
//! rate a pacing thread releases (latency from the release, so no
//! coordinated omission).

use std::time::{Duration, Instant};

use anyhow::{Result, anyhow};
use hyper::{Method, StatusCode};
use serde::Deserialize;
use tokio::sync::mpsc;
use tokio::task::JoinSet;

use crate::args::LoadgenArgs;
use crate::hallway::Hallway;
use crate::http::{HttpConn, HttpTarget, describe};
use crate::stats::{Phase, Summary, Tally};
use crate::window::{Window, measure_window};

/// What a worker asks of its connection, request after request.
pub(crate) trait Workload: Send + 'static {
    /// The route as the server's metrics name it.
    const ROUTE: &'static str;
    /// The next request: method, path and JSON body.
    fn next(&mut self) -> (Method, &str, Option<String>);
    /// Takes the reply to the last request; an error message if it failed.
    fn reply(&mut self, status: StatusCode, body: &[u8]) -> Result<(), String>;
}

/// `GET /healthz`, the baseline.
pub(crate) struct Healthz;

impl Workload for Healthz {
    const ROUTE: &'static str = "/healthz";

    fn next(&mut self) -> (Method, &str, Option<String>) {
        (Method::GET, "/healthz", None)
    }

    fn reply(&mut self, status: StatusCode, body: &[u8]) -> Result<(), String> {
        if status == StatusCode::OK {
            Ok(())
        } else {
            Err(describe(status, body))
        }
    }
}

/// A connection's share of the sessions, observed in turn.
pub(crate) struct Observe {
    /// `(observation path, simulated world)` per session.
    pub(crate) sessions: Vec<(String, Hallway)>,
    pub(crate) cursor: usize,
}

#[derive(Deserialize)]
struct StepReply {
    action_index: usize,
}

impl Workload for Observe {
    const ROUTE: &'static str = "/v1/sessions/{id}/observations";

    fn next(&mut self) -> (Method, &str, Option<String>) {
        let (path, world) = &self.sessions[self.cursor];
        (Method::POST, path.as_str(), Some(world.json()))
    }

    fn reply(&mut self, status: StatusCode, body: &[u8]) -> Result<(), String> {
        let n = self.sessions.len();
        let (_, world) = &mut self.sessions[self.cursor];
        self.cursor = (self.cursor + 1) % n;
        if status != StatusCode::OK {
            // Not applied: the session sends the same observation next time.
            return Err(describe(status, body));
        }
        let step: StepReply = serde_json::from_slice(body).map_err(|e| format!("reply: {e}"))?;
        world.advance(step.action_index);
        Ok(())
    }
}

/// Runs one connection through a phase. Closed loop (`permits` is `None`):
/// the next request leaves as soon as the last reply is in. Open loop: each
/// request waits for a permit, stamped with its release time, and its
/// latency counts from that release, so time spent queued behind a slow
/// reply on this connection is included (no coordinated omission).
async fn http_worker<W: Workload>(
    mut conn: HttpConn,
    mut load: W,
    phase: Phase,
    mut permits: Option<mpsc::UnboundedReceiver<Instant>>,
) -> Result<(HttpConn, W, Tally)> {
    let mut tally = Tally::default();
    while !phase.over() {
        let issued = match &mut permits {
            None => Instant::now(),
            Some(rx) => match rx.recv().await {
                Some(t) => t,
                None => break,
            },
        };
        if phase.over() {
            break;
        }
        let (method, path, body) = load.next();
        let (status, bytes) = conn.send(method, path, body).await?;
        let done = Instant::now();
        tally.record(&phase, issued, done, load.reply(status, &bytes));
    }
    Ok((conn, load, tally))
}

/// Releases `rate` permits a second, evenly spaced, from the start of the
/// phase to its end, to the connections in turn (each gets `rate / n`, as
/// wrk2 does). A thread, because the runtime's timer has millisecond
/// granularity and the spacing is often shorter.
///
/// Returns how late the releases of the window were (p99, max): a mostly
/// sleeping thread released late means the machine itself stalled.
fn pace(txs: &[mpsc::UnboundedSender<Instant>], rate: f64, phase: Phase) -> (Duration, Duration) {
    let mut lateness = Tally::default();
    let mut k: u64 = 0;
    loop {
        let due = phase.start + Duration::from_secs_f64(k as f64 / rate);
        if due >= phase.end {
            break;
        }
        let now = Instant::now();
        if due > now {
            std::thread::sleep(due - now);
        }
        let released = Instant::now();
        lateness.record(&phase, due, released, Ok(()));
        let tx = &txs[(k % txs.len() as u64) as usize];
        if tx.send(released).is_err() {
            break;
        }
        k += 1;
    }
    let s = lateness.summary(&phase);
    (s.p99, s.max)
}

/// Runs every connection through one phase; returns them with the summary.
pub(crate) async fn run_http<W: Workload>(
    workers: Vec<(HttpConn, W)>,
    args: &LoadgenArgs,
    open_loop_rate: Option<f64>,
    (http, server_pid): (&HttpTarget, Option<u32>),
) -> Result<(Vec<(HttpConn, W)>, Summary, Window)> {
    let phase = Phase::new(args);
    let (mut permits, pacer) = match open_loop_rate {
        Some(rate) => {
            let (txs, rxs): (Vec<_>, Vec<_>) =
                workers.iter().map(|_| mpsc::unbounded_channel()).unzip();
            let pacer = std::thread::Builder::new()
                .name("loadgen-pacer".into())
                .spawn(move || pace(&txs, rate, phase))?;
            (rxs.into_iter().map(Some).collect(), Some(pacer))
        }
        None => (Vec::new(), None),
    };
    let mut set = JoinSet::new();
    for (i, (conn, load)) in workers.into_iter().enumerate() {
        let permits = permits.get_mut(i).and_then(Option::take);
        set.spawn(http_worker(conn, load, phase, permits));
    }
    let mut window = measure_window(phase, server_pid, Some((http, W::ROUTE))).await;
    let mut tally = Tally::default();
    let mut back = Vec::new();
    while let Some(joined) = set.join_next().await {
        let (conn, load, t) = joined??;
        tally.merge(t);
        back.push((conn, load));
    }
    if let Some(pacer) = pacer {
        let lag = pacer
            .join()
            .map_err(|_| anyhow!("the pacing thread panicked"))?;
        window.pacer_lag = Some(lag);
    }
    Ok((back, tally.summary(&phase), window))
}
