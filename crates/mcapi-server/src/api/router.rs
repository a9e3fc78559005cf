//! The REST router: the session routes ([`crate::api::rest`]), the
//! dashboard and its events stream ([`crate::api::dashboard`]), the OpenAPI
//! document and its docs page ([`crate::api::openapi`]), health, readiness
//! and metrics; with the body limit, the request timeout, the panic guard
//! and the request metrics around them.

use std::collections::HashMap;
use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::OnceLock;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request};
use axum::http::HeaderValue;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use parking_lot::RwLock;
use tower::{Layer, Service, ServiceBuilder};
use utoipa_swagger_ui::SwaggerUi;

use crate::api::error::ApiError;
use crate::api::extract::AppState;
use crate::api::openapi::document;
use crate::api::rest::{
    create_group, create_session, delete_group, delete_session, get_group, get_session, healthz,
    history, list_sessions, metrics_text, observe, readyz, step_group, values,
};
use crate::api::{admin, conn, dashboard};
use crate::service::{ServiceError, SessionManager};

/// The REST router with every route, limits and metrics middleware.
///
/// Each route gets one layer, [`Edge`] over the panic guard and the body
/// limit, composed without boxing: axum boxes a route once per
/// `Router::layer` call and clones every box on every request, so the
/// middleware is stacked first and installed with a single call.
pub fn router(state: AppState) -> Router {
    let body_limit = state.manager.limits().max_body_bytes;
    let timeout = state.serving.as_ref().map(|s| s.request_timeout);
    let replica = replica_header(&state.manager);
    let per_route = ServiceBuilder::new()
        .layer(EdgeLayer { timeout, replica })
        // A panicking handler answers 500 `internal`, and is recorded.
        .layer(conn::rest_panic_layer())
        .layer(DefaultBodyLimit::max(body_limit))
        .layer(axum::middleware::map_response(json_errors))
        .into_inner();
    Router::new()
        // Full paths, not `nest("/v1", ...)`: a nested router rewrites the
        // URI of every request it serves.
        .route("/v1/sessions", get(list_sessions).post(create_session))
        .route("/v1/sessions/{id}", get(get_session).delete(delete_session))
        .route("/v1/sessions/{id}/observations", post(observe))
        .route("/v1/sessions/{id}/values", get(values))
        .route("/v1/sessions/{id}/history", get(history))
        .route("/v1/groups", post(create_group))
        .route("/v1/groups/{id}", get(get_group).delete(delete_group))
        .route("/v1/groups/{id}/steps", post(step_group))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics_text))
        // Serves the document at /v1/openapi.json and the UI under /docs.
        .merge(SwaggerUi::new("/docs").url("/v1/openapi.json", document(state.manager.limits())))
        .merge(dashboard::routes()) // the page at `/` and the events stream
        .merge(admin::routes()) // shard moves (docs/cluster.md)
        .fallback(not_found)
        .layer(per_route)
        .with_state(state)
}

/// The response header naming the replica that answered (docs/cluster.md).
pub const REPLICA_HEADER: &str = "x-mcapi-replica";

/// The [`REPLICA_HEADER`] value a replica of a cluster sends on every REST
/// and gRPC reply; `None` on a single node, which sends no such header.
pub(crate) fn replica_header(manager: &SessionManager) -> Option<HeaderValue> {
    manager
        .placement()
        .and_then(|p| HeaderValue::from_str(p.replica().as_str()).ok())
}

/// Every 4xx answer is `{"code","message"}`: axum's own rejections (a
/// path that is not UTF-8, a query string that does not parse, a method a
/// route does not take) come as plain text or an empty body, and are
/// turned into the error of the one table ([`ApiError`]), their text kept
/// as the message and their headers (`Allow`) kept. Other answers pass as
/// they are.
async fn json_errors(resp: Response) -> Response {
    let status = resp.status();
    let json = resp
        .headers()
        .get(axum::http::header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/json"));
    if !status.is_client_error() || json {
        return resp;
    }
    let (parts, body) = resp.into_parts();
    // axum's rejection texts are short; more is not read.
    let text = axum::body::to_bytes(body, 4096)
        .await
        .map(|b| String::from_utf8_lossy(&b).trim().to_owned())
        .unwrap_or_default();
    let error = match status {
        axum::http::StatusCode::METHOD_NOT_ALLOWED => ServiceError::MethodNotAllowed(
            "this route does not take that method (the `Allow` header lists those it takes)".into(),
        ),
        axum::http::StatusCode::PAYLOAD_TOO_LARGE => ServiceError::PayloadTooLarge(
            "the request body is larger than the server accepts".into(),
        ),
        axum::http::StatusCode::NOT_FOUND => ServiceError::UnknownRoute(text),
        _ if text.is_empty() => {
            ServiceError::BadRequest(format!("the request was refused ({status})"))
        }
        _ => ServiceError::BadRequest(text),
    };
    let mut out = ApiError(error).into_response();
    for (name, value) in &parts.headers {
        if name != axum::http::header::CONTENT_TYPE && name != axum::http::header::CONTENT_LENGTH {
            out.headers_mut().insert(name, value.clone());
        }
    }
    out
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
    HISTOGRAMS.get_or_init(|| {
        // Handles resolved before the recorder is installed would record
        // nothing, and they are kept.
        crate::telemetry::prometheus();
        RwLock::default()
    })
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

/// The edge of every route: request latency by method, route and status
/// (every label from a bounded set: the method from [`method_label`], the
/// route as declared or `unmatched`, the status code); the request timeout
/// of `mcapi serve`: a request not answered within it (body read included)
/// gets 503 `request_timeout` (only the response head is timed, so an open
/// event stream is not cut); and, on a replica of a cluster, the
/// [`REPLICA_HEADER`] naming it.
#[derive(Debug, Clone)]
struct EdgeLayer {
    timeout: Option<Duration>,
    replica: Option<HeaderValue>,
}

impl<S> Layer<S> for EdgeLayer {
    type Service = Edge<S>;

    fn layer(&self, inner: S) -> Edge<S> {
        Edge {
            inner,
            timeout: self.timeout,
            replica: self.replica.clone(),
        }
    }
}

/// See [`EdgeLayer`].
#[derive(Debug, Clone)]
struct Edge<S> {
    inner: S,
    timeout: Option<Duration>,
    replica: Option<HeaderValue>,
}

impl<S> Service<Request> for Edge<S>
where
    S: Service<Request, Error = Infallible>,
    S::Response: IntoResponse,
    S::Future: Send + 'static,
{
    type Response = Response;
    type Error = Infallible;
    type Future = Pin<Box<dyn Future<Output = Result<Response, Infallible>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: Request) -> Self::Future {
        let started = Instant::now();
        let route = req.extensions().get::<MatchedPath>().cloned();
        let method = method_label(req.method());
        let timeout = self.timeout;
        let replica = self.replica.clone();
        let answer = self.inner.call(req);
        Box::pin(async move {
            let mut response = match timeout {
                None => answer.await?.into_response(),
                Some(limit) => match tokio::time::timeout(limit, answer).await {
                    Ok(response) => response?.into_response(),
                    Err(_) => ApiError(ServiceError::RequestTimeout(format!(
                        "the request was not answered within {} ms (the server's request \
                         timeout); it may or may not have taken effect",
                        limit.as_millis()
                    )))
                    .into_response(),
                },
            };
            if let Some(replica) = replica {
                response.headers_mut().insert(REPLICA_HEADER, replica);
            }
            let route = route.as_ref().map_or("unmatched", MatchedPath::as_str);
            request_histogram(method, route, response.status().as_u16())
                .record(started.elapsed().as_secs_f64());
            Ok(response)
        })
    }
}
