//! `InteractBatch`: several sessions stepped as the core steps them, and a
//! message bounded by its estimated CPU time.

use mcapi_core::Observation;
use mcapi_server::api::grpc::pb;
use mcapi_server::service::Limits;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

use super::{
    FOOD, REST, SEED, START, Server, core_agent_seeded, create_hallway, hallway_move,
    hallway_stimulus, observation, session_info,
};

/// The step of one `InteractBatch` result, or the error's code.
fn outcome(result: &pb::StepResult) -> Result<&pb::Step, &str> {
    match result.outcome.as_ref().expect("a step or an error") {
        pb::step_result::Outcome::Step(step) => Ok(step),
        pb::step_result::Outcome::Error(e) => Err(&e.code),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn interact_batch_steps_several_sessions_as_the_core_does() {
    const SESSIONS: usize = 4;
    const BATCH_TICKS: usize = 400;
    let server = Server::start().await;
    let mut client = server.client().await;
    let mut ids = Vec::new();
    let mut cores = Vec::new();
    for i in 0..SESSIONS as u64 {
        let info = client
            .create_session(pb::CreateSessionRequest {
                model: Some(pb::Model::preset("hallway")),
                agent: Some(pb::SessionConfig {
                    seed: Some(SEED + i),
                    update_mode: pb::UpdateMode::Lockstep.into(),
                    ..Default::default()
                }),
                ..Default::default()
            })
            .await
            .expect("create")
            .into_inner();
        ids.push(info.id);
        cores.push(core_agent_seeded(SEED + i));
    }
    let (tx, rx) = mpsc::channel(4);
    let mut replies = client
        .interact_batch(ReceiverStream::new(rx))
        .await
        .expect("interact_batch")
        .into_inner();
    let mut states = [START; SESSIONS];
    let mut started = [false; SESSIONS];
    let mut alternations = [0usize; SESSIONS];
    let mut last_source = [None; SESSIONS];
    for t in 0..BATCH_TICKS {
        // One observation per session, the sessions in a rotating order.
        let order: Vec<usize> = (0..SESSIONS).map(|k| (k + t) % SESSIONS).collect();
        let mut observations: Vec<pb::Observation> = order
            .iter()
            .map(|&i| {
                let xi = started[i].then(|| hallway_stimulus(states[i]));
                observation(&ids[i], states[i], xi)
            })
            .collect();
        // Now and then: a refused observation of session 1 before its good
        // one (the good one is then not applied), one for a session that
        // does not exist, and an empty message.
        let refused_first = t % 50 == 7;
        if refused_first {
            let at = order.iter().position(|&i| i == 1).expect("session 1");
            observations.insert(at, observation(&ids[1], 999, None));
        }
        if t % 50 == 13 {
            observations.push(observation("s0000.01JDXXXXXXXXXXXXXXXXXXXXXX", 3, None));
        }
        let sent = observations.len();
        tx.send(pb::ObservationBatch { observations })
            .await
            .expect("send");
        let reply = replies.message().await.expect("reply").expect("open");
        assert_eq!(reply.results.len(), sent, "one result per observation");
        let mut results = reply.results.iter();
        for &i in &order {
            if refused_first && i == 1 {
                assert_eq!(
                    outcome(results.next().expect("refused")),
                    Err("unknown_state")
                );
                let skipped = results.next().expect("skipped");
                assert_eq!(outcome(skipped), Err("bad_request"), "t={t}");
                let Some(pb::step_result::Outcome::Error(e)) = &skipped.outcome else {
                    unreachable!("checked above");
                };
                assert!(e.message.contains("not applied"), "{e:?}");
                assert_eq!(e.status, Code::InvalidArgument as u32);
                continue;
            }
            let step = outcome(results.next().expect("a result")).expect("a step");
            let xi = started[i].then(|| hallway_stimulus(states[i]));
            let expected = cores[i]
                .step(&Observation {
                    state: states[i],
                    stimulus: xi.as_deref(),
                    action_taken: None,
                })
                .expect("core step");
            assert_eq!(step.tick, expected.tick, "session {i} tick at t={t}");
            assert_eq!(
                step.action_index as usize, expected.action,
                "session {i} at t={t}"
            );
            assert_eq!(
                step.drive,
                cores[i].drive().vector().to_vec(),
                "session {i} at t={t}"
            );
            assert_eq!(step.reward, expected.reward, "session {i} at t={t}");
            let source = match states[i] {
                FOOD => Some(0),
                REST => Some(1),
                _ => None,
            };
            if let Some(src) = source {
                if last_source[i].is_some_and(|l| l != src) {
                    alternations[i] += 1;
                }
                last_source[i] = Some(src);
            }
            started[i] = true;
            states[i] = hallway_move(states[i], step.action_index);
        }
        if t % 50 == 13 {
            assert_eq!(outcome(results.next().expect("unknown")), Err("not_found"));
        }
        assert!(results.next().is_none());
    }
    assert!(
        alternations.iter().all(|&a| a >= 2),
        "every session balances its drives: {alternations:?}"
    );
    // An empty message gets an empty reply.
    tx.send(pb::ObservationBatch::default())
        .await
        .expect("send");
    let reply = replies.message().await.expect("reply").expect("open");
    assert!(reply.results.is_empty());

    // More observations than `--max-batch` in one message end the stream
    // before it is decoded (10,001 empty observations: 20 KB on the wire).
    let flood = pb::ObservationBatch {
        observations: vec![pb::Observation::default(); Limits::default().max_batch + 1],
    };
    tx.send(flood).await.expect("send");
    let status = replies.message().await.expect_err("the stream ends");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(status.message().contains("more than 10000"), "{status:?}");
    drop(tx);

    // Nothing of the refused message was applied.
    for (i, id) in ids.iter().enumerate() {
        let info = session_info(&mut client, id).await;
        assert_eq!(
            info.drive,
            cores[i].drive().vector().to_vec(),
            "session {i}"
        );
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_interact_batch_message_is_bounded_by_its_estimated_cpu_time() {
    let server = Server::start_with(Limits {
        max_batch_ms: 1,
        ..Limits::default()
    })
    .await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;
    let (tx, rx) = mpsc::channel(4);
    let mut replies = client
        .interact_batch(ReceiverStream::new(rx))
        .await
        .expect("interact_batch")
        .into_inner();
    // A few observations fit in a millisecond...
    let first = vec![observation(&id, START, None)];
    tx.send(pb::ObservationBatch {
        observations: first,
    })
    .await
    .expect("send");
    let reply = replies.message().await.expect("reply").expect("open");
    assert!(outcome(&reply.results[0]).is_ok(), "{reply:?}");
    // ... ten thousand lockstep ticks do not: the message is refused whole.
    let many = vec![observation(&id, START, Some(vec![0.0, 0.0])); 10_000];
    tx.send(pb::ObservationBatch { observations: many })
        .await
        .expect("send");
    let status = replies.message().await.expect_err("the stream ends");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(status.message().contains("--max-batch-ms"), "{status:?}");
    let info = session_info(&mut client, &id).await;
    assert_eq!(info.tick, 0, "nothing of the refused message was applied");
    server.stop().await;
}
