//! The memory scenario: the server's resident memory (`VmRSS`) with many
//! idle hallway sessions, after one observation each and after deleting
//! them (at once and a while later), as KiB per idle session and the RSS
//! left; printed as the memory table, returned as its JSON.

use std::time::{Duration, Instant};

use anyhow::{Result, ensure};
use hyper::{Method, StatusCode};
use serde_json::{Value, json};

use crate::args::LoadgenArgs;
use crate::http::{HttpConn, HttpTarget};
use crate::proc::memory_of;
use crate::report::{mib, thousands};
use crate::sessions::{create_sessions, for_each_session};

pub(crate) async fn memory_scenario(
    args: &LoadgenArgs,
    http: &HttpTarget,
    pid: u32,
) -> Result<Value> {
    let mut levels = args.memory_sessions.clone();
    levels.sort_unstable();
    levels.dedup();
    ensure!(
        levels.last().is_some_and(|&n| n > 0),
        "--memory-sessions: give at least one count above 0"
    );
    let (baseline, _) = memory_of(pid)?;
    let mut rows = vec![("before".to_string(), 0usize, baseline, None)];
    let mut ids: Vec<String> = Vec::new();
    let started = Instant::now();
    let wait = Duration::from_secs(args.evicted_wait_secs);
    for &level in &levels {
        let more = level.saturating_sub(ids.len());
        eprintln!("memory: creating {more} sessions (total {level})");
        ids.extend(create_sessions(http, more, ids.len(), None, args.create_connections).await?);
        let state = match wait_evicted(http, ids.len(), wait).await? {
            Some(n) => format!("idle, {} evicted", thousands(n as f64)),
            None => "idle".into(),
        };
        let (rss, _) = memory_of(pid)?;
        rows.push((state, ids.len(), rss, None));
    }
    let create_rate = ids.len() as f64 / started.elapsed().as_secs_f64();
    let idle_rss = rows.last().map_or(baseline, |r| r.2);
    eprintln!("memory: one observation per session");
    let t = Instant::now();
    for_each_session(http, &ids, Method::POST, args.create_connections).await?;
    let observe_rate = ids.len() as f64 / t.elapsed().as_secs_f64();
    let (observed_rss, hwm) = memory_of(pid)?;
    rows.push((
        "one observation each".into(),
        ids.len(),
        observed_rss,
        Some(hwm),
    ));
    let mut evicted_again = None;
    if let Some(n) = wait_evicted(http, ids.len(), wait).await? {
        let (rss, hwm) = memory_of(pid)?;
        rows.push((
            format!("observed, then {} evicted", thousands(n as f64)),
            ids.len(),
            rss,
            Some(hwm),
        ));
        evicted_again = Some(rss);
    }
    eprintln!("memory: deleting {} sessions", ids.len());
    for_each_session(http, &ids, Method::DELETE, args.create_connections).await?;
    let (deleted_rss, hwm) = memory_of(pid)?;
    rows.push(("all deleted".into(), 0, deleted_rss, Some(hwm)));
    tokio::time::sleep(Duration::from_secs(args.settle_secs)).await;
    let (settled_rss, hwm) = memory_of(pid)?;
    rows.push((
        format!("all deleted, {} s later", args.settle_secs),
        0,
        settled_rss,
        Some(hwm),
    ));

    let n = ids.len();
    let kib = |rss: u64| rss.saturating_sub(baseline) as f64 / n as f64 / 1024.0;
    // How much of what the sessions took the server gave back.
    let taken = observed_rss.max(idle_rss).saturating_sub(baseline);
    let returned = |rss: u64| {
        (taken > 0).then(|| observed_rss.max(idle_rss).saturating_sub(rss) as f64 / taken as f64)
    };
    println!("## Memory: server VmRSS with idle hallway sessions\n");
    println!(
        "Sessions created over {} connections ({} sessions/s), then one first observation \
         each ({} observations/s), then deleted. Per session: (RSS - RSS before) / sessions.\n",
        args.create_connections,
        thousands(create_rate),
        thousands(observe_rate)
    );
    println!("| sessions | state | VmRSS | per session | VmHWM (peak) |");
    println!("|---|---|---|---|---|");
    for (state, n, rss, hwm) in &rows {
        let per = if *n > 0 {
            format!(
                "{:.1} KiB",
                (rss.saturating_sub(baseline)) as f64 / *n as f64 / 1024.0
            )
        } else {
            "—".into()
        };
        println!(
            "| {} | {state} | {} | {per} | {} |",
            thousands(*n as f64),
            mib(*rss),
            hwm.map_or_else(|| "—".to_string(), mib)
        );
    }
    let pct = |r: Option<f64>| r.map_or_else(|| "—".to_string(), |r| format!("{:.0}%", 100.0 * r));
    println!(
        "\n**{:.2} KiB per idle session** ({} sessions; {:.2} KiB after one observation each). \
         **RSS after deleting them all: {}** ({} over the fresh server's {}; {} of what the \
         sessions took returned at once, {} after {} s).\n",
        kib(idle_rss),
        thousands(n as f64),
        kib(observed_rss),
        mib(settled_rss),
        mib(settled_rss.saturating_sub(baseline)),
        mib(baseline),
        pct(returned(deleted_rss)),
        pct(returned(settled_rss)),
        args.settle_secs,
    );
    Ok(json!({
        "sessions": n,
        "baseline_rss_bytes": baseline,
        "idle_rss_bytes": idle_rss,
        "observed_rss_bytes": observed_rss,
        "deleted_rss_bytes": deleted_rss,
        "settled_rss_bytes": settled_rss,
        "settle_secs": args.settle_secs,
        "peak_rss_bytes": hwm,
        "kib_per_idle_session": kib(idle_rss),
        "kib_per_observed_session": kib(observed_rss),
        "kib_per_observed_evicted_session": evicted_again.map(kib),
        "returned_at_once": returned(deleted_rss),
        "returned_after_settle": returned(settled_rss),
        "create_rate": create_rate,
        "observe_rate": observe_rate,
        "levels": rows.iter().map(|(state, n, rss, hwm)| json!({
            "state": state, "sessions": n, "rss_bytes": rss, "hwm_bytes": hwm,
        })).collect::<Vec<_>>(),
    }))
}

/// With `wait` > 0: waits until the server's `mcapi_sessions_evicted`
/// reaches `n` or `wait` has passed, and returns the count last read.
async fn wait_evicted(http: &HttpTarget, n: usize, wait: Duration) -> Result<Option<usize>> {
    if wait.is_zero() {
        return Ok(None);
    }
    let until = Instant::now() + wait;
    eprintln!(
        "memory: waiting up to {} s for the server to evict {n} sessions",
        wait.as_secs()
    );
    loop {
        let mut conn = HttpConn::connect(http).await?;
        let (status, body) = conn.send(Method::GET, "/metrics", None).await?;
        ensure!(status == StatusCode::OK, "/metrics: {status}");
        let evicted = String::from_utf8_lossy(&body)
            .lines()
            .find_map(|l| l.strip_prefix("mcapi_sessions_evicted "))
            .and_then(|v| v.trim().parse::<f64>().ok())
            .unwrap_or(0.0) as usize;
        if evicted >= n || Instant::now() >= until {
            return Ok(Some(evicted));
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}
