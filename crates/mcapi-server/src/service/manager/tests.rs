//! The manager's own tests, called directly (no transport): the life of a
//! session through each of its concerns (create, lookup, observe,
//! lifecycle), what another key sees, the bounds of a listing page and of a
//! batch, and that the same seed gives the same session.

use std::sync::Arc;

use serde_json::json;

use super::*;
use crate::service::agent_config::SessionConfig;
use crate::service::test_support::{obs, rt};

fn manager() -> Arc<SessionManager> {
    Arc::new(SessionManager::new(Limits::default(), 1).expect("manager"))
}

fn hallway(seed: u64) -> CreateSession {
    CreateSession {
        model: json!({"preset": "hallway"}),
        agent: SessionConfig {
            seed: Some(seed),
            ..SessionConfig::default()
        },
    }
}

const KEY_A: Caller = Caller::Key([1; 32]);
const KEY_B: Caller = Caller::Key([2; 32]);

#[test]
fn a_session_is_created_observed_found_and_deleted() {
    let rt = rt();
    let m = manager();
    let info = m.create(Caller::Anyone, hallway(7)).expect("create");
    assert_eq!(info.tick, 0);
    assert_eq!(m.len(), 1);
    rt.block_on(async {
        let steps = m
            .observe(
                Caller::Anyone,
                &info.id,
                vec![obs(0, None), obs(1, Some(vec![0.0, 0.0]))],
            )
            .await
            .expect("a batch of two");
        assert_eq!(steps.len(), 2);
        // The first observation places the agent; the second is tick 1.
        assert_eq!(m.get(Caller::Anyone, &info.id).expect("get").tick, 1);
        m.delete(Caller::Anyone, &info.id).await.expect("delete");
    });
    assert!(m.is_empty());
    assert!(matches!(
        m.get(Caller::Anyone, &info.id),
        Err(ServiceError::NotFound(_))
    ));
}

#[test]
fn another_key_finds_nothing_of_a_session_and_lists_none() {
    let rt = rt();
    let m = manager();
    let id = m.create(KEY_A, hallway(1)).expect("create").id;
    assert!(matches!(m.get(KEY_B, &id), Err(ServiceError::NotFound(_))));
    assert!(m.list(KEY_B, None, None).expect("list").sessions.is_empty());
    assert_eq!(m.list(KEY_A, None, None).expect("list").sessions.len(), 1);
    rt.block_on(async {
        let err = m
            .observe(KEY_B, &id, vec![obs(0, None)])
            .await
            .expect_err("not B's session");
        assert!(matches!(err, ServiceError::NotFound(_)), "{err:?}");
        let err = m.delete(KEY_B, &id).await.expect_err("not B's session");
        assert!(matches!(err, ServiceError::NotFound(_)), "{err:?}");
    });
    assert_eq!(m.len(), 1, "B's delete removed nothing");
}

#[test]
fn listing_pages_through_every_session_in_id_order() {
    let m = manager();
    let mut ids: Vec<String> = (0..5)
        .map(|seed| m.create(Caller::Anyone, hallway(seed)).expect("create").id)
        .collect();
    ids.sort();
    let mut seen = Vec::new();
    let mut after: Option<String> = None;
    loop {
        let page = m
            .list(Caller::Anyone, after.as_deref(), Some(2))
            .expect("a page");
        assert!(page.sessions.len() <= 2);
        seen.extend(page.sessions.iter().map(|s| s.id.clone()));
        match page.next {
            Some(next) => after = Some(next),
            None => break,
        }
    }
    assert_eq!(seen, ids);
    for bad in [0, MAX_PAGE + 1] {
        assert!(
            m.list(Caller::Anyone, None, Some(bad)).is_err(),
            "page size {bad} is refused"
        );
    }
}

#[test]
fn an_empty_or_oversized_batch_is_refused_before_anything_is_applied() {
    let rt = rt();
    let m = manager();
    let id = m.create(Caller::Anyone, hallway(3)).expect("create").id;
    rt.block_on(async {
        let err = m
            .observe(Caller::Anyone, &id, Vec::new())
            .await
            .expect_err("empty");
        assert!(matches!(err, ServiceError::BadRequest(_)), "{err:?}");
        let too_many = vec![obs(0, None); m.limits().max_batch + 1];
        let err = m
            .observe(Caller::Anyone, &id, too_many)
            .await
            .expect_err("over the batch limit");
        assert!(matches!(err, ServiceError::LimitExceeded(_)), "{err:?}");
    });
    assert_eq!(m.get(Caller::Anyone, &id).expect("get").tick, 0);
}

#[test]
fn the_same_seed_and_observations_give_the_same_session() {
    let rt = rt();
    let m = manager();
    let a = m.create(Caller::Anyone, hallway(11)).expect("create").id;
    let b = m.create(Caller::Anyone, hallway(11)).expect("create").id;
    rt.block_on(async {
        let batch = || {
            vec![
                obs(0, None),
                obs(1, Some(vec![1.0, 0.0])),
                obs(2, Some(vec![0.0, 0.0])),
            ]
        };
        let sa = m.observe(Caller::Anyone, &a, batch()).await.expect("a");
        let sb = m.observe(Caller::Anyone, &b, batch()).await.expect("b");
        let json = |s: &[StepOut]| serde_json::to_string(s).expect("serialises");
        assert_eq!(json(&sa), json(&sb));
    });
    let (ia, ib) = (
        m.get(Caller::Anyone, &a).expect("a"),
        m.get(Caller::Anyone, &b).expect("b"),
    );
    assert_eq!(ia.drive, ib.drive);
    assert_eq!(ia.tick, ib.tick);
}

/// A group remembers where it found its members by weak references (no
/// search of the table per member and step); an eviction drops its
/// members' references, so an idle group whose members left memory keeps
/// none of them allocated.
#[test]
fn an_eviction_drops_what_a_group_remembers_of_its_members() {
    use crate::service::groups::{Columns, CreateGroup};
    let rt = rt();
    let data = tempfile::tempdir().expect("data dir");
    let store = Arc::new(mcapi_store::Store::open(data.path()).expect("store"));
    let m = Arc::new(
        SessionManager::with_options(ManagerOptions {
            store: Some(store),
            ..ManagerOptions::new(Limits::default(), 1)
        })
        .expect("manager"),
    );
    m.recover().expect("recovery");
    let body: CreateGroup =
        serde_json::from_value(json!({"model": {"preset": "hallway"}, "n": 3, "seed": 5}))
            .expect("body");
    let info = m.create_group(Caller::Anyone, body).expect("create");
    let step = |stimuli: Vec<f64>| {
        let steps = rt
            .block_on(m.step_group(
                Caller::Anyone,
                &info.id,
                Columns {
                    states: vec![1, 2, 3],
                    stimuli,
                    ..Columns::default()
                },
            ))
            .expect("step");
        assert!(steps.iter().all(|s| s.result.is_ok()));
    };
    step(Vec::new());
    step(vec![0.5; 6]);
    let group = Arc::clone(m.groups.read().get(&info.id).expect("group"));
    let remembered = || {
        group
            .resolved
            .lock()
            .iter()
            .filter(|(_, s)| !s.ptr_eq(&std::sync::Weak::new()))
            .count()
    };
    assert_eq!(remembered(), 3, "each member found once is remembered");
    assert_eq!(m.evict_idle(std::time::Duration::ZERO), 3);
    assert_eq!(remembered(), 0, "the evicted members are forgotten");
    // This step finds them evicted and loads them back (which changes the
    // table); the next finds them in memory and remembers them again.
    step(vec![0.0, 1.0, 0.0, 1.0, 0.0, 1.0]);
    assert_eq!(remembered(), 0, "found evicted");
    step(vec![0.0; 6]);
    assert_eq!(remembered(), 3, "found again once loaded back");
    m.shutdown();
}

#[test]
fn one_policy_update_in_sixteen_is_timed_after_the_first_thirty_two() {
    let m = manager();
    let id = m.create(Caller::Anyone, hallway(5)).expect("create").id;
    let session = m.session(&id).expect("session");
    assert_eq!(
        session.plan_cost_ns(),
        u64::MAX,
        "no estimate before an update"
    );
    let result = session.observe(&[obs(0, None)], false).result;
    result.expect("placed");
    let mut timed = Vec::new();
    for tick in 0..72u64 {
        let stimulus = Some(vec![(tick % 2) as f64, 0.0]);
        let result = session.observe(&[obs(1, stimulus)], false).result;
        result.expect("observed");
        if session.plan_if_needed().expect("planned").is_some() {
            timed.push(tick);
        }
    }
    // Every one of the first 32, then one in 16 (policy versions 32, 48
    // and 64).
    let expected: Vec<u64> = (0..32).chain([32, 48, 64]).collect();
    assert_eq!(timed, expected);
    assert_ne!(
        session.plan_cost_ns(),
        u64::MAX,
        "the first update was measured"
    );
    // Lockstep observations with their updates, timed alike.
    let mut timed = 0;
    for tick in 0..32u64 {
        let stimulus = Some(vec![0.0, (tick % 2) as f64]);
        let observed = session.observe(&[obs(1, stimulus)], true);
        observed.result.expect("observed");
        timed += usize::from(observed.timed.is_some());
    }
    assert_eq!(timed, 2, "policy versions 80 and 96");
    // A batch of several is always timed.
    let batch = vec![obs(1, Some(vec![1.0, 0.0])), obs(1, Some(vec![0.0, 1.0]))];
    assert!(session.observe(&batch, true).timed.is_some());
}
