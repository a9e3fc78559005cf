//! `mcapi-loadgen` (formerly `mcapi loadgen`): a load generator for a
//! running `mcapi serve`, over real sockets (the server's throughput,
//! latency and memory measurements of BENCHMARKS.md).
//!
//! Scenarios:
//!
//! - **rest**: for each number of hallway sessions (default 1, 100 and
//!   10,000) and each update mode, one virtual client per session drives its
//!   agent over `POST /v1/sessions/{id}/observations`: the first observation
//!   `{"state": 25}`, then the move the reply advised on a 50-state chain
//!   (left, right, stay), stimulus `[6, 0]` at state 10, `[0, 6]` at 40 and
//!   `[0, 0]` elsewhere. Each keep-alive HTTP/1.1 connection carries one
//!   request at a time; beyond `--max-connections` sessions the connections
//!   cycle over their share of the sessions, so at most that many requests
//!   are in flight. In the same run and with the same connections, `GET
//!   /healthz` is measured as the baseline. Then the observations go on
//!   open-loop at a fraction (`--paced-fraction`, default one half) of the
//!   measured peak rate: a pacing thread releases requests evenly spaced,
//!   and latency counts from the release (no coordinated omission).
//! - **grpc**: `Interact` over `--grpc-streams` bidirectional streams, one
//!   hallway session each, spread over `--grpc-connections` HTTP/2
//!   connections; one observation in flight per stream. Then, with
//!   `--grpc-batch` N > 1, as many sessions driven as vectorised worlds:
//!   `InteractBatch` streams of N sessions each, one message (N
//!   observations) in flight per stream.
//! - **memory**: the server's resident memory (`VmRSS`) with 10,000 and
//!   100,000 idle hallway sessions, after one observation each, and after
//!   deleting them (at once and `--settle-secs` later); it reports KiB per
//!   idle session and the RSS left after deleting them all. Needs the
//!   server's pid (`--server-pid`, or found in `/proc` when exactly one
//!   `mcapi serve` runs on this machine).
//!
//! Every closed-loop measurement runs for `--warmup-secs`, then counts the
//! requests completed during the next `--duration-secs`; latencies are exact
//! percentiles of every request of that window (nearest rank). Beside the
//! client's view, each REST row gives the server's own handler latency
//! (bucket bounds of its `/metrics` histogram over the window) and the CPU
//! used by the server, the load generator and everything else on the
//! machine during the window (`/proc`): the two share the machine's cores,
//! so neither number means much without the other. Results go to stdout as
//! Markdown tables (and, with `--json FILE`, to that file as one JSON
//! document, for scripts such as `benches/server.sh`); progress goes to
//! stderr.
//!
//! It is its own binary so that the product binary (`mcapi`) does not carry
//! it: it talks to the server over its sockets only (REST and gRPC) and
//! reads the server's CPU and memory from `/proc`. Its modules, each using
//! only modules listed before it:
//!
//! - [`args`]: the options, the scenarios and the update modes;
//! - [`hallway`]: the hallway world as a client simulates it;
//! - [`stats`]: a measurement's phase, its latencies and percentiles;
//! - [`proc`]: sampling `/proc` (CPU, resident memory, the server's pid);
//! - [`http`]: the HTTP/1.1 client on hyper;
//! - [`prometheus`]: the server's `/metrics` histograms;
//! - [`window`]: CPU and handler latency over a measurement window;
//! - [`report`]: the cells of the Markdown report;
//! - [`sessions`]: creating, observing and deleting sessions over REST;
//! - [`driver`]: the REST driver, closed and open loop;
//! - [`rest`], [`grpc`], [`memory`]: the three scenarios;
//!
//! and here, the command line and [`run`], which runs the chosen scenarios
//! and writes the JSON document.

use std::process::ExitCode;

use anyhow::{Context, Result, bail, ensure};
use clap::Parser;
use serde_json::{Value, json};

mod args;
mod driver;
mod grpc;
mod hallway;
mod http;
mod memory;
mod proc;
mod prometheus;
mod report;
mod rest;
mod sessions;
mod stats;
mod window;

use args::{LoadgenArgs, Scenario};
use http::HttpTarget;

/// The allocator the load generator had inside the `mcapi` binary (see
/// Cargo.toml), so its own CPU use is measured as before.
#[cfg(feature = "mimalloc")]
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Load-test a running server over real sockets (REST, gRPC, memory) and print the results.
#[derive(Debug, Parser)]
#[command(name = "mcapi-loadgen", version, about)]
struct Cli {
    #[command(flatten)]
    args: LoadgenArgs,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli.args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Runs the chosen scenarios against a running server and prints the results.
fn run(args: LoadgenArgs) -> Result<()> {
    ensure!(args.duration_secs > 0, "--duration-secs must be at least 1");
    ensure!(
        args.paced_fraction > 0.0 && args.paced_fraction <= 1.0,
        "--paced-fraction must be in (0, 1]"
    );
    ensure!(
        args.max_connections > 0 && args.create_connections > 0,
        "connection counts must be at least 1"
    );
    ensure!(
        args.grpc_streams > 0 && args.grpc_connections > 0,
        "--grpc-streams and --grpc-connections must be at least 1"
    );
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    if let Some(n) = args.threads {
        ensure!(n > 0, "--threads must be at least 1");
        builder.worker_threads(n);
    }
    builder.enable_all().build()?.block_on(run_scenarios(args))
}

async fn run_scenarios(args: LoadgenArgs) -> Result<()> {
    let http = HttpTarget::parse(&args.http)?;
    let server_pid = match args.server_pid {
        Some(pid) => Some(pid),
        None => proc::find_server_pid()?,
    };
    let memory = matches!(args.scenario, Scenario::Memory | Scenario::All);
    if memory && server_pid.is_none() {
        bail!("the memory scenario needs the server's pid: pass --server-pid");
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!("# mcapi loadgen\n");
    println!(
        "REST {}, gRPC {}, server pid {}; {cores} cores shared by the server and the load \
         generator; {} s warm-up + {} s per measurement.\n",
        args.http,
        args.grpc,
        server_pid.map_or_else(|| "unknown".to_string(), |p| p.to_string()),
        args.warmup_secs,
        args.duration_secs
    );
    let mut report = serde_json::Map::new();
    report.insert("cores".into(), json!(cores));
    report.insert("warmup_secs".into(), json!(args.warmup_secs));
    report.insert("duration_secs".into(), json!(args.duration_secs));
    if matches!(args.scenario, Scenario::Rest | Scenario::All) {
        report.insert(
            "rest".into(),
            rest::rest_scenario(&args, &http, server_pid).await?,
        );
    }
    if matches!(args.scenario, Scenario::Grpc | Scenario::All) {
        report.insert("grpc".into(), grpc::grpc_scenario(&args, server_pid).await?);
    }
    if let (true, Some(pid)) = (memory, server_pid) {
        report.insert(
            "memory".into(),
            memory::memory_scenario(&args, &http, pid).await?,
        );
    }
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&Value::Object(report))?;
        std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
