//! Faults stay with the request and the session they hit: a panicking
//! update quarantines its session, the tick worker survives, and every
//! other session goes on.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use serde_json::json;

use super::session::Update;
use super::test_support::{obs, rt};
use super::*;

fn manager(workers: usize) -> Arc<SessionManager> {
    let opts = ManagerOptions {
        // Every update goes through the tick pool.
        inline_plan: Duration::ZERO,
        ..ManagerOptions::new(Limits::default(), workers)
    };
    Arc::new(SessionManager::with_options(opts).expect("manager"))
}

fn create(m: &SessionManager, mode: UpdateMode) -> String {
    let req = CreateSession {
        model: json!({"preset": "hallway"}),
        agent: SessionConfig {
            seed: Some(7),
            update_mode: Some(mode),
            ..SessionConfig::default()
        },
    };
    m.create(Caller::Anyone, req).expect("create").id
}

#[test]
fn a_panicking_lockstep_update_quarantines_its_session_and_the_worker_survives() {
    let rt = rt();
    // One worker: if the panic killed it, the second session would wait forever.
    let m = manager(1);
    let bad = create(&m, UpdateMode::Lockstep);
    let good = create(&m, UpdateMode::Lockstep);
    rt.block_on(async {
        m.observe(Caller::Anyone, &bad, vec![obs(0, None)])
            .await
            .expect("first observation");
        m.session(&bad)
            .expect("session")
            .panic_next
            .store(Update::Observe as u8, Ordering::Release);
        let err = m
            .observe(Caller::Anyone, &bad, vec![obs(1, Some(vec![0.0, 0.0]))])
            .await
            .expect_err("the update panicked");
        assert!(
            matches!(err, ServiceError::SessionFailed(ref id) if *id == bad),
            "{err:?}"
        );
        // Quarantined for every reader and writer, not served half-updated.
        let again = m
            .observe(Caller::Anyone, &bad, vec![obs(1, Some(vec![0.0, 0.0]))])
            .await
            .expect_err("quarantined");
        assert!(matches!(again, ServiceError::SessionFailed(_)), "{again:?}");
        assert!(matches!(
            m.get(Caller::Anyone, &bad),
            Err(ServiceError::SessionFailed(_))
        ));
        assert!(matches!(
            m.values(Caller::Anyone, &bad, ValueSelection::default()),
            Err(ServiceError::SessionFailed(_))
        ));
        // The worker survived: another session is served by the same pool.
        for t in 0..5 {
            let stimulus = (t > 0).then(|| vec![0.0, 0.0]);
            m.observe(Caller::Anyone, &good, vec![obs(t, stimulus)])
                .await
                .expect("the other session goes on");
        }
        assert_eq!(m.get(Caller::Anyone, &good).expect("get").tick, 4);
        // Deleting the quarantined session works and frees its slot.
        m.delete(Caller::Anyone, &bad).await.expect("delete");
        assert!(matches!(
            m.get(Caller::Anyone, &bad),
            Err(ServiceError::NotFound(_))
        ));
        assert_eq!(m.len(), 1);
    });
    m.shutdown();
}

#[test]
fn a_panicking_async_plan_quarantines_its_session_without_killing_the_worker() {
    let rt = rt();
    let m = manager(1);
    let bad = create(&m, UpdateMode::Async);
    let good = create(&m, UpdateMode::Lockstep);
    let session = m.session(&bad).expect("session");
    rt.block_on(async {
        m.observe(Caller::Anyone, &bad, vec![obs(0, None)])
            .await
            .expect("first");
        session
            .panic_next
            .store(Update::Plan as u8, Ordering::Release);
        // The reply comes at once; the plan job panics on the pool.
        m.observe(Caller::Anyone, &bad, vec![obs(1, Some(vec![1.0, 0.0]))])
            .await
            .expect("async reply before the plan");
        // The pool is FIFO with one worker: once the lockstep job of the
        // other session is answered, the panicking plan job has run.
        m.observe(Caller::Anyone, &good, vec![obs(0, None)])
            .await
            .expect("the worker survived");
        m.observe(Caller::Anyone, &good, vec![obs(1, Some(vec![1.0, 0.0]))])
            .await
            .expect("the worker survived");
    });
    assert!(session.is_failed());
    assert!(matches!(
        m.history(Caller::Anyone, &bad, None),
        Err(ServiceError::SessionFailed(_))
    ));
    m.shutdown();
}

#[test]
fn a_key_quota_counts_sessions_and_estimated_bytes() {
    let limits = Limits {
        max_key_sessions: 2,
        ..Limits::default()
    };
    let m = SessionManager::new(limits, 1).expect("manager");
    create(&m, UpdateMode::Lockstep);
    let second = create(&m, UpdateMode::Lockstep);
    let req = CreateSession {
        model: json!({"preset": "hallway"}),
        agent: SessionConfig::default(),
    };
    let err = m
        .create(Caller::Anyone, req.clone())
        .expect_err("quota reached");
    assert!(matches!(err, ServiceError::QuotaExceeded(_)), "{err:?}");
    rt().block_on(m.delete(Caller::Anyone, &second))
        .expect("delete");
    m.create(Caller::Anyone, req.clone())
        .expect("a deleted session gives its slot back");

    // Bytes: a quota smaller than two hallway sessions.
    let first = m.list(Caller::Anyone, None, None).expect("list").sessions[0]
        .id
        .clone();
    let one = m.get(Caller::Anyone, &first).expect("get").cost.bytes;
    let limits = Limits {
        max_key_bytes: one + one / 2,
        ..Limits::default()
    };
    let m = SessionManager::new(limits, 1).expect("manager");
    m.create(Caller::Anyone, req.clone()).expect("one fits");
    let err = m.create(Caller::Anyone, req).expect_err("two do not");
    assert!(
        matches!(&err, ServiceError::QuotaExceeded(msg) if msg.contains("--max-key-bytes")),
        "{err:?}"
    );
    m.shutdown();
}
