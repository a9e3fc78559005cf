//! Continuous worlds over REST in process: a session created with an
//! observation space and driven with vectors, and every absurd or malformed
//! continuous model and observation refused with its exact status, code and
//! message, the server serving on after each.

use mcapi_server::service::Limits;
use serde_json::{Value, json};

async fn start(limits: Limits) -> String {
    let (_, addr) = crate::serve_rest(limits).await;
    format!("http://{addr}")
}

async fn call(
    client: &reqwest::Client,
    method: &str,
    url: &str,
    body: Option<&Value>,
) -> (u16, Value) {
    let req = match method {
        "POST" => client.post(url),
        _ => client.get(url),
    };
    let req = match body {
        Some(b) => req.json(b),
        None => req,
    };
    let resp = req.send().await.expect("request");
    let status = resp.status().as_u16();
    (status, resp.json().await.unwrap_or(Value::Null))
}

fn square(extra: Value) -> Value {
    let mut model = json!({"observation_space": {"low": [0, 0], "high": [1, 1]},
                           "actions": ["n", "s", "e", "w"], "stimuli": ["food", "rest"]});
    if let (Some(m), Some(e)) = (model.as_object_mut(), extra.as_object()) {
        for (k, v) in e {
            m.insert(k.clone(), v.clone());
        }
    }
    model
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_continuous_session_is_driven_with_vectors() {
    let base = start(Limits::default()).await;
    let client = reqwest::Client::new();
    let (status, info) = call(
        &client,
        "POST",
        &format!("{base}/v1/sessions"),
        Some(&json!({"model": square(json!({"out_of_bounds": "clip"})), "agent": {"seed": 4}})),
    )
    .await;
    assert_eq!(status, 201, "{info}");
    // The default basis for d = 2 is shown in the summary, as built: the
    // grid of 64 × 64 cells.
    assert_eq!(
        info["model"]["continuous"]["basis"],
        json!({"kind": "grid", "cells_per_dim": 64}),
        "{info}"
    );
    assert_eq!(info["model"]["basis"]["k"], 4096, "{info}");
    assert_eq!(info["model"]["states"], 0);
    assert!(
        info["cost"]["bytes"].as_u64().unwrap_or(0) > 100_000,
        "{info}"
    );
    let id = info["id"].as_str().expect("id");
    let url = format!("{base}/v1/sessions/{id}/observations");
    let mut x = [0.5f64, 0.5];
    let (status, mut step) = call(&client, "POST", &url, Some(&json!({"observation": x}))).await;
    assert_eq!(status, 200, "{step}");
    for t in 0..120 {
        let a = step["action_index"].as_u64().expect("action") as usize;
        let (dx, dy) = [(0.0, 0.05), (0.0, -0.05), (0.05, 0.0), (-0.05, 0.0)][a];
        // Now and then a step out of the box, clipped.
        let out = if t % 40 == 39 { 2.0 } else { 0.0 };
        x = [
            (x[0] + dx).clamp(0.0, 1.0) + out,
            (x[1] + dy).clamp(0.0, 1.0),
        ];
        let stimulus = [
            f64::from(u8::from(x[0] < 0.2)),
            f64::from(u8::from(x[0] > 0.8)),
        ];
        let (status, reply) = call(
            &client,
            "POST",
            &url,
            Some(&json!({"observation": x, "stimulus": stimulus})),
        )
        .await;
        assert_eq!(status, 200, "{reply}");
        assert_eq!(reply["tick"], json!(t + 1));
        let d: Vec<f64> = reply["drive"]
            .as_array()
            .expect("drive")
            .iter()
            .map(|v| v.as_f64().expect("number"))
            .collect();
        assert!(
            (d.iter().map(|v| v * v).sum::<f64>().sqrt() - 1.0).abs() < 1e-9,
            "|D| = 1"
        );
        x[0] = x[0].min(1.0);
        step = reply;
    }
    let (_, info) = call(&client, "GET", &format!("{base}/v1/sessions/{id}"), None).await;
    assert_eq!(info["tick"], 120);
    assert_eq!(info["stats"]["continuous"]["clipped"], 3, "{info}");
    assert!(
        info["stats"]["continuous"]["samples"].as_u64().unwrap_or(0) > 20,
        "{info}"
    );
    let (status, values) = call(
        &client,
        "GET",
        &format!("{base}/v1/sessions/{id}/values?include=all"),
        None,
    )
    .await;
    assert_eq!(status, 200, "{values}");
    let points = values["points"].as_array().expect("points");
    assert_eq!(points.len(), 31 * 31, "a grid over the box");
    assert_eq!(values["v"].as_array().map(Vec::len), Some(points.len()));
    assert_eq!(values["q"][0].as_array().map(Vec::len), Some(4));
    assert!(
        values.get("r").is_none() && values.get("xi").is_none(),
        "{values}"
    );
    assert!(
        values["v"]
            .as_array()
            .expect("v")
            .iter()
            .all(|v| v.as_f64().is_some_and(f64::is_finite))
    );
    // A batch, and the history's observations.
    let (status, reply) = call(
        &client,
        "POST",
        &url,
        Some(&json!({"observations": [
            {"observation": [0.1, 0.1], "stimulus": [1, 0]},
            {"observation": [0.1, 0.2], "stimulus": [1, 0], "action_taken": "w"}]})),
    )
    .await;
    assert_eq!(status, 200, "{reply}");
    assert_eq!(reply["steps"][1]["tick"], 122);
    let (_, history) = call(
        &client,
        "GET",
        &format!("{base}/v1/sessions/{id}/history?limit=2"),
        None,
    )
    .await;
    assert_eq!(history[0]["observation"], json!([0.1, 0.1]), "{history}");
    assert_eq!(history[1]["observation"], json!([0.1, 0.2]), "{history}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn absurd_continuous_models_and_observations_are_refused_precisely() {
    let base = start(Limits {
        max_body_bytes: 1 << 20,
        ..Limits::default()
    })
    .await;
    let client = reqwest::Client::new();
    let create = format!("{base}/v1/sessions");
    let far = vec![0.0; 65];
    let creates: Vec<(Value, u16, &str)> = vec![
        (
            json!({"observation_space": {"low": far, "high": vec![1.0; 65]},
                "actions": ["a"], "stimuli": ["x"]}),
            400,
            "dimension",
        ),
        (
            square(json!({"observation_space": {"low": [0, 1], "high": [1, 1]}})),
            400,
            "low",
        ),
        (
            square(json!({"observation_space": {"low": [0, 0], "high": [1]}})),
            400,
            "high",
        ),
        (
            square(json!({"observation_space": {"low": [], "high": []}})),
            400,
            "dimension",
        ),
        (
            square(json!({"observation_space": {"low": [0, -1e300], "high": [1, 1e300]}})),
            400,
            "1e12",
        ),
        (
            square(json!({"basis": {"kind": "fourier", "order": 1_000_000_000u64}})),
            400,
            "order",
        ),
        (
            square(json!({"basis": {"kind": "fourier", "order": 5, "max_coupling": 0}})),
            400,
            "max_coupling",
        ),
        (
            json!({"observation_space": {"low": vec![0.0; 8], "high": vec![1.0; 8]},
                "actions": ["a", "b"], "stimuli": ["x"],
                "basis": {"kind": "fourier", "order": 9}}),
            400,
            "features",
        ),
        (
            square(json!({"basis": {"kind": "rbf", "centres_per_dim": 4_000_000_000u64}})),
            400,
            "centres_per_dim",
        ),
        (
            square(json!({"basis": {"kind": "rbf", "centres_per_dim": 8, "width": 1e308}})),
            400,
            "width",
        ),
        (
            square(json!({"basis": {"kind": "tiles", "tilings": 1_000_000, "tiles_per_dim": 4}})),
            400,
            "tilings",
        ),
        (
            square(
                json!({"basis": {"kind": "tiles", "tilings": 4, "tiles_per_dim": 4, "table": 4_000_000_000u64}}),
            ),
            400,
            "table",
        ),
        (
            square(json!({"basis": {"kind": "pvf", "k": 4_000_000_000u64}})),
            400,
            "pvf `k`",
        ),
        (
            square(json!({"basis": {"kind": "pvf", "k": 8, "nodes": 4_000_000_000u64}})),
            400,
            "pvf `nodes`",
        ),
        (
            square(json!({"basis": {"kind": "pvf", "k": 8, "neighbours": 100_000}})),
            400,
            "pvf `neighbours`",
        ),
        (
            square(json!({"basis": {"kind": "pvf", "k": 64, "nodes": 10}})),
            400,
            "pvf `k`",
        ),
        (
            square(json!({"basis": {"kind": "proto_value", "k": 5}})),
            400,
            "unknown variant",
        ),
        (
            square(json!({"samples": {"max": 1_000_000_000u64}})),
            400,
            "samples.max",
        ),
        (
            square(json!({"samples": {"per_cell": 0}})),
            400,
            "samples.per_cell",
        ),
        (
            square(json!({"samples": {"cells_per_dim": 4_000_000_000u64}})),
            400,
            "samples.cells_per_dim",
        ),
        (
            square(json!({"samples": {"known_after": 4_000_000_000u64}})),
            400,
            "samples.known_after",
        ),
        (
            square(json!({"samples": {"max": -1}})),
            400,
            "invalid value",
        ),
        (
            square(json!({"actions": (0..65).map(|i| format!("a{i}")).collect::<Vec<_>>()})),
            400,
            "actions",
        ),
        (square(json!({"actions": ["n", "n"]})), 400, "twice"),
        (square(json!({"stimuli": []})), 400, "stimuli"),
        (square(json!({"stimuli": [""]})), 400, "empty name"),
        (square(json!({"actions": ["n", " "]})), 400, "empty name"),
        (
            square(json!({"stimuli": ["x".repeat(1000)]})),
            413,
            "length in bytes",
        ),
        (
            square(json!({"stimuli": (0..65).map(|i| format!("s{i}")).collect::<Vec<_>>()})),
            413,
            "--max-stimuli",
        ),
        (
            square(json!({"out_of_bounds": "wrap"})),
            400,
            "unknown variant",
        ),
        (
            square(json!({"transitions": "learn"})),
            400,
            "always learned",
        ),
        (square(json!({"grid": ["#a#"]})), 400, "unknown field"),
        // The grid: every count bounded before anything is allocated.
        (
            square(json!({"basis": {"kind": "grid", "cells_per_dim": 4_294_967_295u64}})),
            400,
            "`cells_per_dim` 4294967295",
        ),
        (
            square(json!({"basis": {"kind": "grid", "cells_per_dim": 65}})),
            400,
            "at most 4096 cells",
        ),
        (
            square(json!({"basis": {"kind": "grid", "cells_per_dim": 1}})),
            400,
            "`cells_per_dim` 1",
        ),
        (
            square(json!({"basis": {"kind": "grid", "cells_per_dim": 4_294_967_296u64}})),
            400,
            "expected u32",
        ),
        (
            square(json!({"basis": {"kind": "grid", "cells_per_dim": 64},
                          "actions": (0..5).map(|i| format!("a{i}")).collect::<Vec<_>>()})),
            400,
            "16384 (cell, action) pairs",
        ),
        (
            square(json!({"basis": {"kind": "grid", "cells_per_dim": 16, "neighbours": 0}})),
            400,
            "`neighbours` 0",
        ),
        (
            square(
                json!({"basis": {"kind": "grid", "cells_per_dim": 16, "neighbours": 1_000_000}}),
            ),
            400,
            "`neighbours` 1000000",
        ),
        (
            square(json!({"basis": {"kind": "grid", "cells_per_dim": 16, "reach": 1e308}})),
            400,
            "`reach`",
        ),
        (
            square(json!({"basis": {"kind": "grid", "cells_per_dim": 16, "reach": -1}})),
            400,
            "`reach`",
        ),
        (
            square(json!({"basis": {"kind": "grid", "cells_per_dim": 16, "width": 1}})),
            400,
            "unknown field",
        ),
        (
            json!({"observation_space": {"low": [0, 0, 0], "high": [1, 1, 1]},
                   "actions": ["n"], "stimuli": ["food"],
                   "basis": {"kind": "grid", "cells_per_dim": 17}}),
            400,
            "cells_per_dim^3",
        ),
    ];
    for (model, status, needle) in creates {
        let (got, reply) = call(&client, "POST", &create, Some(&json!({"model": model}))).await;
        assert_eq!(got, status, "{model}: {reply}");
        assert!(
            reply["message"]
                .as_str()
                .is_some_and(|m| m.contains(needle)),
            "{model}: `{needle}` not in {reply}"
        );
    }
    // A curiosity channel needs numbered states.
    let (got, reply) = call(
        &client,
        "POST",
        &create,
        Some(&json!({"model": square(json!({})), "agent": {"curiosity": {"signal_dim": 2}}})),
    )
    .await;
    assert_eq!(got, 400, "{reply}");
    assert!(
        reply["message"]
            .as_str()
            .is_some_and(|m| m.contains("continuous")),
        "{reply}"
    );

    let (got, info) = call(
        &client,
        "POST",
        &create,
        Some(&json!({"model": square(json!({"out_of_bounds": "refuse"}))})),
    )
    .await;
    assert_eq!(got, 201, "{info}");
    let id = info["id"].as_str().expect("id");
    let url = format!("{base}/v1/sessions/{id}/observations");
    let huge = vec![0.5; 100_000];
    let observations: Vec<(String, u16, &str)> = vec![
        (
            json!({"observation": [0.5]}).to_string(),
            400,
            "has 1 coordinates",
        ),
        (
            json!({"observation": huge}).to_string(),
            400,
            "has 100000 coordinates",
        ),
        (
            json!({"observation": [1.5, 0.5]}).to_string(),
            400,
            "invalid_observation",
        ),
        (json!({"observation": []}).to_string(), 400, "coordinates"),
        (
            "{\"observation\": [1e400, 0]}".to_string(),
            400,
            "malformed",
        ),
        (json!({"state": 3}).to_string(), 400, "continuous"),
        (
            json!({"state": 3, "observation": [0.5, 0.5]}).to_string(),
            400,
            "not both",
        ),
        (json!({}).to_string(), 400, "`observation`"),
        (
            json!({"observation": [0.5, 0.5], "signal": [1.0]}).to_string(),
            400,
            "curiosity",
        ),
        (json!({"observation": "near"}).to_string(), 400, "malformed"),
        (
            json!({"observation": [0.5, 0.5], "stimulus": [0, 1]}).to_string(),
            400,
            "first observation",
        ),
    ];
    for (body, status, needle) in observations {
        let resp = client
            .post(&url)
            .header("content-type", "application/json")
            .body(body.clone())
            .send()
            .await
            .expect("request");
        let got = resp.status().as_u16();
        let reply: Value = resp.json().await.unwrap_or(Value::Null);
        let short = &body[..body.len().min(80)];
        assert_eq!(got, status, "{short}: {reply}");
        assert!(
            reply.to_string().contains(needle),
            "{short}: `{needle}` not in {reply}"
        );
    }
    // Nothing was applied; a good observation still is.
    let (got, reply) = call(
        &client,
        "POST",
        &url,
        Some(&json!({"observation": [1.0, 0.0]})),
    )
    .await;
    assert_eq!(got, 200, "{reply}");
    assert_eq!(reply["tick"], 0);
    let (got, reply) = call(
        &client,
        "GET",
        &format!("{base}/v1/sessions/{id}/values?include=r"),
        None,
    )
    .await;
    assert_eq!(got, 400, "{reply}");
    // A model whose estimated tick is beyond the server's budget: 413.
    let tight = start(Limits {
        max_tick_us: 1_000,
        ..Limits::default()
    })
    .await;
    let (got, reply) = call(
        &client,
        "POST",
        &format!("{tight}/v1/sessions"),
        Some(&json!({"model": square(json!({"samples": {"max": 16384},
            "basis": {"kind": "rbf", "centres_per_dim": 8}}))})),
    )
    .await;
    assert_eq!(got, 413, "{reply}");
}
