//! The gRPC transport (tonic), package `mcapi.v1`, service `Agents`
//! (docs/grpc.md): a thin adapter over [`SessionManager`]. Each method
//! decodes its message ([`convert`]), makes one call into the service and
//! encodes the answer; errors go through the one table in
//! [`crate::api::error`]. Health (`grpc.health.v1`) and reflection (v1) are
//! served beside it.
//!
//! Streams: `Interact` reads the next observation only when its bounded
//! reply channel has room (backpressure), and stops when the client goes
//! away; `Watch` sends a snapshot per interval. Both end, with UNAVAILABLE,
//! when the server shuts down, so a graceful shutdown is not held up by
//! long-lived streams.
//!
//! Bounds ([`serve_with`], docs/limits.md): keys are checked and `Observe`
//! batches counted before a message is decoded ([`guard`]); a caller's
//! `Watch` streams count against its budget of watch streams, shared with
//! the REST event streams ([`crate::api::streams`]); connections, HTTP/2
//! streams per connection, keep-alive and the request timeout come from
//! [`ConnLimits`]; a panicking method, or a stream that panics while
//! answering a message, ends with INTERNAL (`internal_panic`).

pub mod convert;
pub mod guard;

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use futures_util::future::join_all;
use thiserror::Error;
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio::time::MissedTickBehavior;
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::MetadataMap;
use tonic::service::Routes;
use tonic::{Request, Response, Status, Streaming};
use tracing::Instrument;

use crate::api::conn::{ConnLimits, grpc_panic_layer, limited_incoming};
use crate::api::error::{step_error, to_status};
use crate::api::streams::{StreamLimiter, StreamSlot};
use crate::service::{Caller, ObservationIn, ServiceError, SessionManager, StepOut, Watch};

use pb::agents_server::{Agents, AgentsServer};

/// Generated messages, client and server of `proto/mcapi/v1/agents.proto`.
pub use mcapi_proto as pb;
/// Metadata key naming the session a call concerns (docs/sessions.md, "Session ids and ownership").
pub use mcapi_proto::SESSION_METADATA;

/// Why the gRPC server could not start or stopped with an error.
#[derive(Debug, Error)]
pub enum ServeError {
    /// Binding the address failed.
    #[error("binding the gRPC address: {0}")]
    Bind(#[from] std::io::Error),
    /// The reflection service could not load the descriptors.
    #[error("building the reflection service: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// The transport failed.
    #[error("gRPC transport: {0}")]
    Transport(#[from] tonic::transport::Error),
}

/// The `Agents` service over a session manager.
#[derive(Clone)]
pub struct AgentsService {
    manager: Arc<SessionManager>,
    stream_buffer: usize,
    stopping: watch::Receiver<bool>,
    streams: Option<Arc<StreamLimiter>>,
}

impl AgentsService {
    /// A service whose streams hold up to `stream_buffer` replies each.
    /// `stopping` turning true ends every open stream (server shutdown).
    pub fn new(
        manager: Arc<SessionManager>,
        stream_buffer: usize,
        stopping: watch::Receiver<bool>,
    ) -> Self {
        Self {
            manager,
            stream_buffer: stream_buffer.max(1),
            stopping,
            streams: None,
        }
    }

    /// `Watch` streams count against `streams` (shared with the REST event
    /// streams); without it they are not limited.
    pub fn with_streams(mut self, streams: Arc<StreamLimiter>) -> Self {
        self.streams = Some(streams);
        self
    }

    /// Starts an `Interact`-like stream: each message in is answered by
    /// `answer` with one message out, in order; the next message is read
    /// only once the reply found room in the stream's buffer. An error
    /// reply ends the stream, as do the client going away and shutdown.
    fn interact_stream<In, Out, F, Fut>(
        &self,
        request: Request<Streaming<In>>,
        name: &'static str,
        answer: F,
    ) -> Result<Response<ReceiverStream<Result<Out, Status>>>, Status>
    where
        In: Send + 'static,
        Out: Send + 'static,
        F: Fn(In, Arc<SessionManager>, Caller, Arc<Option<String>>) -> Fut + Send + 'static,
        Fut: Future<Output = Result<Out, Status>> + Send,
    {
        let caller = caller(&self.manager, &request)?;
        let meta = Arc::new(metadata_session(request.metadata())?);
        let span = tracing::info_span!(
            "stream",
            method = name,
            session = meta.as_deref().unwrap_or("")
        );
        let mut inbound = request.into_inner();
        let (tx, rx) = mpsc::channel(self.stream_buffer);
        let manager = Arc::clone(&self.manager);
        let ends = tx.clone();
        let serve = async move {
            loop {
                let reply = match inbound.message().await {
                    Ok(Some(message)) => {
                        answer(message, Arc::clone(&manager), caller, Arc::clone(&meta)).await
                    }
                    Ok(None) => return,
                    // A malformed message or a broken connection.
                    Err(status) => Err(status),
                };
                let failed = reply.is_err();
                if tx.send(reply).await.is_err() || failed {
                    return;
                }
            }
        };
        spawn_stream(name, span, ends, self.stopping.clone(), serve, ());
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    /// A slot for a new `Watch` stream of `caller`.
    fn stream_slot(
        &self,
        caller: Caller,
        peer: Option<std::net::IpAddr>,
    ) -> Result<Option<StreamSlot>, Status> {
        let Some(streams) = &self.streams else {
            return Ok(None);
        };
        streams.acquire(caller, peer).map(Some).map_err(to_status)
    }
}

/// Runs a stream's `work` on a task of its own until it ends, the client
/// goes away or the server stops (the stream then ends with UNAVAILABLE).
/// A panic in `work` ends the stream with INTERNAL (`internal_panic`), never
/// with the OK that a reply channel closed by the unwinding task would
/// give: `ends` is a sender of the stream kept for that last word. `hold`
/// is dropped when the stream ends (a `Watch` stream's slot).
fn spawn_stream<T: Send + 'static>(
    name: &'static str,
    span: tracing::Span,
    ends: mpsc::Sender<Result<T, Status>>,
    stopping: watch::Receiver<bool>,
    work: impl Future<Output = ()> + Send + 'static,
    hold: impl Send + 'static,
) {
    let worker = tokio::spawn(work.instrument(span.clone()));
    let abort = worker.abort_handle();
    tokio::spawn(
        async move {
            tokio::select! {
                joined = worker => {
                    if let Err(e) = joined
                        && e.is_panic()
                    {
                        let what = crate::api::conn::panic_text(&*e.into_panic());
                        let status = to_status(ServiceError::Panicked(format!(
                            "the {name} stream panicked: {what}"
                        )));
                        let _ = ends.send(Err(status)).await;
                    }
                }
                () = ends.closed() => {
                    abort.abort();
                    tracing::debug!("client went away");
                }
                () = stopped(stopping) => {
                    abort.abort();
                    let _ = ends.send(Err(shutting_down())).await;
                }
            }
            drop(hold);
        }
        .instrument(span),
    );
}

/// Resolves once `stopping` turns true; never if its sender is gone.
async fn stopped(mut stopping: watch::Receiver<bool>) {
    if stopping.wait_for(|s| *s).await.is_err() {
        std::future::pending::<()>().await;
    }
}

fn shutting_down() -> Status {
    to_status(ServiceError::Unavailable(
        "the server is shutting down".into(),
    ))
}

/// The caller: as [`guard::GuardLayer`] authenticated it before the
/// message was decoded, else from the `authorization` metadata
/// (`Bearer <key>`).
fn caller<T>(manager: &SessionManager, request: &Request<T>) -> Result<Caller, Status> {
    if let Some(caller) = request.extensions().get::<Caller>() {
        return Ok(*caller);
    }
    let metadata = request.metadata();
    let header = match metadata.get("authorization") {
        None => None,
        Some(v) => Some(v.to_str().map_err(|_| {
            to_status(ServiceError::Unauthenticated(
                "the `authorization` metadata must be `Bearer <key>`".into(),
            ))
        })?),
    };
    manager.authenticate(header).map_err(to_status)
}

/// The `x-mcapi-session` metadata, if sent.
fn metadata_session(metadata: &MetadataMap) -> Result<Option<String>, Status> {
    metadata
        .get(SESSION_METADATA)
        .map(|v| {
            v.to_str().map(str::to_string).map_err(|_| {
                to_status(ServiceError::field(
                    SESSION_METADATA,
                    "must be printable ASCII",
                ))
            })
        })
        .transpose()
}

#[tonic::async_trait]
impl Agents for AgentsService {
    async fn create_session(
        &self,
        request: Request<pb::CreateSessionRequest>,
    ) -> Result<Response<pb::SessionInfo>, Status> {
        let caller = caller(&self.manager, &request)?;
        let req = convert::create_session(request.into_inner()).map_err(to_status)?;
        let manager = Arc::clone(&self.manager);
        // Building a model (PVFs: an eigendecomposition) must not block the
        // runtime; the build stops if this call is abandoned (the guard is
        // dropped with its future).
        let watch = Watch::default();
        let _abandon = watch.abandon_on_drop();
        let info = tokio::task::spawn_blocking(move || match req {
            convert::CreateCall::Json(req) => manager.create_watched(caller, req, &watch),
            convert::CreateCall::Typed { model, agent } => {
                manager.create_parsed(caller, model, &agent, &watch)
            }
        })
        .await
        .map_err(|e| to_status(ServiceError::Internal(format!("create task: {e}"))))?
        .map_err(to_status)?;
        Ok(Response::new(convert::session_info(info)))
    }

    async fn get_session(
        &self,
        request: Request<pb::GetSessionRequest>,
    ) -> Result<Response<pb::SessionInfo>, Status> {
        let caller = caller(&self.manager, &request)?;
        let meta = metadata_session(request.metadata())?;
        let pb::GetSessionRequest { session_id } = request.into_inner();
        let id = convert::session_id(session_id, meta.as_deref()).map_err(to_status)?;
        let info = self
            .manager
            .off_runtime(move |m| m.get(caller, &id))
            .await
            .map_err(to_status)?;
        Ok(Response::new(convert::session_info(info)))
    }

    async fn list_sessions(
        &self,
        request: Request<pb::ListSessionsRequest>,
    ) -> Result<Response<pb::ListSessionsResponse>, Status> {
        let caller = caller(&self.manager, &request)?;
        let (after, limit) = convert::list_request(request.into_inner());
        let page = self
            .manager
            .off_runtime(move |m| m.list(caller, after.as_deref(), limit))
            .await
            .map_err(to_status)?;
        Ok(Response::new(convert::session_page(page)))
    }

    async fn delete_session(
        &self,
        request: Request<pb::DeleteSessionRequest>,
    ) -> Result<Response<pb::DeleteSessionResponse>, Status> {
        let caller = caller(&self.manager, &request)?;
        let meta = metadata_session(request.metadata())?;
        let pb::DeleteSessionRequest { session_id } = request.into_inner();
        let id = convert::session_id(session_id, meta.as_deref()).map_err(to_status)?;
        self.manager.delete(caller, &id).await.map_err(to_status)?;
        Ok(Response::new(pb::DeleteSessionResponse {}))
    }

    async fn observe(
        &self,
        request: Request<pb::ObserveRequest>,
    ) -> Result<Response<pb::ObserveResponse>, Status> {
        let caller = caller(&self.manager, &request)?;
        let meta = metadata_session(request.metadata())?;
        let (id, batch) =
            convert::observe_request(request.into_inner(), meta.as_deref()).map_err(to_status)?;
        let steps = self
            .manager
            .observe(caller, &id, batch)
            .await
            .map_err(to_status)?;
        Ok(Response::new(pb::ObserveResponse {
            steps: steps.into_iter().map(convert::step).collect(),
        }))
    }

    type InteractStream = ReceiverStream<Result<pb::Step, Status>>;

    async fn interact(
        &self,
        request: Request<Streaming<pb::Observation>>,
    ) -> Result<Response<Self::InteractStream>, Status> {
        self.interact_stream(
            request,
            "interact",
            |obs, manager, caller, meta| async move {
                let reply = match convert::observation(obs, meta.as_deref()) {
                    Ok((id, obs)) => manager.observe(caller, &id, vec![obs]).await,
                    Err(e) => Err(e),
                };
                // An error ends the stream.
                reply
                    .and_then(one_step)
                    .map(convert::step)
                    .map_err(to_status)
            },
        )
    }

    type InteractBatchStream = ReceiverStream<Result<pb::StepBatch, Status>>;

    async fn interact_batch(
        &self,
        request: Request<Streaming<pb::ObservationBatch>>,
    ) -> Result<Response<Self::InteractBatchStream>, Status> {
        self.interact_stream(
            request,
            "interact_batch",
            |batch, manager, caller, meta| async move {
                let results = observe_batch(&manager, caller, batch.observations, meta.as_deref());
                Ok(pb::StepBatch {
                    results: results.await.map_err(to_status)?,
                })
            },
        )
    }

    type WatchStream = ReceiverStream<Result<pb::SessionInfo, Status>>;

    async fn watch(
        &self,
        request: Request<pb::WatchRequest>,
    ) -> Result<Response<Self::WatchStream>, Status> {
        let caller = caller(&self.manager, &request)?;
        let meta = metadata_session(request.metadata())?;
        let peer = request.remote_addr().map(|a| a.ip());
        let (id, interval) =
            convert::watch_request(request.into_inner(), meta.as_deref()).map_err(to_status)?;
        // An unknown session fails the call itself, before any stream.
        let first = {
            let id = id.clone();
            self.manager
                .off_runtime(move |m| m.get(caller, &id))
                .await
                .map_err(to_status)?
        };
        // Held by the stream's task: given back when the stream ends.
        let slot = self.stream_slot(caller, peer)?;
        // One slot: a slow reader gets fresh snapshots, not a backlog of old ones.
        let (tx, rx) = mpsc::channel(1);
        let manager = Arc::clone(&self.manager);
        let span = tracing::info_span!("watch", session = %id);
        let ends = tx.clone();
        let work = async move { watch_loop(&manager, caller, &id, interval, first, &tx).await };
        spawn_stream("watch", span, ends, self.stopping.clone(), work, slot);
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn get_values(
        &self,
        request: Request<pb::GetValuesRequest>,
    ) -> Result<Response<pb::Values>, Status> {
        let caller = caller(&self.manager, &request)?;
        let meta = metadata_session(request.metadata())?;
        let (id, sel) =
            convert::values_request(request.into_inner(), meta.as_deref()).map_err(to_status)?;
        // The permit is held until the message is built; tonic encodes it
        // after the handler returns.
        let values = self
            .manager
            .off_runtime(move |m| m.values(caller, &id, sel))
            .await
            .map_err(to_status)?;
        Ok(Response::new(convert::values(values.value)))
    }

    async fn create_group(
        &self,
        request: Request<pb::CreateGroupRequest>,
    ) -> Result<Response<pb::GroupInfo>, Status> {
        let caller = caller(&self.manager, &request)?;
        let (model, agent, n, seed) =
            convert::create_group(request.into_inner()).map_err(to_status)?;
        let manager = Arc::clone(&self.manager);
        // Building N agents (and a model) must not block the runtime; it
        // stops if this call is abandoned (the guard goes with its future).
        let watch = Watch::default();
        let _abandon = watch.abandon_on_drop();
        let info = tokio::task::spawn_blocking(move || {
            manager.create_group_parsed(caller, model, &agent, n, seed, &watch)
        })
        .await
        .map_err(|e| to_status(ServiceError::Internal(format!("create task: {e}"))))?
        .map_err(to_status)?;
        Ok(Response::new(convert::group_info(info)))
    }

    async fn get_group(
        &self,
        request: Request<pb::GetGroupRequest>,
    ) -> Result<Response<pb::GroupInfo>, Status> {
        let caller = caller(&self.manager, &request)?;
        let meta = metadata_session(request.metadata())?;
        let pb::GetGroupRequest { group_id } = request.into_inner();
        let id = convert::group_id(group_id, meta.as_deref()).map_err(to_status)?;
        let info = self
            .manager
            .off_runtime(move |m| m.get_group(caller, &id))
            .await
            .map_err(to_status)?;
        Ok(Response::new(convert::group_info(info)))
    }

    async fn delete_group(
        &self,
        request: Request<pb::DeleteGroupRequest>,
    ) -> Result<Response<pb::DeleteGroupResponse>, Status> {
        let caller = caller(&self.manager, &request)?;
        let meta = metadata_session(request.metadata())?;
        let pb::DeleteGroupRequest { group_id } = request.into_inner();
        let id = convert::group_id(group_id, meta.as_deref()).map_err(to_status)?;
        self.manager
            .delete_group(caller, &id)
            .await
            .map_err(to_status)?;
        Ok(Response::new(pb::DeleteGroupResponse {}))
    }

    type StepGroupStream = ReceiverStream<Result<pb::GroupStepReply, Status>>;

    async fn step_group(
        &self,
        request: Request<Streaming<pb::GroupStepRequest>>,
    ) -> Result<Response<Self::StepGroupStream>, Status> {
        let caller = caller(&self.manager, &request)?;
        let meta = metadata_session(request.metadata())?;
        let span = tracing::info_span!(
            "stream",
            method = "step_group",
            group = meta.as_deref().unwrap_or("")
        );
        let inbound = request.into_inner();
        let (tx, rx) = mpsc::channel(STEP_GROUP_IN_FLIGHT);
        let manager = Arc::clone(&self.manager);
        let ends = tx.clone();
        let serve = step_group_stream(manager, caller, meta, inbound, tx);
        spawn_stream("step_group", span, ends, self.stopping.clone(), serve, ());
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn get_history(
        &self,
        request: Request<pb::GetHistoryRequest>,
    ) -> Result<Response<pb::History>, Status> {
        let caller = caller(&self.manager, &request)?;
        let meta = metadata_session(request.metadata())?;
        let (id, limit) =
            convert::history_request(request.into_inner(), meta.as_deref()).map_err(to_status)?;
        let entries = self
            .manager
            .off_runtime(move |m| m.history(caller, &id, limit))
            .await
            .map_err(to_status)?;
        Ok(Response::new(convert::history(entries.value)))
    }
}

/// Messages of one `StepGroup` stream the server reads before answering
/// them (docs/groups.md, "Pipelining"): one being applied and the rest
/// waiting; its replies wait for the client in a buffer as long.
pub const STEP_GROUP_IN_FLIGHT: usize = 8;

/// Serves a `StepGroup` stream: a reader checks each message's group id
/// and `seq` and decodes its columns, up to [`STEP_GROUP_IN_FLIGHT`]
/// messages ahead; the steps are applied one message at a time, in order,
/// each answered before the next is applied. The first message that does
/// not fit ends the stream with its status, after the replies before it.
async fn step_group_stream(
    manager: Arc<SessionManager>,
    caller: Caller,
    meta: Option<String>,
    mut inbound: Streaming<pb::GroupStepRequest>,
    tx: mpsc::Sender<Result<pb::GroupStepReply, Status>>,
) {
    let (ahead_tx, mut ahead) = mpsc::channel(STEP_GROUP_IN_FLIGHT - 1);
    let read = async move {
        let mut group: Option<String> = None;
        let mut last_seq: Option<u64> = None;
        loop {
            let item = match inbound.message().await {
                Ok(Some(message)) => {
                    step_message(message, meta.as_deref(), &mut group, &mut last_seq)
                }
                Ok(None) => return,
                Err(status) => Err(status),
            };
            let failed = item.is_err();
            if ahead_tx.send(item).await.is_err() || failed {
                return;
            }
        }
    };
    let apply = async move {
        // The stimulus dimensions of the group, for refused members' rows.
        let mut width: Option<usize> = None;
        while let Some(item) = ahead.recv().await {
            let reply = match item {
                Ok((id, seq, columns)) => {
                    let numbered = !columns.seqs.is_empty();
                    let n = match width {
                        Some(n) => Ok(n),
                        None => manager
                            .group_for(caller, &id)
                            .map(|g| *width.insert(g.model.stimuli.len())),
                    };
                    match n {
                        Ok(n) => manager
                            .step_group(caller, &id, columns)
                            .await
                            .map(|steps| convert::group_step_reply(seq, n, steps, numbered))
                            .map_err(to_status),
                        Err(e) => Err(to_status(e)),
                    }
                }
                Err(status) => Err(status),
            };
            let failed = reply.is_err();
            if tx.send(reply).await.is_err() || failed {
                return;
            }
        }
    };
    tokio::join!(read, apply);
}

/// One `StepGroup` message checked against the stream so far: the group
/// is the first message's (or the metadata's), later ones name it again or
/// leave it empty; each `seq` is the previous one's plus one.
fn step_message(
    message: pb::GroupStepRequest,
    meta: Option<&str>,
    group: &mut Option<String>,
    last_seq: &mut Option<u64>,
) -> Result<(String, u64, crate::service::groups::Columns), Status> {
    let (id, seq, columns) = convert::group_step(message).map_err(to_status)?;
    let id = match group.as_deref() {
        None => convert::group_id(id, meta).map_err(to_status)?,
        Some(first) if id.is_empty() || id == first => first.to_string(),
        Some(first) => {
            return Err(to_status(ServiceError::field(
                "group_id",
                format!("`{id}` differs from the stream's group `{first}`"),
            )));
        }
    };
    if let Some(last) = *last_seq
        && Some(seq) != last.checked_add(1)
    {
        let why = if seq <= last {
            "does not increase"
        } else {
            "skips ahead"
        };
        return Err(to_status(ServiceError::SequenceOutOfOrder(format!(
            "`seq` is {seq} after {last}: it {why}; each message's `seq` is the previous one's plus one"
        ))));
    }
    *last_seq = Some(seq);
    group.get_or_insert_with(|| id.clone());
    Ok((id, seq, columns))
}

/// The one step of a one-observation batch.
fn one_step(steps: Vec<StepOut>) -> Result<StepOut, ServiceError> {
    steps
        .into_iter()
        .next()
        .ok_or_else(|| ServiceError::Internal("observe returned no step".into()))
}

/// The results of one `InteractBatch` message, one per observation in
/// order. Each session's observations are applied in order, one at a time;
/// the sessions run concurrently (so a durable store commits them together).
/// After a session's observation is refused, its later ones in the message
/// are not applied. A message whose estimated CPU time is over
/// `--max-batch-ms` is refused whole (it ends the stream).
async fn observe_batch(
    manager: &SessionManager,
    caller: Caller,
    observations: Vec<pb::Observation>,
    meta: Option<&str>,
) -> Result<Vec<pb::StepResult>, ServiceError> {
    let n = observations.len();
    let mut results = vec![pb::StepResult::default(); n];
    // The observations by session, sessions in order of first appearance.
    let mut groups: Vec<(String, Vec<(usize, ObservationIn)>)> = Vec::new();
    let mut group_of: HashMap<String, usize> = HashMap::with_capacity(n);
    for (i, obs) in observations.into_iter().enumerate() {
        match convert::observation(obs, meta) {
            Ok((id, obs)) => match group_of.get(&id) {
                Some(&g) => groups[g].1.push((i, obs)),
                None => {
                    group_of.insert(id.clone(), groups.len());
                    groups.push((id, vec![(i, obs)]));
                }
            },
            Err(e) => results[i] = refused(e),
        }
    }
    manager.check_message_cost(
        caller,
        groups.iter().map(|(id, items)| (id.as_str(), items.len())),
    )?;
    let per_session = groups.into_iter().map(|(id, items)| async move {
        let mut out = Vec::with_capacity(items.len());
        let mut refused_at: Option<usize> = None;
        for (i, obs) in items {
            let outcome = match refused_at {
                Some(first) => Err(ServiceError::BadRequest(format!(
                    "not applied: observations[{first}] of the same session was refused \
                     earlier in this message"
                ))),
                None => manager
                    .observe(caller, &id, vec![obs])
                    .await
                    .and_then(one_step),
            };
            out.push((
                i,
                match outcome {
                    Ok(step) => pb::StepResult {
                        outcome: Some(pb::step_result::Outcome::Step(convert::step(step))),
                    },
                    Err(e) => {
                        refused_at.get_or_insert(i);
                        refused(e)
                    }
                },
            ));
        }
        out
    });
    for (i, result) in join_all(per_session).await.into_iter().flatten() {
        results[i] = result;
    }
    Ok(results)
}

/// A refused observation's result.
fn refused(e: ServiceError) -> pb::StepResult {
    pb::StepResult {
        outcome: Some(pb::step_result::Outcome::Error(step_error(e))),
    }
}

/// A snapshot now and one per `interval`, until the session is deleted
/// (ends with NOT_FOUND) or the client goes away.
async fn watch_loop(
    manager: &Arc<SessionManager>,
    caller: Caller,
    id: &str,
    interval: Duration,
    first: crate::service::SessionInfo,
    tx: &mpsc::Sender<Result<pb::SessionInfo, Status>>,
) {
    let mut ticker = tokio::time::interval(interval);
    ticker.set_missed_tick_behavior(MissedTickBehavior::Delay);
    ticker.tick().await;
    if tx.send(Ok(convert::session_info(first))).await.is_err() {
        return;
    }
    loop {
        ticker.tick().await;
        let owned = id.to_string();
        match manager.off_runtime(move |m| m.get(caller, &owned)).await {
            Ok(info) => {
                if tx.send(Ok(convert::session_info(info))).await.is_err() {
                    return;
                }
            }
            Err(e) => {
                let _ = tx.send(Err(to_status(e))).await;
                return;
            }
        }
    }
}

/// How the gRPC server runs: stream buffers, connection limits and the
/// stream budget shared with the REST event streams.
#[derive(Debug, Clone)]
pub struct GrpcOptions {
    /// Buffered replies per `Interact` stream.
    pub stream_buffer: usize,
    /// Connection limits of the port.
    pub limits: ConnLimits,
    /// Concurrent `Watch` streams per caller.
    pub streams: Arc<StreamLimiter>,
}

impl GrpcOptions {
    /// Default connection limits with this stream buffer.
    pub fn new(stream_buffer: usize) -> Self {
        let limits = ConnLimits::default();
        Self {
            stream_buffer,
            streams: StreamLimiter::new(limits.max_streams_per_key),
            limits,
        }
    }
}

/// `Agents` (with the body-size limit of the manager), health and
/// reflection v1, ready for a tonic server. Health reports `mcapi.v1.Agents`
/// NOT_SERVING while stored sessions are recovered and after shutdown
/// begins, SERVING in between.
pub async fn router(
    manager: Arc<SessionManager>,
    stream_buffer: usize,
    stopping: watch::Receiver<bool>,
) -> Result<Routes, ServeError> {
    router_with(manager, &GrpcOptions::new(stream_buffer), stopping).await
}

/// As [`router`], with the `Watch` streams counted against `opts.streams`.
pub async fn router_with(
    manager: Arc<SessionManager>,
    opts: &GrpcOptions,
    stopping: watch::Receiver<bool>,
) -> Result<Routes, ServeError> {
    let max_message = manager.limits().max_body_bytes;
    let (health, health_service) = tonic_health::server::health_reporter();
    let ready = manager.is_ready();
    if ready {
        health.set_serving::<AgentsServer<AgentsService>>().await;
    } else {
        health
            .set_not_serving::<AgentsServer<AgentsService>>()
            .await;
    }
    tokio::spawn({
        let manager = Arc::clone(&manager);
        let mut stopping = stopping.clone();
        async move {
            if !ready {
                while !manager.is_ready() && !*stopping.borrow() {
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
                if !*stopping.borrow() {
                    health.set_serving::<AgentsServer<AgentsService>>().await;
                }
            }
            let _ = stopping.wait_for(|stop| *stop).await;
            health
                .set_not_serving::<AgentsServer<AgentsService>>()
                .await;
        }
    });
    let service = AgentsService::new(manager, opts.stream_buffer, stopping)
        .with_streams(Arc::clone(&opts.streams));
    let agents = AgentsServer::new(service).max_decoding_message_size(max_message);
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    Ok(Routes::new(agents)
        .add_service(health_service)
        .add_service(reflection))
}

/// Serves gRPC on `addr` until `shutdown` resolves, then ends open streams
/// and drains in-flight calls.
pub async fn serve(
    addr: SocketAddr,
    manager: Arc<SessionManager>,
    stream_buffer: usize,
    shutdown: impl Future<Output = ()>,
) -> Result<(), ServeError> {
    let listener = TcpListener::bind(addr).await?;
    serve_on(listener, manager, stream_buffer, shutdown).await
}

/// As [`serve`], on a listener the caller bound (tests bind port 0), with
/// the default connection limits.
pub async fn serve_on(
    listener: TcpListener,
    manager: Arc<SessionManager>,
    stream_buffer: usize,
    shutdown: impl Future<Output = ()>,
) -> Result<(), ServeError> {
    serve_with(
        listener,
        None,
        manager,
        GrpcOptions::new(stream_buffer),
        shutdown,
    )
    .await
}

/// As [`serve_on`], on `listener` and, if given, the Unix socket `socket`
/// too, with these options: at most `max_connections` connections on
/// each, each with its HTTP/2 preface due within the header-read
/// timeout, HTTP/2 and TCP keep-alive, `http2_max_streams` calls per
/// connection, the request timeout (in [`guard`]); keys checked and
/// `Observe` batches counted before decoding ([`guard`]); a panicking
/// method answers INTERNAL.
pub async fn serve_with(
    listener: TcpListener,
    socket: Option<tokio::net::UnixListener>,
    manager: Arc<SessionManager>,
    opts: GrpcOptions,
    shutdown: impl Future<Output = ()>,
) -> Result<(), ServeError> {
    let (stop_tx, stop_rx) = watch::channel(false);
    let guard = guard::GuardLayer::new(Arc::clone(&manager), opts.limits.request_timeout());
    // Clustered, every call's response metadata names this replica.
    let replica = crate::api::router::replica_header(&manager);
    let routes = router_with(manager, &opts, stop_rx).await?;
    if let Ok(addr) = listener.local_addr() {
        tracing::info!(%addr, "gRPC listening");
    }
    if let Some(path) = socket
        .as_ref()
        .and_then(|s| s.local_addr().ok())
        .and_then(|a| a.as_pathname().map(|p| p.display().to_string()))
    {
        tracing::info!(socket = %path, "gRPC listening on a Unix socket");
    }
    let signal = async move {
        shutdown.await;
        tracing::info!("gRPC shutting down");
        // Ends Interact and Watch streams, which would hold the drain up.
        let _ = stop_tx.send(true);
    };
    let limits = &opts.limits;
    let layers = tower::ServiceBuilder::new()
        .layer(grpc_panic_layer())
        .map_response(
            move |mut response: axum::http::Response<tonic::body::Body>| {
                if let Some(value) = &replica {
                    response
                        .headers_mut()
                        .insert(crate::api::router::REPLICA_HEADER, value.clone());
                }
                response
            },
        )
        .layer(guard);
    tonic::transport::Server::builder()
        .max_concurrent_streams(limits.http2_max_streams)
        .http2_keepalive_interval(Some(Duration::from_millis(limits.http2_keepalive_ms)))
        .http2_keepalive_timeout(Some(Duration::from_millis(
            limits.http2_keepalive_timeout_ms,
        )))
        .layer(layers)
        .add_routes(routes)
        .serve_with_incoming_shutdown(limited_incoming(listener, socket, limits), signal)
        .await?;
    Ok(())
}
