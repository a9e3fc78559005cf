//! A served session (its GET body, Ξ table and history) checked bit for
//! bit against a replayed core agent.

use mcapi_core::{Agent, AgentParams};
use serde_json::Value;

use crate::floats::{assert_bits_eq, floats};
use crate::hallway::Obs;
use crate::replay::{Expected, replay};
use crate::reply::Reply;
use crate::rest::{rest, rest_get};

/// Checks a session's GET body, its Ξ table (`values?include=xi`) and its
/// history against a replayed core agent, bit for bit.
pub fn assert_session_matches(
    agent: &Agent,
    expected_history: &[Expected],
    info: &Value,
    values: &Value,
    history: &Value,
    ctx: &str,
) {
    assert_eq!(info["tick"].as_u64(), Some(agent.tick()), "{ctx}: tick");
    assert_eq!(values["tick"].as_u64(), Some(agent.tick()), "{ctx}: tick");
    assert_eq!(
        info["state"].as_u64().map(|s| s as usize),
        agent.state(),
        "{ctx}: state"
    );
    assert_bits_eq(
        &floats(&info["drive"]),
        agent.drive().vector(),
        &format!("{ctx}: D"),
    );
    assert_eq!(
        info["stats"]["lambda1_estimate"].as_f64().map(f64::to_bits),
        Some(agent.drive().lambda1_estimate().to_bits()),
        "{ctx}: λ₁ estimate (D's running second moment)"
    );
    let constant: Vec<usize> = info["stats"]["constant_stimuli"]
        .as_array()
        .expect("constant_stimuli")
        .iter()
        .map(|v| v.as_u64().expect("index") as usize)
        .collect();
    assert_eq!(
        constant,
        agent.stimulus().constant_columns(),
        "{ctx}: constant stimuli"
    );
    match agent.learned() {
        Some(l) => assert_eq!(
            values["known_fraction"].as_f64().map(f64::to_bits),
            Some(l.known_fraction().to_bits()),
            "{ctx}: known fraction of the learned model"
        ),
        None => assert!(
            values.get("known_fraction").is_none(),
            "{ctx}: a session with posted transitions has no known fraction: {values}"
        ),
    }
    let model = agent.planning_model().model();
    let xi = values["xi"].as_array().expect("xi");
    assert_eq!(xi.len(), model.states(), "{ctx}: Ξ rows");
    for (s, row) in xi.iter().enumerate() {
        let row = row.as_array().expect("Ξ row");
        assert_eq!(row.len(), model.n_actions(), "{ctx}: Ξ[{s}]");
        for (a, cell) in row.iter().enumerate() {
            match model.pair(s, a) {
                None => assert!(cell.is_null(), "{ctx}: Ξ[{s}][{a}] should be null"),
                Some(p) => assert_bits_eq(
                    &floats(cell),
                    agent.stimulus().row(p),
                    &format!("{ctx}: Ξ[{s}][{a}]"),
                ),
            }
        }
    }
    let history = history.as_array().expect("history");
    let keep = expected_history
        .len()
        .min(mcapi_server::service::agent_config::DEFAULT_HISTORY);
    let want = &expected_history[expected_history.len() - keep..];
    assert_eq!(history.len(), want.len(), "{ctx}: history length");
    for (got, want) in history.iter().zip(want) {
        let t = want.tick;
        assert_eq!(got["tick"].as_u64(), Some(t), "{ctx}: history tick");
        assert_eq!(
            got["state"].as_u64(),
            Some(want.state as u64),
            "{ctx}: history state at tick {t}"
        );
        assert_bits_eq(
            &floats(&got["drive"]),
            &want.drive,
            &format!("{ctx}: history drive at tick {t}"),
        );
        assert_eq!(
            got["reward"].as_f64().map(f64::to_bits),
            Some(want.reward.to_bits()),
            "{ctx}: history reward at tick {t}"
        );
        assert_eq!(
            got["known_fraction"].as_f64().map(f64::to_bits),
            want.known_fraction.map(f64::to_bits),
            "{ctx}: history known fraction at tick {t}"
        );
        if let Some(a) = want.action {
            assert_eq!(
                got["action"].as_u64(),
                Some(a as u64),
                "{ctx}: history action at tick {t}"
            );
        }
    }
}

/// GETs a session, its Ξ table and its history and checks them against a
/// replay of `applied`.
pub async fn check_session(
    client: &reqwest::Client,
    base: &str,
    key: Option<&str>,
    id: &str,
    params: &AgentParams,
    applied: &[(Obs, Option<Reply>)],
    ctx: &str,
) {
    let (agent, expected) = replay(params, applied, ctx);
    check_replayed(client, base, key, id, &agent, &expected, ctx).await;
}

/// GETs a session, its Ξ table and its history and checks them against an
/// agent that replayed its observations (and the history it gave).
pub async fn check_replayed(
    client: &reqwest::Client,
    base: &str,
    key: Option<&str>,
    id: &str,
    agent: &Agent,
    expected: &[Expected],
    ctx: &str,
) {
    let (status, info) = rest_get(client, base, key, id).await;
    assert_eq!(status, 200, "{ctx}: get: {info}");
    let (status, values) = rest(
        client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{id}/values?include=xi"),
        key,
        None,
    )
    .await;
    assert_eq!(status, 200, "{ctx}: values: {values}");
    let (status, history) = rest(
        client,
        reqwest::Method::GET,
        &format!("{base}/v1/sessions/{id}/history"),
        key,
        None,
    )
    .await;
    assert_eq!(status, 200, "{ctx}: history: {history}");
    assert_session_matches(agent, expected, &info, &values, &history, ctx);
}
