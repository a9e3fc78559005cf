//! Idle sessions leave memory and come back bit for bit (docs/sessions.md,
//! "Idle sessions"):
//! - sessions driven while another thread evicts every session not in use,
//!   as often as it can, answer exactly as the same sessions on a server
//!   that never evicts: every reply, then Q, π, V, R, Ξ and the history;
//! - only sessions whose planner restores exactly leave memory once they
//!   have observed (the functional-graph engine, and continuous worlds,
//!   whose snapshot holds the whole agent); PVF and learned-model sessions
//!   leave only while they are as built;
//! - after a restart every recovered session starts evicted: listing them
//!   loads none, each loads on its first request with its state as it was,
//!   an evicted session can be deleted;
//! - the memory store never evicts.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use mcapi_server::service::{
    Caller, CreateSession, Limits, ManagerOptions, ObservationIn, ServiceError, SessionConfig,
    SessionManager, StepOut, ValueSelection,
};
use mcapi_store::Store;
use mcapi_testkit::{assert_bits_eq, stimulus};
use serde_json::{Value, json};

/// The four kinds of session driven: (model, agent).
fn kinds() -> Vec<(Value, Value)> {
    vec![
        // Functional-graph engine: evicted between any two requests.
        (json!({"preset": "hallway"}), json!({"seed": 1})),
        (
            json!({"preset": "hallway"}),
            json!({"seed": 2, "epsilon": 0.2}),
        ),
        // A⁻¹ and a learned P̂: stay once they have observed.
        (
            json!({"preset": "hallway", "basis": {"kind": "proto_value", "k": 5}}),
            json!({"seed": 3}),
        ),
        (
            json!({"states": 50, "actions": ["left", "right", "stay"],
                   "stimuli": ["food", "rest"], "transitions": "learn"}),
            json!({"seed": 4}),
        ),
    ]
}

fn durable(store: Arc<Store>) -> SessionManager {
    let manager = SessionManager::with_options(ManagerOptions {
        store: Some(store),
        snapshot_every: 7,
        evict_after: Some(Duration::from_secs(3600)),
        ..ManagerOptions::new(Limits::default(), 1)
    })
    .expect("manager");
    let report = manager.recover().expect("recovery");
    assert_eq!(report.skipped, 0, "{report:?}");
    manager
}

fn in_memory() -> SessionManager {
    let manager = SessionManager::new(Limits::default(), 1).expect("manager");
    manager.recover().expect("recovery");
    manager
}

/// What a hallway session is priced at (its `cost.bytes`).
fn hallway_price() -> u64 {
    let agent = SessionConfig::default();
    in_memory()
        .create(
            Caller::Anyone,
            CreateSession {
                model: json!({"preset": "hallway"}),
                agent,
            },
        )
        .expect("create")
        .cost
        .bytes
}

/// A manager on a fresh store that evicts (after an hour, unless a key's
/// quota `max_key_bytes` needs room first); the directory lives as long
/// as it is kept.
fn durable_with_quota(max_key_bytes: u64) -> (tempfile::TempDir, SessionManager) {
    let data = tempfile::tempdir().expect("data dir");
    let store = Arc::new(Store::open(data.path()).expect("store"));
    let manager = SessionManager::with_options(ManagerOptions {
        store: Some(store),
        evict_after: Some(Duration::from_secs(3600)),
        ..ManagerOptions::new(
            Limits {
                max_key_bytes,
                ..Limits::default()
            },
            1,
        )
    })
    .expect("manager");
    manager.recover().expect("recovery");
    (data, manager)
}

fn create(manager: &SessionManager, model: &Value, agent: &Value) -> String {
    let agent: SessionConfig = serde_json::from_value(agent.clone()).expect("agent config");
    manager
        .create(
            Caller::Anyone,
            CreateSession {
                model: model.clone(),
                agent,
            },
        )
        .expect("create")
        .id
}

/// The hallway's next state; the learned session may also walk into a
/// wall (and stays).
fn step_state(s: usize, a: usize) -> usize {
    match a {
        0 => s.saturating_sub(1),
        1 => (s + 1).min(49),
        _ => s,
    }
}

fn observation(state: usize, first: bool) -> ObservationIn {
    ObservationIn {
        state: Some(state),
        observation: None,
        stimulus: (!first).then(|| stimulus(state).to_vec()),
        action_taken: None,
        signal: None,
        signal_source: None,
        seq: None,
    }
}

fn assert_same_step(got: &StepOut, want: &StepOut, ctx: &str) {
    assert_eq!(got.tick, want.tick, "{ctx}: tick");
    assert_eq!(got.action_index, want.action_index, "{ctx}: action");
    assert_eq!(
        got.policy_version, want.policy_version,
        "{ctx}: policy version"
    );
    assert_eq!(got.reward.to_bits(), want.reward.to_bits(), "{ctx}: reward");
    assert_bits_eq(&got.drive, &want.drive, &format!("{ctx}: drive"));
}

/// Everything a client can read of a session, as JSON (f64s print exactly).
fn everything(manager: &SessionManager, id: &str) -> Value {
    read(manager, id, "v,q,policy,r,xi")
}

/// The value tables `selection` names, the history and the session's
/// info, as JSON.
fn read(manager: &SessionManager, id: &str, selection: &str) -> Value {
    let all = ValueSelection::parse(Some(selection)).expect("selection");
    let values = manager
        .values(Caller::Anyone, id, all)
        .expect("values")
        .value;
    let history = manager
        .history(Caller::Anyone, id, None)
        .expect("history")
        .value;
    let info = manager.get(Caller::Anyone, id).expect("get");
    json!({
        "values": values,
        "history": history,
        "drive": info.drive,
        "tick": info.tick,
        "policy_version": info.policy_version,
        "state": info.state,
        "stats": info.stats,
    })
}

#[test]
fn sessions_evicted_between_requests_answer_exactly_as_resident_ones() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let store = Arc::new(Store::open(data.path()).expect("store"));
    let evicting = Arc::new(durable(Arc::clone(&store)));
    let resident = in_memory();
    let pairs: Vec<(String, String)> = kinds()
        .iter()
        .map(|(m, a)| (create(&evicting, m, a), create(&resident, m, a)))
        .collect();
    // Created and never observed, every session is as its record builds it.
    assert_eq!(evicting.evict_idle(Duration::ZERO), 4);
    assert_eq!(evicting.evicted_len(), 4);
    assert_eq!(
        resident.evict_idle(Duration::ZERO),
        0,
        "no store, no eviction"
    );

    // Another thread evicts every session no request holds, over and over.
    let stop = Arc::new(AtomicBool::new(false));
    let evictions = Arc::new(AtomicUsize::new(0));
    let evictor = std::thread::spawn({
        let (manager, stop, evictions) = (
            Arc::clone(&evicting),
            Arc::clone(&stop),
            Arc::clone(&evictions),
        );
        move || {
            while !stop.load(Ordering::Relaxed) {
                evictions.fetch_add(manager.evict_idle(Duration::ZERO), Ordering::Relaxed);
                std::thread::yield_now();
            }
        }
    });
    let mut states = vec![25usize; pairs.len()];
    for tick in 0..150 {
        for (k, (a, b)) in pairs.iter().enumerate() {
            let obs = || vec![observation(states[k], tick == 0)];
            let got = rt
                .block_on(evicting.observe(Caller::Anyone, a, obs()))
                .expect("observe (evicting)");
            let want = rt
                .block_on(resident.observe(Caller::Anyone, b, obs()))
                .expect("observe (resident)");
            assert_same_step(&got[0], &want[0], &format!("session kind {k}, tick {tick}"));
            states[k] = step_state(states[k], got[0].action_index);
        }
    }
    stop.store(true, Ordering::Relaxed);
    evictor.join().expect("evictor");
    let evictions = evictions.load(Ordering::Relaxed);
    assert!(
        evictions >= 100,
        "the two hallway sessions should have left memory between most requests: {evictions} evictions"
    );
    // Once observed, only the functional-graph sessions may leave.
    evicting.evict_idle(Duration::ZERO);
    assert_eq!(evicting.evicted_len(), 2, "PVF and learned sessions stay");
    for (k, (a, b)) in pairs.iter().enumerate() {
        assert_eq!(
            everything(&evicting, a),
            everything(&resident, b),
            "session kind {k}: values, history and info"
        );
    }
    assert_eq!(evicting.evicted_len(), 0, "every read loaded its session");
}

#[test]
fn after_a_restart_sessions_start_evicted_and_load_on_their_first_request() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let store = Arc::new(Store::open(data.path()).expect("store"));
    let manager = durable(Arc::clone(&store));
    let ids: Vec<String> = kinds()
        .iter()
        .map(|(m, a)| create(&manager, m, a))
        .collect();
    let mut states = vec![25usize; ids.len()];
    for tick in 0..40 {
        for (k, id) in ids.iter().enumerate() {
            let step = rt
                .block_on(manager.observe(
                    Caller::Anyone,
                    id,
                    vec![observation(states[k], tick == 0)],
                ))
                .expect("observe");
            states[k] = step_state(states[k], step[0].action_index);
        }
    }
    let before: Vec<Value> = ids.iter().map(|id| everything(&manager, id)).collect();
    manager.shutdown();
    drop(manager);
    drop(store);

    let store = Arc::new(Store::open(data.path()).expect("reopen"));
    let manager = durable(store);
    assert_eq!(manager.evicted_len(), 4, "recovered sessions start evicted");
    let page = manager.list(Caller::Anyone, None, None).expect("list");
    assert_eq!(page.sessions.len(), 4);
    assert!(page.sessions.iter().all(|s| s.tick == 39), "{page:?}");
    assert_eq!(manager.evicted_len(), 4, "listing loads nothing");
    for (k, id) in ids.iter().enumerate() {
        let after = everything(&manager, id);
        assert_eq!(after["tick"], before[k]["tick"], "kind {k}");
        assert_eq!(after["drive"], before[k]["drive"], "kind {k}: D");
        assert_eq!(after["history"], before[k]["history"], "kind {k}: history");
        assert_eq!(
            after["values"]["xi"], before[k]["values"]["xi"],
            "kind {k}: Ξ"
        );
    }
    assert_eq!(manager.evicted_len(), 0);
    // An evicted session can be deleted; the others stay.
    assert_eq!(
        manager.evict_idle(Duration::ZERO),
        4,
        "untouched since loaded"
    );
    rt.block_on(manager.delete(Caller::Anyone, &ids[0]))
        .expect("delete an evicted session");
    assert!(manager.get(Caller::Anyone, &ids[0]).is_err(), "deleted");
    assert_eq!(manager.len(), 3);
    assert_eq!(manager.evicted_len(), 3);
    manager.shutdown();
}

/// A key's quota of bytes charges a resident session its estimate and an
/// evicted one its stub; when a creation or a load would go over it, the
/// key's sessions idle for a second or more are evicted to make room, the
/// least recently active first; a load that still does not fit is refused
/// with `unavailable` and the session stays in the store.
#[test]
fn a_key_over_its_quota_evicts_its_idle_sessions_to_make_room() {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let hallway = json!({"preset": "hallway"});
    let price = hallway_price();
    // Room for three resident sessions (and a few stubs of about 200 bytes).
    let quota = 3 * price + 100;
    let (_data, manager) = durable_with_quota(quota);
    let [a, b, c] = [1, 2, 3].map(|seed| create(&manager, &hallway, &json!({ "seed": seed })));
    assert_eq!(manager.usage(Caller::Anyone).bytes, 3 * price);
    let fourth = |seed: u64| {
        let agent: SessionConfig = serde_json::from_value(json!({ "seed": seed })).expect("agent");
        manager.create(
            Caller::Anyone,
            CreateSession {
                model: hallway.clone(),
                agent,
            },
        )
    };
    // All three were active within the second: none gives way.
    match fourth(4) {
        Err(ServiceError::QuotaExceeded(m)) => assert!(m.contains("--max-key-bytes"), "{m}"),
        other => panic!("a fourth session within the second: {other:?}"),
    }
    assert_eq!(manager.evicted_len(), 0);

    std::thread::sleep(Duration::from_millis(1100));
    let d = fourth(4)
        .expect("room is made by evicting the idle sessions")
        .id;
    // The oldest went first, and enough of them to leave a tenth of the
    // quota free: a and b.
    assert_eq!(manager.evicted_len(), 2);
    let usage = manager.usage(Caller::Anyone);
    assert_eq!(usage.sessions, 4);
    assert!(usage.bytes < 2 * price + 1000, "{usage:?}");

    rt.block_on(async {
        // Loading a back charges its full price: c, idle for a second,
        // makes room.
        manager
            .observe(Caller::Anyone, &a, vec![observation(0, true)])
            .await
            .expect("a loads back, c makes room");
        assert_eq!(manager.evicted_len(), 2, "c left, a came back");
        // a and d are fresh: b cannot be loaded back now.
        match manager
            .observe(Caller::Anyone, &b, vec![observation(0, true)])
            .await
        {
            Err(ServiceError::Unavailable(m)) => {
                assert!(m.contains("--max-key-bytes") && m.contains(&b), "{m}");
            }
            other => panic!("b loaded over the quota: {other:?}"),
        }
        assert!(manager.usage(Caller::Anyone).bytes <= quota);
        // Deleting is how a key makes room: never refused for the quota.
        manager
            .delete(Caller::Anyone, &b)
            .await
            .expect("an evicted session is deleted at a full quota");
        tokio::time::sleep(Duration::from_millis(1100)).await;
        manager
            .observe(Caller::Anyone, &c, vec![observation(0, true)])
            .await
            .expect("c loads once another session has been idle a second");
        assert!(manager.usage(Caller::Anyone).bytes <= quota);
        for id in [&a, &c, &d] {
            manager.delete(Caller::Anyone, id).await.expect("delete");
        }
    });
    assert_eq!(manager.usage(Caller::Anyone), Default::default());
}

/// Creations racing each other at a full quota each get room: one that
/// loses the room it was admitted to, to another committed first, makes
/// room again instead of being refused.
#[test]
fn concurrent_creations_at_a_full_quota_all_get_room() {
    let hallway = json!({"preset": "hallway"});
    let price = hallway_price();
    let (_data, manager) = durable_with_quota(20 * price);
    for seed in 0..20 {
        create(&manager, &hallway, &json!({ "seed": seed }));
    }
    std::thread::sleep(Duration::from_millis(1100));
    let refused = AtomicUsize::new(0);
    std::thread::scope(|scope| {
        for t in 0..8u64 {
            let (manager, hallway, refused) = (&manager, &hallway, &refused);
            scope.spawn(move || {
                for i in 0..2 {
                    let agent: SessionConfig =
                        serde_json::from_value(json!({ "seed": 100 + 2 * t + i })).expect("agent");
                    let created = manager.create(
                        Caller::Anyone,
                        CreateSession {
                            model: hallway.clone(),
                            agent,
                        },
                    );
                    if let Err(e) = created {
                        eprintln!("refused: {e}");
                        refused.fetch_add(1, Ordering::Relaxed);
                    }
                }
            });
        }
    });
    assert_eq!(refused.load(Ordering::Relaxed), 0);
    let usage = manager.usage(Caller::Anyone);
    assert_eq!(usage.sessions, 36);
    assert!(usage.bytes <= 20 * price, "{usage:?}");
    assert!(manager.evicted_len() >= 16);
}

/// A continuous world's session leaves memory between requests once it
/// has observed, as the functional-graph ones do: its snapshot holds the
/// whole agent (docs/algorithm.md §9.7), and the session loaded back from
/// it answers as the one that never left.
#[test]
fn continuous_sessions_evicted_between_requests_answer_exactly_as_resident_ones() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let store = Arc::new(Store::open(data.path()).expect("store"));
    let evicting = durable(Arc::clone(&store));
    let resident = in_memory();
    let model = json!({
        "observation_space": {"low": [0, 0], "high": [1, 1]},
        "actions": ["north", "south", "east", "west"],
        "stimuli": ["food", "rest"],
        "basis": {"kind": "fourier", "order": 3},
        "samples": {"max": 256},
    });
    let agent = json!({"seed": 5});
    let (a, b) = (
        create(&evicting, &model, &agent),
        create(&resident, &model, &agent),
    );
    let mut x = [0.5f64, 0.5];
    let mut evictions = 0;
    for tick in 0..150 {
        let obs = || {
            let food = x[0] < 0.2 && x[1] < 0.2;
            let rest = x[0] > 0.8 && x[1] > 0.8;
            vec![ObservationIn {
                state: None,
                observation: Some(x.to_vec()),
                stimulus: (tick > 0)
                    .then(|| vec![f64::from(u8::from(food)), f64::from(u8::from(rest))]),
                action_taken: None,
                signal: None,
                signal_source: None,
                seq: None,
            }]
        };
        let got = rt
            .block_on(evicting.observe(Caller::Anyone, &a, obs()))
            .expect("observe (evicting)");
        let want = rt
            .block_on(resident.observe(Caller::Anyone, &b, obs()))
            .expect("observe (resident)");
        assert_same_step(&got[0], &want[0], &format!("tick {tick}"));
        let (dx, dy) = [(0.0, 0.07), (0.0, -0.07), (0.07, 0.0), (-0.07, 0.0)][got[0].action_index];
        x = [(x[0] + dx).clamp(0.0, 1.0), (x[1] + dy).clamp(0.0, 1.0)];
        // The request's task may hold the session a moment past its reply.
        let deadline = Instant::now() + Duration::from_secs(5);
        let mut evicted = evicting.evict_idle(Duration::ZERO);
        while evicted == 0 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(1));
            evicted = evicting.evict_idle(Duration::ZERO);
        }
        evictions += evicted;
    }
    assert_eq!(
        evictions, 150,
        "the session left memory after every request"
    );
    // A continuous world has V, Q and π (no R or Ξ tables).
    let all = |manager: &SessionManager, id: &str| read(manager, id, "v,q,policy");
    assert_eq!(
        all(&evicting, &a),
        all(&resident, &b),
        "values, history and info"
    );
    assert!(
        all(&resident, &b)["stats"]["continuous"]["samples"].as_u64() > Some(20),
        "the store filled"
    );
}
