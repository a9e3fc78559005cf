//! The live dashboard (README, "Dashboard"): a page served at `/` and the
//! server-sent-events stream of a session it reads,
//! `GET /v1/sessions/{id}/events`.
//!
//! The page (HTML, JS, CSS and the vendored uPlot 1.6.32 with its licence,
//! all under `src/api/dashboard/`) is embedded in the binary, so it works
//! offline. Every asset is served with its content type,
//! `Cache-Control: no-cache` and an `ETag` (a browser revalidates and gets
//! 304 while the binary is unchanged).
//!
//! The events stream is a thin adapter like every other handler: it
//! authenticates with [`Auth`], then **polls** the session layer every
//! `interval_ms` (`values` for the tick and policy version, `history` for
//! new ticks, `values` again for V and the policy when the policy changed).
//! Polling keeps the observation hot path free of any broadcast cost: an
//! observation pays nothing for the streams watching its session, and a
//! watcher costs one brief session lock per interval however fast the
//! session ticks.

use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::{Arc, LazyLock};
use std::time::Duration;

use axum::extract::rejection::QueryRejection;
use axum::extract::{ConnectInfo, Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Extension, Router};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tokio::sync::mpsc;
use tokio::time::MissedTickBehavior;
use tokio_stream::wrappers::ReceiverStream;
use tracing::Instrument;

use crate::api::error::{ApiError, ErrorBody, classify, public_message};
use crate::api::extract::{AppState, Auth, query};
use crate::service::{Caller, HistoryEntry, ServiceError, SessionManager, ValueSelection};

/// Default polling interval of the events stream.
pub const DEFAULT_INTERVAL_MS: u64 = 250;
/// Shortest polling interval accepted.
pub const MIN_INTERVAL_MS: u64 = 50;
/// Longest polling interval accepted.
pub const MAX_INTERVAL_MS: u64 = 10_000;
/// At most this many `tick` events per interval (and at the start of a
/// stream): when a session ticked more often since the last poll, only the
/// newest this many are sent (the ticks jump; `/history` has them all).
pub const MAX_TICKS_PER_POLL: usize = 1000;
/// Events buffered per stream: a slow reader slows its stream's polling
/// instead of growing a queue.
const STREAM_BUFFER: usize = 256;

/// One embedded file of the page.
struct Asset {
    /// Route.
    path: &'static str,
    /// `Content-Type`.
    content_type: &'static str,
    /// The bytes.
    body: &'static [u8],
}

const ASSETS: [Asset; 6] = [
    Asset {
        path: "/",
        content_type: "text/html; charset=utf-8",
        body: include_bytes!("dashboard/index.html"),
    },
    Asset {
        path: "/assets/app.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_bytes!("dashboard/app.js"),
    },
    Asset {
        path: "/assets/app.css",
        content_type: "text/css; charset=utf-8",
        body: include_bytes!("dashboard/app.css"),
    },
    Asset {
        path: "/assets/uplot.iife.min.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_bytes!("dashboard/uplot.iife.min.js"),
    },
    Asset {
        path: "/assets/uplot.min.css",
        content_type: "text/css; charset=utf-8",
        body: include_bytes!("dashboard/uplot.min.css"),
    },
    Asset {
        path: "/assets/LICENSE-uPlot",
        content_type: "text/plain; charset=utf-8",
        body: include_bytes!("dashboard/LICENSE-uPlot"),
    },
];

/// The page may load scripts, styles and data only from this server.
/// (`'unsafe-inline'` styles: uPlot positions its elements with inline
/// styles.)
const CSP: &str = "default-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; \
                   object-src 'none'; base-uri 'none'; frame-ancestors 'none'";

/// Strong ETags of [`ASSETS`], by index: 16 hex digits of the SHA-256.
static ETAGS: LazyLock<Vec<HeaderValue>> = LazyLock::new(|| {
    ASSETS
        .iter()
        .map(|a| {
            let hex: String = Sha256::digest(a.body)[..8]
                .iter()
                .map(|b| format!("{b:02x}"))
                .collect();
            HeaderValue::from_str(&format!("\"{hex}\""))
                .unwrap_or_else(|_| HeaderValue::from_static("\"0\""))
        })
        .collect()
});

/// The page's routes (`/` and `/assets/*`) and the events stream
/// (`/v1/sessions/{id}/events`), merged into the REST router.
pub fn routes() -> Router<AppState> {
    let mut router = Router::new().route("/v1/sessions/{id}/events", get(events));
    for (i, asset) in ASSETS.iter().enumerate() {
        router = router.route(
            asset.path,
            get(move |headers: HeaderMap| async move { serve_asset(i, &headers) }),
        );
    }
    router
}

fn serve_asset(i: usize, headers: &HeaderMap) -> Response {
    let (Some(asset), Some(etag)) = (ASSETS.get(i), ETAGS.get(i)) else {
        return ApiError(ServiceError::Internal(format!("no asset {i}"))).into_response();
    };
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"));
    let common = [
        (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        (header::ETAG, etag.clone()),
    ];
    if fresh {
        return (StatusCode::NOT_MODIFIED, common).into_response();
    }
    (
        common,
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static(asset.content_type),
            ),
            (
                header::X_CONTENT_TYPE_OPTIONS,
                HeaderValue::from_static("nosniff"),
            ),
            (
                header::CONTENT_SECURITY_POLICY,
                HeaderValue::from_static(CSP),
            ),
        ],
        asset.body,
    )
        .into_response()
}

/// Query of the events stream.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct EventsQuery {
    /// Polling interval in milliseconds, 50..=10000 (default 250).
    #[param(nullable = false, minimum = 50, maximum = 10000)]
    interval_ms: Option<u64>,
}

impl EventsQuery {
    fn interval(&self) -> Result<Duration, ServiceError> {
        let ms = self.interval_ms.unwrap_or(DEFAULT_INTERVAL_MS);
        if !(MIN_INTERVAL_MS..=MAX_INTERVAL_MS).contains(&ms) {
            return Err(ServiceError::field(
                "interval_ms",
                format!("is {ms}; must be between {MIN_INTERVAL_MS} and {MAX_INTERVAL_MS}"),
            ));
        }
        Ok(Duration::from_millis(ms))
    }
}

/// Data of the `end` event.
#[derive(Debug, Serialize)]
struct EndEvent<'a> {
    /// The session.
    id: &'a str,
    /// Why the stream ends: `deleted`.
    reason: &'static str,
}

/// Live events of a session (server-sent events, `text/event-stream`).
///
/// At the start one `session` event (the session, as `GET /v1/sessions/{id}`)
/// and a `tick` event for each of the last 1000 ticks kept in the history;
/// then, every `interval_ms`, a `tick` event per new history entry (as
/// `GET /v1/sessions/{id}/history`; at most 1000 per interval, the newest)
/// and a `values` event (V and the greedy policy, as
/// `GET /v1/sessions/{id}/values`) whenever the policy version changed.
/// When the session is deleted: an `end` event, then the stream closes.
/// Comment lines keep idle connections open. A caller (an API key; a
/// client address without keys) holds at most `--max-streams-per-key`
/// event and gRPC `Watch` streams at once: 429 `too_many_streams` beyond.
#[utoipa::path(get, path = "/v1/sessions/{id}/events", tag = "inspection", operation_id = "get_events",
    params(("id" = String, Path, description = "The session's id, as `POST /v1/sessions` returned it."), EventsQuery),
    responses(
        (status = 200, description = "`session`, `tick`, `values` and `end` events; the schema is one event's",
            content_type = "text/event-stream", body = crate::api::schemas::SseEvent),
        (status = 400, response = crate::api::schemas::BadRequest),
        (status = 401, response = crate::api::schemas::Unauthorized),
        (status = 404, response = crate::api::schemas::NotFound),
        (status = 421, response = crate::api::schemas::MisdirectedRequest),
        (status = 429, response = crate::api::schemas::TooManyRequests),
        (status = 500, response = crate::api::schemas::InternalError),
        (status = 503, response = crate::api::schemas::Unavailable)))]
pub async fn events(
    State(state): State<AppState>,
    Auth(caller): Auth,
    Path(id): Path<String>,
    q: Result<Query<EventsQuery>, QueryRejection>,
    peer: Option<Extension<ConnectInfo<SocketAddr>>>,
) -> Result<Response, ApiError> {
    let interval = query(q)?.interval()?;
    // An unknown session fails the request itself, before any stream.
    let first = {
        let id = id.clone();
        state
            .manager
            .off_runtime(move |m| m.get(caller, &id))
            .await?
    };
    let first = json_event("session", &first)?;
    // Held by the stream's task: given back when the stream ends.
    let slot = match &state.serving {
        Some(serving) => {
            let peer = peer.map(|Extension(ConnectInfo(addr))| addr.ip());
            Some(serving.streams.acquire(caller, peer)?)
        }
        None => None,
    };
    let stopping = state.serving.as_ref().map(|s| s.stopping.clone());
    let (tx, rx) = mpsc::channel(STREAM_BUFFER);
    let manager = Arc::clone(&state.manager);
    let span = tracing::debug_span!("events", session = %id);
    tokio::spawn(
        async move {
            let stopped = async {
                match stopping {
                    Some(mut rx) => {
                        let _ = rx.wait_for(|stop| *stop).await;
                    }
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                () = stream_loop(&manager, caller, &id, interval, first, &tx) => {}
                () = tx.closed() => tracing::debug!("client went away"),
                () = stopped => tracing::debug!("server stopping"),
            }
            drop(slot);
        }
        .instrument(span),
    );
    Ok(Sse::new(ReceiverStream::new(rx))
        .keep_alive(KeepAlive::default())
        .into_response())
}

fn json_event(name: &str, data: &impl Serialize) -> Result<Event, ServiceError> {
    Event::default()
        .event(name)
        .json_data(data)
        .map_err(|e| ServiceError::Internal(format!("encoding a `{name}` event: {e}")))
}

/// What a stream has sent so far.
#[derive(Debug, Default, Clone, Copy)]
struct Cursor {
    /// Tick of the newest `tick` event sent.
    tick: Option<u64>,
    /// Policy version of the newest `values` event sent.
    policy_version: Option<u64>,
}

/// Sends `first`, then polls until the session is gone or sending fails.
async fn stream_loop(
    manager: &Arc<SessionManager>,
    caller: Caller,
    id: &str,
    interval: Duration,
    first: Event,
    tx: &mpsc::Sender<Result<Event, Infallible>>,
) {
    if tx.send(Ok(first)).await.is_err() {
        return;
    }
    let mut ticker = tokio::time::interval(interval);
    ticker.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let mut cursor = Cursor::default();
    loop {
        ticker.tick().await;
        // Reading the session and encoding its tables happen off the runtime.
        let owned = id.to_string();
        let polled = manager
            .off_runtime(move |m| {
                let mut next = cursor;
                poll(m, caller, &owned, &mut next).map(|events| (events, next))
            })
            .await;
        let (events, last) = match polled {
            Ok((events, next)) => {
                cursor = next;
                (events, None)
            }
            Err(ServiceError::NotFound(_)) => (Vec::new(), Some(end_event(id))),
            Err(e) => (Vec::new(), Some(error_event(&e))),
        };
        for event in events.into_iter().chain(last.iter().cloned()) {
            if tx.send(Ok(event)).await.is_err() {
                return;
            }
        }
        if last.is_some() {
            return;
        }
    }
}

fn end_event(id: &str) -> Event {
    json_event(
        "end",
        &EndEvent {
            id,
            reason: "deleted",
        },
    )
    .unwrap_or_else(|_| Event::default().event("end").data("{}"))
}

/// An `error` event with the `{"code","message"}` body a request would get.
fn error_event(e: &ServiceError) -> Event {
    let (status, _, code) = classify(e);
    let body = ErrorBody {
        code: code.to_string(),
        message: public_message(e, status),
        expected_seq: None,
        oldest_seq: None,
    };
    json_event("error", &body).unwrap_or_else(|_| Event::default().event("error").data("{}"))
}

/// The events due since `cursor`, which it advances.
fn poll(
    manager: &SessionManager,
    caller: Caller,
    id: &str,
    cursor: &mut Cursor,
) -> Result<Vec<Event>, ServiceError> {
    // No tables: just the tick and the policy version.
    let now = manager.values(caller, id, ValueSelection::default())?.value;
    let mut events = Vec::new();
    let due = match cursor.tick {
        Some(last) => usize::try_from(now.tick.saturating_sub(last)).unwrap_or(usize::MAX),
        None => MAX_TICKS_PER_POLL,
    };
    if due > 0 {
        // A little more than is due: the session may tick between the two
        // calls, and the filter below drops what was sent already.
        let want = due.min(MAX_TICKS_PER_POLL).saturating_add(64);
        let history = manager.history(caller, id, Some(want))?.value;
        let new: Vec<&HistoryEntry> = history
            .iter()
            .filter(|e| cursor.tick.is_none_or(|last| e.tick > last))
            .collect();
        let skip = new.len().saturating_sub(MAX_TICKS_PER_POLL);
        for entry in &new[skip..] {
            events.push(json_event("tick", entry)?);
        }
        // Ticks up to `now.tick` missing from the ring never will be in it
        // (no stimulus, or no history kept).
        cursor.tick = Some(new.last().map_or(now.tick, |e| e.tick.max(now.tick)));
    }
    if cursor.policy_version != Some(now.policy_version) {
        let values = manager
            .values(
                caller,
                id,
                ValueSelection {
                    v: true,
                    policy: true,
                    ..ValueSelection::default()
                },
            )?
            .value;
        cursor.policy_version = Some(values.policy_version);
        events.push(json_event("values", &values)?);
    }
    Ok(events)
}
