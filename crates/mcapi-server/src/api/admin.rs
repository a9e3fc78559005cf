//! The admin routes of a replica that a shard move drives
//! (`service::shards`, docs/cluster.md "How a shard moves"). Each needs
//! the admin key (`--admin-key`) as `Authorization: Bearer <key>`, and is
//! refused with 403 `forbidden` without it. Shard data travels as postcard
//! bytes (`application/octet-stream`), everything else as JSON.
//!
//! ```text
//! GET  /admin/shards                                 every shard's state here (cluster status)
//! GET  /admin/shards/{shard}                         status
//! POST /admin/shards/{shard}/export                  body: a manifest (empty: the whole shard)
//! POST /admin/shards/{shard}/freeze?lease_ms=L       503 to clients for L ms at most (default 30000)
//! POST /admin/shards/{shard}/thaw                    served here again
//! POST /admin/shards/{shard}/commit?epoch=E&owner=R&token=T
//!                                                    R's from E, if the freeze T's lease still runs
//! POST /admin/shards/{shard}/import?begin=true|false body: shard data
//! POST /admin/shards/{shard}/abort                   the import's copy deleted
//! POST /admin/shards/{shard}/activate?epoch=E        served here from epoch E
//! POST /admin/shards/{shard}/release?epoch=E&owner=R the new owner R; data deleted here
//! ```

use axum::Json;
use axum::Router;
use axum::body::Body;
use axum::extract::rejection::{PathRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::Deserialize;

use crate::api::error::ApiError;
use crate::api::extract::AppState;
use crate::service::ServiceError;
use crate::service::shards::{Manifest, ShardData, freeze_lease, parse_shard};
use mcapi_shards::ReplicaName;

/// Largest request body of an admin route: one shard's data.
pub const MAX_ADMIN_BODY: usize = 1 << 30;

/// The admin routes. Their body limit is [`MAX_ADMIN_BODY`], read only
/// after the admin key checked: an unauthenticated caller cannot make the
/// server buffer a shard-sized body.
pub fn routes() -> Router<AppState> {
    Router::new()
        .route("/admin/shards", get(all_shards))
        .route("/admin/shards/{shard}", get(status))
        .route("/admin/shards/{shard}/{step}", post(step))
}

/// The body of an admitted call, at most [`MAX_ADMIN_BODY`] bytes.
async fn read_body(body: Body) -> Result<axum::body::Bytes, ServiceError> {
    axum::body::to_bytes(body, MAX_ADMIN_BODY)
        .await
        .map_err(|e| {
            ServiceError::PayloadTooLarge(format!(
                "an admin call's body is at most {MAX_ADMIN_BODY} bytes (one shard's data): {e}"
            ))
        })
}

fn admit(state: &AppState, headers: &HeaderMap) -> Result<(), ServiceError> {
    let auth = headers
        .get(header::AUTHORIZATION)
        .map(|v| v.to_str().unwrap_or(""));
    state.manager.authenticate_admin(auth)
}

async fn status(
    State(state): State<AppState>,
    headers: HeaderMap,
    path: Result<Path<String>, PathRejection>,
) -> Result<Response, ApiError> {
    // The key first: nothing of the request is read for a caller without it.
    admit(&state, &headers)?;
    let Path(shard) = path.map_err(|e| ServiceError::BadRequest(e.body_text()))?;
    let shard = parse_shard(&shard)?;
    Ok(Json(state.manager.shard_status(shard)?).into_response())
}

async fn all_shards(
    State(state): State<AppState>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    admit(&state, &headers)?;
    let all = state.manager.off_runtime(|m| m.all_shards()).await?;
    Ok(Json(all).into_response())
}

/// The query of a step.
#[derive(Debug, Deserialize)]
struct StepQuery {
    begin: Option<bool>,
    epoch: Option<u64>,
    owner: Option<String>,
    lease_ms: Option<u64>,
    token: Option<u64>,
}

fn owner_of(q: &StepQuery) -> Result<ReplicaName, ServiceError> {
    q.owner
        .as_deref()
        .ok_or_else(|| ServiceError::field("owner", "is required"))
        .and_then(|o| ReplicaName::parse(o).map_err(|e| ServiceError::field("owner", e)))
}

/// Decodes a postcard body whole: an empty body is the default, and bytes
/// left after the value are refused (postcard alone would ignore them, so
/// 64 MiB of zeros read as an empty shard).
fn decode<T: serde::de::DeserializeOwned + Default>(
    body: &[u8],
    what: &str,
) -> Result<T, ServiceError> {
    if body.is_empty() {
        return Ok(T::default());
    }
    let (value, rest) = postcard::take_from_bytes(body)
        .map_err(|e| ServiceError::BadRequest(format!("the {what} does not decode: {e}")))?;
    if !rest.is_empty() {
        return Err(ServiceError::BadRequest(format!(
            "the {what} does not decode: {} bytes of {} are left after it",
            rest.len(),
            body.len()
        )));
    }
    Ok(value)
}

fn epoch_of(q: &StepQuery) -> Result<u64, ServiceError> {
    match q.epoch {
        Some(e) if e >= 1 && e <= i64::MAX as u64 => Ok(e),
        Some(e) => Err(ServiceError::field(
            "epoch",
            format!("must be between 1 and {}, not {e}", i64::MAX),
        )),
        None => Err(ServiceError::field("epoch", "is required")),
    }
}

fn octets(bytes: Vec<u8>) -> Response {
    ([(header::CONTENT_TYPE, "application/octet-stream")], bytes).into_response()
}

async fn step(
    State(state): State<AppState>,
    headers: HeaderMap,
    path: Result<Path<(String, String)>, PathRejection>,
    query: Result<Query<StepQuery>, QueryRejection>,
    body: Body,
) -> Result<Response, ApiError> {
    // The key first: nothing of the request is read for a caller without it.
    admit(&state, &headers)?;
    let Path((shard, step)) = path.map_err(|e| ServiceError::BadRequest(e.body_text()))?;
    let Query(q) = query
        .map_err(|e| ServiceError::BadRequest(format!("bad query string: {}", e.body_text())))?;
    let shard = parse_shard(&shard)?;
    let body = read_body(body).await?;
    let manager = &state.manager;
    let _one = manager.moving.lock().await;
    let answer = match step.as_str() {
        "export" => {
            let manifest: Option<Manifest> = if body.is_empty() {
                None
            } else {
                Some(decode(&body, "manifest")?)
            };
            if let Some(m) = &manifest
                && m.sessions.len() > manager.limits().max_sessions
            {
                return Err(ServiceError::LimitExceeded(format!(
                    "the manifest lists {} sessions; this replica holds at most {}",
                    m.sessions.len(),
                    manager.limits().max_sessions
                ))
                .into());
            }
            let data = manager
                .off_runtime(move |m| m.export_shard(shard, manifest.as_ref()))
                .await?;
            let bytes = postcard::to_allocvec(&data)
                .map_err(|e| ServiceError::Internal(format!("encoding shard data: {e}")))?;
            octets(bytes)
        }
        "freeze" => {
            let lease = freeze_lease(q.lease_ms)?;
            Json(manager.freeze_shard(shard, lease).await?).into_response()
        }
        "thaw" => Json(manager.thaw_shard(shard)?).into_response(),
        "commit" => {
            let epoch = epoch_of(&q)?;
            let owner = owner_of(&q)?;
            let token = q
                .token
                .ok_or_else(|| ServiceError::field("token", "is required (the freeze's)"))?;
            Json(manager.commit_shard(shard, token, &owner, epoch)?).into_response()
        }
        "import" => {
            let data: ShardData = decode(&body, "shard data")?;
            let n = manager
                .import_shard(shard, data, q.begin.unwrap_or(false))
                .await?;
            Json(serde_json::json!({ "sessions": n })).into_response()
        }
        "abort" => {
            let n = manager.abort_import(shard).await?;
            Json(serde_json::json!({ "deleted": n })).into_response()
        }
        "activate" => {
            let epoch = epoch_of(&q)?;
            let n = manager
                .off_runtime(move |m| m.activate_shard(shard, epoch))
                .await?;
            Json(serde_json::json!({ "sessions": n })).into_response()
        }
        "release" => {
            let epoch = epoch_of(&q)?;
            let owner = owner_of(&q)?;
            let n = manager.release_shard(shard, &owner, epoch).await?;
            Json(serde_json::json!({ "deleted": n })).into_response()
        }
        other => {
            return Err(ServiceError::UnknownRoute(format!(
                "POST /admin/shards/{{shard}}/{}: the steps are export, freeze, thaw, commit, import, abort, activate, release",
                other.escape_debug()
            ))
            .into());
        }
    };
    Ok(answer)
}
