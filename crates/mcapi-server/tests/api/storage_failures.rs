//! Storage failures, on the session manager in this process: a failed
//! commit rolls the session back and a retry applies once, a delete whose
//! commit fails keeps the session, a lockstep observation whose plan fails is
//! logged.

use mcapi_core::Observation;
use mcapi_testkit::{assert_bits_eq, core_agent, params, stimulus};
use serde_json::json;

/// A failed commit rolls the session back to its durable state (the
/// observations it did not make durable are not kept in memory either), the
/// store refuses nothing afterwards, a retry applies exactly once, and the
/// store still recovers: no hole in the log.
#[test]
fn a_failed_commit_rolls_the_session_back_and_a_retry_applies_once() {
    use mcapi_server::service::{
        Caller, CreateSession, Limits, ManagerOptions, ObservationIn, ServiceError, SessionConfig,
        SessionManager,
    };
    use mcapi_store::Store;
    use std::sync::Arc;

    // Plain threads: `create` and `shutdown` block on the store.
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let open = |store: Arc<Store>| {
        let manager = SessionManager::with_options(ManagerOptions {
            store: Some(store),
            snapshot_every: 4,
            ..ManagerOptions::new(Limits::default(), 1)
        })
        .expect("manager");
        manager.recover().expect("recovery");
        manager
    };
    let obs = |state: usize, first: bool| ObservationIn {
        state: Some(state),
        observation: None,
        stimulus: (!first).then(|| stimulus(state).to_vec()),
        action_taken: None,
        signal: None,
        signal_source: None,
        seq: None,
    };
    let store = Arc::new(Store::open(data.path()).expect("store"));
    let manager = open(Arc::clone(&store));
    let id = manager
        .create(
            Caller::Anyone,
            CreateSession {
                model: json!({"preset": "hallway"}),
                agent: SessionConfig {
                    seed: Some(5),
                    ..SessionConfig::default()
                },
            },
        )
        .expect("create")
        .id;
    let mut core = core_agent(&params(5, None));
    rt.block_on(manager.observe(Caller::Anyone, &id, vec![obs(9, true)]))
        .expect("first");
    core.step(&Observation::first(9)).expect("core first");
    // Ticks 1-5 (a snapshot at 4), then a failing commit for ticks 6-7.
    for s in [10, 11, 12, 11, 10] {
        rt.block_on(manager.observe(Caller::Anyone, &id, vec![obs(s, false)]))
            .expect("observe");
        core.step(&Observation::new(s, &stimulus(s))).expect("core");
    }
    store.fail_next_commits(1);
    let err = rt
        .block_on(manager.observe(Caller::Anyone, &id, vec![obs(9, false), obs(8, false)]))
        .expect_err("the commit fails");
    assert!(matches!(err, ServiceError::Storage(_)), "{err}");
    let info = manager.get(Caller::Anyone, &id).expect("get");
    assert_eq!(info.tick, 5, "rolled back to the durable tick");
    assert_bits_eq(&info.drive, core.drive().vector(), "D after the rollback");
    // The retry applies once, exactly as on a core agent that never failed.
    let steps = rt
        .block_on(manager.observe(Caller::Anyone, &id, vec![obs(9, false), obs(8, false)]))
        .expect("the retry");
    core.step(&Observation::new(9, &stimulus(9))).expect("core");
    core.step(&Observation::new(8, &stimulus(8))).expect("core");
    assert_eq!(steps.last().map(|s| s.tick), Some(7));
    assert!(
        !store.is_broken(&id),
        "the reload resumed the session's writes"
    );
    assert_bits_eq(&steps[1].drive, core.drive().vector(), "D after the retry");
    manager.shutdown();
    drop(manager);
    drop(store);
    // The store recovers: the log has no hole.
    let store = Arc::new(Store::open(data.path()).expect("reopen"));
    let manager = open(store);
    let info = manager.get(Caller::Anyone, &id).expect("recovered");
    assert_eq!(info.tick, 7);
    assert_bits_eq(&info.drive, core.drive().vector(), "D after recovery");
    manager.shutdown();
}

/// A manager on the store in `dir`, recovered; `snapshot_every` as given.
fn in_process(
    store: std::sync::Arc<mcapi_store::Store>,
    snapshot_every: u64,
) -> mcapi_server::service::SessionManager {
    use mcapi_server::service::{Limits, ManagerOptions, SessionManager};
    let manager = SessionManager::with_options(ManagerOptions {
        store: Some(store),
        snapshot_every,
        ..ManagerOptions::new(Limits::default(), 1)
    })
    .expect("manager");
    let report = manager.recover().expect("recovery");
    assert_eq!(report.skipped, 0, "{report:?}");
    manager
}

fn hallway_session(manager: &mcapi_server::service::SessionManager, seed: u64) -> String {
    use mcapi_server::service::{Caller, CreateSession, SessionConfig};
    manager
        .create(
            Caller::Anyone,
            CreateSession {
                model: json!({"preset": "hallway"}),
                agent: SessionConfig {
                    seed: Some(seed),
                    ..SessionConfig::default()
                },
            },
        )
        .expect("create")
        .id
}

fn observation(state: usize, first: bool) -> mcapi_server::service::ObservationIn {
    mcapi_server::service::ObservationIn {
        state: Some(state),
        observation: None,
        stimulus: (!first).then(|| stimulus(state).to_vec()),
        action_taken: None,
        signal: None,
        signal_source: None,
        seq: None,
    }
}

/// DELETE commits before it removes anything: a delete whose commit fails
/// leaves the session in place, served and observed as before; the retry
/// deletes it, and it stays deleted after a restart (the other session is
/// untouched).
#[test]
fn a_delete_whose_commit_fails_keeps_the_session_and_its_retry_deletes_it() {
    use mcapi_server::service::{Caller, ServiceError};
    use mcapi_store::Store;
    use std::sync::Arc;

    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let store = Arc::new(Store::open(data.path()).expect("store"));
    let manager = in_process(Arc::clone(&store), 1000);
    let (gone, kept) = (hallway_session(&manager, 7), hallway_session(&manager, 8));
    for id in [&gone, &kept] {
        rt.block_on(manager.observe(Caller::Anyone, id, vec![observation(9, true)]))
            .expect("first");
        for s in [10, 11, 12] {
            rt.block_on(manager.observe(Caller::Anyone, id, vec![observation(s, false)]))
                .expect("observe");
        }
    }
    store.fail_next_commits(1);
    let err = rt
        .block_on(manager.delete(Caller::Anyone, &gone))
        .expect_err("the delete's commit fails");
    assert!(matches!(err, ServiceError::Storage(_)), "{err}");
    // Nothing was removed: listed, served, observed.
    let info = manager.get(Caller::Anyone, &gone).expect("still there");
    assert_eq!(info.tick, 3);
    let page = manager.list(Caller::Anyone, None, None).expect("list");
    assert!(page.sessions.iter().any(|s| s.id == gone));
    let steps = rt
        .block_on(manager.observe(Caller::Anyone, &gone, vec![observation(11, false)]))
        .expect("observed after the failed delete");
    assert_eq!(steps[0].tick, 4);
    assert!(!store.is_broken(&gone));
    // The retry deletes it.
    rt.block_on(manager.delete(Caller::Anyone, &gone))
        .expect("the retry");
    assert!(matches!(
        manager.get(Caller::Anyone, &gone),
        Err(ServiceError::NotFound(_))
    ));
    assert!(store.session(&gone).expect("read").is_none());
    let err = rt
        .block_on(manager.delete(Caller::Anyone, &gone))
        .expect_err("deleting twice");
    assert!(matches!(err, ServiceError::NotFound(_)), "{err}");
    // A crash (no shutdown snapshot): still deleted; the other one whole.
    drop(manager);
    drop(store);
    let manager = in_process(Arc::new(Store::open(data.path()).expect("reopen")), 1000);
    assert!(matches!(
        manager.get(Caller::Anyone, &gone),
        Err(ServiceError::NotFound(_))
    ));
    assert_eq!(manager.get(Caller::Anyone, &kept).expect("kept").tick, 3);
    manager.shutdown();
}

/// A lockstep observation whose policy update fails after it was applied
/// (`AlgoError::Numerical` from the planner) is logged: the reply is the
/// error, the tick advanced, and after a crash the session comes back
/// exactly as it was served (tick, D, Ξ, history), then goes on.
#[test]
fn a_lockstep_observation_whose_plan_fails_is_logged() {
    use mcapi_core::AlgoError;
    use mcapi_server::service::{Caller, ServiceError, ValueSelection};
    use mcapi_store::Store;
    use std::sync::Arc;

    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let store = Arc::new(Store::open(data.path()).expect("store"));
    let manager = in_process(Arc::clone(&store), 1000);
    let id = hallway_session(&manager, 11);
    let mut core = core_agent(&params(11, None));
    rt.block_on(manager.observe(Caller::Anyone, &id, vec![observation(20, true)]))
        .expect("first");
    core.step(&Observation::first(20)).expect("core first");
    for s in [21, 22] {
        rt.block_on(manager.observe(Caller::Anyone, &id, vec![observation(s, false)]))
            .expect("observe");
        core.step(&Observation::new(s, &stimulus(s))).expect("core");
    }
    manager.session(&id).expect("session").fail_next_plans(1);
    let err = rt
        .block_on(manager.observe(Caller::Anyone, &id, vec![observation(23, false)]))
        .expect_err("the policy update fails");
    assert!(
        matches!(err, ServiceError::Algo(AlgoError::Numerical(_))),
        "{err}"
    );
    // Applied: Ξ, D and the tick moved. The core agent observes it too and
    // acts on its old policy, as the session did.
    core.observe(&Observation::new(23, &stimulus(23)))
        .expect("core observe");
    core.act().expect("core act");
    let live = manager.get(Caller::Anyone, &id).expect("get");
    assert_eq!(live.tick, 3, "the failed update's observation is applied");
    assert_bits_eq(&live.drive, core.drive().vector(), "D");
    let all = ValueSelection::parse(Some("xi")).expect("selection");
    let live_xi = manager
        .values(Caller::Anyone, &id, all)
        .expect("values")
        .value
        .xi;
    let live_history = manager
        .history(Caller::Anyone, &id, None)
        .expect("history")
        .value;
    assert_eq!(live_history.last().map(|h| h.tick), Some(3));
    // A crash: what was served comes back from the log.
    drop(manager);
    drop(store);
    let store = Arc::new(Store::open(data.path()).expect("reopen"));
    let manager = in_process(Arc::clone(&store), 1000);
    let recovered = manager.get(Caller::Anyone, &id).expect("recovered");
    assert_eq!(recovered.tick, 3, "the log has the observation memory had");
    assert_bits_eq(&recovered.drive, &live.drive, "D after recovery");
    assert_eq!(
        manager
            .values(Caller::Anyone, &id, all)
            .expect("values")
            .value
            .xi,
        live_xi,
        "Ξ after recovery"
    );
    assert_eq!(
        manager
            .history(Caller::Anyone, &id, None)
            .expect("history")
            .value,
        live_history,
        "history after recovery"
    );
    // And it goes on, planning again, as a core agent that never crashed.
    let steps = rt
        .block_on(manager.observe(Caller::Anyone, &id, vec![observation(24, false)]))
        .expect("observe after recovery");
    let step = core
        .step(&Observation::new(24, &stimulus(24)))
        .expect("core step");
    assert_eq!(steps[0].tick, 4);
    assert_eq!(steps[0].action_index, step.action, "action after recovery");
    assert_bits_eq(&steps[0].drive, core.drive().vector(), "D after recovery");
    let xi = manager
        .values(Caller::Anyone, &id, all)
        .expect("values")
        .value
        .xi;
    let model = core.planning_model().model();
    for (s, row) in xi.expect("xi").iter().enumerate() {
        for (a, cell) in row.iter().enumerate() {
            if let (Some(p), Some(cell)) = (model.pair(s, a), cell) {
                assert_bits_eq(cell, core.stimulus().row(p), &format!("Ξ[{s}][{a}]"));
            }
        }
    }
    manager.shutdown();
}
