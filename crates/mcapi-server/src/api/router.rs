//! The REST router: the session routes ([`crate::api::rest`]), the
//! dashboard and its events stream ([`crate::api::dashboard`]), the OpenAPI
//! document and its docs page ([`crate::api::openapi`]), health, readiness
//! and metrics; with the body limit, the request timeout, the panic guard
//! and the request metrics around them.

use std::collections::HashMap;
use std::sync::OnceLock;
use std::time::Instant;

use axum::Router;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request};
use axum::middleware::{self, Next};
use axum::response::Response;
use axum::routing::get;
use parking_lot::RwLock;
use utoipa_swagger_ui::SwaggerUi;

use crate::api::error::ApiError;
use crate::api::extract::AppState;
use crate::api::openapi::document;
use crate::api::rest::{
    create_session, delete_session, get_session, healthz, history, list_sessions, metrics_text,
    observe, readyz, values,
};
use crate::api::{conn, dashboard};
use crate::service::ServiceError;

/// The REST router with every route, limits and metrics middleware.
pub fn router(state: AppState) -> Router {
    let body_limit = state.manager.limits().max_body_bytes;
    let v1 = Router::new()
        .route("/sessions", get(list_sessions).post(create_session))
        .route("/sessions/{id}", get(get_session).delete(delete_session))
        .route("/sessions/{id}/observations", axum::routing::post(observe))
        .route("/sessions/{id}/values", get(values))
        .route("/sessions/{id}/history", get(history));
    Router::new()
        .nest("/v1", v1)
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics_text))
        // Serves the document at /v1/openapi.json and the UI under /docs.
        .merge(SwaggerUi::new("/docs").url("/v1/openapi.json", document(state.manager.limits())))
        .merge(dashboard::routes()) // the page at `/` and the events stream
        .fallback(not_found)
        .layer(DefaultBodyLimit::max(body_limit))
        // `mcapi serve` sets the timeout (`conn::RequestTimeout`).
        .layer(middleware::from_fn(conn::request_timeout))
        // A panicking handler answers 500 `internal`, and is recorded.
        .layer(conn::rest_panic_layer())
        .layer(middleware::from_fn(record_request))
        .with_state(state)
}

/// The response header naming the replica that answered (docs/cluster.md).
pub const REPLICA_HEADER: &str = "x-mcapi-replica";

/// Adds `x-mcapi-replica: <name>` to every response of a clustered
/// replica; a single node (`None`) sends no such header.
pub fn with_replica_header(router: Router, replica: Option<&str>) -> Router {
    let Some(value) = replica.and_then(|r| axum::http::HeaderValue::from_str(r).ok()) else {
        return router;
    };
    router.layer(middleware::map_response(move |mut response: Response| {
        let value = value.clone();
        async move {
            response.headers_mut().insert(REPLICA_HEADER, value);
            response
        }
    }))
}

async fn not_found(method: axum::http::Method, uri: axum::http::Uri) -> ApiError {
    ApiError(ServiceError::UnknownRoute(format!(
        "{method} {}",
        uri.path()
    )))
}

/// The `method` label: one of a fixed set, so clients cannot create series.
fn method_label(method: &axum::http::Method) -> &'static str {
    use axum::http::Method as M;
    match *method {
        M::GET => "GET",
        M::POST => "POST",
        M::DELETE => "DELETE",
        M::PUT => "PUT",
        M::PATCH => "PATCH",
        M::HEAD => "HEAD",
        M::OPTIONS => "OPTIONS",
        _ => "other",
    }
}

/// Latency histograms by route, then by method and status, each resolved
/// from the recorder once. Every label comes from a bounded set (the
/// declared routes or `unmatched`, the eight methods of [`method_label`],
/// status codes), so the map stays small; a request whose handle exists
/// formats no label and does not touch the recorder's registry.
type Histograms = HashMap<Box<str>, HashMap<(&'static str, u16), metrics::Histogram>>;

fn histograms() -> &'static RwLock<Histograms> {
    static HISTOGRAMS: OnceLock<RwLock<Histograms>> = OnceLock::new();
    HISTOGRAMS.get_or_init(RwLock::default)
}

/// The latency histogram of one label set.
fn request_histogram(method: &'static str, route: &str, status: u16) -> metrics::Histogram {
    if let Some(h) = histograms()
        .read()
        .get(route)
        .and_then(|by| by.get(&(method, status)))
    {
        return h.clone();
    }
    let h = metrics::histogram!(
        "mcapi_http_request_duration_seconds",
        "method" => method,
        "route" => route.to_string(),
        "status" => status.to_string()
    );
    histograms()
        .write()
        .entry(route.into())
        .or_default()
        .insert((method, status), h.clone());
    h
}

/// Request latency by method, route and status, every label from a bounded
/// set: the method from [`method_label`], the route as declared (or
/// `unmatched`), the status code.
async fn record_request(req: Request, next: Next) -> Response {
    let started = Instant::now();
    let route = req.extensions().get::<MatchedPath>().cloned();
    let method = method_label(req.method());
    let response = next.run(req).await;
    let route = route.as_ref().map_or("unmatched", MatchedPath::as_str);
    request_histogram(method, route, response.status().as_u16())
        .record(started.elapsed().as_secs_f64());
    response
}
