//! `mcapi serve`: binds both transports over one session manager, serves
//! until told to stop, then finishes in-flight requests and stops the tick
//! loop.
//!
//! Both ports are bounded by the connection limits of [`crate::api::conn`]
//! (connections per port, header-read, request and send timeouts, TCP and
//! HTTP/2 keep-alive); REST event streams and gRPC `Watch` streams share
//! one budget per caller ([`crate::api::streams`]).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result};
use tokio::net::{TcpListener, UnixListener};
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::api::conn::serve_http;
use crate::api::extract::Serving;
use crate::api::grpc::GrpcOptions;
use crate::api::streams::StreamLimiter;
use crate::api::{AppState, router};
use crate::config::{ServeConfig, StoreKind};
use crate::service::SessionManager;
use crate::telemetry;
use mcapi_store::Store;

/// A running server.
pub struct Running {
    /// Bound REST address.
    pub http_addr: SocketAddr,
    /// Bound gRPC address.
    pub grpc_addr: SocketAddr,
    /// The session layer.
    pub manager: Arc<SessionManager>,
    stop: watch::Sender<bool>,
    tasks: Vec<JoinHandle<Result<()>>>,
    /// The gRPC socket's file: removed as soon as shutdown begins, before
    /// the listener closes, so that a server started meanwhile (a rolling
    /// restart) never finds it stale, replaces it, and then loses its own
    /// socket to this one's cleanup; or when the server is dropped (a
    /// failed start).
    socket: parking_lot::Mutex<Option<SocketFile>>,
}

/// A bound Unix socket's path; the file is removed on drop.
struct SocketFile(PathBuf);

impl Drop for SocketFile {
    fn drop(&mut self) {
        if let Err(e) = std::fs::remove_file(&self.0)
            && e.kind() != std::io::ErrorKind::NotFound
        {
            tracing::warn!(socket = %self.0.display(), error = %e, "could not remove the gRPC socket");
        }
    }
}

/// Binds the gRPC socket at `path`. A socket file nobody listens on (left
/// by a server that was killed) is replaced; a live socket or anything
/// that is not a socket stops the start instead of being removed.
fn bind_socket(path: &Path) -> Result<(UnixListener, SocketFile)> {
    use std::os::unix::fs::FileTypeExt;
    let shown = path.display();
    if let Ok(meta) = std::fs::symlink_metadata(path) {
        if !meta.file_type().is_socket() {
            anyhow::bail!(
                "--grpc-socket {shown}: the path exists and is not a socket; not replacing it"
            );
        }
        if std::os::unix::net::UnixStream::connect(path).is_ok() {
            anyhow::bail!("--grpc-socket {shown}: another server is listening on it");
        }
        std::fs::remove_file(path)
            .with_context(|| format!("--grpc-socket {shown}: removing a stale socket"))?;
        tracing::info!(socket = %shown, "replaced a stale gRPC socket");
    }
    let listener =
        UnixListener::bind(path).with_context(|| format!("binding the gRPC socket {shown}"))?;
    Ok((listener, SocketFile(path.to_path_buf())))
}

async fn stopped(mut rx: watch::Receiver<bool>) {
    // Either a stop was sent or the sender is gone: both mean stop.
    let _ = rx.wait_for(|stop| *stop).await;
}

/// Validates the configuration, binds both ports and starts serving.
pub async fn start(cfg: &ServeConfig) -> Result<Running> {
    cfg.validate().map_err(anyhow::Error::msg)?;
    let mut options = cfg.manager_options();
    let placement = cfg.placement().map_err(anyhow::Error::msg)?.map(Arc::new);
    if let Some(p) = &placement {
        tracing::info!(replica = %p.replica(), epoch = p.epoch(), shards = p.owned_count(), "serving as one replica of a cluster");
    }
    options.placement = placement;
    if cfg.store == StoreKind::Redb {
        let store = Store::open_configured(&cfg.data_dir, cfg.durability, cfg.store_cache_bytes())
            .context("opening the session store")?;
        tracing::info!(path = %store.path().display(), durability = %store.durability(), "session store open");
        options.store = Some(Arc::new(store));
    }
    let manager = Arc::new(SessionManager::with_options(options)?);
    manager
        .start_evictor()
        .context("starting the evictor thread")?;
    let http = TcpListener::bind(cfg.http)
        .await
        .with_context(|| format!("binding the REST port {}", cfg.http))?;
    let grpc = TcpListener::bind(cfg.grpc)
        .await
        .with_context(|| format!("binding the gRPC port {}", cfg.grpc))?;
    let (socket, socket_file) = match &cfg.grpc_socket {
        Some(path) => {
            let (listener, file) = bind_socket(path)?;
            (Some(listener), Some(file))
        }
        None => (None, None),
    };
    let (http_addr, grpc_addr) = (http.local_addr()?, grpc.local_addr()?);
    let (stop, stop_rx) = watch::channel(false);
    let limits = cfg.conn_limits();
    limits.warn_on_fd_limit(2 + u64::from(socket.is_some()));
    // One budget of watch streams per caller for both transports.
    let streams = StreamLimiter::new(limits.max_streams_per_key);
    let app = router(AppState {
        manager: Arc::clone(&manager),
        metrics: telemetry::prometheus(),
        serving: Some(Serving {
            stopping: stop_rx.clone(),
            streams: Arc::clone(&streams),
            request_timeout: limits.request_timeout(),
        }),
    });
    let rest_task = tokio::spawn({
        let rx = stop_rx.clone();
        let limits = limits.clone();
        async move {
            serve_http(http, app, &limits, stopped(rx)).await;
            Ok(())
        }
    });
    let grpc_task = tokio::spawn({
        let manager = Arc::clone(&manager);
        let opts = GrpcOptions {
            stream_buffer: cfg.stream_buffer,
            limits,
            streams,
        };
        async move {
            crate::api::grpc::serve_with(grpc, socket, manager, opts, stopped(stop_rx))
                .await
                .context("gRPC server")
        }
    });
    tracing::info!(%http_addr, %grpc_addr, workers = cfg.worker_count(), "mcapi serving");
    let running = Running {
        http_addr,
        grpc_addr,
        manager,
        stop,
        tasks: vec![rest_task, grpc_task],
        socket: parking_lot::Mutex::new(socket_file),
    };
    // Health answers during recovery; readiness and the API wait for it.
    let recovering = Arc::clone(&running.manager);
    match tokio::task::spawn_blocking(move || recovering.recover()).await {
        Ok(Ok(_)) => Ok(running),
        Ok(Err(e)) => {
            running.shutdown();
            Err(anyhow::anyhow!("recovering stored sessions: {e}"))
        }
        Err(e) => {
            running.shutdown();
            Err(anyhow::anyhow!("recovery task failed: {e}"))
        }
    }
}

impl Running {
    /// Asks both transports to stop accepting and finish in-flight requests.
    pub fn shutdown(&self) {
        drop(self.socket.lock().take());
        let _ = self.stop.send(true);
    }

    /// Waits for both transports to finish, then drains and stops the tick loop.
    pub async fn wait(self) -> Result<()> {
        let mut result = Ok(());
        for task in self.tasks {
            match task.await {
                Ok(Ok(())) => {}
                Ok(Err(e)) => result = Err(e),
                Err(e) => result = Err(anyhow::anyhow!("server task failed: {e}")),
            }
        }
        let manager = Arc::clone(&self.manager);
        tokio::task::spawn_blocking(move || manager.shutdown())
            .await
            .context("stopping the tick loop")?;
        drop(self.socket);
        tracing::info!("mcapi stopped");
        result
    }
}

/// Listens for SIGINT (Ctrl-C) and SIGTERM from the moment it is called,
/// and resolves on the first. Call it before the server starts answering:
/// a signal that arrives before anyone listens gets its default action,
/// which ends the process without the graceful shutdown (a SIGTERM right
/// after `/healthz` first answered used to do that). Needs a Tokio runtime.
pub fn shutdown_signal() -> impl std::future::Future<Output = ()> + Send {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let listen = |kind: SignalKind, name: &'static str| {
            signal(kind)
                .inspect_err(
                    |e| tracing::error!(error = %e, signal = name, "cannot listen for the signal"),
                )
                .ok()
        };
        let interrupt = listen(SignalKind::interrupt(), "SIGINT");
        let terminate = listen(SignalKind::terminate(), "SIGTERM");
        async move {
            tokio::select! {
                () = received(interrupt) => {},
                () = received(terminate) => {},
            }
        }
    }
    #[cfg(not(unix))]
    {
        async {
            if let Err(e) = tokio::signal::ctrl_c().await {
                tracing::error!(error = %e, "cannot listen for Ctrl-C");
                std::future::pending::<()>().await;
            }
        }
    }
}

/// Resolves when `signal` arrives; never without a listener.
#[cfg(unix)]
async fn received(signal: Option<tokio::signal::unix::Signal>) {
    match signal {
        Some(mut s) => {
            s.recv().await;
        }
        None => std::future::pending::<()>().await,
    }
}
