//! Restarts of the real binary: a clean restart (SIGTERM) keeps every
//! session exactly and the shutdown snapshot trims the log; a deleted session
//! stays deleted; after kill -9 the history ring comes back as it was served;
//! tighter limits at restart keep the stored sessions.

use crate::common;

use common::{
    Launch, Server, assert_float_roundtrip, grpc_create, grpc_request, http_client, log_events,
    params, rest, rest_create, rest_get, rest_list_all,
};
use mcapi_server::api::grpc::pb;
use reqwest::Method;
use serde_json::json;
use tonic::Code;

use super::{STORE_FILE, Sim, everything, log_path, logs, settled, table_rows};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clean_restart_keeps_every_session_exactly_and_trims_the_log() {
    assert_float_roundtrip();
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    // The default snapshot interval (1000) is never reached: only the
    // shutdown snapshot covers these sessions.
    let launch = Launch::new(data.path(), &[]);
    let mut server = Server::start(&launch, log_path(&logs, "first")).await;
    let client = http_client();
    let mut grpc = server.grpc_client().await;
    let base = server.base();

    // Lockstep (one exploring, so the RNG state matters) and async, over
    // both transports.
    let mut sims = vec![
        Sim::new(
            rest_create(
                &client,
                &base,
                None,
                json!({"seed": 101, "update_mode": "lockstep", "epsilon": 0.1}),
            )
            .await,
            None,
            params(101, Some(0.1)),
            true,
        ),
        Sim::new(
            rest_create(
                &client,
                &base,
                None,
                json!({"seed": 102, "update_mode": "async"}),
            )
            .await,
            None,
            params(102, None),
            false,
        ),
        Sim::new(
            grpc_create(&mut grpc, None, 103, true, None).await,
            None,
            params(103, None),
            true,
        ),
        Sim::new(
            grpc_create(&mut grpc, None, 104, false, None).await,
            None,
            params(104, None),
            false,
        ),
    ];
    for (i, sim) in sims.iter_mut().enumerate() {
        if i < 2 {
            sim.rest_ticks(&client, &base, 150).await;
        } else {
            sim.grpc_ticks(&mut grpc, 150).await;
        }
    }
    let mut before = Vec::new();
    for sim in &sims {
        sim.check(&client, &base, "before the restart").await;
        // Async sessions' queued policy updates land first, so the tables
        // read are those the shutdown snapshot keeps.
        before.push(settled(&client, &base, None, &sim.id).await);
    }

    let status = server.terminate();
    assert!(status.success(), "clean exit: {status}");
    let log = server.log_text();
    let written = log_events(&log, "snapshots written at shutdown");
    assert_eq!(written.len(), 1, "{log}");
    assert_eq!(written[0]["snapshots"], json!(4), "{log}");
    assert_eq!(written[0]["failed"], json!(0), "{log}");
    let rows = table_rows(&data.path().join(STORE_FILE));
    assert_eq!(rows.get("sessions"), Some(&4), "{rows:?}");
    assert_eq!(rows.get("snapshots"), Some(&4), "{rows:?}");
    // 150 observations each were logged; the shutdown snapshot trims what
    // it covers, leaving at most a partly covered chunk per session.
    assert!(
        rows.get("log").is_some_and(|&n| n <= 4),
        "the shutdown snapshot trims the logs: {rows:?}"
    );

    let mut server = Server::start(&launch, log_path(&logs, "second")).await;
    let log = server.log_text();
    let recovered = log_events(&log, "sessions recovered");
    assert_eq!(recovered.len(), 1, "{log}");
    assert_eq!(recovered[0]["sessions"], json!(4), "{log}");
    assert_eq!(recovered[0]["replayed"], json!(0), "nothing left to replay");
    let client = http_client();
    let base = server.base();
    let mut grpc = server.grpc_client().await;
    let mut listed = rest_list_all(&client, &base, None).await;
    listed.sort();
    let mut ids: Vec<String> = sims.iter().map(|s| s.id.clone()).collect();
    ids.sort();
    assert_eq!(listed, ids, "every session, once");
    for (sim, before) in sims.iter().zip(&before) {
        sim.check(&client, &base, "after the restart").await;
        let after = everything(&client, &base, None, &sim.id).await;
        // Nothing was pending, so the restart changed nothing at all:
        // statistics, Q, V, policy, R, Ξ and history included.
        assert_eq!(
            &after, before,
            "{}: everything, after a clean restart",
            sim.id
        );
    }

    // Driving continues; lockstep sessions go on exactly as the core agent
    // that never restarted (same RNG, Q and policy).
    for (i, sim) in sims.iter_mut().enumerate() {
        if i < 2 {
            sim.rest_ticks(&client, &base, 60).await;
        } else {
            sim.grpc_ticks(&mut grpc, 60).await;
        }
        sim.check(&client, &base, "after the restart and more ticks")
            .await;
    }
    let status = server.terminate();
    assert!(status.success(), "clean exit: {status}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_deleted_session_stays_deleted() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    let launch = Launch::new(data.path(), &["--snapshot-every", "20"]);
    let mut server = Server::start(&launch, log_path(&logs, "first")).await;
    let client = http_client();
    let base = server.base();
    let mut grpc = server.grpc_client().await;

    let mut sims = Vec::new();
    for seed in [201, 202, 203] {
        let id = rest_create(&client, &base, None, json!({"seed": seed})).await;
        let mut sim = Sim::new(id, None, params(seed, None), true);
        // Past one snapshot: each has a snapshot and a log.
        sim.rest_ticks(&client, &base, 30).await;
        sims.push(sim);
    }
    let (rest_gone, grpc_gone, kept) = (sims[0].id.clone(), sims[1].id.clone(), 2);
    let (status, _) = rest(
        &client,
        Method::DELETE,
        &format!("{base}/v1/sessions/{rest_gone}"),
        None,
        None,
    )
    .await;
    assert_eq!(status, 204);
    grpc.delete_session(grpc_request(
        pb::DeleteSessionRequest {
            session_id: grpc_gone.clone(),
        },
        None,
        None,
    ))
    .await
    .expect("delete over gRPC");

    let assert_gone = |server_base: String, ids: Vec<String>, ctx: &'static str| {
        let client = client.clone();
        async move {
            for id in ids {
                let (status, body) = rest_get(&client, &server_base, None, &id).await;
                assert_eq!(status, 404, "{ctx}: {id} must stay deleted: {body}");
                assert_eq!(body["code"], "not_found");
            }
        }
    };
    assert_gone(
        base.clone(),
        vec![rest_gone.clone(), grpc_gone.clone()],
        "at once",
    )
    .await;

    // A crash right after the deletes.
    server.kill9();
    let mut server = Server::start(&launch, log_path(&logs, "second")).await;
    let base = server.base();
    let mut grpc = server.grpc_client().await;
    assert_gone(
        base.clone(),
        vec![rest_gone.clone(), grpc_gone.clone()],
        "after kill -9",
    )
    .await;
    let status = grpc
        .get_session(grpc_request(
            pb::GetSessionRequest {
                session_id: grpc_gone.clone(),
            },
            None,
            None,
        ))
        .await
        .expect_err("deleted");
    assert_eq!(status.code(), Code::NotFound);
    assert_eq!(
        rest_list_all(&client, &base, None).await,
        vec![sims[kept].id.clone()]
    );
    sims[kept].check(&client, &base, "after kill -9").await;

    // Deleting a recovered session, and a clean restart.
    let survivor = sims.remove(kept);
    let (status, _) = rest(
        &client,
        Method::DELETE,
        &format!("{base}/v1/sessions/{}", survivor.id),
        None,
        None,
    )
    .await;
    assert_eq!(status, 204);
    let mut fresh = Sim::new(
        rest_create(&client, &base, None, json!({"seed": 204})).await,
        None,
        params(204, None),
        true,
    );
    fresh.rest_ticks(&client, &base, 25).await;
    let status = server.terminate();
    assert!(status.success());
    let rows = table_rows(&data.path().join(STORE_FILE));
    assert_eq!(
        rows.get("sessions"),
        Some(&1),
        "deleted sessions leave no record: {rows:?}"
    );
    assert_eq!(rows.get("snapshots"), Some(&1), "{rows:?}");
    assert!(
        rows.get("log").is_some_and(|&n| n <= 1),
        "deleted sessions leave no log: {rows:?}"
    );

    let mut server = Server::start(&launch, log_path(&logs, "third")).await;
    let base = server.base();
    assert_gone(
        base.clone(),
        vec![rest_gone, grpc_gone, survivor.id.clone()],
        "after a clean restart",
    )
    .await;
    assert_eq!(
        rest_list_all(&client, &base, None).await,
        vec![fresh.id.clone()]
    );
    fresh.check(&client, &base, "after a clean restart").await;
    let (status, _) = rest(
        &client,
        Method::DELETE,
        &format!("{base}/v1/sessions/{}", survivor.id),
        None,
        None,
    )
    .await;
    assert_eq!(status, 404, "deleting twice");
    assert!(server.terminate().success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn crash_recovery_keeps_the_history_exactly() {
    // Snapshots keep the history ring; the ticks logged after the last
    // snapshot must come back as they were served too, LSTDQ error
    // included, not with a made-up value.
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    let launch = Launch::new(data.path(), &["--snapshot-every", "25"]);
    let mut server = Server::start(&launch, log_path(&logs, "first")).await;
    let client = http_client();
    let base = server.base();
    let id = rest_create(&client, &base, None, json!({"seed": 801})).await;
    let mut sim = Sim::new(id.clone(), None, params(801, None), true);
    sim.rest_ticks(&client, &base, 61).await;
    let url = format!("/v1/sessions/{id}/history");
    let (status, before) = rest(&client, Method::GET, &format!("{base}{url}"), None, None).await;
    assert_eq!(status, 200);
    server.kill9();
    let mut server = Server::start(&launch, log_path(&logs, "second")).await;
    let (status, after) = rest(
        &client,
        Method::GET,
        &format!("{}{url}", server.base()),
        None,
        None,
    )
    .await;
    assert_eq!(status, 200);
    sim.check(&client, &server.base(), "after kill -9").await;
    let (before, after) = (
        before.as_array().expect("history"),
        after.as_array().expect("history"),
    );
    assert_eq!(before.len(), 60);
    assert_eq!(after.len(), before.len());
    let differ: Vec<String> = before
        .iter()
        .zip(after)
        .filter(|(b, a)| b != a)
        .map(|(b, a)| {
            format!(
                "tick {}: lstdq_error {} served, {} recovered",
                b["tick"], b["lstdq_error"], a["lstdq_error"]
            )
        })
        .collect();
    assert!(
        differ.is_empty(),
        "{} of {} history entries differ after recovery (the ticks replayed from the log), e.g. {:?}",
        differ.len(),
        before.len(),
        &differ[..differ.len().min(3)]
    );
    assert!(server.terminate().success());
}

/// Limits are for new sessions: a store holding sessions created under
/// looser limits still recovers them all.
#[test]
fn tighter_limits_at_restart_keep_the_stored_sessions() {
    use mcapi_server::service::{
        Caller, CreateSession, Limits, ManagerOptions, ServiceError, SessionConfig, SessionManager,
    };
    use mcapi_store::Store;
    use std::sync::Arc;

    let data = tempfile::tempdir().expect("data dir");
    let open = |limits: Limits| {
        let manager = SessionManager::with_options(ManagerOptions {
            store: Some(Arc::new(Store::open(data.path()).expect("store"))),
            ..ManagerOptions::new(limits, 1)
        })
        .expect("manager");
        manager.recover().expect("recovery");
        manager
    };
    let request = || CreateSession {
        model: json!({"preset": "hallway"}),
        agent: SessionConfig {
            history: Some(500),
            ..SessionConfig::default()
        },
    };
    let manager = open(Limits::default());
    let id = manager
        .create(Caller::Anyone, request())
        .expect("create")
        .id;
    manager.shutdown();
    drop(manager);
    let tight = Limits {
        max_pairs: 10,
        max_history: 100,
        ..Limits::default()
    };
    let manager = open(tight);
    let info = manager.get(Caller::Anyone, &id).expect("recovered");
    assert_eq!((info.model.pairs, info.agent.history), (148, 500));
    let err = manager
        .create(Caller::Anyone, request())
        .expect_err("a new session is held to the limits");
    assert!(matches!(err, ServiceError::LimitExceeded(_)), "{err}");
    manager.shutdown();
}
