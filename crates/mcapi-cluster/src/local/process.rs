//! The supervised processes of `mcapi cluster local`: how one is started
//! (in its own process group, with SIGTERM when the supervisor dies), reaped
//! and started again after a backoff ([`Backoff`]), and the signals sent to
//! it.

use std::ffi::OsString;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};

use super::state::ProcessState;

/// When to start again a process that exited. Pure: the tests drive it with
/// made-up durations.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Backoff {
    /// The wait after a first exit.
    pub first: Duration,
    /// The longest wait.
    pub max: Duration,
    /// A process that ran this long before exiting starts a new streak.
    pub steady: Duration,
}

impl Backoff {
    /// 250 ms, doubling to 30 s; a minute up resets it.
    pub const DEFAULT: Self = Self {
        first: Duration::from_millis(250),
        max: Duration::from_secs(30),
        steady: Duration::from_secs(60),
    };

    /// A process that ran for `ran` exited, after `streak` quick exits in a
    /// row: the wait before starting it again and the new streak.
    pub fn after_exit(&self, ran: Duration, streak: u32) -> (Duration, u32) {
        let streak = if ran >= self.steady {
            1
        } else {
            streak.saturating_add(1)
        };
        let doublings = streak.saturating_sub(1).min(20);
        let wait = self.first.saturating_mul(1 << doublings).min(self.max);
        (wait, streak)
    }
}

/// What a look at a supervised process found worth logging.
#[derive(Debug)]
pub(super) enum Event {
    Exited {
        status: ExitStatus,
        ran: Duration,
        wait: Duration,
    },
    Restarted {
        pid: u32,
    },
    SpawnFailed {
        error: String,
        wait: Duration,
    },
}

pub(super) enum Run {
    Up { child: Child, since: Instant },
    Waiting { until: Instant },
    Stopped,
}

/// One supervised process: how to start it and where it stands.
pub(super) struct Process {
    pub(super) name: String,
    pub(super) program: PathBuf,
    pub(super) args: Vec<OsString>,
    /// Environment variables set for it (a replica's admin key).
    pub(super) env: Vec<(String, String)>,
    pub(super) log: PathBuf,
    /// A replica's (REST, gRPC) addresses.
    pub(super) listen: Option<(SocketAddr, SocketAddr)>,
    /// What answers 200 once it is ready.
    pub(super) ready_url: String,
    pub(super) run: Run,
    pub(super) streak: u32,
    pub(super) restarts: u64,
}

impl Process {
    pub(super) fn pid(&self) -> Option<u32> {
        match &self.run {
            Run::Up { child, .. } => Some(child.id()),
            _ => None,
        }
    }

    pub(super) fn spawn(&mut self) -> Result<u32> {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)
            .with_context(|| format!("opening {}", self.log.display()))?;
        let mut cmd = Command::new(&self.program);
        cmd.args(&self.args)
            .envs(self.env.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::from(log));
        detach(&mut cmd);
        let child = cmd
            .spawn()
            .with_context(|| format!("starting {}", self.program.display()))?;
        let pid = child.id();
        self.run = Run::Up {
            child,
            since: Instant::now(),
        };
        Ok(pid)
    }

    /// Reaps an exit and schedules the restart, or restarts when due.
    pub(super) fn tick(&mut self, now: Instant, backoff: &Backoff) -> Option<Event> {
        match &mut self.run {
            Run::Up { child, since } => {
                let status = match child.try_wait() {
                    Ok(Some(status)) => status,
                    Ok(None) | Err(_) => return None,
                };
                let ran = now.saturating_duration_since(*since);
                let (wait, streak) = backoff.after_exit(ran, self.streak);
                self.streak = streak;
                self.run = Run::Waiting { until: now + wait };
                Some(Event::Exited { status, ran, wait })
            }
            Run::Waiting { until } if now >= *until => {
                self.restarts += 1;
                match self.spawn() {
                    Ok(pid) => Some(Event::Restarted { pid }),
                    Err(e) => {
                        let (wait, streak) = backoff.after_exit(Duration::ZERO, self.streak);
                        self.streak = streak;
                        self.run = Run::Waiting { until: now + wait };
                        Some(Event::SpawnFailed {
                            error: format!("{e:#}"),
                            wait,
                        })
                    }
                }
            }
            Run::Waiting { .. } | Run::Stopped => None,
        }
    }

    pub(super) fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(20)..].join("\n")
    }

    pub(super) fn state(&self) -> ProcessState {
        ProcessState {
            name: self.name.clone(),
            pid: self.pid(),
            http: self.listen.map(|(h, _)| h.to_string()),
            grpc: self.listen.map(|(_, g)| g.to_string()),
            restarts: self.restarts,
            log: self.log.clone(),
        }
    }
}

/// Its own process group (a terminal's Ctrl-C is the supervisor's alone) and,
/// on Linux, SIGTERM when the supervisor dies.
pub(super) fn detach(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    cmd.process_group(0);
    #[cfg(target_os = "linux")]
    // SAFETY: the closure runs in the child between fork and exec and calls
    // only prctl(2), which is async-signal-safe; it touches no memory of
    // the parent. The supervisor spawns from its one thread (a current-
    // thread runtime), whose exit is what PR_SET_PDEATHSIG watches.
    unsafe {
        cmd.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) == -1 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

/// Sends `signal` to `pid`; a process already gone is not an error.
pub(super) fn send_signal(pid: u32, signal: libc::c_int) {
    if let Ok(pid) = libc::pid_t::try_from(pid) {
        // SAFETY: kill(2) takes plain integers and touches no memory.
        unsafe {
            libc::kill(pid, signal);
        }
    }
}

/// Whether a process with this pid exists (signal 0 checks, sends nothing).
pub(super) fn alive(pid: u32) -> bool {
    match libc::pid_t::try_from(pid) {
        // SAFETY: as in `send_signal`.
        Ok(pid) if pid > 0 => unsafe { libc::kill(pid, 0) == 0 },
        _ => false,
    }
}
