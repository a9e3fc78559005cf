//! What every REST handler (the session routes of [`crate::api::rest`] and
//! the events stream of [`crate::api::dashboard`]) extracts from a request:
//! the shared [`AppState`], the caller ([`Auth`]), a JSON body read the way
//! the OpenAPI document reads it ([`JsonBody`], [`JsonValue`]) and a query
//! string ([`query`]), each rejection a `{"code","message"}` error.

use std::sync::Arc;
use std::time::Duration;

use axum::Json;
use axum::extract::rejection::{JsonRejection, QueryRejection};
use axum::extract::{FromRequest, FromRequestParts, Query, Request};
use axum::http::StatusCode;
use axum::http::request::Parts;
use metrics_exporter_prometheus::PrometheusHandle;
use serde_json::Value;
use tokio::sync::watch;

use crate::api::error::ApiError;
use crate::api::streams::StreamLimiter;
use crate::service::{Caller, CreateSession, ServiceError, SessionManager};

/// Shared state of the handlers.
#[derive(Clone)]
pub struct AppState {
    /// The session layer.
    pub manager: Arc<SessionManager>,
    /// Renders `/metrics`.
    pub metrics: Option<PrometheusHandle>,
    /// What `mcapi serve` adds around the routes; `None` (no request
    /// timeout, no stream budget, streams end only with their client or
    /// session) where tests mount the router by itself.
    pub serving: Option<Serving>,
}

/// The server's side of the REST routes.
#[derive(Clone)]
pub struct Serving {
    /// Turns true when the server shuts down: open event streams end (a
    /// graceful shutdown waits for in-flight responses, and an event
    /// stream never finishes by itself).
    pub stopping: watch::Receiver<bool>,
    /// The watch streams per caller, shared with gRPC.
    pub streams: Arc<StreamLimiter>,
    /// A request not answered within this (body read included) gets 503
    /// `request_timeout`.
    pub request_timeout: Duration,
}

/// The caller of a request, from its `Authorization` header (see
/// `service::auth`); every `/v1` handler takes one.
pub struct Auth(pub Caller);

impl FromRequestParts<AppState> for Auth {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, ApiError> {
        let header = match parts.headers.get(axum::http::header::AUTHORIZATION) {
            None => None,
            Some(v) => Some(v.to_str().map_err(|_| {
                ServiceError::Unauthenticated(
                    "the `Authorization` header must be `Bearer <key>`".into(),
                )
            })?),
        };
        Ok(Self(state.manager.authenticate(header)?))
    }
}

/// A JSON body whose rejections become `{"code","message"}` errors. Numbers
/// are read as JSON Schema reads them (see [`integral_numbers_as_integers`])
/// and objects are required where `T` has structs (see [`BodyShape`]).
pub struct JsonBody<T>(pub T);

/// Where a request type has structs, as JSON pointers (`*`: every item of
/// an array). serde reads a struct from an array of its fields in order as
/// well as from an object (`"params": [3, 0.01]`), a form the OpenAPI
/// document does not have: such bodies are refused before they are typed.
pub trait BodyShape {
    /// Pointers to the values that must be objects (or null) when present.
    const OBJECTS: &'static [&'static str];
}

impl BodyShape for CreateSession {
    const OBJECTS: &'static [&'static str] = &[
        "",
        "/agent",
        "/agent/curiosity",
        "/agent/curiosity/params",
        "/model",
        "/model/basis",
        "/model/transitions/*",
    ];
}

/// The structs of an observation body: the observation, or each of a batch.
pub(crate) const OBSERVE_OBJECTS: &[&str] = &["", "/observations/*"];

/// Refuses a body with an array (or any non-object but null) where the
/// request type has a struct.
pub fn require_objects(value: &Value, pointers: &[&str]) -> Result<(), ServiceError> {
    fn walk(value: &Value, path: &[&str], at: &mut Vec<String>) -> Result<(), ServiceError> {
        let Some((first, rest)) = path.split_first() else {
            return match value {
                Value::Object(_) | Value::Null => Ok(()),
                _ if at.is_empty() => Err(ServiceError::BadRequest(
                    "the body must be a JSON object".into(),
                )),
                _ => Err(ServiceError::field(&at.join("."), "must be a JSON object")),
            };
        };
        match (*first, value) {
            ("*", Value::Array(items)) => {
                for (i, item) in items.iter().enumerate() {
                    at.push(i.to_string());
                    walk(item, rest, at)?;
                    at.pop();
                }
                Ok(())
            }
            (key, Value::Object(map)) if key != "*" => match map.get(key) {
                Some(child) => {
                    at.push(key.to_string());
                    walk(child, rest, at)?;
                    at.pop();
                    Ok(())
                }
                None => Ok(()),
            },
            // Not there, or not a container: the typed parse says what is wrong.
            _ => Ok(()),
        }
    }
    for pointer in pointers {
        let path: Vec<&str> = pointer.split('/').skip(1).collect();
        walk(value, &path, &mut Vec::new())?;
    }
    Ok(())
}

impl<S, T> FromRequest<S> for JsonBody<T>
where
    T: serde::de::DeserializeOwned + BodyShape,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let JsonValue(value) = JsonValue::from_request(req, state).await?;
        require_objects(&value, T::OBJECTS)?;
        typed(&value)
            .map(Self)
            .map_err(|rejection| ApiError(json_rejection(&rejection)))
    }
}

/// A checked value typed from its text again, so errors name the field's
/// path.
fn typed<T: serde::de::DeserializeOwned>(value: &Value) -> Result<T, JsonRejection> {
    let bytes = serde_json::to_vec(value).unwrap_or_default();
    Json::<T>::from_bytes(&bytes).map(|Json(v)| v)
}

/// One part of a create request that gRPC carries as JSON text (the
/// deprecated `model_json`, a curiosity channel's `params_json`), read
/// exactly as REST reads that part of its body: placed at its pointer `at`
/// in the body (`/model`, `/agent/curiosity/params`), numbers read as JSON
/// Schema reads them, objects required where [`CreateSession`] has structs
/// (with REST's messages, which name the part's path), then typed. `field`
/// is the proto field named when the text is not JSON or does not type.
pub fn create_part<T: serde::de::DeserializeOwned>(
    field: &str,
    text: &str,
    at: &str,
) -> Result<T, ServiceError> {
    let mut part: Value = serde_json::from_str(text)
        .map_err(|e| ServiceError::field(field, format!("is not valid JSON: {e}")))?;
    integral_numbers_as_integers(&mut part);
    let mut body = part;
    for key in at.split('/').skip(1).collect::<Vec<_>>().into_iter().rev() {
        body = Value::Object([(key.to_owned(), body)].into_iter().collect());
    }
    require_objects(&body, CreateSession::OBJECTS)?;
    let part = body.pointer(at).unwrap_or(&Value::Null);
    typed(part).map_err(|rejection| ServiceError::field(field, rejection.body_text()))
}

/// A JSON body as a value, numbers read as JSON Schema reads them.
pub struct JsonValue(pub Value);

impl<S> FromRequest<S> for JsonValue
where
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let Json(mut value) = Json::<Value>::from_request(req, state)
            .await
            .map_err(|rejection| ApiError(json_rejection(&rejection)))?;
        integral_numbers_as_integers(&mut value);
        Ok(Self(value))
    }
}

/// Rewrites every number with no fractional part written as a float
/// (`3.0`, `1e3`, `-0.0`) to the integer it equals, where that fits 64
/// bits; true if any was rewritten. JSON Schema (and so the OpenAPI
/// document) counts such numbers as integers, so a body valid for the
/// document must not be refused because a count or index was written
/// `3.0`; floating-point fields take the integer back unchanged.
pub fn integral_numbers_as_integers(value: &mut Value) -> bool {
    match value {
        Value::Number(n) if !n.is_i64() && !n.is_u64() => {
            let Some(x) = n.as_f64() else { return false };
            // 2^64 and -2^63, exact in f64.
            const TWO_64: f64 = 18_446_744_073_709_551_616.0;
            const MINUS_TWO_63: f64 = -9_223_372_036_854_775_808.0;
            if x.fract() != 0.0 || !(MINUS_TWO_63..TWO_64).contains(&x) {
                return false;
            }
            *value = if x >= 0.0 {
                Value::from(x as u64)
            } else {
                Value::from(x as i64)
            };
            true
        }
        Value::Array(items) => items
            .iter_mut()
            .fold(false, |any, v| integral_numbers_as_integers(v) | any),
        Value::Object(map) => map
            .values_mut()
            .fold(false, |any, v| integral_numbers_as_integers(v) | any),
        _ => false,
    }
}

fn json_rejection(rejection: &JsonRejection) -> ServiceError {
    if rejection.status() == StatusCode::PAYLOAD_TOO_LARGE {
        return ServiceError::PayloadTooLarge(
            "the request body is larger than the server accepts".into(),
        );
    }
    match rejection {
        JsonRejection::MissingJsonContentType(_) => {
            ServiceError::BadRequest("expected `Content-Type: application/json`".into())
        }
        other => ServiceError::BadRequest(format!("malformed JSON body: {}", other.body_text())),
    }
}

pub(crate) fn query<T>(q: Result<Query<T>, QueryRejection>) -> Result<T, ApiError> {
    q.map(|Query(v)| v).map_err(|e| {
        ApiError(ServiceError::BadRequest(format!(
            "bad query string: {}",
            e.body_text()
        )))
    })
}
