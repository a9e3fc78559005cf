//! Sequence numbers on observations, exactly-once delivery
//! (docs/sessions.md, "Delivery guarantees"), over REST and in the manager
//! across eviction and restart:
//! - `seq` equal to the applied count applies; lower and in the window
//!   replays the recorded reply, byte for byte but for `"replayed": true`,
//!   and applies nothing; beyond it is `seq_gap`, before the window
//!   `seq_expired`, with other content `seq_conflict` (409 each, with the
//!   seq to resume from in the body);
//! - a batch may replay a prefix and apply the rest; its seqs are
//!   consecutive, all or none;
//! - a `seq` that is no integer below 2^64 is a precise 400;
//! - replays survive eviction, a restart and a shard move (the ring, its
//!   digests and replies are in the snapshot and the log).
//!
//! gRPC's are in `grpc::seq`.

use std::sync::Arc;
use std::time::Duration;

use mcapi_server::service::{
    Caller, CreateSession, Limits, ManagerOptions, ObservationIn, ServiceError, SessionConfig,
    SessionManager, StepOut,
};
use mcapi_store::Store;
use mcapi_testkit::{http_client, rest, stimulus};
use serde_json::{Value, json};

/// POSTs `body` and returns the status and the body's text as sent.
async fn post_raw(client: &reqwest::Client, url: &str, body: &Value) -> (u16, String) {
    let resp = client.post(url).json(body).send().await.expect("request");
    let status = resp.status().as_u16();
    (status, resp.text().await.expect("body"))
}

/// The hallway's next state under action `a`.
fn next_state(s: usize, a: u64) -> usize {
    match a {
        0 => s.saturating_sub(1),
        1 => (s + 1).min(49),
        _ => s,
    }
}

fn obs_json(state: usize, seq: u64) -> Value {
    if seq == 0 {
        json!({"state": state, "seq": seq})
    } else {
        json!({"state": state, "stimulus": stimulus(state), "seq": seq})
    }
}

#[tokio::test]
async fn rest_applies_replays_and_refuses_seqs_as_documented() {
    let (_manager, addr) = super::serve_rest(Limits::default()).await;
    let base = format!("http://{addr}");
    let client = http_client();
    let (status, created) = rest(
        &client,
        reqwest::Method::POST,
        &format!("{base}/v1/sessions"),
        None,
        Some(&json!({"model": {"preset": "hallway"}, "agent": {"seed": 5, "epsilon": 0.3, "history": 4}})),
    )
    .await;
    assert_eq!(status, 201, "{created}");
    let id = created["id"].as_str().expect("id");
    let url = format!("{base}/v1/sessions/{id}/observations");
    let get = |client: reqwest::Client, base: String| async move {
        rest(
            &client,
            reqwest::Method::GET,
            &format!("{base}/v1/sessions/{id}"),
            None,
            None,
        )
        .await
        .1
    };
    assert_eq!(get(client.clone(), base.clone()).await["next_seq"], 0);

    // Seq 0, the first observation (no tick), is replayed too.
    let mut state = 25;
    let mut sent = Vec::new();
    let (status, first) = post_raw(&client, &url, &obs_json(state, 0)).await;
    assert_eq!(status, 200, "{first}");
    assert!(
        !first.contains("replayed"),
        "a fresh reply says nothing: {first}"
    );
    let (status, again) = post_raw(&client, &url, &obs_json(state, 0)).await;
    assert_eq!(status, 200, "{again}");
    assert_eq!(again.replace(r#","replayed":true"#, ""), first);
    assert!(again.contains(r#""replayed":true"#), "{again}");
    let step: Value = serde_json::from_str(&first).expect("json");
    sent.push((obs_json(state, 0), first));
    state = next_state(state, step["action_index"].as_u64().expect("action"));

    for seq in 1..=6u64 {
        let body = obs_json(state, seq);
        let (status, text) = post_raw(&client, &url, &body).await;
        assert_eq!(status, 200, "seq {seq}: {text}");
        let step: Value = serde_json::from_str(&text).expect("json");
        assert_eq!(step["tick"], seq, "seq n is tick n");
        state = next_state(state, step["action_index"].as_u64().expect("action"));
        sent.push((body, text));
    }
    let info = get(client.clone(), base.clone()).await;
    assert_eq!(
        (info["tick"].clone(), info["next_seq"].clone()),
        (json!(6), json!(7))
    );

    // The window is the ring of 4: seqs 3 to 6 replay, bit for bit, and
    // apply nothing.
    for (seq, (body, text)) in sent.iter().enumerate().skip(3) {
        let (status, again) = post_raw(&client, &url, body).await;
        assert_eq!(status, 200, "replay of {seq}: {again}");
        assert_eq!(
            &again.replace(r#","replayed":true"#, ""),
            text,
            "replay of {seq}"
        );
        assert_ne!(&again, text, "marked replayed");
    }
    let after = get(client.clone(), base.clone()).await;
    assert_eq!(after["tick"], info["tick"], "replays applied nothing");
    assert_eq!(after["drive"], info["drive"]);
    assert_eq!(after["policy_version"], info["policy_version"]);
    // History reads show ticks only, as before: the first observation's
    // entry is not one.
    let (_, history) = rest(
        &client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{id}/history"),
        None,
        None,
    )
    .await;
    let ticks: Vec<u64> = history["ticks"]
        .as_array()
        .or_else(|| history.as_array())
        .expect("history entries")
        .iter()
        .map(|e| e["tick"].as_u64().expect("tick"))
        .collect();
    assert_eq!(ticks, vec![3, 4, 5, 6]);

    // Older than the window: seq_expired, naming where it begins.
    let (status, body) = rest(&client, reqwest::Method::POST, &url, None, Some(&sent[2].0)).await;
    assert_eq!(
        (status, body["code"].as_str()),
        (409, Some("seq_expired")),
        "{body}"
    );
    assert_eq!(body["oldest_seq"], 3, "{body}");
    assert!(
        body["message"]
            .as_str()
            .expect("message")
            .contains("begins at seq 3"),
        "{body}"
    );
    // Beyond the next: seq_gap, naming the expected seq.
    let (status, body) = rest(
        &client,
        reqwest::Method::POST,
        &url,
        None,
        Some(&obs_json(state, 9)),
    )
    .await;
    assert_eq!(
        (status, body["code"].as_str()),
        (409, Some("seq_gap")),
        "{body}"
    );
    assert_eq!(body["expected_seq"], 7, "{body}");
    assert!(
        body["message"]
            .as_str()
            .expect("message")
            .contains("must have seq 7"),
        "{body}"
    );
    // Applied with other content: seq_conflict.
    let mut other = sent[6].0.clone();
    other["stimulus"] = json!([6.0, 0.0]);
    let (status, body) = rest(&client, reqwest::Method::POST, &url, None, Some(&other)).await;
    assert_eq!(
        (status, body["code"].as_str()),
        (409, Some("seq_conflict")),
        "{body}"
    );
    let mut other = sent[6].0.clone();
    other["action_taken"] = json!(2);
    let (status, body) = rest(&client, reqwest::Method::POST, &url, None, Some(&other)).await;
    assert_eq!(
        body["code"], "seq_conflict",
        "an action taken is content too: {status} {body}"
    );
    assert_eq!(
        get(client.clone(), base.clone()).await["tick"],
        6,
        "refusals applied nothing"
    );

    // A batch replays its prefix and applies the rest.
    let s7 = obs_json(state, 7);
    let (status, text) = post_raw(
        &client,
        &url,
        &json!({"observations": [sent[5].0, sent[6].0, s7]}),
    )
    .await;
    assert_eq!(status, 200, "{text}");
    let batch: Value = serde_json::from_str(&text).expect("json");
    let steps = batch["steps"].as_array().expect("steps");
    assert_eq!(steps.len(), 3);
    for (k, seq) in [5usize, 6].into_iter().enumerate() {
        let mut want: Value = serde_json::from_str(&sent[seq].1).expect("json");
        want["replayed"] = json!(true);
        assert_eq!(steps[k], want, "batch replay of {seq}");
    }
    assert_eq!(steps[2]["tick"], 7);
    assert!(steps[2].get("replayed").is_none(), "{}", steps[2]);
    let state = next_state(state, steps[2]["action_index"].as_u64().expect("action"));
    // Seqs of a batch are consecutive, and all or none.
    for (observations, words) in [
        (
            json!([obs_json(state, 8), obs_json(state, 10)]),
            "`observations[1].seq`: is 10, expected 9",
        ),
        (
            json!([obs_json(state, 8), {"state": state, "stimulus": stimulus(state)}]),
            "`observations[1].seq`: is missing, expected 9",
        ),
        (
            json!([{"state": state, "stimulus": stimulus(state)}, obs_json(state, 9)]),
            "`observations[1].seq`: is given, but `observations[0].seq` is not",
        ),
    ] {
        let (status, body) = rest(
            &client,
            reqwest::Method::POST,
            &url,
            None,
            Some(&json!({ "observations": observations })),
        )
        .await;
        assert_eq!(
            (status, body["code"].as_str()),
            (400, Some("bad_request")),
            "{body}"
        );
        let message = body["message"].as_str().expect("message");
        assert!(message.contains(words), "{message}");
    }
    assert_eq!(get(client.clone(), base.clone()).await["next_seq"], 8);

    // A seq that is no integer below 2^64: a precise 400, nothing applied.
    for (seq, words) in [
        (json!(-1), "not the negative number -1"),
        (json!(2.5), "not the fractional number 2.5"),
        (json!(1e20), "beyond 2^64 - 1"),
        (json!("8"), "not the string \"8\""),
        (json!([8]), "not an array"),
    ] {
        let body = json!({"state": state, "stimulus": stimulus(state), "seq": seq});
        let (status, body) = rest(&client, reqwest::Method::POST, &url, None, Some(&body)).await;
        assert_eq!(
            (status, body["code"].as_str()),
            (400, Some("bad_request")),
            "{seq}: {body}"
        );
        let message = body["message"].as_str().expect("message");
        assert!(
            message.contains("`seq` must be an integer from 0 to 18446744073709551615")
                && message.contains(words),
            "{seq}: {message}"
        );
    }
    // A bare 2^64 - 1 is a seq like any other (a gap here).
    let body = json!({"state": state, "stimulus": stimulus(state), "seq": u64::MAX});
    let (status, body) = rest(&client, reqwest::Method::POST, &url, None, Some(&body)).await;
    assert_eq!(
        (status, body["code"].as_str()),
        (409, Some("seq_gap")),
        "{body}"
    );

    // Without seq, as before: applied as it comes.
    let body = json!({"state": state, "stimulus": stimulus(state)});
    let (status, body) = rest(&client, reqwest::Method::POST, &url, None, Some(&body)).await;
    assert_eq!((status, body["tick"].clone()), (200, json!(8)), "{body}");
    assert_eq!(get(client.clone(), base.clone()).await["next_seq"], 9);
}

/// A session with `history: 0` keeps no window: every applied seq is
/// expired, and the oldest it names is the next.
#[tokio::test]
async fn without_history_nothing_replays() {
    let (_manager, addr) = super::serve_rest(Limits::default()).await;
    let base = format!("http://{addr}");
    let client = http_client();
    let (_, created) = rest(
        &client,
        reqwest::Method::POST,
        &format!("{base}/v1/sessions"),
        None,
        Some(&json!({"model": {"preset": "hallway"}, "agent": {"seed": 5, "history": 0}})),
    )
    .await;
    let id = created["id"].as_str().expect("id");
    let url = format!("{base}/v1/sessions/{id}/observations");
    let (status, _) = rest(
        &client,
        reqwest::Method::POST,
        &url,
        None,
        Some(&obs_json(3, 0)),
    )
    .await;
    assert_eq!(status, 200);
    let (status, body) = rest(
        &client,
        reqwest::Method::POST,
        &url,
        None,
        Some(&obs_json(3, 0)),
    )
    .await;
    assert_eq!(
        (status, body["code"].as_str()),
        (409, Some("seq_expired")),
        "{body}"
    );
    assert_eq!(body["oldest_seq"], 1, "{body}");
}

fn durable(store: Arc<Store>) -> SessionManager {
    let manager = SessionManager::with_options(ManagerOptions {
        store: Some(store),
        snapshot_every: 5,
        evict_after: Some(Duration::from_secs(3600)),
        ..ManagerOptions::new(Limits::default(), 1)
    })
    .expect("manager");
    let report = manager.recover().expect("recovery");
    assert_eq!(report.skipped, 0, "{report:?}");
    manager
}

fn observation(state: usize, seq: u64) -> ObservationIn {
    ObservationIn {
        state: Some(state),
        observation: None,
        stimulus: (seq > 0).then(|| stimulus(state).to_vec()),
        action_taken: None,
        signal: None,
        signal_source: None,
        seq: Some(seq),
    }
}

/// The reply as it must come back when replayed.
fn replayed(step: &StepOut) -> StepOut {
    StepOut {
        replayed: true,
        ..step.clone()
    }
}

fn assert_bit_identical(got: &StepOut, want: &StepOut, what: &str) {
    assert_eq!(got, want, "{what}");
    let bits = |s: &StepOut| {
        (
            s.reward.to_bits(),
            s.drive.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
        )
    };
    assert_eq!(bits(got), bits(want), "{what}: bits");
}

/// Replays across eviction and a restart, for a session that is evicted
/// (the functional-graph engine) and one that is not (a PVF basis), with
/// snapshots every 5 observations: the window comes back from the
/// snapshot's ring and the log after it.
#[test]
fn replays_survive_eviction_and_restart() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let store = Arc::new(Store::open(data.path()).expect("store"));
    let manager = durable(Arc::clone(&store));
    let kinds = [
        (
            json!({"preset": "hallway"}),
            json!({"seed": 11, "epsilon": 0.2, "history": 6}),
        ),
        (
            json!({"preset": "hallway", "basis": {"kind": "proto_value", "k": 5}}),
            json!({"seed": 12, "history": 6}),
        ),
    ];
    let mut runs = Vec::new();
    for (model, agent) in &kinds {
        let agent: SessionConfig = serde_json::from_value(agent.clone()).expect("agent");
        let id = manager
            .create(
                Caller::Anyone,
                CreateSession {
                    model: model.clone(),
                    agent,
                },
            )
            .expect("create")
            .id;
        let mut state = 25;
        let mut steps = Vec::new();
        for seq in 0..13u64 {
            let obs = observation(state, seq);
            let step = rt
                .block_on(manager.observe(Caller::Anyone, &id, vec![obs.clone()]))
                .expect("observe")
                .remove(0);
            state = next_state(state, step.action_index as u64);
            steps.push((obs, step));
        }
        runs.push((id, steps));
    }
    let check = |manager: &SessionManager, when: &str| {
        for (id, steps) in &runs {
            // The window: the last 6 observations.
            for (seq, (obs, step)) in steps.iter().enumerate().skip(7) {
                let got = rt
                    .block_on(manager.observe(Caller::Anyone, id, vec![obs.clone()]))
                    .unwrap_or_else(|e| panic!("{when}: replay of {seq}: {e}"));
                assert_bit_identical(&got[0], &replayed(step), &format!("{when}: seq {seq}"));
            }
            let expired =
                rt.block_on(manager.observe(Caller::Anyone, id, vec![steps[6].0.clone()]));
            assert!(
                matches!(expired, Err(ServiceError::SeqExpired { oldest: 7, got: 6 })),
                "{when}: {expired:?}"
            );
            let mut other = steps[12].0.clone();
            other.stimulus = Some(vec![0.5, 0.5]);
            let conflict = rt.block_on(manager.observe(Caller::Anyone, id, vec![other]));
            assert!(
                matches!(conflict, Err(ServiceError::SeqConflict(12))),
                "{when}: {conflict:?}"
            );
            let info = manager.get(Caller::Anyone, id).expect("get");
            assert_eq!(
                (info.tick, info.next_seq),
                (12, 13),
                "{when}: nothing applied"
            );
        }
    };
    check(&manager, "resident");
    assert!(
        manager.evict_idle(Duration::ZERO) >= 1,
        "the hallway leaves memory"
    );
    check(&manager, "evicted and loaded back");
    manager.shutdown();
    drop(manager);
    drop(store);
    let store = Arc::new(Store::open(data.path()).expect("reopen"));
    let manager = durable(store);
    check(&manager, "restarted");
}

/// A session moved to another replica replays there: the window travels
/// in the snapshot and the log tail a shard move carries.
#[test]
fn replays_survive_a_shard_move() {
    use mcapi_shards::moves::Manifest;
    use mcapi_shards::plan::{ordinal_names, plan};
    use mcapi_shards::{Placement, ReplicaName, ShardMap};

    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let tmp = tempfile::tempdir().expect("tempdir");
    let names = ordinal_names("mcapi", 2).expect("names");
    // mcapi-0 owns one shard only, so the session it creates is there.
    let shard = plan(&names, None).expect("plan").map.shards_of(&names[0])[0];
    let owners: Vec<ReplicaName> = (0..1024u16)
        .map(|s| names[usize::from(s != shard)].clone())
        .collect();
    let map = ShardMap::from_owners(1, &owners).expect("map");
    let replica = |name: &str, dir: &str| {
        let placement = Arc::new(
            Placement::new(map.clone(), ReplicaName::parse(name).expect("name"))
                .expect("placement"),
        );
        let manager = SessionManager::with_options(ManagerOptions {
            placement: Some(placement),
            store: Some(Arc::new(Store::open(&tmp.path().join(dir)).expect("store"))),
            snapshot_every: 5,
            ..ManagerOptions::new(Limits::default(), 1)
        })
        .expect("manager");
        manager.recover().expect("recover");
        manager
    };
    let (a, b) = (replica("mcapi-0", "a"), replica("mcapi-1", "b"));
    let agent: SessionConfig =
        serde_json::from_value(json!({"seed": 21, "history": 4})).expect("agent");
    let id = a
        .create(
            Caller::Anyone,
            CreateSession {
                model: json!({"preset": "hallway"}),
                agent,
            },
        )
        .expect("create")
        .id;
    let mut state = 25;
    let mut steps = Vec::new();
    for seq in 0..8u64 {
        let obs = observation(state, seq);
        let step = rt
            .block_on(a.observe(Caller::Anyone, &id, vec![obs.clone()]))
            .expect("observe")
            .remove(0);
        state = next_state(state, step.action_index as u64);
        steps.push((obs, step));
    }
    // The move: snapshot, then (frozen) the delta, then the target serves.
    let snapshot = a.export_shard(shard, None).expect("snapshot");
    let manifest = snapshot.manifest(&Manifest::default());
    rt.block_on(b.import_shard(shard, snapshot, true))
        .expect("import");
    rt.block_on(a.freeze_shard(shard, mcapi_server::service::shards::DEFAULT_FREEZE_LEASE))
        .expect("freeze");
    let delta = a.export_shard(shard, Some(&manifest)).expect("delta");
    rt.block_on(b.import_shard(shard, delta, false))
        .expect("delta import");
    assert_eq!(b.activate_shard(shard, 2).expect("activate"), 1);
    for (seq, (obs, step)) in steps.iter().enumerate().skip(4) {
        let got = rt
            .block_on(b.observe(Caller::Anyone, &id, vec![obs.clone()]))
            .unwrap_or_else(|e| panic!("replay of {seq} on the target: {e}"));
        assert_bit_identical(&got[0], &replayed(step), &format!("moved: seq {seq}"));
    }
    let info = b.get(Caller::Anyone, &id).expect("get");
    assert_eq!((info.tick, info.next_seq), (7, 8), "nothing applied");
}
