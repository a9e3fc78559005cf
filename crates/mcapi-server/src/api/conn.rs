//! Connection limits of both transports (docs/limits.md): how many
//! connections a port holds, how long a client may take to send a request
//! head (REST) or the HTTP/2 preface (gRPC), how long a
//! request may take, TCP keep-alive, and panic isolation.
//!
//! The REST port is served here with hyper's HTTP/1.1 connection builder
//! (`axum::serve` cannot set hyper's header-read timeout): one accept task
//! takes a connection only with a free slot of the port's semaphore, so a
//! flood of half-open connections waits in the kernel's listen backlog
//! instead of using file descriptors; each connection gets hyper's
//! `header_read_timeout`, which hyper starts whenever it waits for a request
//! head, so it is also the idle limit of a kept-alive connection. A graceful
//! shutdown stops accepting, lets in-flight requests finish and closes idle
//! connections (event streams end through [`crate::api::dashboard::Stopping`]).
//!
//! The gRPC port keeps tonic's server and gets its connections from the
//! same kind of accept task ([`limited_incoming`]), from its TCP port and,
//! with `--grpc-socket`, from a Unix socket as well (each listener with a
//! budget of its own); each connection must
//! deliver the 24-byte HTTP/2 preface within the header-read timeout (h2
//! itself waits for it forever), then HTTP/2 keep-alive pings find dead
//! peers. Its writes are gathered ([`crate::api::coalesce`]).

use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::Router;
use axum::extract::{ConnectInfo, Request};
use axum::response::IntoResponse;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use serde::Serialize;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream, UnixListener, UnixStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc};
use tokio::time::Sleep;
use tokio_stream::wrappers::ReceiverStream;
use tower::ServiceExt;
use tower_http::catch_panic::{CatchPanicLayer, ResponseForPanic};

use crate::api::coalesce::Coalesced;
use crate::api::error::{ApiError, to_status};
use crate::service::ServiceError;

/// Connection limits of both ports (flags under "Connection limits" in
/// [`crate::config::ServeConfig`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ConnLimits {
    /// Open connections per port.
    pub max_connections: usize,
    /// Time to send a request head (REST; also the keep-alive idle limit)
    /// or the HTTP/2 preface (gRPC), in ms.
    pub header_read_timeout_ms: u64,
    /// Time to answer one request, in ms (streams excepted once open).
    pub request_timeout_ms: u64,
    /// Concurrent event and `Watch` streams per API key (per client IP
    /// without keys).
    pub max_streams_per_key: usize,
    /// Concurrent HTTP/2 streams per gRPC connection.
    pub http2_max_streams: u32,
    /// HTTP/2 keep-alive ping interval, in ms.
    pub http2_keepalive_ms: u64,
    /// HTTP/2 keep-alive ping timeout, in ms.
    pub http2_keepalive_timeout_ms: u64,
    /// TCP keep-alive idle time, in seconds.
    pub tcp_keepalive_secs: u64,
}

impl Default for ConnLimits {
    fn default() -> Self {
        Self {
            // Two ports: 8192 descriptors at most, within common fd limits.
            max_connections: 4096,
            // hyper's own default; nginx's client_header_timeout is 60 s.
            header_read_timeout_ms: 30_000,
            // nginx's client_body_timeout / send_timeout are 60 s.
            request_timeout_ms: 60_000,
            max_streams_per_key: 16,
            // hyper's default for HTTP/2 servers.
            http2_max_streams: 200,
            http2_keepalive_ms: 60_000,
            // hyper's default ping timeout.
            http2_keepalive_timeout_ms: 20_000,
            tcp_keepalive_secs: 60,
        }
    }
}

impl ConnLimits {
    /// Header-read timeout.
    pub fn header_read_timeout(&self) -> Duration {
        Duration::from_millis(self.header_read_timeout_ms)
    }

    /// Request timeout.
    pub fn request_timeout(&self) -> Duration {
        Duration::from_millis(self.request_timeout_ms)
    }

    /// TCP keep-alive idle time.
    pub fn tcp_keepalive(&self) -> Duration {
        Duration::from_secs(self.tcp_keepalive_secs)
    }

    /// Checks the limits (part of `ServeConfig::validate`).
    pub fn validate(&self) -> Result<(), String> {
        let nonzero = [
            ("--max-connections", self.max_connections as u64),
            ("--header-read-timeout-ms", self.header_read_timeout_ms),
            ("--request-timeout-ms", self.request_timeout_ms),
            ("--max-streams-per-key", self.max_streams_per_key as u64),
            ("--http2-max-streams", u64::from(self.http2_max_streams)),
            ("--http2-keepalive-ms", self.http2_keepalive_ms),
            (
                "--http2-keepalive-timeout-ms",
                self.http2_keepalive_timeout_ms,
            ),
            ("--tcp-keepalive-secs", self.tcp_keepalive_secs),
        ];
        for (flag, value) in nonzero {
            if value == 0 {
                return Err(format!("{flag} must be at least 1"));
            }
        }
        // A tokio semaphore holds at most usize::MAX >> 3 permits.
        if self.max_connections > 1 << 24 {
            return Err(format!(
                "--max-connections must be at most {}, not {}",
                1 << 24,
                self.max_connections
            ));
        }
        let day_ms = 86_400_000;
        for (flag, ms) in [
            ("--header-read-timeout-ms", self.header_read_timeout_ms),
            ("--request-timeout-ms", self.request_timeout_ms),
            ("--http2-keepalive-ms", self.http2_keepalive_ms),
            (
                "--http2-keepalive-timeout-ms",
                self.http2_keepalive_timeout_ms,
            ),
        ] {
            if ms > day_ms {
                return Err(format!("{flag} must be at most {day_ms} (a day), not {ms}"));
            }
        }
        if self.tcp_keepalive_secs > 86_400 {
            return Err(format!(
                "--tcp-keepalive-secs must be at most 86400 (a day), not {}",
                self.tcp_keepalive_secs
            ));
        }
        Ok(())
    }

    /// Logs a warning when `listeners` listeners (the two ports, and the
    /// gRPC socket if there is one) at their connection limit would need
    /// more file descriptors than the process may open.
    pub fn warn_on_fd_limit(&self, listeners: u64) {
        let Some(limit) = open_files_limit() else {
            return;
        };
        // The listeners' connections, plus the store, the listeners
        // themselves and some headroom.
        let need = (self.max_connections as u64).saturating_mul(listeners) + 256;
        if need > limit {
            tracing::warn!(
                max_connections = self.max_connections,
                listeners,
                open_files_limit = limit,
                "--max-connections on every listener may exceed the open-files limit (ulimit -n); \
                 accepting then pauses for a second at a time"
            );
        }
    }
}

/// The soft limit on open files (Linux: `/proc/self/limits`).
fn open_files_limit() -> Option<u64> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = limits.lines().find(|l| l.starts_with("Max open files"))?;
    line.split_whitespace().nth(3)?.parse().ok()
}

/// A listener the accept task can take connections from.
trait Listener: Send + Sync + 'static {
    type Stream: Send + 'static;
    type Peer: Send + 'static;

    fn poll_accept(
        &self,
        cx: &mut Context<'_>,
    ) -> Poll<std::io::Result<(Self::Stream, Self::Peer)>>;

    /// Socket options of an accepted connection.
    fn tune(stream: &Self::Stream, limits: &ConnLimits);
}

impl Listener for TcpListener {
    type Stream = TcpStream;
    type Peer = SocketAddr;

    fn poll_accept(&self, cx: &mut Context<'_>) -> Poll<std::io::Result<(TcpStream, SocketAddr)>> {
        TcpListener::poll_accept(self, cx)
    }

    fn tune(stream: &TcpStream, limits: &ConnLimits) {
        tune(stream, limits.tcp_keepalive());
    }
}

impl Listener for UnixListener {
    type Stream = UnixStream;
    type Peer = tokio::net::unix::SocketAddr;

    fn poll_accept(&self, cx: &mut Context<'_>) -> Poll<std::io::Result<(UnixStream, Self::Peer)>> {
        UnixListener::poll_accept(self, cx)
    }

    /// Nothing to set: no Nagle, and a peer that goes away closes the socket.
    fn tune(_: &UnixStream, _: &ConnLimits) {}
}

/// One accepted connection with its slot of the listener's budget.
struct Accepted<S, P> {
    stream: S,
    peer: P,
    permit: OwnedSemaphorePermit,
}

/// Accepts connections on `listener`, each only once a slot of
/// `max_connections` is free, and hands them over a one-slot channel. Ends
/// (closing the listener) when the receiver is dropped.
fn spawn_acceptor<L: Listener>(
    listener: L,
    limits: &ConnLimits,
) -> mpsc::Receiver<Accepted<L::Stream, L::Peer>> {
    let (tx, rx) = mpsc::channel(1);
    let slots = Arc::new(Semaphore::new(limits.max_connections));
    let limits = limits.clone();
    tokio::spawn(async move {
        loop {
            let permit = tokio::select! {
                permit = Arc::clone(&slots).acquire_owned() => match permit {
                    Ok(p) => p,
                    Err(_) => return,
                },
                () = tx.closed() => return,
            };
            let accepted = tokio::select! {
                accepted = std::future::poll_fn(|cx| listener.poll_accept(cx)) => accepted,
                () = tx.closed() => return,
            };
            let (stream, peer) = match accepted {
                Ok(pair) => pair,
                Err(e) if is_connection_error(&e) => continue,
                Err(e) => {
                    // EMFILE and the like: back off instead of spinning, as
                    // hyper's and axum's accept loops do.
                    tracing::error!(error = %e, "accepting a connection failed; retrying in 1 s");
                    tokio::time::sleep(Duration::from_secs(1)).await;
                    continue;
                }
            };
            L::tune(&stream, &limits);
            if tx
                .send(Accepted {
                    stream,
                    peer,
                    permit,
                })
                .await
                .is_err()
            {
                return;
            }
        }
    });
    rx
}

fn is_connection_error(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::ConnectionRefused
            | std::io::ErrorKind::ConnectionAborted
            | std::io::ErrorKind::ConnectionReset
    )
}

/// `TCP_NODELAY` and TCP keep-alive on an accepted connection.
fn tune(stream: &TcpStream, keepalive: Duration) {
    if let Err(e) = stream.set_nodelay(true) {
        tracing::debug!(error = %e, "TCP_NODELAY not set");
    }
    let sock = socket2::SockRef::from(stream);
    if let Err(e) = sock.set_tcp_keepalive(&socket2::TcpKeepalive::new().with_time(keepalive)) {
        tracing::debug!(error = %e, "TCP keep-alive not set");
    }
}

/// Serves `app` over HTTP/1.1 on `listener` until `shutdown` resolves, then
/// stops accepting, lets in-flight requests finish and closes idle
/// connections. Handlers see the peer as `ConnectInfo<SocketAddr>`.
pub async fn serve_http(
    listener: TcpListener,
    app: Router,
    limits: &ConnLimits,
    shutdown: impl Future<Output = ()>,
) {
    let mut accepted = spawn_acceptor(listener, limits);
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(limits.header_read_timeout())
        .keep_alive(true);
    let graceful = GracefulShutdown::new();
    tokio::pin!(shutdown);
    loop {
        let Accepted {
            stream,
            peer,
            permit,
        } = tokio::select! {
            next = accepted.recv() => match next {
                Some(a) => a,
                None => break,
            },
            () = &mut shutdown => break,
        };
        let service = app
            .clone()
            .map_request(move |mut req: Request<hyper::body::Incoming>| {
                req.extensions_mut().insert(ConnectInfo(peer));
                req
            });
        let conn =
            builder.serve_connection(TokioIo::new(stream), TowerToHyperService::new(service));
        let conn = graceful.watch(conn);
        tokio::spawn(async move {
            if let Err(e) = conn.await {
                // Header-read timeouts, resets, malformed requests.
                tracing::debug!(%peer, error = %e, "connection ended with an error");
            }
            drop(permit);
        });
    }
    // Closes the listener: nothing new is accepted while the rest drain.
    drop(accepted);
    tracing::info!(connections = graceful.count(), "REST shutting down");
    graceful.shutdown().await;
}

/// The gRPC connections, for tonic's `serve_with_incoming_shutdown`: from
/// the TCP port and, if given, the Unix socket, at most `max_connections`
/// at once from each, each with a deadline for the HTTP/2 preface (and TCP
/// keep-alive on the port's).
pub fn limited_incoming(
    listener: TcpListener,
    socket: Option<UnixListener>,
    limits: &ConnLimits,
) -> impl tokio_stream::Stream<Item = std::io::Result<LimitedIo>> + use<> {
    let preface_within = limits.header_read_timeout();
    let (tx, rx) = mpsc::channel(1);
    let mut tcp = spawn_acceptor(listener, limits);
    let mut unix = socket.map(|socket| spawn_acceptor(socket, limits));
    tokio::spawn(async move {
        loop {
            let from_socket = async {
                match &mut unix {
                    Some(accepted) => accepted.recv().await,
                    None => std::future::pending().await,
                }
            };
            let (stream, permit) = tokio::select! {
                next = tcp.recv() => match next {
                    Some(a) => (GrpcStream::Tcp(a.stream), a.permit),
                    None => return,
                },
                next = from_socket => match next {
                    Some(a) => (GrpcStream::Unix(a.stream), a.permit),
                    None => return,
                },
                () = tx.closed() => return,
            };
            let io = LimitedIo {
                inner: Coalesced::new(stream),
                _permit: permit,
                preface: Some(Box::pin(tokio::time::sleep(preface_within))),
                preface_left: H2_PREFACE_LEN,
            };
            if tx.send(Ok(io)).await.is_err() {
                return;
            }
        }
    });
    ReceiverStream::new(rx)
}

/// Bytes of the HTTP/2 client connection preface.
const H2_PREFACE_LEN: usize = 24;

/// A gRPC connection holding its slot of its listener's budget; reads fail
/// with `TimedOut` if the HTTP/2 preface has not arrived by its deadline.
pub struct LimitedIo {
    inner: Coalesced<GrpcStream>,
    _permit: OwnedSemaphorePermit,
    preface: Option<Pin<Box<Sleep>>>,
    preface_left: usize,
}

impl tonic::transport::server::Connected for LimitedIo {
    type ConnectInfo = tonic::transport::server::TcpConnectInfo;

    /// A Unix socket's peer has no address: its calls have no
    /// `remote_addr`, so without API keys its streams count against the
    /// server's one budget ([`crate::api::streams`]).
    fn connect_info(&self) -> Self::ConnectInfo {
        match self.inner.get_ref() {
            GrpcStream::Tcp(stream) => stream.connect_info(),
            GrpcStream::Unix(_) => tonic::transport::server::TcpConnectInfo {
                local_addr: None,
                remote_addr: None,
            },
        }
    }
}

/// A gRPC connection: from the TCP port, or from the Unix socket
/// (`--grpc-socket`), which spares a client on the same host the kernel's
/// TCP path.
pub enum GrpcStream {
    /// From the TCP port.
    Tcp(TcpStream),
    /// From the Unix socket.
    Unix(UnixStream),
}

impl AsyncRead for GrpcStream {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        match self.get_mut() {
            Self::Tcp(s) => Pin::new(s).poll_read(cx, buf),
            Self::Unix(s) => Pin::new(s).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for GrpcStream {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        match self.get_mut() {
            Self::Tcp(s) => Pin::new(s).poll_write(cx, buf),
            Self::Unix(s) => Pin::new(s).poll_write(cx, buf),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        match self.get_mut() {
            Self::Tcp(s) => Pin::new(s).poll_flush(cx),
            Self::Unix(s) => Pin::new(s).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        match self.get_mut() {
            Self::Tcp(s) => Pin::new(s).poll_shutdown(cx),
            Self::Unix(s) => Pin::new(s).poll_shutdown(cx),
        }
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        match self.get_mut() {
            Self::Tcp(s) => Pin::new(s).poll_write_vectored(cx, bufs),
            Self::Unix(s) => Pin::new(s).poll_write_vectored(cx, bufs),
        }
    }

    fn is_write_vectored(&self) -> bool {
        match self {
            Self::Tcp(s) => s.is_write_vectored(),
            Self::Unix(s) => s.is_write_vectored(),
        }
    }
}

impl AsyncRead for LimitedIo {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                let read = buf.filled().len() - before;
                this.preface_left = this.preface_left.saturating_sub(read);
                if this.preface_left == 0 || read == 0 {
                    this.preface = None;
                }
                Poll::Ready(Ok(()))
            }
            Poll::Pending => {
                let expired = this
                    .preface
                    .as_mut()
                    .is_some_and(|deadline| deadline.as_mut().poll(cx).is_ready());
                if !expired {
                    return Poll::Pending;
                }
                this.preface = None;
                tracing::debug!("no HTTP/2 preface within the header-read timeout");
                Poll::Ready(Err(std::io::Error::new(
                    std::io::ErrorKind::TimedOut,
                    "no HTTP/2 preface within the header-read timeout",
                )))
            }
            ready => ready,
        }
    }
}

impl AsyncWrite for LimitedIo {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

/// A connection whose writes fail with `TimedOut` once one has made no
/// progress for `limit` (nginx's `send_timeout`): a REST client that stops
/// reading its response or its event stream does not hold its connection,
/// nor its stream slot, forever.
pub struct SendTimeout<T> {
    inner: T,
    limit: Duration,
    /// Set while a write is blocked: when it started to be.
    stalled: Option<Pin<Box<Sleep>>>,
}

impl<T> SendTimeout<T> {
    /// `inner` with writes that may block for at most `limit`.
    pub fn new(inner: T, limit: Duration) -> Self {
        Self {
            inner,
            limit,
            stalled: None,
        }
    }

    /// The outcome of a write poll: progress clears the stall, a stall
    /// past the limit is an error.
    fn check<R>(
        &mut self,
        cx: &mut Context<'_>,
        polled: Poll<std::io::Result<R>>,
    ) -> Poll<std::io::Result<R>> {
        if polled.is_ready() {
            self.stalled = None;
            return polled;
        }
        let limit = self.limit;
        let stalled = self
            .stalled
            .get_or_insert_with(|| Box::pin(tokio::time::sleep(limit)));
        if stalled.as_mut().poll(cx).is_ready() {
            self.stalled = None;
            tracing::debug!("a write made no progress within the send timeout");
            return Poll::Ready(Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                "the client did not read for longer than the send timeout",
            )));
        }
        Poll::Pending
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for SendTimeout<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for SendTimeout<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        let polled = Pin::new(&mut self.inner).poll_write(cx, buf);
        self.check(cx, polled)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        let polled = Pin::new(&mut self.inner).poll_flush(cx);
        self.check(cx, polled)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let polled = Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        self.check(cx, polled)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

/// The text of a panic payload.
pub(crate) fn panic_text(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else {
        "a non-string panic payload".to_string()
    }
}

/// Answers a panicking REST handler with 500
/// `{"code":"internal_panic",...}` (the panic is logged, not sent).
#[derive(Debug, Clone, Copy, Default)]
pub struct RestPanic;

impl ResponseForPanic for RestPanic {
    type ResponseBody = axum::body::Body;

    fn response_for_panic(
        &mut self,
        err: Box<dyn std::any::Any + Send + 'static>,
    ) -> axum::http::Response<Self::ResponseBody> {
        ApiError(ServiceError::Panicked(format!(
            "a request handler panicked: {}",
            panic_text(&*err)
        )))
        .into_response()
    }
}

/// Catches panics of REST handlers: that request gets a 500, the
/// connection and every other request go on.
pub fn rest_panic_layer() -> CatchPanicLayer<RestPanic> {
    CatchPanicLayer::custom(RestPanic)
}

/// Answers a panicking gRPC method with INTERNAL (code `internal_panic`).
#[derive(Debug, Clone, Copy, Default)]
pub struct GrpcPanic;

impl ResponseForPanic for GrpcPanic {
    type ResponseBody = tonic::body::Body;

    fn response_for_panic(
        &mut self,
        err: Box<dyn std::any::Any + Send + 'static>,
    ) -> axum::http::Response<Self::ResponseBody> {
        to_status(ServiceError::Panicked(format!(
            "a gRPC method panicked: {}",
            panic_text(&*err)
        )))
        .into_http()
    }
}

/// Catches panics of gRPC methods: that call gets INTERNAL, the connection
/// and every other call go on.
pub fn grpc_panic_layer() -> CatchPanicLayer<GrpcPanic> {
    CatchPanicLayer::custom(GrpcPanic)
}

#[cfg(test)]
mod tests {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    use super::*;

    #[tokio::test]
    async fn a_write_blocked_past_the_send_timeout_fails() {
        let (near, mut far) = tokio::io::duplex(64);
        let mut io = SendTimeout::new(near, Duration::from_millis(200));
        // Progress: the peer reads as it goes.
        let reader = tokio::spawn(async move {
            let mut buf = vec![0u8; 1000];
            far.read_exact(&mut buf).await.map(|_| far)
        });
        io.write_all(&[1u8; 1000])
            .await
            .expect("written while read");
        let _far = reader.await.expect("reader").expect("read");
        // The peer stops reading: the write fails after the limit.
        let started = std::time::Instant::now();
        let err = io
            .write_all(&[2u8; 1000])
            .await
            .expect_err("a stalled write fails");
        assert_eq!(err.kind(), std::io::ErrorKind::TimedOut);
        let took = started.elapsed();
        assert!(
            took >= Duration::from_millis(150) && took < Duration::from_secs(2),
            "{took:?}"
        );
    }

    #[test]
    fn zero_and_huge_limits_are_refused() {
        assert_eq!(ConnLimits::default().validate(), Ok(()));
        let zero = ConnLimits {
            max_streams_per_key: 0,
            ..ConnLimits::default()
        };
        assert_eq!(
            zero.validate(),
            Err("--max-streams-per-key must be at least 1".into())
        );
        let long = ConnLimits {
            request_timeout_ms: 86_400_001,
            ..ConnLimits::default()
        };
        assert!(long.validate().is_err());
    }
}
