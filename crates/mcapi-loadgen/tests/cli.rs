//! The `mcapi-loadgen` binary's command line, without a server: its help
//! names the scenarios, and options out of range are refused before any
//! connection. (Being an integration test, this also has Cargo build the
//! binary itself next to `mcapi`, where tests/integration/serve.rs runs it.)

use std::process::Command;

fn loadgen(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_mcapi-loadgen"))
        .args(args)
        .output()
        .expect("mcapi-loadgen runs")
}

#[test]
fn the_help_names_the_scenarios() {
    let out = loadgen(&["--help"]);
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for flag in ["--scenario", "--http", "--grpc", "--json", "--server-pid"] {
        assert!(help.contains(flag), "{flag} missing from:\n{help}");
    }
}

#[test]
fn a_window_of_zero_seconds_is_refused_before_any_connection() {
    let out = loadgen(&["--duration-secs", "0", "--http", "http://127.0.0.1:9"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--duration-secs must be at least 1"), "{err}");
}
