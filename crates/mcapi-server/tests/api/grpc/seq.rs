//! Sequence numbers over gRPC (docs/sessions.md, "Delivery guarantees"):
//! `Observe`, `Interact` and `InteractBatch` replay an applied seq with the
//! recorded step and `replayed` set; a gap, an expired seq and a conflict
//! are `FAILED_PRECONDITION` with their stable codes, the seq to resume
//! from in a trailer; `GetSession` says the next seq.

use mcapi_server::api::grpc::pb;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

use super::{
    START, Server, create_hallway, hallway_move, hallway_stimulus, observation, session_info,
    with_session,
};

fn with_seq(mut obs: pb::Observation, seq: u64) -> pb::Observation {
    obs.seq = Some(seq);
    obs
}

async fn observe(
    client: &mut pb::agents_client::AgentsClient<tonic::transport::Channel>,
    id: &str,
    observations: Vec<pb::Observation>,
) -> Result<Vec<pb::Step>, tonic::Status> {
    client
        .observe(with_session(
            id,
            pb::ObserveRequest {
                session_id: id.into(),
                observations,
            },
        ))
        .await
        .map(|r| r.into_inner().steps)
}

fn code_of(status: &tonic::Status) -> (Code, String) {
    let stable = status
        .metadata()
        .get("x-mcapi-error-code")
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default()
        .to_string();
    (status.code(), stable)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn observe_interact_and_interact_batch_replay_applied_seqs() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;
    assert_eq!(session_info(&mut client, &id).await.next_seq, 0);

    // Observe: seqs 0..5 applied, each replayed once right after.
    let mut state = START;
    let mut sent = Vec::new();
    for seq in 0..6u64 {
        let stimulus = (seq > 0).then(|| hallway_stimulus(state));
        let obs = with_seq(observation(&id, state, stimulus), seq);
        let step = observe(&mut client, &id, vec![obs.clone()])
            .await
            .expect("observe")
            .remove(0);
        assert!(!step.replayed);
        assert_eq!(step.tick, seq);
        let again = observe(&mut client, &id, vec![obs.clone()])
            .await
            .expect("replay")
            .remove(0);
        assert_eq!(
            again,
            pb::Step {
                replayed: true,
                ..step.clone()
            },
            "seq {seq}"
        );
        state = hallway_move(state, step.action_index);
        sent.push((obs, step));
    }
    let info = session_info(&mut client, &id).await;
    assert_eq!((info.tick, info.next_seq), (5, 6));

    // Errors: FAILED_PRECONDITION, the stable code and the seq trailer.
    let gap = observe(
        &mut client,
        &id,
        vec![with_seq(
            observation(&id, state, Some(hallway_stimulus(state))),
            8,
        )],
    )
    .await
    .expect_err("a gap");
    assert_eq!(
        code_of(&gap),
        (Code::FailedPrecondition, "seq_gap".into()),
        "{gap:?}"
    );
    assert_eq!(
        gap.metadata()
            .get("x-mcapi-expected-seq")
            .and_then(|v| v.to_str().ok()),
        Some("6")
    );
    let mut other = sent[5].0.clone();
    other.state = other.state.saturating_sub(1);
    let conflict = observe(&mut client, &id, vec![other])
        .await
        .expect_err("a conflict");
    assert_eq!(
        code_of(&conflict),
        (Code::FailedPrecondition, "seq_conflict".into())
    );
    let bad = observe(
        &mut client,
        &id,
        vec![sent[4].0.clone(), with_seq(sent[5].0.clone(), 7)],
    )
    .await
    .expect_err("not consecutive");
    assert_eq!(
        code_of(&bad),
        (Code::InvalidArgument, "bad_request".into()),
        "{bad:?}"
    );

    // Interact: a replay, then the next seq applied.
    let (tx, rx) = mpsc::channel(4);
    let mut stream = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    tx.send(sent[3].0.clone()).await.expect("send");
    let step = stream.message().await.expect("reply").expect("a step");
    assert_eq!(
        step,
        pb::Step {
            replayed: true,
            ..sent[3].1.clone()
        }
    );
    let next = with_seq(observation(&id, state, Some(hallway_stimulus(state))), 6);
    tx.send(next.clone()).await.expect("send");
    let step = stream.message().await.expect("reply").expect("a step");
    assert_eq!((step.tick, step.replayed), (6, false));
    drop(tx);
    while stream.message().await.expect("clean end").is_some() {}

    // InteractBatch: the replay and an error per entry.
    let (tx, rx) = mpsc::channel(2);
    let mut stream = client
        .interact_batch(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact_batch")
        .into_inner();
    tx.send(pb::ObservationBatch {
        observations: vec![next.clone()],
    })
    .await
    .expect("send");
    let reply = stream.message().await.expect("reply").expect("a batch");
    match reply.results[0].outcome.as_ref().expect("outcome") {
        pb::step_result::Outcome::Step(s) => {
            assert_eq!(
                s,
                &pb::Step {
                    replayed: true,
                    ..step.clone()
                }
            );
        }
        pb::step_result::Outcome::Error(e) => panic!("replay refused: {e:?}"),
    }
    tx.send(pb::ObservationBatch {
        observations: vec![with_seq(next.clone(), 9)],
    })
    .await
    .expect("send");
    let reply = stream.message().await.expect("reply").expect("a batch");
    match reply.results[0].outcome.as_ref().expect("outcome") {
        pb::step_result::Outcome::Error(e) => {
            assert_eq!(
                (e.code.as_str(), e.status),
                ("seq_gap", Code::FailedPrecondition as u32)
            );
        }
        pb::step_result::Outcome::Step(s) => panic!("a gap applied: {s:?}"),
    }
    drop(tx);
    while stream.message().await.expect("clean end").is_some() {}
    assert_eq!(session_info(&mut client, &id).await.next_seq, 7);
    server.stop().await;
}
