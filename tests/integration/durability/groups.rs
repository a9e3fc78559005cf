//! Session groups under kill -9 (docs/groups.md, "Durability, shards and
//! clusters"): a group stepped over `StepGroup` with four messages in flight
//! is killed mid-stream; after the restart
//! - every member has applied at least every message acknowledged before
//!   the kill and at most every message sent (nothing acknowledged is lost,
//!   nothing is made up);
//! - each member is bit-equal (Ξ, D, history) to a core agent with the
//!   member's derived seed fed the observations it applied;
//! - the group is rebuilt from its members' records and steps on from
//!   where each member stands.
//!
//! Under both `--durability` modes: `sync` (acknowledged after
//! `fdatasync`) and `os` (after `write`; survives kill -9, not a power cut).
//! The `sync` run snapshots every 16 observations, so its members recover
//! from snapshots written at steps spread by their phases (each member's
//! own) and the log after them; the `os` run, with the default interval,
//! from the log alone.

use std::collections::VecDeque;
use std::time::Duration;

use mcapi_server::service::groups::member_seed;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

use super::*;
use common::{Launch, Server, http_client, next_hallway_obs, params, rest_get};

/// Members of the group.
const N: usize = 12;
/// Messages kept in flight: the client sends the next one before it has
/// read the replies of the four before it.
const IN_FLIGHT: usize = 4;
/// Messages acknowledged before the kill.
const ACKED_BEFORE_KILL: usize = 60;
const GROUP_SEED: u64 = 4242;

fn le(xs: impl IntoIterator<Item = f64>) -> Vec<u8> {
    xs.into_iter().flat_map(f64::to_le_bytes).collect()
}

/// Every member's trajectory, decided by the client alone (each reports
/// the action it took, so no message waits for an earlier reply): message
/// `t` carries every member's observation `t`.
struct Trajectories {
    obs: Vec<Vec<Obs>>,
    rngs: Vec<ChaCha8Rng>,
}

impl Trajectories {
    fn new() -> Self {
        Self {
            obs: vec![Vec::new(); N],
            rngs: (0..N)
                .map(|i| ChaCha8Rng::seed_from_u64(0xfeed ^ i as u64))
                .collect(),
        }
    }

    /// Draws every member's next observation and builds its message.
    fn next_message(&mut self, group_id: &str, seq: u64) -> pb::GroupStepRequest {
        let mut states = Vec::with_capacity(N);
        let mut stimuli = Vec::new();
        let mut taken = Vec::new();
        for (obs, rng) in self.obs.iter_mut().zip(&mut self.rngs) {
            let next = next_hallway_obs(rng, obs.last().map(|o| o.state), None, false);
            states.push(next.state as u32);
            if let (Some(x), Some(a)) = (next.stimulus, next.report) {
                stimuli.extend(x);
                taken.push(a as u32);
            }
            obs.push(next);
        }
        pb::GroupStepRequest {
            group_id: group_id.into(),
            seq,
            states,
            stimuli: le(stimuli),
            action_taken: taken,
            ..Default::default()
        }
    }
}

async fn create_group(client: &reqwest::Client, base: &str) -> (String, Vec<String>) {
    let (status, body) = rest(
        client,
        Method::POST,
        &format!("{base}/v1/groups"),
        None,
        Some(&json!({
            "model": {"preset": "hallway"},
            "agent": {"update_mode": "lockstep"},
            "n": N,
            "seed": GROUP_SEED,
        })),
    )
    .await;
    assert_eq!(status, 201, "create group: {body}");
    let members = body["members"]
        .as_array()
        .expect("members")
        .iter()
        .map(|m| m.as_str().expect("member id").to_string())
        .collect();
    (body["id"].as_str().expect("group id").to_string(), members)
}

/// Steps the group until `ACKED_BEFORE_KILL` messages are acknowledged,
/// with `IN_FLIGHT` more sent, then kills the server without reading on.
/// Returns how many messages were acknowledged and how many sent.
async fn step_then_kill(
    server: &mut Server,
    group: &str,
    traj: &mut Trajectories,
) -> (usize, usize) {
    let mut client = server.grpc_client().await;
    let (tx, rx) = mpsc::channel(IN_FLIGHT * 2);
    let mut replies = client
        .step_group(ReceiverStream::new(rx))
        .await
        .expect("step_group")
        .into_inner();
    let mut pending = VecDeque::new();
    let (mut sent, mut acked) = (0usize, 0usize);
    loop {
        while pending.len() < IN_FLIGHT {
            tx.send(traj.next_message(group, sent as u64))
                .await
                .expect("send");
            pending.push_back(sent);
            sent += 1;
        }
        if acked == ACKED_BEFORE_KILL {
            break;
        }
        let reply = replies
            .message()
            .await
            .expect("a reply")
            .expect("the stream goes on");
        let seq = pending.pop_front().expect("a message in flight");
        assert_eq!(reply.seq, seq as u64, "replies in order");
        assert!(
            reply.statuses.is_empty(),
            "no member refused: {:?}",
            reply.statuses
        );
        assert_eq!(
            reply.ticks,
            vec![seq as u64; N],
            "every member at tick {seq}"
        );
        acked += 1;
    }
    // Four messages are in flight; a moment later some are applied, none
    // is acknowledged.
    tokio::time::sleep(Duration::from_millis(1)).await;
    server.kill9();
    (acked, sent)
}

async fn group_steps_survive_kill_9(durability: &str, snapshot_every: &str) {
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    let launch = Launch::new(
        data.path(),
        &[
            "--durability",
            durability,
            "--snapshot-every",
            snapshot_every,
        ],
    );
    let mut server = Server::start(&launch, log_path(&logs, "first")).await;
    let client = http_client();
    let (group, members) = create_group(&client, &server.base()).await;
    let mut traj = Trajectories::new();
    let (acked, sent) = step_then_kill(&mut server, &group, &mut traj).await;

    let server = Server::start(&launch, log_path(&logs, "second")).await;
    let base = server.base();
    let (status, info) = rest(
        &client,
        Method::GET,
        &format!("{base}/v1/groups/{group}"),
        None,
        None,
    )
    .await;
    assert_eq!(status, 200, "the group is rebuilt after kill -9: {info}");
    assert_eq!(
        info["members"],
        json!(members),
        "the same members, by index"
    );
    let mut applied_counts = Vec::with_capacity(N);
    for (i, id) in members.iter().enumerate() {
        let (status, body) = rest_get(&client, &base, None, id).await;
        assert_eq!(status, 200, "{id}: {body}");
        let applied = body["tick"].as_u64().expect("tick") as usize + 1;
        assert!(
            (acked..=sent).contains(&applied),
            "member {i} ({durability}): {applied} observations applied, {acked} acknowledged, {sent} sent"
        );
        let ctx = format!("member {i} after kill -9 ({durability})");
        let seen: Vec<(Obs, Option<Reply>)> = traj.obs[i][..applied]
            .iter()
            .map(|o| (o.clone(), None))
            .collect();
        check_session(
            &client,
            &base,
            None,
            id,
            &params(member_seed(GROUP_SEED, i as u64), None),
            &seen,
            &ctx,
        )
        .await;
        applied_counts.push(applied);
    }
    eprintln!(
        "{durability}: {acked} acknowledged, {sent} sent, applied per member {applied_counts:?}"
    );

    // The rebuilt group steps on: each member from where it stands, over
    // REST this time.
    let states: Vec<usize> = (0..N)
        .map(|i| traj.obs[i][applied_counts[i] - 1].state)
        .collect();
    let body = json!({
        "states": states,
        "stimuli": states.iter().map(|&s| common::hallway::stimulus(s)).collect::<Vec<_>>(),
        "action_taken": vec![2; N],
    });
    let (status, reply) = rest(
        &client,
        Method::POST,
        &format!("{base}/v1/groups/{group}/steps"),
        None,
        Some(&body),
    )
    .await;
    assert_eq!(status, 200, "a step after recovery: {reply}");
    let ticks: Vec<usize> = reply["ticks"]
        .as_array()
        .expect("ticks")
        .iter()
        .map(|t| t.as_u64().expect("a tick") as usize)
        .collect();
    assert_eq!(
        ticks, applied_counts,
        "each member goes on from its own tick"
    );
    let mut server = server;
    assert!(server.terminate().success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn group_steps_survive_kill_9_with_sync_durability() {
    tokio::time::timeout(
        Duration::from_secs(120),
        group_steps_survive_kill_9("sync", "16"),
    )
    .await
    .expect("within two minutes");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn group_steps_survive_kill_9_with_os_durability() {
    tokio::time::timeout(
        Duration::from_secs(120),
        group_steps_survive_kill_9("os", "1000"),
    )
    .await
    .expect("within two minutes");
}
