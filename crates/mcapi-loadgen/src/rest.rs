//! The REST scenario: for each session count and update mode, observations
//! against the `GET /healthz` baseline on the same connections (closed
//! loop), then observations at a fraction of that peak rate (open loop);
//! printed as the REST tables, returned as their JSON.

use anyhow::{Result, ensure};
use hyper::Method;
use serde_json::{Value, json};

use crate::args::{LoadgenArgs, Mode};
use crate::driver::{Healthz, Observe, run_http};
use crate::hallway::Hallway;
use crate::http::{HttpConn, HttpTarget, connect_all};
use crate::report::{cores, handler, latency, per_request, thousands};
use crate::sessions::{create_sessions, for_each_session};
use crate::stats::Summary;
use crate::window::Window;

/// One row of the REST tables.
struct RestRow {
    sessions: usize,
    mode: Mode,
    connections: usize,
    healthz: (Summary, Window),
    observe: (Summary, Window),
    /// The open-loop run: target rate and what it gave.
    paced: Option<(f64, Summary, Window)>,
}

pub(crate) async fn rest_scenario(
    args: &LoadgenArgs,
    http: &HttpTarget,
    pid: Option<u32>,
) -> Result<Value> {
    let mut rows = Vec::new();
    for &n in &args.sessions {
        ensure!(n > 0, "--sessions: counts must be at least 1");
        for &mode in &args.modes {
            let connections = n.min(args.max_connections);
            eprintln!(
                "rest: {n} {} sessions over {connections} connections",
                mode.as_str()
            );
            let ids = create_sessions(http, n, 0, Some(mode), args.create_connections).await?;

            // The baseline, on the same connections.
            let conns = connect_all(http, connections).await?;
            let workers = conns.into_iter().map(|c| (c, Healthz)).collect();
            let (workers, healthz, healthz_window) =
                run_http(workers, args, None, (http, pid)).await?;
            eprintln!("  /healthz {:.0} req/s", healthz.rate);

            // Connection w owns sessions w, w + connections, ...
            let workers: Vec<(HttpConn, Observe)> = workers
                .into_iter()
                .enumerate()
                .map(|(w, (conn, _))| {
                    let sessions = ids
                        .iter()
                        .skip(w)
                        .step_by(connections)
                        .map(|id| {
                            let world = Hallway::new().numbered(args.seq);
                            (format!("/v1/sessions/{id}/observations"), world)
                        })
                        .collect();
                    let load = Observe {
                        sessions,
                        cursor: 0,
                    };
                    (conn, load)
                })
                .collect();
            let (workers, observe, observe_window) =
                run_http(workers, args, None, (http, pid)).await?;
            eprintln!("  observe {:.0} req/s", observe.rate);

            let paced = if args.no_paced || observe.rate <= 0.0 {
                None
            } else {
                let rate = observe.rate * args.paced_fraction;
                let (_, summary, window) = run_http(workers, args, Some(rate), (http, pid)).await?;
                eprintln!(
                    "  observe at {rate:.0}/s: {:.0}/s, p99 {}",
                    summary.rate,
                    latency(summary.p99)
                );
                Some((rate, summary, window))
            };
            for_each_session(http, &ids, Method::DELETE, args.create_connections).await?;
            rows.push(RestRow {
                sessions: n,
                mode,
                connections,
                healthz: (healthz, healthz_window),
                observe: (observe, observe_window),
                paced,
            });
        }
    }
    print_rest(&rows, args);
    Ok(rows.iter().map(RestRow::json).collect())
}

impl RestRow {
    fn json(&self) -> Value {
        let ((h, hw), (o, ow)) = (&self.healthz, &self.observe);
        json!({
            "sessions": self.sessions,
            "mode": self.mode.as_str(),
            "connections": self.connections,
            "healthz": { "summary": h.json(), "window": hw.json(h.rate) },
            "observe": { "summary": o.json(), "window": ow.json(o.rate) },
            "observe_over_healthz": (h.rate > 0.0).then(|| o.rate / h.rate),
            "paced": self.paced.as_ref().map(|(target, s, w)| json!({
                "target_rate": target,
                "summary": s.json(),
                "window": w.json(s.rate),
            })),
        })
    }
}

fn print_rest(rows: &[RestRow], args: &LoadgenArgs) {
    println!("## REST: observe against GET /healthz (closed loop)\n");
    println!(
        "One keep-alive HTTP/1.1 connection per session up to {n} sessions; beyond that \
         {n} connections (= requests in flight) cycle over the sessions. Latencies are the \
         client's (p50 / p99 / max); \"handler\" is the bucket bound of the server's own \
         p50 / p99 from its /metrics histogram.\n",
        n = args.max_connections
    );
    println!(
        "| sessions | mode | conns | /healthz req/s | /healthz p50 / p99 | observe req/s | \
         observe / healthz | observe p50 / p99 / max | observe handler p50 / p99 | \
         server CPU µs/req: healthz / observe | CPU (observe): server / loadgen / other | \
         errors |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        let ((h, hw), (o, ow)) = (&r.healthz, &r.observe);
        println!(
            "| {} | {} | {} | {} | {} / {} | {} | {:.0}% | {} / {} / {} | {} | {} / {} | {} | {} |",
            thousands(r.sessions as f64),
            r.mode.as_str(),
            r.connections,
            thousands(h.rate),
            latency(h.p50),
            latency(h.p99),
            thousands(o.rate),
            100.0 * o.rate / h.rate.max(f64::MIN_POSITIVE),
            latency(o.p50),
            latency(o.p99),
            latency(o.max),
            handler(ow.handler),
            per_request(hw.cpu, h.rate),
            per_request(ow.cpu, o.rate),
            cores(ow.cpu),
            h.errors + o.errors,
        );
    }
    if rows.iter().any(|r| r.paced.is_some()) {
        println!(
            "\n## REST: observe at {:.0}% of the peak rate (open loop)\n",
            100.0 * args.paced_fraction
        );
        println!(
            "Requests are released by a pacing thread at a fixed rate ({:.0}% of the closed-loop \
             observe rate of the same row), evenly spaced and dealt to the connections above in \
             turn. Latency counts from the release, so time queued behind a slow reply on the \
             same connection is included. The pacer's lag is how late that thread itself \
             released requests: a mostly sleeping thread running late means the whole machine \
             stalled.\n",
            100.0 * args.paced_fraction
        );
        println!(
            "| sessions | mode | target req/s | achieved req/s | p50 | p99 | max | \
             handler p50 / p99 | pacer lag p99 / max | server CPU µs/req | \
             CPU: server / loadgen / other | errors |"
        );
        println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
        for r in rows {
            if let Some((target, s, w)) = &r.paced {
                println!(
                    "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                    thousands(r.sessions as f64),
                    r.mode.as_str(),
                    thousands(*target),
                    thousands(s.rate),
                    latency(s.p50),
                    latency(s.p99),
                    latency(s.max),
                    handler(w.handler),
                    w.pacer_lag.map_or_else(
                        || "—".to_string(),
                        |(p99, max)| format!("{} / {}", latency(p99), latency(max))
                    ),
                    per_request(w.cpu, s.rate),
                    cores(w.cpu),
                    s.errors
                );
            }
        }
    }
    for r in rows {
        let summaries = [&r.healthz.0, &r.observe.0]
            .into_iter()
            .chain(r.paced.as_ref().map(|(_, s, _)| s));
        for s in summaries {
            if let Some(e) = &s.first_error {
                println!(
                    "\nFirst error ({} {} sessions): {e}",
                    r.sessions,
                    r.mode.as_str()
                );
            }
        }
    }
    println!();
}
