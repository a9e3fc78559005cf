//! Sampling `/proc`: the CPU seconds of the server, of the load generator
//! and of the whole machine (turned into the cores each kept busy over a
//! window, [`CpuUse`]), a process's resident memory, and the pid of the one
//! `mcapi serve` on this machine.

use std::collections::HashSet;

use anyhow::{Context, Result, anyhow, bail};

/// Clock ticks per second of `/proc` CPU times (`USER_HZ`, fixed at 100 on Linux).
const USER_HZ: f64 = 100.0;

/// CPU seconds a process has used (user + system), from `/proc/<pid>/stat`.
fn cpu_seconds(pid: &str) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name, which is in parentheses and may hold spaces.
    let rest = &stat[stat.rfind(')')? + 1..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime + stime) / USER_HZ)
}

/// Busy CPU seconds of the whole machine (all cores), from `/proc/stat`.
fn machine_busy_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let line = stat.lines().next()?.strip_prefix("cpu ")?;
    let ticks: Vec<f64> = line
        .split_whitespace()
        .filter_map(|f| f.parse().ok())
        .collect();
    // user nice system idle iowait irq softirq steal (guest time is in user).
    let busy: f64 = [0, 1, 2, 5, 6, 7]
        .iter()
        .filter_map(|&i| ticks.get(i))
        .sum();
    Some(busy / USER_HZ)
}

/// Cores kept busy over a window by the server, by the load generator and
/// by everything else on the machine (other processes, the hypervisor's
/// steal time): the machines are shared, so the last says how noisy a
/// measurement was.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct CpuUse {
    pub(crate) server: Option<f64>,
    pub(crate) loadgen: Option<f64>,
    pub(crate) other: Option<f64>,
}

/// CPU seconds of the server, this process and the machine.
pub(crate) fn cpu_now(server_pid: Option<u32>) -> [Option<f64>; 3] {
    [
        server_pid.and_then(|p| cpu_seconds(&p.to_string())),
        cpu_seconds("self"),
        machine_busy_seconds(),
    ]
}

pub(crate) fn cpu_use(before: [Option<f64>; 3], after: [Option<f64>; 3], secs: f64) -> CpuUse {
    let used = |i: usize| {
        before[i]
            .zip(after[i])
            .map(|(a, b): (f64, f64)| (b - a) / secs)
    };
    let (server, loadgen, machine) = (used(0), used(1), used(2));
    CpuUse {
        server,
        loadgen,
        other: machine
            .zip(loadgen)
            .map(|(m, l)| (m - l - server.unwrap_or(0.0)).max(0.0)),
    }
}

/// `VmRSS` and `VmHWM` of a process, in bytes.
pub(crate) fn memory_of(pid: u32) -> Result<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .with_context(|| format!("reading /proc/{pid}/status"))?;
    let field = |name: &str| -> Result<u64> {
        let line = status
            .lines()
            .find(|l| l.starts_with(name))
            .ok_or_else(|| anyhow!("no {name} in /proc/{pid}/status"))?;
        let kib: u64 = line
            .trim_start_matches(name)
            .trim()
            .trim_end_matches("kB")
            .trim()
            .parse()?;
        Ok(kib * 1024)
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?))
}

/// The pid of the one `mcapi serve` process on this machine, if there is one.
pub(crate) fn find_server_pid() -> Result<Option<u32>> {
    let me = std::process::id();
    let mut found = HashSet::new();
    for entry in std::fs::read_dir("/proc")?.flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<u32>().ok())
        else {
            continue;
        };
        let Ok(cmdline) = std::fs::read(entry.path().join("cmdline")) else {
            continue;
        };
        let mut argv = cmdline.split(|&b| b == 0).map(String::from_utf8_lossy);
        let is_mcapi = argv
            .next()
            .is_some_and(|a| a.rsplit('/').next().is_some_and(|f| f.starts_with("mcapi")));
        if pid != me && is_mcapi && argv.any(|a| a == "serve") {
            found.insert(pid);
        }
    }
    match found.len() {
        0 => Ok(None),
        1 => Ok(found.into_iter().next()),
        _ => bail!("several `mcapi serve` processes ({found:?}): pass --server-pid"),
    }
}
