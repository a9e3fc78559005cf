//! Sessions over gRPC: a hallway agent driven over `Interact` gets the same
//! actions and drives as the core; the unary calls; grid models come with
//! their layout.

use std::time::Instant;

use mcapi_core::Observation;
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::observation::ActionTaken;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

use super::{
    FOOD, REST, SEED, START, Server, TICKS, assert_code, core_agent, create_hallway, hallway_move,
    hallway_stimulus, observation, session_info, with_session,
};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hallway_over_interact_alternates_and_matches_the_core() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let info = create_hallway(&mut client, pb::UpdateMode::Lockstep).await;
    let id = info.id.clone();
    assert!(
        id.starts_with('s') && id.as_bytes()[5] == b'.',
        "id `{id}` is s<shard>.<ulid>"
    );
    let agent_cfg = info.agent.expect("effective config");
    assert_eq!(agent_cfg.seed, SEED);
    assert_eq!(agent_cfg.update_mode, pb::UpdateMode::Lockstep as i32);
    let model = info.model.expect("model summary");
    assert_eq!((model.states, model.actions.len()), (50, 3));
    assert_eq!(model.basis.expect("basis").kind, "indicator");

    let (tx, rx) = mpsc::channel(4);
    let mut steps = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    let mut core = core_agent();

    let started = Instant::now();
    let mut s = START;
    let mut last_source = None;
    let mut alternations = 0;
    let mut visits = [0usize; 2];
    let mut last_state = s;
    for t in 0..=TICKS {
        let xi = (t > 0).then(|| hallway_stimulus(s));
        tx.send(observation(&id, s, xi.clone()))
            .await
            .expect("send observation");
        let step = steps.message().await.expect("step").expect("stream open");

        let expected = core
            .step(&Observation {
                state: s,
                stimulus: xi.as_deref(),
                action_taken: None,
            })
            .expect("core step");
        assert_eq!(step.tick, expected.tick, "tick at t={t}");
        assert_eq!(
            step.action_index as usize, expected.action,
            "action at t={t}"
        );
        assert_eq!(step.drive, core.drive().vector().to_vec(), "drive at t={t}");
        assert_eq!(step.reward, expected.reward, "reward at t={t}");
        assert_eq!(
            step.policy_version,
            core.policy_version(),
            "policy version at t={t}"
        );
        assert_eq!(
            step.action,
            ["left", "right", "stay"][step.action_index as usize]
        );

        let source = match s {
            FOOD => Some(0),
            REST => Some(1),
            _ => None,
        };
        if let Some(src) = source {
            visits[src] += 1;
            if last_source.is_some_and(|l| l != src) {
                alternations += 1;
            }
            last_source = Some(src);
        }
        last_state = s;
        s = hallway_move(s, step.action_index);
    }
    drop(tx);
    assert!(
        steps.message().await.expect("clean end").is_none(),
        "stream ends after the client's"
    );
    let elapsed = started.elapsed();
    eprintln!(
        "{TICKS} lockstep ticks over Interact in {elapsed:?} ({:.0} µs/tick); \
         {alternations} alternations, visits {visits:?}",
        elapsed.as_micros() as f64 / TICKS as f64
    );
    assert!(
        alternations >= 10,
        "only {alternations} alternations (visits {visits:?})"
    );

    let info = session_info(&mut client, &id).await;
    assert_eq!(info.tick, TICKS as u64);
    assert_eq!(info.state, Some(last_state as u64));
    assert_eq!(info.drive, core.drive().vector().to_vec());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unary_calls_list_observe_values_delete() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let a = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;
    let b = create_hallway(&mut client, pb::UpdateMode::Async).await.id;

    let page = client
        .list_sessions(pb::ListSessionsRequest {
            after: None,
            limit: Some(1),
        })
        .await
        .expect("list")
        .into_inner();
    assert_eq!(page.sessions.len(), 1);
    let first = page.sessions[0].id.clone();
    assert_eq!(page.next.as_deref(), Some(first.as_str()));
    let rest = client
        .list_sessions(pb::ListSessionsRequest {
            after: page.next,
            limit: None,
        })
        .await
        .expect("list")
        .into_inner();
    assert_eq!(rest.sessions.len(), 1);
    assert_eq!(rest.next, None);
    let mut ids = vec![first, rest.sessions[0].id.clone()];
    ids.sort();
    let mut want = vec![a.clone(), b.clone()];
    want.sort();
    assert_eq!(ids, want);

    // A batch: one step per observation, in order, ids filled from the request.
    let mut batch = vec![observation("", START, None)];
    batch.extend((1..=5).map(|_| pb::Observation {
        action_taken: Some(ActionTaken::ActionName("stay".into())),
        ..observation("", START, Some(vec![0.0, 0.0]))
    }));
    let steps = client
        .observe(pb::ObserveRequest {
            session_id: a.clone(),
            observations: batch,
        })
        .await
        .expect("observe")
        .into_inner()
        .steps;
    assert_eq!(
        steps.iter().map(|s| s.tick).collect::<Vec<_>>(),
        vec![0, 1, 2, 3, 4, 5]
    );

    let values = client
        .get_values(with_session(
            &a,
            pb::GetValuesRequest {
                session_id: a.clone(),
                include: vec!["q".into(), "xi".into(), "policy".into()],
            },
        ))
        .await
        .expect("values")
        .into_inner();
    assert_eq!(values.tick, 5);
    assert!(values.v.is_none() && values.r.is_none());
    // 50 states x 3 actions, less left in 0 and right in 49.
    assert_eq!(values.q.expect("q").pairs.len(), 148);
    let xi = values.xi.expect("xi");
    assert_eq!(xi.pairs.len(), 148);
    assert!(xi.pairs.iter().all(|p| p.values.len() == 2));
    assert_eq!(values.policy.expect("policy").actions.len(), 50);
    let defaults = client
        .get_values(pb::GetValuesRequest {
            session_id: a.clone(),
            include: vec![],
        })
        .await
        .expect("values")
        .into_inner();
    assert_eq!(defaults.v.expect("v by default").values.len(), 50);
    assert!(defaults.policy.is_some() && defaults.q.is_none());

    client
        .delete_session(with_session(
            &a,
            pb::DeleteSessionRequest {
                session_id: a.clone(),
            },
        ))
        .await
        .expect("delete");
    assert_code(
        client
            .get_session(pb::GetSessionRequest {
                session_id: a.clone(),
            })
            .await,
        Code::NotFound,
        &a,
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grid_models_come_with_their_layout() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let create = |model: &str| pb::CreateSessionRequest {
        model_json: model.into(),
        model: None,
        agent: None,
    };
    let grid = client
        .create_session(create(
            &serde_json::json!({
                "grid": ["#####", "#a.b#", "#.#.#", "#####"],
                "sources": {"a": 0, "b": 1},
            })
            .to_string(),
        ))
        .await
        .expect("grid session")
        .into_inner();
    let layout = grid
        .model
        .and_then(|m| m.layout)
        .expect("a grid model has a layout");
    assert_eq!((layout.rows, layout.cols), (4, 5));
    let cells: Vec<(u64, u64)> = layout.cells.iter().map(|c| (c.row, c.col)).collect();
    assert_eq!(cells, vec![(1, 1), (1, 2), (1, 3), (2, 1), (2, 3)]);
    let marks: Vec<(&str, u64)> = layout
        .marks
        .iter()
        .map(|m| (m.mark.as_str(), m.state))
        .collect();
    assert_eq!(marks, vec![("a", 0), ("b", 2)]);
    let hallway = client
        .create_session(create(r#"{"preset": "hallway"}"#))
        .await
        .expect("hallway session")
        .into_inner();
    assert!(hallway.model.expect("model").layout.is_none());
}
