//! Sessions over REST, many at a time: creating hallway sessions (waiting
//! out a server that is busy creating), and sending each one first
//! observation or a `DELETE`, spread over several connections.

use std::sync::Arc;
use std::time::Duration;

use anyhow::{Result, ensure};
use hyper::{Method, StatusCode};
use serde::Deserialize;
use tokio::task::JoinSet;

use crate::args::Mode;
use crate::hallway::Hallway;
use crate::http::{HttpConn, HttpTarget, describe};

#[derive(Deserialize)]
struct Created {
    id: String,
}

/// The longest wait between two attempts to create a session the server
/// refused with 503 (it limits concurrent creations).
const CREATE_RETRY_MAX: Duration = Duration::from_millis(2560);

/// Creates `n` hallway sessions (seed i for the i-th) over `conns`
/// connections; returns their ids in order.
pub(crate) async fn create_sessions(
    target: &HttpTarget,
    n: usize,
    first_seed: usize,
    mode: Option<Mode>,
    conns: usize,
) -> Result<Vec<String>> {
    let conns = conns.clamp(1, n.max(1));
    let mut set = JoinSet::new();
    for w in 0..conns {
        let target = target.clone();
        set.spawn(async move {
            let mut conn = HttpConn::connect(&target).await?;
            let mut ids = Vec::new();
            for i in (w..n).step_by(conns) {
                let seed = first_seed + i;
                let agent = match mode {
                    Some(m) => format!(r#"{{"seed":{seed},"update_mode":"{}"}}"#, m.as_str()),
                    None => format!(r#"{{"seed":{seed}}}"#),
                };
                let body = format!(r#"{{"model":{{"preset":"hallway"}},"agent":{agent}}}"#);
                // A server busy creating (503 "retry shortly") is waited for,
                // with backoff, up to about 5 s.
                let mut wait = Duration::from_millis(5);
                let (status, bytes) = loop {
                    let (status, bytes) = conn
                        .send(Method::POST, "/v1/sessions", Some(body.clone()))
                        .await?;
                    if status != StatusCode::SERVICE_UNAVAILABLE || wait > CREATE_RETRY_MAX {
                        break (status, bytes);
                    }
                    tokio::time::sleep(wait).await;
                    wait *= 2;
                };
                ensure!(
                    status == StatusCode::CREATED,
                    "creating a session: {}",
                    describe(status, &bytes)
                );
                let created: Created = serde_json::from_slice(&bytes)?;
                ids.push((i, created.id));
            }
            Ok::<_, anyhow::Error>(ids)
        });
    }
    let mut ids = vec![String::new(); n];
    while let Some(joined) = set.join_next().await {
        for (i, id) in joined?? {
            ids[i] = id;
        }
    }
    Ok(ids)
}

/// Sends `POST` (one first observation) or `DELETE` to every session.
pub(crate) async fn for_each_session(
    target: &HttpTarget,
    ids: &[String],
    method: Method,
    conns: usize,
) -> Result<()> {
    let ids: Arc<[String]> = ids.into();
    let conns = conns.clamp(1, ids.len().max(1));
    let mut set = JoinSet::new();
    for w in 0..conns {
        let (target, ids, method) = (target.clone(), Arc::clone(&ids), method.clone());
        set.spawn(async move {
            let mut conn = HttpConn::connect(&target).await?;
            for id in ids.iter().skip(w).step_by(conns) {
                let (status, bytes) = if method == Method::DELETE {
                    conn.send(Method::DELETE, &format!("/v1/sessions/{id}"), None)
                        .await?
                } else {
                    let path = format!("/v1/sessions/{id}/observations");
                    conn.send(method.clone(), &path, Some(Hallway::new().json()))
                        .await?
                };
                ensure!(
                    status.is_success(),
                    "{method} session {id}: {}",
                    describe(status, &bytes)
                );
            }
            Ok::<_, anyhow::Error>(())
        });
    }
    while let Some(joined) = set.join_next().await {
        joined??;
    }
    Ok(())
}
