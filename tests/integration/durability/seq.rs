//! Exactly-once delivery on the real binary (docs/sessions.md, "Delivery
//! guarantees"): observations sent with `seq`, then the server killed with
//! kill -9 (or the session evicted from memory): the last seqs sent again
//! are answered with the replies they got the first time, byte for byte but
//! for `"replayed": true`, the session's tick does not move, and the next
//! seq applies.

use crate::common;

use common::{Launch, Server, http_client, rest, rest_create};
use reqwest::Method;
use serde_json::{Value, json};

use super::{log_path, logs};

/// The hallway's stimulus in state `s`: food at 10, rest at 40.
fn stimulus(s: usize) -> [f64; 2] {
    match s {
        10 => [6.0, 0.0],
        40 => [0.0, 6.0],
        _ => [0.0, 0.0],
    }
}

fn next_state(s: usize, a: u64) -> usize {
    match a {
        0 => s.saturating_sub(1),
        1 => (s + 1).min(49),
        _ => s,
    }
}

/// Sends seqs `0..n` and returns each body sent with its reply's text.
async fn send(client: &reqwest::Client, url: &str, n: u64) -> Vec<(Value, String)> {
    let mut state = 25;
    let mut sent = Vec::new();
    for seq in 0..n {
        let body = if seq == 0 {
            json!({"state": state, "seq": seq})
        } else {
            json!({"state": state, "stimulus": stimulus(state), "seq": seq})
        };
        let resp = client.post(url).json(&body).send().await.expect("observe");
        assert_eq!(resp.status().as_u16(), 200, "seq {seq}");
        let text = resp.text().await.expect("body");
        let step: Value = serde_json::from_str(&text).expect("json");
        state = next_state(state, step["action_index"].as_u64().expect("action"));
        sent.push((body, text));
    }
    sent
}

/// Sends `seqs` of `sent` again: each must come back as it was, marked
/// replayed.
async fn resend(client: &reqwest::Client, url: &str, sent: &[(Value, String)], when: &str) {
    for (seq, (body, first)) in sent.iter().enumerate().rev().take(5) {
        let resp = client.post(url).json(body).send().await.expect("observe");
        assert_eq!(resp.status().as_u16(), 200, "{when}: seq {seq}");
        let again = resp.text().await.expect("body");
        assert!(
            again.contains(r#""replayed":true"#),
            "{when}: seq {seq}: {again}"
        );
        assert_eq!(
            &again.replace(r#","replayed":true"#, ""),
            first,
            "{when}: seq {seq} replayed"
        );
    }
}

async fn tick_and_next(client: &reqwest::Client, base: &str, id: &str) -> (Value, Value) {
    let (status, info) = rest(
        client,
        Method::GET,
        &format!("{base}/v1/sessions/{id}"),
        None,
        None,
    )
    .await;
    assert_eq!(status, 200, "{info}");
    (info["tick"].clone(), info["next_seq"].clone())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_seq_resent_after_kill_9_is_replayed_and_applies_nothing() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    // A snapshot in the middle: the window comes back from the snapshot's
    // ring and from the log after it.
    let launch = Launch::new(data.path(), &["--snapshot-every", "25"]);
    let mut server = Server::start(&launch, log_path(&logs, "first")).await;
    let client = http_client();
    let id = rest_create(
        &client,
        &server.base(),
        None,
        json!({"seed": 33, "epsilon": 0.2}),
    )
    .await;
    let url = |base: &str| format!("{base}/v1/sessions/{id}/observations");
    let sent = send(&client, &url(&server.base()), 40).await;
    server.kill9();

    let mut server = Server::start(&launch, log_path(&logs, "second")).await;
    let base = server.base();
    resend(&client, &url(&base), &sent, "after kill -9").await;
    assert_eq!(
        tick_and_next(&client, &base, &id).await,
        (json!(39), json!(40)),
        "replays applied nothing"
    );
    // A changed resend conflicts; the next seq applies.
    let mut other = sent[39].0.clone();
    other["stimulus"] = json!([6.0, 6.0]);
    let (status, body) = rest(&client, Method::POST, &url(&base), None, Some(&other)).await;
    assert_eq!(
        (status, body["code"].as_str()),
        (409, Some("seq_conflict")),
        "{body}"
    );
    let (status, body) = rest(
        &client,
        Method::POST,
        &url(&base),
        None,
        Some(&json!({"state": 3, "stimulus": [0, 0], "seq": 41})),
    )
    .await;
    assert_eq!(
        (status, body["expected_seq"].clone()),
        (409, json!(40)),
        "{body}"
    );
    assert!(server.terminate().success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_seq_resent_to_an_evicted_session_is_replayed() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    let launch = Launch::new(data.path(), &["--evict-idle-secs", "1"]);
    let mut server = Server::start(&launch, log_path(&logs, "evicting")).await;
    let client = http_client();
    let base = server.base();
    let id = rest_create(&client, &base, None, json!({"seed": 34})).await;
    let url = format!("{base}/v1/sessions/{id}/observations");
    let sent = send(&client, &url, 30).await;
    // Wait until it has left memory (the gauge of evicted sessions).
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    loop {
        let metrics = client
            .get(format!("{base}/metrics"))
            .send()
            .await
            .expect("metrics")
            .text()
            .await
            .expect("text");
        if metrics
            .lines()
            .any(|l| l.starts_with("mcapi_sessions_evicted ") && !l.ends_with(" 0"))
        {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "not evicted within 20 s"
        );
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    }
    resend(&client, &url, &sent, "evicted").await;
    assert_eq!(
        tick_and_next(&client, &base, &id).await,
        (json!(29), json!(30))
    );
    assert!(server.terminate().success());
}
