//! REST: one request through the real router, the checks every response
//! must pass, and the fuzzing of the create and observe routes.

use std::time::Instant;

use axum::body::Body;
use axum::http::Request;
use http_body_util::BodyExt;
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;
use serde_json::{Value, json};
use tower::ServiceExt;

use super::{
    DEFAULT_CASES, case_limit, cases, check_rss, count, env, one_at_a_time, rss_mib, runner,
    summary,
};
use crate::json::{body, create_bases, observe_bases};

pub(crate) async fn rest_call(
    app: &axum::Router,
    method: &str,
    uri: &str,
    body: Vec<u8>,
) -> (u16, Value) {
    let req = Request::builder()
        .method(method)
        .uri(uri)
        .header("content-type", "application/json")
        .body(Body::from(body))
        .expect("request");
    let resp = app
        .clone()
        .oneshot(req)
        .await
        .expect("the router is infallible");
    let status = resp.status().as_u16();
    let bytes = resp.into_body().collect().await.expect("body").to_bytes();
    let value = if bytes.is_empty() {
        Value::Null
    } else {
        serde_json::from_slice(&bytes)
            .unwrap_or_else(|_| Value::String(String::from_utf8_lossy(&bytes).into_owned()))
    };
    (status, value)
}

/// The response contract: no server error but 503, errors `{"code","message"}`
/// (`seq_gap` adds `expected_seq`, `seq_expired` `oldest_seq`, a number each).
pub(crate) fn check_response(
    what: &str,
    input: &[u8],
    status: u16,
    body: &Value,
) -> Result<(), TestCaseError> {
    let shown = || String::from_utf8_lossy(&input[..input.len().min(600)]).into_owned();
    prop_assert!(
        status < 500 || status == 503,
        "{what}: {status} {body} for input {}",
        shown()
    );
    if status >= 400 {
        let obj = body.as_object();
        let detail = match body["code"].as_str() {
            Some("seq_gap") => Some("expected_seq"),
            Some("seq_expired") => Some("oldest_seq"),
            _ => None,
        };
        prop_assert!(
            obj.is_some_and(|o| {
                o["code"].is_string()
                    && o["message"].is_string()
                    && match detail {
                        None => o.len() == 2,
                        Some(d) => o.len() == 3 && o[d].is_u64(),
                    }
            }),
            "{what}: error body {body} is not {{\"code\",\"message\"}} (input {})",
            shown()
        );
    }
    Ok(())
}

/// Sends a create body; an accepted session takes two observations and is
/// deleted.
fn fuzz_create(body: Vec<u8>) -> Result<(), TestCaseError> {
    let e = env();
    let started = Instant::now();
    let (status, info) =
        e.rt.block_on(rest_call(&e.rest, "POST", "/v1/sessions", body.clone()));
    count(format!(
        "create {status} {}",
        info["code"].as_str().unwrap_or("")
    ));
    check_response("POST /v1/sessions", &body, status, &info)?;
    if status == 201 {
        let id = info["id"].as_str().unwrap_or_default().to_string();
        let states = info["model"]["states"].as_u64().unwrap_or(1);
        let curious = info["agent"]["curiosity"].is_object();
        let stimuli = info["model"]["stimuli"]
            .as_array()
            .map_or(0, Vec::len)
            .saturating_sub(usize::from(curious));
        let uri = format!("/v1/sessions/{id}/observations");
        // A continuous world's session takes vectors in its box.
        let dim = info["model"]["continuous"]["observation_space"]["low"]
            .as_array()
            .map(Vec::len);
        let firsts = match dim {
            Some(d) => [
                json!({"observation": vec![0.0; d]}),
                json!({"observation": vec![0.5; d], "stimulus": vec![1.5; stimuli]}),
            ],
            None => [
                json!({"state": 0}),
                json!({"state": states.saturating_sub(1), "stimulus": vec![1.5; stimuli]}),
            ],
        };
        for obs in firsts {
            let bytes = obs.to_string().into_bytes();
            let (status, reply) = e.rt.block_on(rest_call(&e.rest, "POST", &uri, bytes));
            check_response(
                &format!("an observation {obs} on a session created from"),
                &body,
                status,
                &reply,
            )?;
        }
        let (status, reply) = e.rt.block_on(rest_call(
            &e.rest,
            "DELETE",
            &format!("/v1/sessions/{id}"),
            Vec::new(),
        ));
        prop_assert_eq!(status, 204, "{}", reply);
    }
    prop_assert!(
        started.elapsed() < case_limit(),
        "a create took {:?}: {}",
        started.elapsed(),
        String::from_utf8_lossy(&body[..body.len().min(600)])
    );
    check_rss()
}

fn fuzz_observe(session: usize, body: Vec<u8>) -> Result<(), TestCaseError> {
    let e = env();
    let (id, _, _) = &e.sessions[session % e.sessions.len()];
    let started = Instant::now();
    let uri = format!("/v1/sessions/{id}/observations");
    let (status, reply) =
        e.rt.block_on(rest_call(&e.rest, "POST", &uri, body.clone()));
    count(format!(
        "observe {status} {}",
        reply["code"].as_str().unwrap_or("")
    ));
    check_response(&format!("POST {uri}"), &body, status, &reply)?;
    prop_assert!(
        started.elapsed() < case_limit(),
        "an observation took {:?}",
        started.elapsed()
    );
    check_rss()
}

#[test]
fn rest_create_survives_arbitrary_bodies() {
    let _serial = one_at_a_time();
    let started = Instant::now();
    let mut runner = runner(DEFAULT_CASES);
    let result = runner.run(&body(create_bases()), fuzz_create);
    eprintln!(
        "rest create: {} cases in {:.1?} (RSS {} MiB)",
        cases(DEFAULT_CASES),
        started.elapsed(),
        rss_mib()
    );
    eprintln!("responses so far: {}", summary());
    if let Err(e) = result {
        panic!("{e}");
    }
}

#[test]
fn rest_observe_survives_arbitrary_bodies() {
    let _serial = one_at_a_time();
    let started = Instant::now();
    let mut runner = runner(DEFAULT_CASES);
    let result = runner.run(&(0usize..5, body(observe_bases())), |(s, b)| {
        fuzz_observe(s, b)
    });
    eprintln!(
        "rest observe: {} cases in {:.1?} (RSS {} MiB)",
        cases(DEFAULT_CASES),
        started.elapsed(),
        rss_mib()
    );
    eprintln!("responses so far: {}", summary());
    if let Err(e) = result {
        panic!("{e}");
    }
}
