//! Recovery time of the durable store (docs/sessions.md, "Durability and recovery"): 10,000 hallway sessions,
//! each with 1,000 logged observations and no snapshot after its first
//! tick, as a crash would leave them; then the time `SessionManager::recover`
//! takes to load, replay and re-plan all of them.
//!
//! `cargo bench --bench recovery [-- SESSIONS OBSERVATIONS]` (defaults
//! 10000 1000). A one-shot measurement, not criterion: the fixture takes a
//! minute to write, and the quantity is a wall time of seconds.
//!
//! Without `--bench` (as `cargo test --all-targets` runs it) it is a smoke
//! test of the same code on 20 sessions of 20 observations, as criterion
//! benches do in test mode: the checks run, the minutes do not.

use std::sync::Arc;
use std::time::Instant;

use mcapi_server::service::Limits;
use mcapi_server::service::{
    Caller, CreateSession, ManagerOptions, ObservationIn, SessionConfig, SessionManager, UpdateMode,
};
use mcapi_store::Store;

fn hallway_stimulus(state: usize) -> Vec<f64> {
    match state {
        10 => vec![6.0, 0.0],
        40 => vec![0.0, 6.0],
        _ => vec![0.0, 0.0],
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let bench = std::env::args().any(|a| a == "--bench");
    let (default_sessions, default_observations) = if bench { (10_000, 1000) } else { (20, 20) };
    let sessions = args.first().copied().unwrap_or(default_sessions);
    let observations = args.get(1).copied().unwrap_or(default_observations);
    let dir = tempfile::tempdir()?;
    let workers = std::thread::available_parallelism().map_or(2, |n| n.get());
    let options = |store: Arc<Store>| ManagerOptions {
        store: Some(store),
        // No snapshot: every observation stays in the log.
        snapshot_every: u64::MAX,
        ..ManagerOptions::new(Limits::default(), workers)
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(workers)
        .build()?;

    // Fixture: sessions driven through the hallway, observations in batches.
    let started = Instant::now();
    {
        let store = Arc::new(Store::open(dir.path())?);
        let manager = Arc::new(SessionManager::with_options(options(Arc::clone(&store)))?);
        manager.recover()?;
        let ids: Vec<String> = (0..sessions)
            .map(|i| {
                manager
                    .create(
                        Caller::Anyone,
                        CreateSession {
                            model: serde_json::json!({"preset": "hallway"}),
                            agent: SessionConfig {
                                seed: Some(i as u64),
                                update_mode: Some(UpdateMode::Async),
                                ..SessionConfig::default()
                            },
                        },
                    )
                    .map(|info| info.id)
            })
            .collect::<Result<_, _>>()?;
        runtime.block_on(async {
            let mut tasks = Vec::new();
            for chunk in ids.chunks(ids.len().div_ceil(64).max(1)) {
                let manager = Arc::clone(&manager);
                let chunk = chunk.to_vec();
                tasks.push(tokio::spawn(async move {
                    for id in chunk {
                        let mut state = 25usize;
                        let mut first = true;
                        let mut left = observations;
                        while left > 0 {
                            // Batches follow the advised actions of the previous batch's last step.
                            let n = left.min(250);
                            let mut batch = Vec::with_capacity(n);
                            for _ in 0..n {
                                batch.push(ObservationIn {
                                    state: Some(state),
                                    observation: None,
                                    stimulus: (!first).then(|| hallway_stimulus(state)),
                                    action_taken: None,
                                    signal: None,
                                    signal_source: None,
                                    seq: None,
                                });
                                first = false;
                                // Moves right then left along the hallway; the
                                // reported state need not follow the advice.
                                state = if state >= 45 { 5 } else { state + 1 };
                            }
                            let steps = manager.observe(Caller::Anyone, &id, batch).await?;
                            anyhow::ensure!(steps.len() == n, "one step per observation");
                            left -= n;
                        }
                    }
                    anyhow::Ok(())
                }));
            }
            for t in tasks {
                t.await??;
            }
            anyhow::Ok(())
        })?;
        // A crash: no shutdown snapshot. Only wait for the log to be written.
        drop(manager);
        store.close();
    }
    let file = dir.path().join(mcapi_store::FILE_NAME);
    let bytes = std::fs::metadata(&file)?.len();
    println!(
        "fixture: {sessions} sessions x {observations} observations written in {:.1} s; store file {:.0} MiB",
        started.elapsed().as_secs_f64(),
        bytes as f64 / (1 << 20) as f64
    );

    // Recovery, as `mcapi serve` does it at start: open (with the integrity
    // check) and recover.
    let started = Instant::now();
    let store = Arc::new(Store::open(dir.path())?);
    let opened = started.elapsed().as_secs_f64();
    let manager = SessionManager::with_options(options(store))?;
    let report = manager.recover()?;
    let total = started.elapsed().as_secs_f64();
    anyhow::ensure!(
        report.sessions as usize == sessions,
        "every session recovered"
    );
    anyhow::ensure!(
        report.replayed as usize == sessions * observations,
        "every observation replayed"
    );
    println!(
        "recovery: {} sessions, {} log entries replayed: open + integrity check {:.2} s, recover {:.2} s, total {:.2} s ({:.0} entries/s)",
        report.sessions,
        report.replayed,
        opened,
        report.seconds,
        total,
        report.replayed as f64 / total
    );
    Ok(())
}
