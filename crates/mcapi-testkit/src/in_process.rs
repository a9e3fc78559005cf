//! The full server in this test's own process (`server::start`), for the
//! tests that compare it with the core or measure their own memory.

use std::path::Path;

/// `mcapi serve`'s options, parsed as the binary parses them.
#[derive(clap::Parser)]
struct ServeCli {
    #[command(flatten)]
    serve: mcapi_server::config::ServeConfig,
}

/// The full server in this process (`server::start`: both ports on
/// loopback port 0, 2 tick workers, the durable store in `data`).
pub async fn start_in_process(data: &Path) -> mcapi_server::server::Running {
    try_start_in_process(data, &[])
        .await
        .expect("server starts")
}

/// [`start_in_process`] with `more` flags after its own (a later flag
/// wins), for the tests that expect the start to fail: its error, with
/// its causes.
pub async fn try_start_in_process(
    data: &Path,
    more: &[&str],
) -> Result<mcapi_server::server::Running, String> {
    use clap::Parser;
    let mut args = vec![
        "mcapi",
        "--http",
        "127.0.0.1:0",
        "--grpc",
        "127.0.0.1:0",
        "--workers",
        "2",
        "--data-dir",
        data.to_str().expect("utf-8 path"),
    ];
    args.extend_from_slice(more);
    let cfg = ServeCli::parse_from(args).serve;
    mcapi_server::server::start(&cfg)
        .await
        .map_err(|e| format!("{e:#}"))
}
