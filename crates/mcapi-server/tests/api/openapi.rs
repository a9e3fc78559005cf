//! The OpenAPI document is exact (docs/rest.md): every operation is
//! tagged and documents its errors, the session routes are linked from
//! `POST /v1/sessions`, every bound the server enforces is in the schema
//! with the value of the limit it describes, and the body forms are
//! `oneOf`s. The server side of each bound (the contract's other half) is
//! exercised by schemathesis (`make contract`) and the fuzzer
//! (`crates/mcapi-server/tests/fuzz/`); here, three bodies the schema once
//! let through are sent through the real router.

use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use http_body_util::BodyExt;
use mcapi_server::api::openapi::document;
use mcapi_server::api::{AppState, router};
use mcapi_server::service::{Limits, MAX_PAGE, SessionManager};
use serde_json::{Value, json};
use tower::ServiceExt;

fn doc(limits: &Limits) -> Value {
    serde_json::to_value(document(limits)).expect("the document serialises")
}

fn schema<'a>(doc: &'a Value, name: &str) -> &'a Value {
    let s = &doc["components"]["schemas"][name];
    assert!(s.is_object(), "no schema `{name}`");
    s
}

const SESSION_ROUTES: [(&str, &str); 6] = [
    ("get", "/v1/sessions/{id}"),
    ("delete", "/v1/sessions/{id}"),
    ("post", "/v1/sessions/{id}/observations"),
    ("get", "/v1/sessions/{id}/values"),
    ("get", "/v1/sessions/{id}/history"),
    ("get", "/v1/sessions/{id}/events"),
];

#[test]
fn every_operation_is_tagged_and_documents_its_errors() {
    let d = doc(&Limits::default());
    let tags: Vec<&str> = d["tags"]
        .as_array()
        .expect("tags")
        .iter()
        .map(|t| t["name"].as_str().expect("tag name"))
        .collect();
    assert_eq!(
        tags,
        [
            "sessions",
            "observations",
            "inspection",
            "groups",
            "operations"
        ]
    );
    let mut operations = 0;
    for (path, item) in d["paths"].as_object().expect("paths") {
        for (method, op) in item.as_object().expect("path item") {
            operations += 1;
            let tag = op["tags"][0].as_str().expect("a tag");
            assert!(tags.contains(&tag), "{method} {path}: unknown tag {tag}");
            assert!(op["operationId"].is_string(), "{method} {path}");
            assert!(op["summary"].is_string(), "{method} {path}: a summary");
            let responses = op["responses"].as_object().expect("responses");
            if path.starts_with("/v1/") {
                for code in ["401", "503"] {
                    assert!(
                        responses.contains_key(code),
                        "{method} {path} does not document {code}"
                    );
                }
                if path.contains("{id}") {
                    assert!(responses.contains_key("404"), "{method} {path}: 404");
                    // A clustered replica refuses another replica's session.
                    assert!(responses.contains_key("421"), "{method} {path}: 421");
                }
                if op["parameters"]
                    .as_array()
                    .is_some_and(|p| p.iter().any(|p| p["in"] == "query"))
                    || op["requestBody"].is_object()
                {
                    assert!(responses.contains_key("400"), "{method} {path}: 400");
                }
                for (code, r) in responses {
                    if code.starts_with('4') || code.starts_with('5') {
                        let name = r["$ref"].as_str().expect("a reusable error response");
                        let name = name.trim_start_matches("#/components/responses/");
                        assert_eq!(
                            d["components"]["responses"][name]["content"]["application/json"]["schema"]
                                ["$ref"],
                            "#/components/schemas/ErrorBody",
                            "{method} {path} {code}"
                        );
                    }
                }
            } else {
                assert_eq!(op["security"], json!([{}]), "{path} needs no key");
            }
            // Query parameters are in the query, never required, never null.
            for p in op["parameters"].as_array().into_iter().flatten() {
                if p["name"] == "id" {
                    assert_eq!(p["in"], "path");
                } else {
                    assert_eq!(p["in"], "query", "{method} {path} {}", p["name"]);
                    assert_ne!(p["required"], true);
                    assert!(p["schema"]["type"].is_string(), "{}", p["schema"]);
                }
            }
        }
    }
    assert_eq!(operations, 15);
    for code in ["413", "429"] {
        assert!(d["paths"]["/v1/sessions"]["post"]["responses"][code].is_object());
    }
    assert!(d["paths"]["/v1/sessions/{id}/observations"]["post"]["responses"]["413"].is_object());
}

#[test]
fn creating_a_session_links_to_every_session_route() {
    let d = doc(&Limits::default());
    let links = d["paths"]["/v1/sessions"]["post"]["responses"]["201"]["links"]
        .as_object()
        .expect("links on 201");
    for (method, path) in SESSION_ROUTES {
        let op = &d["paths"][path][method];
        let id = op["operationId"].as_str().expect("operationId");
        let link = links
            .values()
            .find(|l| l["operationId"] == id)
            .unwrap_or_else(|| panic!("no link to {method} {path}"));
        assert_eq!(link["parameters"]["id"], "$response.body#/id");
    }
}

#[test]
fn bounds_are_the_limits_of_the_server() {
    let limits = Limits {
        max_pairs: 1234,
        max_stimuli: 7,
        max_batch: 99,
        max_history: 555,
        max_features: 321,
        max_name_bytes: 17,
        max_curiosity_window: 77,
        max_roc_centres: 9,
        max_signal_sources: 12,
        max_group_members: 40,
        ..Limits::default()
    };
    let d = doc(&limits);
    let group = &schema(&d, "CreateGroup")["properties"];
    assert_eq!(group["n"]["maximum"], 40);
    assert_eq!(group["n"]["minimum"], 1);
    let step = &schema(&d, "GroupStep")["properties"];
    for column in ["mask", "states", "observations", "stimuli", "action_taken"] {
        assert_eq!(step[column]["maxItems"], 40, "{column}");
    }
    assert_eq!(step["mask"]["items"]["maximum"], 39);
    assert_eq!(step["states"]["items"]["maximum"], 1233);
    assert_eq!(step["stimuli"]["items"]["maxItems"], 7);
    let full = schema(&d, "FullModelNext");
    assert_eq!(full["properties"]["states"]["maximum"], 1234);
    assert_eq!(full["properties"]["states"]["minimum"], 1);
    assert_eq!(full["properties"]["actions"]["maxItems"], 1234);
    assert_eq!(full["properties"]["stimuli"]["maxItems"], 7);
    assert_eq!(
        full["properties"]["next"]["items"]["items"]["maximum"],
        1233
    );
    assert_eq!(full["properties"]["actions"]["items"]["maxLength"], 17);
    assert_eq!(full["properties"]["state_names"]["items"]["maxLength"], 17);
    let params = &schema(&d, "CuriosityParams")["properties"];
    assert_eq!(params["tau"]["maximum"], 77);
    assert_eq!(params["lag"]["maximum"], 77);
    assert_eq!(params["max_centres"]["maximum"], 9);
    assert_eq!(params["max_sources"]["maximum"], 12);
    let grid = schema(&d, "GridModel");
    assert_eq!(
        grid["properties"]["sources"]["additionalProperties"]["maximum"],
        6
    );
    assert_eq!(grid["properties"]["sources"]["maxProperties"], 7);
    let basis = &schema(&d, "Basis")["oneOf"];
    assert_eq!(basis[1]["properties"]["k"]["maximum"], 321);
    let batch = schema(&d, "ObserveBatch");
    assert_eq!(batch["properties"]["observations"]["maxItems"], 99);
    assert_eq!(batch["properties"]["observations"]["minItems"], 1);
    let config = schema(&d, "SessionConfig");
    assert_eq!(config["properties"]["history"]["maximum"], 555);
    assert_eq!(config["properties"]["priorities"]["maxItems"], 7);
    let obs = schema(&d, "Observation");
    assert_eq!(obs["properties"]["signal_source"]["maximum"], 11);
    assert_eq!(obs["properties"]["state"]["maximum"], 1233);
    assert_eq!(obs["properties"]["stimulus"]["maxItems"], 7);
    assert_eq!(obs["properties"]["stimulus"]["items"]["maximum"], 1e12);
    assert_eq!(obs["properties"]["stimulus"]["items"]["minimum"], -1e12);
    assert_eq!(
        obs["properties"]["signal"]["maxItems"],
        mcapi_core::curiosity::MAX_SIGNAL_DIM
    );
    // A continuous world's bounds are the core's.
    assert_eq!(
        obs["properties"]["observation"]["maxItems"],
        mcapi_core::continuous::space::MAX_DIM
    );
    let continuous = schema(&d, "ContinuousModel");
    assert_eq!(continuous["properties"]["stimuli"]["maxItems"], 7);
    assert_eq!(
        continuous["properties"]["actions"]["maxItems"],
        mcapi_core::continuous::model::MAX_ACTIONS
    );
    assert_eq!(
        schema(&d, "SampleParams")["properties"]["max"]["maximum"],
        mcapi_core::continuous::model::MAX_SAMPLES
    );
    assert_eq!(
        schema(&d, "ContinuousBasis")["oneOf"][0]["properties"]["order"]["maximum"],
        mcapi_core::continuous::basis::MAX_ORDER
    );
    let create = schema(&d, "CreateSession");
    assert!(
        create["description"]
            .as_str()
            .expect("description")
            .contains("at most 1234 state-action pairs"),
        "the document says which limits it describes"
    );

    // Query parameters.
    let params = |path: &str| d["paths"][path]["get"]["parameters"].clone();
    let list = params("/v1/sessions");
    let limit = list
        .as_array()
        .expect("params")
        .iter()
        .find(|p| p["name"] == "limit")
        .expect("limit");
    assert_eq!(limit["schema"]["minimum"], 1);
    assert_eq!(limit["schema"]["maximum"], MAX_PAGE);
    let history = params("/v1/sessions/{id}/history");
    assert_eq!(history[1]["name"], "limit");
    assert_eq!(history[1]["schema"]["minimum"], 1);
    let events = params("/v1/sessions/{id}/events");
    assert_eq!(events[1]["name"], "interval_ms");
    assert_eq!(
        events[1]["schema"]["minimum"],
        mcapi_server::api::dashboard::MIN_INTERVAL_MS
    );
    assert_eq!(
        events[1]["schema"]["maximum"],
        mcapi_server::api::dashboard::MAX_INTERVAL_MS
    );
}

#[test]
fn every_body_form_is_a_closed_one_of_branch() {
    let d = doc(&Limits::default());
    let model = schema(&d, "Model")["oneOf"].as_array().expect("oneOf");
    let branches: Vec<&str> = model
        .iter()
        .map(|b| b["$ref"].as_str().expect("$ref"))
        .collect();
    assert_eq!(
        branches,
        [
            "#/components/schemas/PresetModel",
            "#/components/schemas/GridModel",
            "#/components/schemas/FullModelNext",
            "#/components/schemas/FullModelTransitions",
            "#/components/schemas/GridModelLearned",
            "#/components/schemas/FullModelLearned",
            "#/components/schemas/ContinuousModel"
        ]
    );
    // Each branch is closed and requires its distinguishing key, so `{}` is
    // none of them (`model: {}` was once schema-valid).
    for (name, key) in [
        ("PresetModel", "preset"),
        ("GridModel", "grid"),
        ("FullModelNext", "next"),
        ("FullModelTransitions", "transitions"),
        ("GridModelLearned", "learn"),
        ("FullModelLearned", "transitions"),
        ("ContinuousModel", "observation_space"),
    ] {
        let s = schema(&d, name);
        assert_eq!(s["additionalProperties"], false, "{name}");
        let required = s["required"].as_array().expect("required");
        assert!(required.contains(&json!(key)), "{name} requires {key}");
    }
    // `next` and `transitions` exclude each other.
    assert_eq!(
        schema(&d, "FullModelNext")["properties"]["transitions"]["type"],
        "null"
    );
    assert_eq!(
        schema(&d, "FullModelTransitions")["properties"]["next"]["type"],
        "null"
    );
    // `action_taken`: an index or a name, not any object (`action_taken:
    // {}` was once schema-valid).
    let action = schema(&d, "ActionRef")["oneOf"].as_array().expect("oneOf");
    assert_eq!(action[0]["type"], "integer");
    assert_eq!(action[1]["type"], "string");
    let obs = schema(&d, "Observation");
    assert_eq!(
        obs["properties"]["action_taken"]["oneOf"][1]["$ref"],
        "#/components/schemas/ActionRef"
    );
    let observe = schema(&d, "ObserveRequest")["oneOf"]
        .as_array()
        .expect("oneOf");
    assert_eq!(observe.len(), 2);
    let rate = schema(&d, "StimulusRate")["oneOf"]
        .as_array()
        .expect("oneOf");
    assert_eq!(rate[1]["enum"], json!(["sample_mean"]));
}

async fn call(app: &axum::Router, method: &str, uri: &str, body: Option<Value>) -> (u16, Value) {
    let mut req = Request::builder().method(method).uri(uri);
    let body = match body {
        Some(v) => {
            req = req.header("content-type", "application/json");
            Body::from(v.to_string())
        }
        None => Body::empty(),
    };
    let resp = app
        .clone()
        .oneshot(req.body(body).expect("request"))
        .await
        .expect("infallible");
    let status = resp.status().as_u16();
    let bytes = resp.into_body().collect().await.expect("body").to_bytes();
    (
        status,
        serde_json::from_slice(&bytes).unwrap_or(Value::Null),
    )
}

fn app() -> axum::Router {
    let manager = Arc::new(SessionManager::new(Limits::default(), 1).expect("manager"));
    router(AppState {
        manager,
        metrics: None,
        serving: None,
    })
}

#[tokio::test]
async fn three_bodies_once_schema_valid_and_the_examples() {
    let app = app();
    // The documented examples are accepted.
    let d = doc(&Limits::default());
    let create = schema(&d, "CreateSession")["examples"][0].clone();
    let (status, info) = call(&app, "POST", "/v1/sessions", Some(create)).await;
    assert_eq!(status, 201, "{info}");
    let id = info["id"].as_str().expect("id").to_string();
    for form in [
        "PresetModel",
        "GridModel",
        "GridModelLearned",
        "FullModelLearned",
    ] {
        let model = schema(&d, form)["examples"][0].clone();
        let (status, body) =
            call(&app, "POST", "/v1/sessions", Some(json!({"model": model}))).await;
        assert_eq!(status, 201, "{form}: {body}");
    }
    let obs = format!("/v1/sessions/{id}/observations");
    let (status, body) = call(&app, "POST", &obs, Some(json!({"state": 25}))).await;
    assert_eq!(status, 200, "{body}");
    let example = schema(&d, "Observation")["examples"][0].clone();
    let (status, body) = call(&app, "POST", &obs, Some(example)).await;
    assert_eq!(status, 200, "{body}");
    // `action_taken` by index and by name.
    for taken in [json!(1), json!("left")] {
        let (status, body) = call(
            &app,
            "POST",
            &obs,
            Some(json!({"state": 26, "stimulus": [0, 0], "action_taken": taken})),
        )
        .await;
        assert_eq!(status, 200, "action_taken {taken}: {body}");
    }
    // ... and nothing else.
    let (status, body) = call(
        &app,
        "POST",
        &obs,
        Some(json!({"state": 26, "stimulus": [0, 0], "action_taken": {}})),
    )
    .await;
    assert_eq!(status, 400, "{body}");
    let (status, body) = call(&app, "POST", "/v1/sessions", Some(json!({"model": {}}))).await;
    assert_eq!((status, body["code"].as_str()), (400, Some("bad_request")));
    // `limit` below its minimum is refused, on both routes that take one.
    for uri in [
        "/v1/sessions?limit=0".to_string(),
        format!("/v1/sessions/{id}/history?limit=0"),
    ] {
        let (status, body) = call(&app, "GET", &uri, None).await;
        assert_eq!(status, StatusCode::BAD_REQUEST.as_u16(), "{uri}: {body}");
        assert!(body["message"].as_str().expect("message").contains("limit"));
    }
    let (status, body) = call(
        &app,
        "GET",
        &format!("/v1/sessions/{id}/history?limit=1"),
        None,
    )
    .await;
    assert_eq!(status, 200);
    assert_eq!(body.as_array().expect("entries").len(), 1);
}
