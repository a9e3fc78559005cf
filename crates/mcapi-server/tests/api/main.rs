//! mcapi-server's integration tests, in one test binary: the library in
//! this process (the REST router, the gRPC service, the session manager over
//! a real store, the full server of `server::start`), no `mcapi` binary. One
//! link of the whole server instead of one per file, which is most of what a
//! cold `make test` spends compiling. Each module is one subject (`cargo
//! test -p mcapi-server --test api rest::` runs one). `tests/fuzz/` and
//! `tests/grpc_model.rs` beside this folder stay binaries of their own: they
//! measure their own process's resident memory, which other tests would
//! disturb here. The tests that run the `mcapi` binary are the root
//! package's (`tests/integration/` at the workspace root); the helpers both
//! share are the mcapi-testkit crate.

mod builds;
mod continuous;
mod eviction;
mod groups;
mod grpc;
mod numerics;
mod openapi;
mod panics;
mod parity;
mod responses;
mod rest;
mod seq;
mod shard_move;
mod storage_failures;
mod unix_socket;

/// The REST router over a fresh manager with these limits, served on a free
/// local port: the manager (for checks from inside) and the address.
async fn serve_rest(
    limits: mcapi_server::service::Limits,
) -> (
    std::sync::Arc<mcapi_server::service::SessionManager>,
    std::net::SocketAddr,
) {
    let manager = std::sync::Arc::new(
        mcapi_server::service::SessionManager::new(limits, 2).expect("manager"),
    );
    let state = mcapi_server::api::AppState {
        manager: std::sync::Arc::clone(&manager),
        metrics: None,
        serving: None,
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("addr");
    tokio::spawn(async move {
        axum::serve(listener, mcapi_server::api::router(state))
            .await
            .expect("serve")
    });
    (manager, addr)
}

/// [`serve_rest`] and the gRPC service over the same manager, each on a
/// free local port: the manager, the REST base URL and the gRPC endpoint.
async fn serve_both(
    limits: mcapi_server::service::Limits,
) -> (
    std::sync::Arc<mcapi_server::service::SessionManager>,
    String,
    String,
) {
    let (manager, rest) = serve_rest(limits).await;
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = format!("http://{}", grpc.local_addr().expect("addr"));
    tokio::spawn(mcapi_server::api::grpc::serve_on(
        grpc,
        std::sync::Arc::clone(&manager),
        8,
        std::future::pending(),
    ));
    (manager, format!("http://{rest}"), addr)
}

/// POSTs `body` to `base` + `path`: the status and the JSON reply (null if
/// the reply is not JSON).
async fn post_json(base: &str, path: &str, body: &serde_json::Value) -> (u16, serde_json::Value) {
    let resp = reqwest::Client::new()
        .post(format!("{base}{path}"))
        .json(body)
        .send()
        .await
        .expect("request");
    let status = resp.status().as_u16();
    (status, resp.json().await.unwrap_or(serde_json::Value::Null))
}
