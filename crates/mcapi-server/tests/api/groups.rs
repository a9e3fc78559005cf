//! Session groups over REST and in the store (docs/groups.md): a group
//! created, stepped by JSON columns, read and deleted over a real socket,
//! its members answering bit for bit as sessions with the derived seeds
//! observed alone; a continuous group stepped by observation rows; every
//! malformed body with its status and code; a group and its members after
//! a restart on a durable store.

use std::net::SocketAddr;
use std::sync::Arc;

use mcapi_server::api::{AppState, router};
use mcapi_server::service::groups::{Columns, CreateGroup, member_seed};
use mcapi_server::service::{Caller, Limits, ManagerOptions, ObservationIn, SessionManager};
use mcapi_store::Store;
use mcapi_testkit::{assert_bits_eq, floats};
use serde_json::{Value, json};

async fn start(limits: Limits) -> String {
    let manager = Arc::new(SessionManager::new(limits, 2).expect("manager"));
    let state = AppState {
        manager,
        metrics: None,
        serving: None,
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr: SocketAddr = listener.local_addr().expect("addr");
    tokio::spawn(async move { axum::serve(listener, router(state)).await.expect("serve") });
    format!("http://{addr}")
}

/// A manager on the durable store in `dir`, recovered from it, with
/// `threads` planning threads; the store too, for tests that stop it as a
/// crash would.
fn durable_manager(dir: &std::path::Path, threads: usize) -> (Arc<SessionManager>, Arc<Store>) {
    let store = Arc::new(Store::open(dir).expect("store"));
    let manager = SessionManager::with_options(ManagerOptions {
        store: Some(Arc::clone(&store)),
        ..ManagerOptions::new(Limits::default(), threads)
    })
    .expect("manager");
    manager.recover().expect("recovery");
    (Arc::new(manager), store)
}

async fn call(method: reqwest::Method, url: &str, body: Option<&Value>) -> (u16, Value) {
    let client = reqwest::Client::new();
    let mut req = client.request(method, url);
    if let Some(b) = body {
        req = req.json(b);
    }
    let resp = req.send().await.expect("request");
    let status = resp.status().as_u16();
    (status, resp.json().await.unwrap_or(Value::Null))
}

async fn post(url: &str, body: &Value) -> (u16, Value) {
    call(reqwest::Method::POST, url, Some(body)).await
}

fn stimulus(state: u64) -> Value {
    match state {
        10 => json!([6.0, 0.0]),
        40 => json!([0.0, 6.0]),
        _ => json!([0.0, 0.0]),
    }
}

fn moved(state: u64, action: u64) -> u64 {
    match action {
        0 => state - 1,
        1 => state + 1,
        _ => state,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_group_is_created_stepped_read_and_deleted_over_rest_as_sessions_alone() {
    const N: usize = 3;
    let base = start(Limits::default()).await;
    let (status, group) = post(
        &format!("{base}/v1/groups"),
        &json!({"model": {"preset": "hallway"}, "n": N, "seed": 99}),
    )
    .await;
    assert_eq!(status, 201, "{group}");
    let id = group["id"].as_str().expect("id").to_string();
    assert!(id.contains(".g"), "{id}");
    assert_eq!(group["size"], N);
    assert_eq!(group["seed"], 99);
    assert_eq!(group["stimuli"], 2);
    let members: Vec<String> = group["members"]
        .as_array()
        .expect("members")
        .iter()
        .map(|m| m.as_str().expect("an id").to_string())
        .collect();
    let (status, got) = call(
        reqwest::Method::GET,
        &format!("{base}/v1/groups/{id}"),
        None,
    )
    .await;
    assert_eq!((status, &got), (200, &group));

    // The group by columns; each member's observations kept to replay.
    let mut states = [25u64; N];
    let mut sent: Vec<Vec<Value>> = vec![Vec::new(); N];
    let mut answers: Vec<Vec<Value>> = vec![Vec::new(); N];
    for t in 0..200 {
        // Every other tick steps members 0 and 2 only.
        let mask: Vec<usize> = if t % 2 == 1 {
            vec![0, 2]
        } else {
            (0..N).collect()
        };
        let mut body = json!({"states": mask.iter().map(|&i| states[i]).collect::<Vec<_>>()});
        if t > 0 {
            body["stimuli"] = mask.iter().map(|&i| stimulus(states[i])).collect();
        }
        if t % 2 == 1 {
            body["mask"] = json!(mask);
        }
        let (status, reply) = post(&format!("{base}/v1/groups/{id}/steps"), &body).await;
        assert_eq!(status, 200, "{reply}");
        assert_eq!(reply["errors"], json!([]));
        for (j, &i) in mask.iter().enumerate() {
            let mut obs = json!({"state": states[i]});
            if !sent[i].is_empty() {
                obs["stimulus"] = stimulus(states[i]);
            }
            sent[i].push(obs);
            answers[i].push(json!({
                "action": reply["actions"][j],
                "drive": reply["drives"][j],
                "reward": reply["rewards"][j],
                "policy_version": reply["policy_versions"][j],
                "tick": reply["ticks"][j],
            }));
            states[i] = moved(states[i], reply["actions"][j].as_u64().expect("action"));
        }
    }
    // Each member's trajectory, bit for bit, from a session of its own.
    for i in 0..N {
        let (status, alone) = post(
            &format!("{base}/v1/sessions"),
            &json!({"model": {"preset": "hallway"}, "agent": {"seed": member_seed(99, i as u64)}}),
        )
        .await;
        assert_eq!(status, 201, "{alone}");
        let alone = alone["id"].as_str().expect("id").to_string();
        for (t, obs) in sent[i].iter().enumerate() {
            let (status, step) =
                post(&format!("{base}/v1/sessions/{alone}/observations"), obs).await;
            assert_eq!(status, 200, "{step}");
            let want = &answers[i][t];
            assert_eq!(step["action_index"], want["action"], "member {i} tick {t}");
            assert_eq!(step["tick"], want["tick"], "member {i} tick {t}");
            assert_eq!(step["policy_version"], want["policy_version"]);
            assert_bits_eq(&floats(&step["drive"]), &floats(&want["drive"]), "drive");
            assert_bits_eq(
                &[step["reward"].as_f64().expect("reward")],
                &[want["reward"].as_f64().expect("reward")],
                "reward",
            );
        }
    }
    // Members are sessions; the group's delete removes them.
    let (status, info) = call(
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{}", members[1]),
        None,
    )
    .await;
    assert_eq!(status, 200);
    assert_eq!(info["tick"], 99, "member 1 stepped every other tick");
    let (status, _) = call(
        reqwest::Method::DELETE,
        &format!("{base}/v1/groups/{id}"),
        None,
    )
    .await;
    assert_eq!(status, 204);
    for m in &members {
        let (status, _) = call(
            reqwest::Method::GET,
            &format!("{base}/v1/sessions/{m}"),
            None,
        )
        .await;
        assert_eq!(status, 404);
    }
    let (status, body) = call(
        reqwest::Method::GET,
        &format!("{base}/v1/groups/{id}"),
        None,
    )
    .await;
    assert_eq!((status, body["code"].as_str()), (404, Some("not_found")));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_continuous_group_steps_by_observation_rows() {
    let base = start(Limits::default()).await;
    let model = json!({"observation_space": {"low": [0, 0], "high": [1, 1]},
                       "actions": ["n", "s", "e", "w"], "stimuli": ["food", "rest"]});
    let (status, group) = post(
        &format!("{base}/v1/groups"),
        &json!({"model": model, "n": 2, "seed": 5}),
    )
    .await;
    assert_eq!(status, 201, "{group}");
    assert_eq!(group["observation_dim"], 2);
    let id = group["id"].as_str().expect("id");
    let url = format!("{base}/v1/groups/{id}/steps");
    let (status, reply) = post(&url, &json!({"observations": [[0.1, 0.2], [0.3, 0.4]]})).await;
    assert_eq!(status, 200, "{reply}");
    let (status, reply) = post(
        &url,
        &json!({"observations": [[0.2, 0.2], [0.3, 0.5]], "stimuli": [[1.0, 0.0], [0.0, 0.0]]}),
    )
    .await;
    assert_eq!(status, 200, "{reply}");
    assert_eq!(reply["ticks"], json!([1, 1]));
    for (body, code, needle) in [
        (
            json!({"states": [1, 2]}),
            "column_length",
            "`observations` has 0 entries; 4 expected",
        ),
        (
            json!({"observations": [[0.1, 0.2]]}),
            "column_length",
            "has 2 entries; 4 expected",
        ),
        (
            json!({"observations": [[0.1, 0.2], [0.3]]}),
            "column_length",
            "`observations[1]` has 1",
        ),
    ] {
        let (status, err) = post(&url, &body).await;
        assert_eq!(
            (status, err["code"].as_str()),
            (400, Some(code)),
            "{body}: {err}"
        );
        assert!(
            err["message"].as_str().expect("message").contains(needle),
            "{err}"
        );
    }
    // A ragged row refuses the whole step.
    let (status, reply) = post(
        &url,
        &json!({"observations": [[0.2, 0.2], [0.3, 0.5, 0.1]], "stimuli": [[0.0, 0.0], [0.0, 0.0]]}),
    )
    .await;
    assert_eq!(
        (status, reply["code"].as_str()),
        (400, Some("column_length")),
        "{reply}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_malformed_rest_step_and_group_gets_its_status() {
    let base = start(Limits {
        max_sessions: 20,
        ..Limits::default()
    })
    .await;
    let (status, group) = post(
        &format!("{base}/v1/groups"),
        &json!({"model": {"preset": "hallway"}, "n": 4}),
    )
    .await;
    assert_eq!(status, 201, "{group}");
    assert!(group["seed"].is_u64(), "a drawn seed is returned: {group}");
    let id = group["id"].as_str().expect("id");
    let url = format!("{base}/v1/groups/{id}/steps");
    let (status, first) = post(&url, &json!({"states": [25, 25, 25, 25]})).await;
    assert_eq!(status, 200, "{first}");
    let stim = json!([[0, 0], [0, 0], [0, 0], [0, 0]]);
    let cases = [
        (json!({"states": [1, 2, 3]}), 400, "column_length"),
        (
            json!({"states": [1, 2, 3, 4], "stimuli": [[0, 0], [0, 0]]}),
            400,
            "column_length",
        ),
        (
            json!({"states": [1, 2, 3, 4], "stimuli": [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]}),
            400,
            "column_length",
        ),
        (
            json!({"states": [1, 2, 3, 4], "stimuli": stim, "action_taken": [0]}),
            400,
            "column_length",
        ),
        (
            json!({"states": [1, 2], "stimuli": [[0, 0], [0, 0]], "mask": [1, 1]}),
            400,
            "invalid_mask",
        ),
        (
            json!({"states": [1, 2], "stimuli": [[0, 0], [0, 0]], "mask": [3, 1]}),
            400,
            "invalid_mask",
        ),
        (
            json!({"states": [1], "stimuli": [[0, 0]], "mask": [4]}),
            400,
            "invalid_mask",
        ),
        (
            json!({"states": [1, 2, 3, 4], "extra": 1}),
            400,
            "bad_request",
        ),
        (
            json!({"states": [1, 50, 3, 4], "stimuli": stim}),
            400,
            "unknown_state",
        ),
        (
            json!({"states": [1_000_000, 2, 3, 4], "stimuli": stim}),
            400,
            "unknown_state",
        ),
        (
            json!({"states": [1, 2, 3, 4], "stimuli": [[0, 0], [0, 2e12], [0, 0], [0, 0]]}),
            400,
            "stimulus_too_large",
        ),
        (json!({"states": [-1, 2, 3, 4]}), 400, "bad_request"),
        (
            json!({"states": [1, 2, 3, 4], "stimuli": stim, "action_taken": [null, null, null, 4294967295u64]}),
            400,
            "bad_request",
        ),
        (json!([1, 2, 3]), 400, "bad_request"),
    ];
    for (body, want, code) in cases {
        let (status, err) = post(&url, &body).await;
        assert_eq!(
            (status, err["code"].as_str()),
            (want, Some(code)),
            "{body}: {err}"
        );
    }
    // What only a member refuses: that member only.
    let (status, reply) = post(
        &url,
        &json!({"states": [24, 25, 26, 25], "stimuli": stim, "action_taken": [null, 5, null, 9]}),
    )
    .await;
    assert_eq!(status, 200, "{reply}");
    assert_eq!(
        reply["errors"]
            .as_array()
            .expect("errors")
            .iter()
            .map(|e| (
                e["index"].as_u64().expect("index"),
                e["code"].as_str().expect("code")
            ))
            .collect::<Vec<_>>(),
        [(1, "unknown_action"), (3, "unknown_action")]
    );
    assert_eq!(reply["actions"][1], Value::Null);
    assert_eq!(reply["ticks"], json!([1, null, 1, null]));
    let (status, err) = post(
        &format!("{base}/v1/groups/s0000.g01ARZ3NDEKTSV4RRFFQ69G5FAV/steps"),
        &json!({"states": [1]}),
    )
    .await;
    assert_eq!(
        (status, err["code"].as_str()),
        (404, Some("not_found")),
        "{err}"
    );
    // Groups that do not fit, refused whole.
    for (body, want, code) in [
        (
            json!({"model": {"preset": "hallway"}, "n": 0}),
            400,
            "bad_request",
        ),
        (
            json!({"model": {"preset": "hallway"}, "n": 18_446_744_073_709_551_615u64}),
            413,
            "limit_exceeded",
        ),
        (
            json!({"model": {"preset": "hallway"}, "n": 17}),
            429,
            "too_many_sessions",
        ),
        (
            json!({"model": {"preset": "hallway"}, "n": 2, "agent": {"seed": 1}}),
            400,
            "bad_request",
        ),
        (json!({"model": {"preset": "hallway"}}), 400, "bad_request"),
    ] {
        let (status, err) = post(&format!("{base}/v1/groups"), &body).await;
        assert_eq!(
            (status, err["code"].as_str()),
            (want, Some(code)),
            "{body}: {err}"
        );
    }
    let (status, page) = call(reqwest::Method::GET, &format!("{base}/v1/sessions"), None).await;
    assert_eq!(status, 200);
    assert_eq!(
        page["sessions"].as_array().expect("page").len(),
        4,
        "only the first group"
    );
}

#[test]
fn a_group_and_its_stepped_members_survive_a_restart() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let open = || durable_manager(data.path(), 1).0;
    let manager = open();
    let group = manager
        .create_group(
            Caller::Anyone,
            serde_json::from_value::<CreateGroup>(
                json!({"model": {"preset": "hallway"}, "n": 5, "seed": 3}),
            )
            .expect("body"),
        )
        .expect("create");
    let step = |manager: &Arc<SessionManager>, first: bool| {
        rt.block_on(manager.step_group(
            Caller::Anyone,
            &group.id,
            Columns {
                states: vec![25; 5],
                stimuli: if first { Vec::new() } else { vec![0.0; 10] },
                ..Columns::default()
            },
        ))
        .expect("step")
    };
    for t in 0..10 {
        assert!(step(&manager, t == 0).iter().all(|m| m.result.is_ok()));
    }
    let before: Vec<_> = step(&manager, false)
        .into_iter()
        .map(|m| m.result.expect("step"))
        .collect();
    manager.shutdown();
    drop(manager);

    let manager = open();
    let got = manager.get_group(Caller::Anyone, &group.id).expect("group");
    assert_eq!(got, group, "the same group, members and seed");
    assert_eq!(manager.groups_len(), 1);
    for (i, m) in group.members.iter().enumerate() {
        let info = manager
            .get(Caller::Anyone, m.as_deref().expect("member"))
            .expect("member");
        assert_eq!(info.tick, before[i].tick);
        assert_bits_eq(&info.drive, &before[i].drive, "drive");
    }
    // It steps on where it was, and its delete outlives another restart.
    let after = step(&manager, false);
    assert!(
        after
            .iter()
            .all(|m| m.result.as_ref().is_ok_and(|s| s.tick == 11))
    );
    rt.block_on(manager.delete_group(Caller::Anyone, &group.id))
        .expect("delete");
    manager.shutdown();
    drop(manager);
    let manager = open();
    assert_eq!(manager.len(), 0);
    assert_eq!(manager.groups_len(), 0);
    manager.shutdown();
}

/// A group step finds each member where the session table has it now:
/// members evicted to the store between steps are loaded back and step on
/// bit for bit as the members of a twin group (same seed) that never left
/// memory; a member deleted alone is refused as not found while the others
/// step; a member evicted again after stepping from memory is found again.
/// (A step remembers where it found each member while the table is
/// unchanged; every eviction, load and delete changes it.)
#[test]
fn a_group_steps_on_through_its_members_evicted_loaded_back_and_deleted() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let (manager, _) = durable_manager(data.path(), 1);
    let create = || {
        manager
            .create_group(
                Caller::Anyone,
                serde_json::from_value::<CreateGroup>(
                    json!({"model": {"preset": "hallway"}, "n": 6, "seed": 11}),
                )
                .expect("body"),
            )
            .expect("create")
    };
    let (evicted, twin) = (create(), create());
    let states = [3, 9, 10, 25, 40, 41];
    let step = |group: &str, first: bool| {
        rt.block_on(manager.step_group(
            Caller::Anyone,
            group,
            Columns {
                states: states.to_vec(),
                stimuli: if first {
                    Vec::new()
                } else {
                    (0..6).flat_map(|i| [i as f64 * 0.5, 1.0]).collect()
                },
                ..Columns::default()
            },
        ))
        .expect("step")
    };
    let same = |a: &[mcapi_server::service::groups::MemberStep],
                b: &[mcapi_server::service::groups::MemberStep],
                what: &str| {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            let (x, y) = (
                x.result.as_ref().expect(what),
                y.result.as_ref().expect(what),
            );
            assert_eq!((x.tick, x.action_index), (y.tick, y.action_index), "{what}");
            assert_bits_eq(&x.drive, &y.drive, what);
        }
    };
    for t in 0..5 {
        same(
            &step(&evicted.id, t == 0),
            &step(&twin.id, t == 0),
            "in memory",
        );
    }
    // Both groups leave memory; only the first is stepped (and so loaded
    // back) while the twin is loaded back by its own steps later.
    assert_eq!(
        manager.evict_idle(std::time::Duration::ZERO),
        12,
        "all evicted"
    );
    let loaded = step(&evicted.id, false);
    same(&loaded, &step(&twin.id, false), "loaded back");
    assert_eq!(
        manager.evict_idle(std::time::Duration::ZERO),
        12,
        "evicted again"
    );
    for _ in 0..3 {
        same(
            &step(&evicted.id, false),
            &step(&twin.id, false),
            "after a reload",
        );
    }
    // One member deleted alone: refused by the group step, the rest step.
    let gone = evicted.members[2].as_deref().expect("member");
    rt.block_on(manager.delete(Caller::Anyone, gone))
        .expect("delete");
    let after = step(&evicted.id, false);
    let twin_after = step(&twin.id, false);
    for (i, (x, y)) in after.iter().zip(&twin_after).enumerate() {
        if i == 2 {
            let e = x
                .result
                .as_ref()
                .expect_err("the deleted member is refused");
            assert!(e.to_string().contains(gone), "{e}");
        } else {
            let (x, y) = (
                x.result.as_ref().expect("step"),
                y.result.as_ref().expect("step"),
            );
            assert_eq!(x.tick, y.tick);
            assert_bits_eq(&x.drive, &y.drive, "beside a deleted member");
        }
    }
    manager.shutdown();
}

/// A crash (the store stopped as `kill -9` leaves its files) with group
/// steps still in the write-ahead log, none applied to the database: each
/// member comes back as it stood, its history too, though its entries were
/// written as a step's batch; a member observed alone between two steps
/// (its write sends the batch holding its previous entry first) and a
/// member deleted after them come back as such.
#[test]
fn group_steps_left_in_the_log_by_a_crash_are_recovered_member_by_member() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let data = tempfile::tempdir().expect("data dir");
    let open = || durable_manager(data.path(), 1);
    let (manager, store) = open();
    let group = manager
        .create_group(
            Caller::Anyone,
            serde_json::from_value::<CreateGroup>(
                json!({"model": {"preset": "hallway"}, "n": 6, "seed": 5}),
            )
            .expect("body"),
        )
        .expect("create");
    let members: Vec<String> = group.members.iter().flatten().cloned().collect();
    let step = |manager: &Arc<SessionManager>, t: usize| {
        let steps = rt
            .block_on(manager.step_group(
                Caller::Anyone,
                &group.id,
                Columns {
                    states: (0..6).map(|i| ((t + i) % 40) as u32).collect(),
                    stimuli: if t == 0 {
                        Vec::new()
                    } else {
                        (0..12).map(|k| ((t * 12 + k) % 7) as f64 * 0.25).collect()
                    },
                    ..Columns::default()
                },
            ))
            .expect("step");
        assert!(steps.iter().all(|m| m.result.is_ok()), "step {t}");
    };
    for t in 0..8 {
        step(&manager, t);
    }
    let alone = ObservationIn {
        state: Some(24),
        observation: None,
        stimulus: Some(vec![1.0, 0.5]),
        action_taken: None,
        signal: None,
        signal_source: None,
        seq: None,
    };
    rt.block_on(manager.observe(Caller::Anyone, &members[1], vec![alone]))
        .expect("member 1 alone");
    for t in 8..11 {
        step(&manager, t);
    }
    rt.block_on(manager.delete(Caller::Anyone, &members[2]))
        .expect("delete member 2");
    let state = |manager: &Arc<SessionManager>, id: &str| {
        let info = manager.get(Caller::Anyone, id).expect("member");
        let history = manager
            .history(Caller::Anyone, id, None)
            .expect("history")
            .value;
        (
            info.tick,
            info.drive,
            serde_json::to_value(history).expect("json"),
        )
    };
    let before: Vec<_> = members
        .iter()
        .map(|m| (m != &members[2]).then(|| state(&manager, m)))
        .collect();
    store.crash();
    drop(manager);
    drop(store);

    let (manager, _store) = open();
    for (i, (m, want)) in members.iter().zip(before).enumerate() {
        let Some((tick, drive, history)) = want else {
            assert!(
                manager.get(Caller::Anyone, m).is_err(),
                "member {i} stays deleted"
            );
            continue;
        };
        let got = state(&manager, m);
        assert_eq!(got.0, tick, "member {i}: tick");
        assert_eq!(got.0, if i == 1 { 11 } else { 10 }, "member {i}: tick");
        assert_bits_eq(&got.1, &drive, "drive");
        assert_eq!(got.2, history, "member {i}: history");
    }
    manager.shutdown();
}

/// Server time per member-observation on the group path against the
/// per-session path, in this process (no transport), in memory and on a
/// durable store: `cargo test -p mcapi-server --test api groups::measure --
/// --ignored --nocapture`.
#[test]
#[ignore = "a measurement, not a check"]
fn measure_group_steps_against_single_observations() {
    let (group_us, single_us) = measure(
        &Arc::new(SessionManager::new(Limits::default(), 2).expect("manager")),
        1000,
        200,
    );
    eprintln!(
        "1000 hallway members x 200 ticks, lockstep, in memory: {group_us:.2} µs per member-observation by group steps, {single_us:.2} µs by single observations"
    );
    let data = tempfile::tempdir().expect("data dir");
    let (manager, _) = durable_manager(data.path(), 2);
    let (group_us, single_us) = measure(&manager, 200, 10);
    eprintln!(
        "200 hallway members x 10 ticks, lockstep, durable store (fsync): {group_us:.2} µs per member-observation by group steps, {single_us:.2} µs by single observations"
    );
}

/// (group, single) µs per member-observation of `n` hallway members
/// stepped `ticks` times each way.
fn measure(manager: &Arc<SessionManager>, n: usize, ticks: usize) -> (f64, f64) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let group = manager
        .create_group(
            Caller::Anyone,
            serde_json::from_value::<CreateGroup>(
                json!({"model": {"preset": "hallway"}, "n": n, "seed": 1}),
            )
            .expect("body"),
        )
        .expect("create");
    let members: Vec<String> = group.members.iter().flatten().cloned().collect();
    let mut states = vec![25u32; n];
    let started = std::time::Instant::now();
    for t in 0..ticks {
        let steps = rt
            .block_on(manager.step_group(
                Caller::Anyone,
                &group.id,
                Columns {
                    states: states.clone(),
                    stimuli: if t == 0 { Vec::new() } else { vec![0.0; 2 * n] },
                    ..Columns::default()
                },
            ))
            .expect("step");
        for (s, m) in states.iter_mut().zip(steps) {
            let a = m.result.expect("applied").action_index;
            *s = u32::try_from(moved(u64::from(*s), a as u64)).expect("state");
        }
    }
    let group_us = started.elapsed().as_secs_f64() * 1e6 / (n * ticks) as f64;
    let started = std::time::Instant::now();
    for _ in 0..ticks {
        for (k, id) in members.iter().enumerate() {
            let obs = mcapi_server::service::ObservationIn {
                state: Some(states[k] as usize),
                observation: None,
                stimulus: Some(vec![0.0, 0.0]),
                action_taken: None,
                signal: None,
                signal_source: None,
                seq: None,
            };
            let step = rt
                .block_on(manager.observe(Caller::Anyone, id, vec![obs]))
                .expect("observe");
            states[k] = u32::try_from(moved(u64::from(states[k]), step[0].action_index as u64))
                .expect("state");
        }
    }
    let single_us = started.elapsed().as_secs_f64() * 1e6 / (n * ticks) as f64;
    manager.shutdown();
    (group_us, single_us)
}

#[test]
fn a_step_beyond_the_batch_time_budget_is_refused_whole() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let manager = Arc::new(
        SessionManager::new(
            Limits {
                max_batch_ms: 0,
                ..Limits::default()
            },
            1,
        )
        .expect("manager"),
    );
    let group = manager
        .create_group(
            Caller::Anyone,
            serde_json::from_value::<CreateGroup>(
                json!({"model": {"preset": "hallway"}, "n": 1000, "seed": 1}),
            )
            .expect("body"),
        )
        .expect("create");
    let step = |mask: Vec<u32>| {
        let m = if mask.is_empty() { 1000 } else { mask.len() };
        rt.block_on(manager.step_group(
            Caller::Anyone,
            &group.id,
            Columns {
                mask,
                states: vec![25; m],
                ..Columns::default()
            },
        ))
    };
    // At least 1 µs each: 1000 members cost at least 1 ms.
    let e = step(Vec::new()).expect_err("over the budget");
    assert!(
        matches!(&e, mcapi_server::service::ServiceError::LimitExceeded(m) if m.contains("--max-batch-ms")),
        "{e}"
    );
    for m in group.members.iter().flatten() {
        let info = manager.get(Caller::Anyone, m).expect("member");
        assert_eq!(info.state, None, "nothing applied");
    }
    // A mask of a few fits.
    let steps = step(vec![0, 1, 2]).expect("three members");
    assert!(steps.iter().all(|s| s.result.is_ok()));
    manager.shutdown();
}

/// The member ids and index of each member's refusal in a REST reply.
fn refusals(reply: &Value) -> Vec<(u64, &str)> {
    reply["errors"]
        .as_array()
        .expect("errors")
        .iter()
        .map(|e| {
            (
                e["index"].as_u64().expect("index"),
                e["code"].as_str().expect("code"),
            )
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resent_rest_group_step_with_its_seqs_is_replayed_and_a_refused_seq_refuses_its_member_only()
 {
    let base = start(Limits::default()).await;
    let (status, group) = post(
        &format!("{base}/v1/groups"),
        &json!({"model": {"preset": "hallway"}, "agent": {"history": 2}, "n": 3, "seed": 5}),
    )
    .await;
    assert_eq!(status, 201, "{group}");
    let id = group["id"].as_str().expect("id");
    let members: Vec<String> = group["members"]
        .as_array()
        .expect("members")
        .iter()
        .map(|m| m.as_str().expect("an id").to_string())
        .collect();
    let url = format!("{base}/v1/groups/{id}/steps");
    let zeros = json!([[0, 0], [0, 0], [0, 0]]);
    // Without seqs: no `replayed` column (at least once, as before).
    let (status, first) = post(&url, &json!({"states": [25, 25, 25]})).await;
    assert_eq!(status, 200, "{first}");
    assert!(first.get("replayed").is_none(), "{first}");
    let step = json!({"states": [24, 26, 25], "stimuli": zeros, "seqs": [1, 1, 1]});
    let (status, applied) = post(&url, &step).await;
    assert_eq!(status, 200, "{applied}");
    assert_eq!(applied["replayed"], json!([false, false, false]));
    assert_eq!(applied["ticks"], json!([1, 1, 1]));
    // The same step again: every member replayed, bit for bit, nothing applied.
    let (status, again) = post(&url, &step).await;
    assert_eq!(status, 200, "{again}");
    assert_eq!(again["replayed"], json!([true, true, true]));
    assert_eq!(again["errors"], json!([]));
    for column in ["actions", "ticks", "policy_versions"] {
        assert_eq!(again[column], applied[column], "{column}");
    }
    for j in 0..3 {
        assert_bits_eq(
            &floats(&again["drives"][j]),
            &floats(&applied["drives"][j]),
            "drive",
        );
    }
    assert_bits_eq(
        &floats(&again["rewards"]),
        &floats(&applied["rewards"]),
        "rewards",
    );
    for m in &members {
        let (status, info) = call(
            reqwest::Method::GET,
            &format!("{base}/v1/sessions/{m}"),
            None,
        )
        .await;
        assert_eq!((status, &info["tick"]), (200, &json!(1)), "{info}");
    }
    // Member 0 applies seq 2; member 1 resends seq 1 with another state
    // (a conflict), member 2 skips ahead (a gap): refused alone, with the
    // codes and details of a lone observation.
    let (status, mixed) = post(
        &url,
        &json!({"states": [23, 27, 25], "stimuli": zeros, "seqs": [2, 1, 4]}),
    )
    .await;
    assert_eq!(status, 200, "{mixed}");
    assert_eq!(refusals(&mixed), [(1, "seq_conflict"), (2, "seq_gap")]);
    assert_eq!(mixed["errors"][1]["expected_seq"], 2, "{mixed}");
    assert_eq!(mixed["ticks"], json!([2, null, null]));
    assert_eq!(mixed["actions"][1], Value::Null);
    assert_eq!(mixed["replayed"], json!([false, false, false]));
    // Absurd seqs are gaps: u64::MAX, and one far ahead on a masked member.
    let (status, far) = post(
        &url,
        &json!({"mask": [1, 2], "states": [27, 25], "stimuli": [[0, 0], [0, 0]],
                "seqs": [18_446_744_073_709_551_615u64, 1_000_000_000_000u64]}),
    )
    .await;
    assert_eq!(status, 200, "{far}");
    assert_eq!(refusals(&far), [(1, "seq_gap"), (2, "seq_gap")]);
    assert_eq!(far["errors"][0]["expected_seq"], 2);
    assert_eq!(far["ticks"], json!([null, null]));
    // Beyond the window (history 2): member 0 has applied seqs 0..=3 now.
    let (status, reply) = post(
        &url,
        &json!({"mask": [0], "states": [22], "stimuli": [[0, 0]], "seqs": [3]}),
    )
    .await;
    assert_eq!(
        (status, &reply["replayed"]),
        (200, &json!([false])),
        "{reply}"
    );
    let (status, expired) = post(
        &url,
        &json!({"mask": [0], "states": [25], "stimuli": [[0, 0]], "seqs": [0]}),
    )
    .await;
    assert_eq!(status, 200, "{expired}");
    assert_eq!(refusals(&expired), [(0, "seq_expired")]);
    assert_eq!(expired["errors"][0]["oldest_seq"], 2, "{expired}");
    // A `seqs` column of the wrong length, or not of u64s: the step refused whole.
    for (body, code, needle) in [
        (
            json!({"states": [25, 25, 25], "stimuli": zeros, "seqs": [2, 2]}),
            "column_length",
            "`seqs` has 2 entries; 3 expected (one per member stepped: 3)",
        ),
        (
            json!({"mask": [2], "states": [25], "stimuli": [[0, 0]], "seqs": [2, 2, 2]}),
            "column_length",
            "`seqs` has 3 entries; 1 expected",
        ),
        (
            json!({"states": [25, 25, 25], "stimuli": zeros, "seqs": [2, -1, 2]}),
            "bad_request",
            "seqs",
        ),
        (
            json!({"states": [25, 25, 25], "stimuli": zeros, "seqs": [2, 2, 18_446_744_073_709_551_616.0]}),
            "bad_request",
            "seqs",
        ),
    ] {
        let (status, err) = post(&url, &body).await;
        assert_eq!(
            (status, err["code"].as_str()),
            (400, Some(code)),
            "{body}: {err}"
        );
        assert!(
            err["message"].as_str().expect("message").contains(needle),
            "{body}: {err}"
        );
    }
    // Nothing of the refused steps was applied.
    for (m, tick) in members.iter().zip([3, 1, 1]) {
        let (_, info) = call(
            reqwest::Method::GET,
            &format!("{base}/v1/sessions/{m}"),
            None,
        )
        .await;
        assert_eq!(info["tick"], tick, "{m}: {info}");
    }
}
