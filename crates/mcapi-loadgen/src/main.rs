//! `mcapi-loadgen`: the load generator for a running `mcapi serve`, as its
//! own binary so that the product binary (`mcapi`) does not carry it. It
//! talks to the server over its sockets only (REST and gRPC) and reads the
//! server's CPU and memory from `/proc`; the scenarios are in [`loadgen`].

use std::process::ExitCode;

use clap::Parser;

mod loadgen;

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
    args: loadgen::LoadgenArgs,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match loadgen::run(cli.args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
