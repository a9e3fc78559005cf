//! Signals to a child process and waiting for it to exit (std sends
//! SIGKILL only), and reading its JSON log.

use std::process::{Child, Command, ExitStatus};
use std::time::{Duration, Instant};

use serde_json::Value;

/// `kill <signal> <pid>`, e.g. `signal(pid, "-TERM")` (std sends SIGKILL only).
pub fn signal(pid: u32, signal: &str) {
    let ok = Command::new("kill")
        .args([signal, &pid.to_string()])
        .status()
        .expect("kill runs")
        .success();
    assert!(ok, "kill {signal} {pid} failed");
}

/// SIGTERM to a child, then its exit status within `timeout`; past it, the
/// child is killed and the test fails with `log()`.
pub fn terminate(child: &mut Child, timeout: Duration, log: &dyn Fn() -> String) -> ExitStatus {
    signal(child.id(), "-TERM");
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            return status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "{} did not stop within {timeout:?} of SIGTERM; log:\n{}",
                child.id(),
                log()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Parsed JSON log lines whose `fields.message` is `message`.
pub fn log_events(log: &str, message: &str) -> Vec<Value> {
    log.lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v["fields"]["message"].as_str() == Some(message))
        .map(|v| v["fields"].clone())
        .collect()
}
