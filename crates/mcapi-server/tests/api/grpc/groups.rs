//! Session groups over gRPC (docs/groups.md): `CreateGroup`, `GetGroup`,
//! `DeleteGroup` and `StepGroup` with several messages in flight; each
//! member's trajectory bit-equal to a session with the member's derived
//! seed driven alone through `Interact`; every malformed column, mask and
//! `seq` answered with its own code; a member's refusal does not stop the
//! others; a step resent with its members' `seqs` replayed bit for bit, a
//! member's refused seq refusing that member only.

use std::collections::VecDeque;

use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_server::service::Limits;
use mcapi_server::service::groups::member_seed;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Code, Status, Streaming};

use super::{SEED, START, Server, assert_code, hallway_move, hallway_stimulus, with_session};

fn le(xs: &[f64]) -> Vec<u8> {
    xs.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn f64s(bytes: &[u8]) -> Vec<f64> {
    assert_eq!(bytes.len() % 8, 0, "whole numbers");
    bytes
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
        .collect()
}

async fn create_group(
    client: &mut AgentsClient<Channel>,
    n: u32,
    mode: pb::UpdateMode,
) -> pb::GroupInfo {
    client
        .create_group(pb::CreateGroupRequest {
            model: Some(pb::Model::preset("hallway")),
            agent: Some(pb::SessionConfig {
                update_mode: mode.into(),
                ..Default::default()
            }),
            n,
            seed: Some(SEED),
        })
        .await
        .expect("create group")
        .into_inner()
}

/// A `StepGroup` stream: its sender and its replies.
async fn open(
    client: &mut AgentsClient<Channel>,
) -> (
    mpsc::Sender<pb::GroupStepRequest>,
    Streaming<pb::GroupStepReply>,
) {
    let (tx, rx) = mpsc::channel(8);
    let replies = client
        .step_group(ReceiverStream::new(rx))
        .await
        .expect("step_group")
        .into_inner();
    (tx, replies)
}

/// A message in flight: its mask's number, the mask and the stimuli sent.
type InFlight = (usize, Vec<u32>, Vec<Option<Vec<f64>>>);

/// A malformed-step case: its name, the good messages before it, the
/// message, and the code, stable code and words it is refused with.
type Case<'a> = (
    &'a str,
    Vec<pb::GroupStepRequest>,
    pb::GroupStepRequest,
    Code,
    &'a str,
    &'a str,
);

/// What one member was sent and answered at one tick.
#[derive(Debug, Clone, PartialEq)]
struct Tick {
    state: usize,
    stimulus: Option<Vec<f64>>,
    action: u32,
    drive: Vec<u64>,
    reward: u64,
    policy_version: u64,
    tick: u64,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn members_step_as_sessions_driven_alone_with_three_messages_in_flight() {
    const N: usize = 6;
    const TICKS: usize = 300;
    let server = Server::start().await;
    let mut client = server.client().await;
    let group = create_group(&mut client, N as u32, pb::UpdateMode::Lockstep).await;
    assert_eq!(group.size, N as u32);
    assert_eq!(group.seed, SEED);
    assert_eq!(group.stimuli, 2);
    assert_eq!(group.member_ids.len(), N);
    let shard = &group.group_id[..6];
    for (i, id) in group.member_ids.iter().enumerate() {
        assert_eq!(&id[..6], shard, "every member is on the group's shard");
        let info = super::session_info(&mut client, id).await;
        assert_eq!(
            info.agent.expect("config").seed,
            member_seed(SEED, i as u64)
        );
    }
    // Three masks, each stepped on its own as soon as its last reply came:
    // three messages in flight.
    let masks: [Vec<u32>; 3] = [vec![0, 2, 4], vec![1], vec![3, 5]];
    let (tx, mut replies) = open(&mut client).await;
    let mut states = [START; N];
    let mut last: [Option<usize>; N] = [None; N];
    let mut trajectories: Vec<Vec<Tick>> = vec![Vec::new(); N];
    let mut seq = 40u64;
    let mut in_flight: VecDeque<InFlight> = VecDeque::new();
    let send = |mask: &[u32], states: &[usize; N], last: &[Option<usize>; N], seq: u64| {
        let stimuli: Vec<Option<Vec<f64>>> = mask
            .iter()
            .map(|&i| last[i as usize].map(|_| hallway_stimulus(states[i as usize])))
            .collect();
        let flat: Vec<f64> = stimuli.iter().flatten().flatten().copied().collect();
        let message = pb::GroupStepRequest {
            group_id: if seq == 40 {
                group.group_id.clone()
            } else {
                String::new()
            },
            seq,
            states: mask.iter().map(|&i| states[i as usize] as u32).collect(),
            stimuli: le(&flat),
            mask: mask.to_vec(),
            ..Default::default()
        };
        (message, stimuli)
    };
    for (k, mask) in masks.iter().enumerate() {
        let (message, stimuli) = send(mask, &states, &last, seq);
        tx.send(message).await.expect("send");
        in_flight.push_back((k, mask.clone(), stimuli));
        seq += 1;
    }
    let mut steps_left = [TICKS; 3];
    let mut max_in_flight = 0;
    while let Some((k, mask, stimuli)) = in_flight.pop_front() {
        max_in_flight = max_in_flight.max(in_flight.len() + 1);
        let reply = replies.message().await.expect("reply").expect("a reply");
        assert!(reply.statuses.is_empty(), "{:?}", reply.statuses);
        assert_eq!(reply.seq, seq - 1 - in_flight.len() as u64, "in order");
        let drives = f64s(&reply.drives);
        let rewards = f64s(&reply.rewards);
        for (j, &i) in mask.iter().enumerate() {
            let i = i as usize;
            trajectories[i].push(Tick {
                state: states[i],
                stimulus: stimuli[j].clone(),
                action: reply.actions[j],
                drive: drives[2 * j..2 * j + 2]
                    .iter()
                    .map(|x| x.to_bits())
                    .collect(),
                reward: rewards[j].to_bits(),
                policy_version: reply.policy_versions[j],
                tick: reply.ticks[j],
            });
            last[i] = Some(states[i]);
            states[i] = hallway_move(states[i], reply.actions[j]);
        }
        steps_left[k] -= 1;
        if steps_left[k] > 0 {
            let (message, stimuli) = send(&mask, &states, &last, seq);
            tx.send(message).await.expect("send");
            in_flight.push_back((k, mask, stimuli));
            seq += 1;
        }
    }
    assert_eq!(max_in_flight, 3);
    drop(tx);
    assert!(replies.message().await.expect("ends cleanly").is_none());

    // Each member again, as a session of its own driven through Interact.
    for (i, want) in trajectories.iter().enumerate() {
        let alone = client
            .create_session(pb::CreateSessionRequest {
                model: Some(pb::Model::preset("hallway")),
                agent: Some(pb::SessionConfig {
                    seed: Some(member_seed(SEED, i as u64)),
                    update_mode: pb::UpdateMode::Lockstep.into(),
                    ..Default::default()
                }),
                ..Default::default()
            })
            .await
            .expect("create")
            .into_inner();
        let (otx, orx) = mpsc::channel(4);
        let mut steps = client
            .interact(with_session(&alone.id, ReceiverStream::new(orx)))
            .await
            .expect("interact")
            .into_inner();
        for (t, tick) in want.iter().enumerate() {
            otx.send(super::observation(
                &alone.id,
                tick.state,
                tick.stimulus.clone(),
            ))
            .await
            .expect("send");
            let step = steps.message().await.expect("step").expect("a step");
            let got = Tick {
                state: tick.state,
                stimulus: tick.stimulus.clone(),
                action: step.action_index,
                drive: step.drive.iter().map(|x| x.to_bits()).collect(),
                reward: step.reward.to_bits(),
                policy_version: step.policy_version,
                tick: step.tick,
            };
            assert_eq!(&got, tick, "member {i}, tick {t}");
        }
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_group_is_read_its_members_are_sessions_and_deleting_it_deletes_them() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let group = create_group(&mut client, 3, pb::UpdateMode::Async).await;
    let got = client
        .get_group(with_session(
            &group.group_id,
            pb::GetGroupRequest {
                group_id: group.group_id.clone(),
            },
        ))
        .await
        .expect("get group")
        .into_inner();
    assert_eq!(got, group);
    assert_eq!(got.update_mode, i32::from(pb::UpdateMode::Async));
    // Async members step too, without a mask (every member).
    let (tx, mut replies) = open(&mut client).await;
    let mut states = vec![START as u32; 3];
    for t in 0..20u64 {
        tx.send(pb::GroupStepRequest {
            group_id: group.group_id.clone(),
            seq: t,
            states: states.clone(),
            stimuli: if t == 0 { Vec::new() } else { le(&[0.0; 6]) },
            ..Default::default()
        })
        .await
        .expect("send");
        let reply = replies.message().await.expect("reply").expect("a reply");
        assert_eq!(reply.seq, t);
        assert!(reply.statuses.is_empty(), "{:?}", reply.statuses);
        assert_eq!(reply.ticks, vec![t; 3]);
        for (s, a) in states.iter_mut().zip(&reply.actions) {
            *s = hallway_move(*s as usize, *a) as u32;
        }
    }
    drop(tx);
    // Each member is an ordinary session.
    let member = super::session_info(&mut client, &group.member_ids[1]).await;
    assert_eq!(member.tick, 19);
    let history = client
        .get_history(with_session(
            &group.member_ids[1],
            pb::GetHistoryRequest {
                session_id: group.member_ids[1].clone(),
                limit: Some(5),
            },
        ))
        .await
        .expect("history")
        .into_inner();
    assert_eq!(history.entries.len(), 5);
    // One member deleted alone: the group steps the others, and reports it.
    client
        .delete_session(with_session(
            &group.member_ids[2],
            pb::DeleteSessionRequest {
                session_id: group.member_ids[2].clone(),
            },
        ))
        .await
        .expect("delete one member");
    let (tx, mut replies) = open(&mut client).await;
    tx.send(pb::GroupStepRequest {
        group_id: group.group_id.clone(),
        seq: 0,
        states: vec![1, 2, 3],
        stimuli: le(&[0.0; 6]),
        ..Default::default()
    })
    .await
    .expect("send");
    let reply = replies.message().await.expect("reply").expect("a reply");
    assert_eq!(reply.statuses.len(), 1, "{:?}", reply.statuses);
    assert_eq!(reply.statuses[0].index, 2);
    assert_eq!(reply.statuses[0].code, "not_found");
    assert_eq!(reply.actions[2], u32::MAX);
    assert_eq!(
        f64s(&reply.rewards)[2],
        0.0,
        "a refused member's placeholder is 0, never NaN"
    );
    assert_eq!(reply.ticks[..2], [20, 20]);
    drop(tx);
    client
        .delete_group(pb::DeleteGroupRequest {
            group_id: group.group_id.clone(),
        })
        .await
        .expect("delete group");
    for id in &group.member_ids {
        assert_code(
            client
                .get_session(pb::GetSessionRequest {
                    session_id: id.clone(),
                })
                .await,
            Code::NotFound,
            "not found",
        );
    }
    assert_code(
        client
            .get_group(pb::GetGroupRequest {
                group_id: group.group_id.clone(),
            })
            .await,
        Code::NotFound,
        "group",
    );
    server.stop().await;
}

/// The status a one-message stream ends with (after `before` good ones).
async fn refused(
    client: &mut AgentsClient<Channel>,
    before: Vec<pb::GroupStepRequest>,
    bad: pb::GroupStepRequest,
) -> Status {
    let (tx, mut replies) = open(client).await;
    for message in before {
        tx.send(message).await.expect("send");
        replies
            .message()
            .await
            .expect("a good reply")
            .expect("reply");
    }
    tx.send(bad).await.expect("send");
    let status = replies.message().await.expect_err("refused");
    drop(tx);
    status
}

fn stable(status: &Status) -> &str {
    status
        .metadata()
        .get("x-mcapi-error-code")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_malformed_step_gets_its_own_code_and_a_refused_member_stops_no_other() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let group = create_group(&mut client, 4, pb::UpdateMode::Lockstep).await;
    let id = group.group_id.clone();
    let first = |seq: u64| pb::GroupStepRequest {
        group_id: id.clone(),
        seq,
        states: vec![START as u32; 4],
        ..Default::default()
    };
    let later = |seq: u64| pb::GroupStepRequest {
        group_id: String::new(),
        seq,
        states: vec![START as u32; 4],
        stimuli: le(&[0.0; 8]),
        ..Default::default()
    };
    let cases: Vec<Case> = vec![
        (
            "seq backwards",
            vec![first(5)],
            later(4),
            Code::InvalidArgument,
            "sequence_out_of_order",
            "does not increase",
        ),
        (
            "seq repeated",
            vec![first(5)],
            later(5),
            Code::InvalidArgument,
            "sequence_out_of_order",
            "does not increase",
        ),
        (
            "seq skips",
            vec![first(5)],
            later(7),
            Code::InvalidArgument,
            "sequence_out_of_order",
            "skips ahead",
        ),
        (
            "a seqs column of the wrong length",
            vec![],
            pb::GroupStepRequest {
                seqs: vec![0; 3],
                ..first(0)
            },
            Code::InvalidArgument,
            "column_length",
            "`seqs` has 3 entries; 4 expected (one per member stepped: 4)",
        ),
        (
            "too few states",
            vec![],
            pb::GroupStepRequest {
                states: vec![1, 2, 3],
                ..first(0)
            },
            Code::InvalidArgument,
            "column_length",
            "`states` has 3 entries; 4 expected",
        ),
        (
            "stimuli not whole numbers",
            vec![first(0)],
            pb::GroupStepRequest {
                stimuli: vec![0; 13],
                ..later(1)
            },
            Code::InvalidArgument,
            "column_length",
            "13 bytes",
        ),
        (
            "stimuli of another width",
            vec![first(0)],
            pb::GroupStepRequest {
                stimuli: le(&[0.0; 12]),
                ..later(1)
            },
            Code::InvalidArgument,
            "column_length",
            "`stimuli` has 12 entries; 8 expected",
        ),
        (
            "action_taken too short",
            vec![first(0)],
            pb::GroupStepRequest {
                action_taken: vec![0],
                ..later(1)
            },
            Code::InvalidArgument,
            "column_length",
            "`action_taken`",
        ),
        (
            "observations for numbered states",
            vec![],
            pb::GroupStepRequest {
                observations: le(&[0.5; 4]),
                ..first(0)
            },
            Code::InvalidArgument,
            "column_length",
            "`observations`",
        ),
        (
            "mask repeats",
            vec![],
            pb::GroupStepRequest {
                mask: vec![0, 1, 1],
                states: vec![1, 1, 1],
                ..first(0)
            },
            Code::InvalidArgument,
            "invalid_mask",
            "repeats",
        ),
        (
            "mask decreases",
            vec![],
            pb::GroupStepRequest {
                mask: vec![2, 1],
                states: vec![1, 1],
                ..first(0)
            },
            Code::InvalidArgument,
            "invalid_mask",
            "below",
        ),
        (
            "a state beyond the model",
            vec![first(0)],
            pb::GroupStepRequest {
                states: vec![24, 50, 26, 25],
                ..later(1)
            },
            Code::InvalidArgument,
            "unknown_state",
            "state 50 is out of range (the model has 50 states)",
        ),
        (
            "a NaN stimulus",
            vec![first(0)],
            pb::GroupStepRequest {
                stimuli: le(&[0.0, 0.0, 0.0, 0.0, f64::NAN, 0.0, 0.0, 1.0]),
                ..later(1)
            },
            Code::InvalidArgument,
            "non_finite_number",
            "non-finite",
        ),
        (
            "an infinite stimulus",
            vec![first(0)],
            pb::GroupStepRequest {
                stimuli: le(&[0.0, f64::NEG_INFINITY, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
                ..later(1)
            },
            Code::InvalidArgument,
            "non_finite_number",
            "non-finite",
        ),
        (
            "a stimulus beyond 1e12",
            vec![first(0)],
            pb::GroupStepRequest {
                stimuli: le(&[0.0, 0.0, 0.0, 0.0, 0.0, 2e12, 0.0, 1.0]),
                ..later(1)
            },
            Code::InvalidArgument,
            "stimulus_too_large",
            "exceeds the limit",
        ),
        (
            "mask beyond the group",
            vec![],
            pb::GroupStepRequest {
                mask: vec![4],
                states: vec![1],
                ..first(0)
            },
            Code::InvalidArgument,
            "invalid_mask",
            "0..4",
        ),
        (
            "mask longer than the group",
            vec![],
            pb::GroupStepRequest {
                mask: (0..100_000).collect(),
                states: vec![1; 100_000],
                ..first(0)
            },
            Code::InvalidArgument,
            "invalid_mask",
            "0..4",
        ),
        (
            "no group",
            vec![],
            pb::GroupStepRequest {
                group_id: String::new(),
                ..first(0)
            },
            Code::InvalidArgument,
            "bad_request",
            "group_id",
        ),
        (
            "another group later",
            vec![first(0)],
            pb::GroupStepRequest {
                group_id: "s0000.gX".into(),
                ..later(1)
            },
            Code::InvalidArgument,
            "bad_request",
            "differs",
        ),
        (
            "unknown group",
            vec![],
            pb::GroupStepRequest {
                group_id: "s0000.g01ARZ3NDEKTSV4RRFFQ69G5FAV".into(),
                ..first(0)
            },
            Code::NotFound,
            "not_found",
            "group",
        ),
    ];
    for (name, before, bad, code, stable_code, needle) in cases {
        let status = refused(&mut client, before, bad).await;
        assert_eq!(status.code(), code, "{name}: {status:?}");
        assert_eq!(stable(&status), stable_code, "{name}: {status:?}");
        assert!(
            status.message().contains(needle),
            "{name}: {}",
            status.message()
        );
    }
    // A message beyond the server's message size: refused before decoding.
    let status = refused(
        &mut client,
        vec![],
        pb::GroupStepRequest {
            stimuli: vec![0; (16 << 20) + 8],
            ..first(0)
        },
    )
    .await;
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert_eq!(stable(&status), "limit_exceeded");
    assert!(
        status
            .message()
            .contains("a StepGroup message has 16777270 bytes; the limit is 16777216"),
        "{}",
        status.message()
    );

    // What only a member refuses: that member only, with Interact's code
    // (members 1 and 3 cannot have taken actions 7 and 3 of three).
    let members = {
        let (tx, mut replies) = open(&mut client).await;
        tx.send(pb::GroupStepRequest {
            states: vec![START as u32; 4],
            ..first(0)
        })
        .await
        .expect("send");
        replies.message().await.expect("reply").expect("a reply");
        tx.send(pb::GroupStepRequest {
            states: vec![24, 24, 26, 25],
            stimuli: le(&[0.0; 8]),
            action_taken: vec![u32::MAX, 7, u32::MAX, 3],
            ..later(1)
        })
        .await
        .expect("send");
        let reply = replies.message().await.expect("reply").expect("a reply");
        drop(tx);
        reply
    };
    let codes: Vec<(u32, &str)> = members
        .statuses
        .iter()
        .map(|s| (s.index, s.code.as_str()))
        .collect();
    assert_eq!(
        codes,
        [(1, "unknown_action"), (3, "unknown_action")],
        "{:?}",
        members.statuses
    );
    assert!(
        members
            .statuses
            .iter()
            .all(|s| s.status == Code::InvalidArgument as u32)
    );
    assert_eq!(
        members.ticks,
        [1, 0, 1, 0],
        "members 0 and 2 applied, the others not"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_group_that_does_not_fit_is_refused_whole_before_anything_exists() {
    let server = Server::start_with(Limits {
        max_sessions: 10,
        ..Limits::default()
    })
    .await;
    let mut client = server.client().await;
    let create = |n: u32, agent: pb::SessionConfig| pb::CreateGroupRequest {
        model: Some(pb::Model::preset("hallway")),
        agent: Some(agent),
        n,
        seed: Some(1),
    };
    let cases = [
        (
            0,
            pb::SessionConfig::default(),
            Code::InvalidArgument,
            "bad_request",
            "`n`",
        ),
        // Absurd: refused before any member is built.
        (
            u32::MAX,
            pb::SessionConfig::default(),
            Code::ResourceExhausted,
            "limit_exceeded",
            "the limit is 10000",
        ),
        (
            10_001,
            pb::SessionConfig::default(),
            Code::ResourceExhausted,
            "limit_exceeded",
            "the limit is 10000",
        ),
        (
            11,
            pb::SessionConfig::default(),
            Code::ResourceExhausted,
            "too_many_sessions",
            "10 sessions",
        ),
        (
            2,
            pb::SessionConfig {
                seed: Some(3),
                ..Default::default()
            },
            Code::InvalidArgument,
            "bad_request",
            "agent.seed",
        ),
    ];
    for (n, agent, code, stable_code, needle) in cases {
        let status = client
            .create_group(create(n, agent))
            .await
            .expect_err("refused");
        assert_eq!(status.code(), code, "n = {n}: {status:?}");
        assert_eq!(stable(&status), stable_code, "n = {n}");
        assert!(
            status.message().contains(needle),
            "n = {n}: {}",
            status.message()
        );
    }
    let page = client
        .list_sessions(pb::ListSessionsRequest::default())
        .await
        .expect("list")
        .into_inner();
    assert!(page.sessions.is_empty(), "nothing was created");
    // Ten fit; one more group of one does not.
    let group = client
        .create_group(create(10, pb::SessionConfig::default()))
        .await
        .expect("ten fit")
        .into_inner();
    assert_eq!(group.member_ids.len(), 10);
    assert_code(
        client
            .create_group(create(1, pb::SessionConfig::default()))
            .await,
        Code::ResourceExhausted,
        "10 sessions",
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn more_messages_in_flight_than_the_server_reads_ahead_wait_and_are_answered_in_order() {
    const MESSAGES: u64 = 40;
    let server = Server::start().await;
    let mut client = server.client().await;
    let group = create_group(&mut client, 2, pb::UpdateMode::Lockstep).await;
    let (tx, rx) = mpsc::channel(MESSAGES as usize);
    // Every message sent before any reply is read: the server reads 8
    // ahead, the rest wait in the transport.
    for seq in 0..MESSAGES {
        tx.send(pb::GroupStepRequest {
            group_id: group.group_id.clone(),
            seq: 1000 + seq,
            states: vec![START as u32; 2],
            stimuli: if seq == 0 { Vec::new() } else { le(&[0.0; 4]) },
            // Each member stays where it is, whatever it was advised.
            action_taken: if seq == 0 { Vec::new() } else { vec![2, 2] },
            ..Default::default()
        })
        .await
        .expect("send");
    }
    drop(tx);
    let mut replies = client
        .step_group(ReceiverStream::new(rx))
        .await
        .expect("step_group")
        .into_inner();
    for seq in 0..MESSAGES {
        let reply = replies.message().await.expect("reply").expect("a reply");
        assert_eq!(reply.seq, 1000 + seq);
        assert!(reply.statuses.is_empty(), "{:?}", reply.statuses);
        assert_eq!(reply.ticks, [seq, seq]);
    }
    assert!(replies.message().await.expect("ends cleanly").is_none());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_step_resent_with_its_seqs_is_replayed_and_a_refused_seq_refuses_its_member_only() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let group = create_group(&mut client, 3, pb::UpdateMode::Lockstep).await;
    let (tx, mut replies) = open(&mut client).await;
    let step = |seq: u64, states: Vec<u32>, seqs: Vec<u64>| pb::GroupStepRequest {
        group_id: if seq == 0 {
            group.group_id.clone()
        } else {
            String::new()
        },
        seq,
        stimuli: if seq == 0 {
            Vec::new()
        } else {
            le(&vec![0.0; 2 * states.len()])
        },
        states,
        seqs,
        ..Default::default()
    };
    tx.send(step(0, vec![START as u32; 3], vec![0, 0, 0]))
        .await
        .expect("send");
    let first = replies.message().await.expect("reply").expect("a reply");
    assert_eq!(first.replayed, [false; 3]);
    assert_eq!(first.ticks, [0, 0, 0]);
    // The same observations resent with the same seqs (a stream reopened
    // after a lost reply would do this): replayed, bit for bit.
    tx.send(step(1, vec![24, 26, 25], vec![1, 1, 1]))
        .await
        .expect("send");
    let applied = replies.message().await.expect("reply").expect("a reply");
    tx.send(step(2, vec![24, 26, 25], vec![1, 1, 1]))
        .await
        .expect("send");
    let again = replies.message().await.expect("reply").expect("a reply");
    assert_eq!(applied.replayed, [false; 3]);
    assert_eq!(again.replayed, [true; 3]);
    assert!(again.statuses.is_empty(), "{:?}", again.statuses);
    assert_eq!(again.ticks, [1, 1, 1], "nothing applied again");
    assert_eq!(
        (
            &again.actions,
            &again.drives,
            &again.rewards,
            &again.policy_versions
        ),
        (
            &applied.actions,
            &applied.drives,
            &applied.rewards,
            &applied.policy_versions
        ),
        "the recorded steps, bit for bit"
    );
    // A conflict (member 0), an applied step (member 1), a gap (member 2).
    tx.send(step(3, vec![23, 27, 25], vec![1, 2, 7]))
        .await
        .expect("send");
    let mixed = replies.message().await.expect("reply").expect("a reply");
    let codes: Vec<(u32, u32, &str, Option<u64>)> = mixed
        .statuses
        .iter()
        .map(|s| (s.index, s.status, s.code.as_str(), s.expected_seq))
        .collect();
    assert_eq!(
        codes,
        [
            (0, Code::FailedPrecondition as u32, "seq_conflict", None),
            (2, Code::FailedPrecondition as u32, "seq_gap", Some(2)),
        ]
    );
    assert_eq!(mixed.ticks, [0, 2, 0]);
    assert_eq!(mixed.actions[0], u32::MAX);
    assert_eq!(f64s(&mixed.drives)[..2], [0.0, 0.0], "0, never NaN");
    assert_eq!(mixed.replayed, [false; 3]);
    // u64::MAX on one member: a gap; the stream goes on.
    tx.send(pb::GroupStepRequest {
        mask: vec![1],
        ..step(4, vec![28], vec![u64::MAX])
    })
    .await
    .expect("send");
    let far = replies.message().await.expect("reply").expect("a reply");
    assert_eq!(far.statuses.len(), 1, "{:?}", far.statuses);
    assert_eq!(
        (far.statuses[0].code.as_str(), far.statuses[0].expected_seq),
        ("seq_gap", Some(3))
    );
    // Without seqs: no `replayed` column.
    tx.send(step(5, vec![23, 28, 25], Vec::new()))
        .await
        .expect("send");
    let plain = replies.message().await.expect("reply").expect("a reply");
    assert!(plain.replayed.is_empty());
    assert_eq!(plain.ticks, [2, 3, 2]);
    drop(tx);
}
