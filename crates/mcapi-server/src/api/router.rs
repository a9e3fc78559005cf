//! The REST router: the session routes ([`crate::api::rest`]), the
//! dashboard and its events stream ([`crate::api::dashboard`]), the OpenAPI
//! document and its docs page ([`crate::api::openapi`]), health, readiness
//! and metrics; with the body limit, the request timeout, the panic guard
//! and the request metrics around them.

use std::time::Instant;

use axum::Router;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request};
use axum::middleware::{self, Next};
use axum::response::Response;
use axum::routing::get;
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

/// Request latency by method, route and status, every label from a bounded
/// set: the method from [`method_label`], the route as declared (or
/// `unmatched`), the status code.
async fn record_request(req: Request, next: Next) -> Response {
    let started = Instant::now();
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| "unmatched".to_string(), |p| p.as_str().to_string());
    let method = method_label(req.method());
    let response = next.run(req).await;
    let status = response.status().as_u16().to_string();
    metrics::histogram!(
        "mcapi_http_request_duration_seconds",
        "method" => method,
        "route" => route,
        "status" => status
    )
    .record(started.elapsed().as_secs_f64());
    response
}
