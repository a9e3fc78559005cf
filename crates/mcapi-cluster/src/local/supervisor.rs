//! The supervisor of `mcapi cluster local`: starts the replicas and the
//! router, waits until all are ready, restarts what exits, takes a
//! rebalance's new replicas on SIGHUP (or stops the leaving ones it moved
//! every shard off) and stops everything in order on SIGTERM or Ctrl-C.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde::Deserialize;

use mcapi_shards::ShardMap;
use mcapi_shards::plan::ordinal_names;

use super::process::{Backoff, Event, Process, Run, send_signal};
use super::setup::{ReplicaTemplate, Setup, check_router, free_ports};
use super::state::State;
use super::{MAP_FILE, MAX_LOCAL_REPLICAS, REQUEST_FILE, RouterUpdate, STATE_FILE};
use crate::files::write_atomic;
use crate::haproxy::write_router;
use crate::haproxy::{RouterSpec, add_backend, drain_backend, remove_backend};
use crate::probe::http_ok;

/// The processes, stopped (SIGKILL) if dropped while any still runs: an
/// error on the way out leaves no child behind.
pub(super) struct Cluster {
    pub(super) processes: Vec<Process>,
    pub(super) template: ReplicaTemplate,
    pub(super) spec: RouterSpec,
    /// The `haproxy` executable (the router's process may run it behind
    /// `ip netns exec`).
    pub(super) haproxy: PathBuf,
    pub(super) dir: PathBuf,
    pub(super) state_file: PathBuf,
    pub(super) state: State,
    pub(super) router_update: RouterUpdate,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        for p in &mut self.processes {
            if let Run::Up { child, .. } = &mut p.run {
                let _ = child.kill();
                let _ = child.wait();
            }
            p.run = Run::Stopped;
        }
        let _ = std::fs::remove_file(&self.state_file);
    }
}

impl Cluster {
    pub(super) fn write_state(&mut self) {
        if let Ok(map) = ShardMap::read(&self.dir.join(MAP_FILE)) {
            self.state.epoch = map.epoch();
        }
        self.state.processes = self.processes.iter().map(Process::state).collect();
        match serde_json::to_string_pretty(&self.state) {
            Ok(text) => {
                if let Err(e) = write_atomic(&self.state_file, &text) {
                    tracing::error!(error = %format!("{e:#}"), "cannot write the state file");
                }
            }
            Err(e) => tracing::error!(error = %e, "cannot encode the state file"),
        }
    }

    /// Starts `range` of the processes and waits until each answers 200 on
    /// its readiness URL; fails if one exits first or the deadline passes.
    pub(super) async fn start(
        &mut self,
        range: std::ops::Range<usize>,
        timeout: Duration,
    ) -> Result<()> {
        for p in &mut self.processes[range.clone()] {
            let pid = p.spawn()?;
            tracing::info!(process = %p.name, pid, "started");
        }
        self.write_state();
        let deadline = Instant::now() + timeout;
        let mut waiting: Vec<usize> = range.collect();
        while !waiting.is_empty() {
            let mut still = Vec::new();
            for &i in &waiting {
                let p = &mut self.processes[i];
                if let Run::Up { child, .. } = &mut p.run
                    && let Ok(Some(status)) = child.try_wait()
                {
                    p.run = Run::Stopped;
                    bail!(
                        "{} exited ({status}) before it was ready; the end of {}:\n{}",
                        p.name,
                        p.log.display(),
                        p.log_tail()
                    );
                }
                if http_ok(&p.ready_url, Duration::from_millis(500)).is_err() {
                    still.push(i);
                }
            }
            waiting = still;
            if waiting.is_empty() {
                break;
            }
            if Instant::now() >= deadline {
                let names: Vec<&str> = waiting
                    .iter()
                    .map(|&i| self.processes[i].name.as_str())
                    .collect();
                bail!(
                    "not ready after {} s: {} (see their logs in {})",
                    timeout.as_secs(),
                    names.join(", "),
                    self.state_file
                        .parent()
                        .map(|d| d.join("logs"))
                        .unwrap_or_default()
                        .display()
                );
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        Ok(())
    }

    /// Looks at every process five times a second, forever: exits are
    /// logged and restarted after their backoff.
    pub(super) async fn watch(&mut self, backoff: Backoff) {
        loop {
            let now = Instant::now();
            let mut changed = false;
            for p in &mut self.processes {
                let Some(event) = p.tick(now, &backoff) else {
                    continue;
                };
                changed = true;
                match event {
                    Event::Exited { status, ran, wait } => tracing::warn!(
                        process = %p.name,
                        %status,
                        ran_s = ran.as_secs_f64(),
                        restart_in_ms = wait.as_millis() as u64,
                        "exited; starting it again after a backoff"
                    ),
                    Event::Restarted { pid } => tracing::info!(
                        process = %p.name,
                        pid,
                        restarts = p.restarts,
                        "started again"
                    ),
                    Event::SpawnFailed { error, wait } => tracing::error!(
                        process = %p.name,
                        %error,
                        retry_in_ms = wait.as_millis() as u64,
                        "cannot start it again"
                    ),
                }
            }
            if changed {
                self.write_state();
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// SIGTERM to `range`, then SIGKILL to whatever still runs after `grace`.
    pub(super) async fn stop(&mut self, range: std::ops::Range<usize>, grace: Duration) {
        for p in &mut self.processes[range.clone()] {
            match &p.run {
                Run::Up { child, .. } => send_signal(child.id(), libc::SIGTERM),
                Run::Waiting { .. } | Run::Stopped => p.run = Run::Stopped,
            }
        }
        let deadline = Instant::now() + grace;
        loop {
            let mut running = 0;
            for p in &mut self.processes[range.clone()] {
                if let Run::Up { child, .. } = &mut p.run {
                    match child.try_wait() {
                        Ok(Some(status)) => {
                            tracing::info!(process = %p.name, %status, "stopped");
                            p.run = Run::Stopped;
                        }
                        Ok(None) | Err(_) => running += 1,
                    }
                }
            }
            if running == 0 {
                return;
            }
            if Instant::now() >= deadline {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        for p in &mut self.processes[range] {
            if let Run::Up { child, .. } = &mut p.run {
                tracing::warn!(process = %p.name, grace_s = grace.as_secs(), "did not stop in time: SIGKILL");
                let _ = child.kill();
                let _ = child.wait();
                p.run = Run::Stopped;
            }
        }
    }

    /// A rebalance's request (`rebalance.json`, then SIGHUP): grows or
    /// shrinks to the number of replicas asked for, then records it in
    /// the state file, which `rebalance` waits on.
    pub(super) async fn resize(
        &mut self,
        ready_timeout: Duration,
        drain_timeout: Duration,
    ) -> Result<()> {
        #[derive(Deserialize)]
        struct Request {
            replicas: usize,
        }
        let path = self.dir.join(REQUEST_FILE);
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let want = serde_json::from_str::<Request>(&text)
            .with_context(|| format!("{} is not a rebalance request", path.display()))?
            .replicas;
        let have = self.processes.len().saturating_sub(1);
        if want > MAX_LOCAL_REPLICAS {
            bail!("{want} replicas asked for; `cluster local` runs at most {MAX_LOCAL_REPLICAS}");
        }
        if want == 0 {
            bail!("0 replicas asked for; a cluster keeps at least one");
        }
        match want.cmp(&have) {
            std::cmp::Ordering::Greater => self.grow(have, want, ready_timeout).await,
            std::cmp::Ordering::Less => self.shrink(have, want, ready_timeout, drain_timeout).await,
            std::cmp::Ordering::Equal => {
                tracing::info!(replicas = have, "rebalance request: as many replicas run");
                self.state.replicas = have;
                self.write_state();
                Ok(())
            }
        }
    }

    /// Starts replicas `have..want` (`--joining`: owning nothing until
    /// shards move to them), writes the router's configuration with them
    /// and adds them to the running HAProxy through its Runtime API.
    /// HAProxy is not restarted: a restart cut the requests in flight and
    /// refused connections until it listened again.
    async fn grow(&mut self, have: usize, want: usize, ready_timeout: Duration) -> Result<()> {
        let names = ordinal_names("mcapi", want).map_err(anyhow::Error::msg)?;
        // Not the ports of a replica waiting to be started again.
        let taken: Vec<u16> = self
            .processes
            .iter()
            .filter_map(|p| p.listen)
            .flat_map(|(http, grpc)| [http.port(), grpc.port()])
            .collect();
        let ports = free_ports((want - have) * 2, &taken)?;
        let router = self.processes.len() - 1;
        for (k, name) in names[have..].iter().enumerate() {
            let (http, grpc) = (ports[2 * k], ports[2 * k + 1]);
            self.spec
                .backends
                .push(self.template.backend(name, http, grpc));
            let p = self.template.process(name, http, grpc, true);
            self.processes.insert(router + k, p);
        }
        self.start(have..want, ready_timeout).await?;
        let map = ShardMap::read(&self.dir.join(MAP_FILE))
            .with_context(|| format!("shard map {}", self.dir.join(MAP_FILE).display()))?;
        // The configuration names them from now on (a restarted HAProxy
        // keeps them); they are no longer spare.
        self.spec
            .spare
            .retain(|n| !names[have..].iter().any(|m| m == n));
        write_router(&self.dir.join("router"), &map, &self.spec)?;
        check_router(&self.haproxy, &self.dir.join("router").join("haproxy.cfg"))?;
        if matches!(self.router_update, RouterUpdate::Runtime) {
            for b in &self.spec.backends[have..] {
                match add_backend(&self.state.admin_socket, b) {
                    Ok(()) => {}
                    // Not running (restarting after an exit): it reads
                    // the configuration just written when it starts.
                    Err(e) if router_absent(&e) => {
                        tracing::warn!(replica = %b.replica, error = %e, "the router's Runtime API does not answer; it takes the replica from its configuration when it starts");
                    }
                    Err(e) => {
                        return Err(anyhow::Error::new(e)
                            .context(format!("adding {} to the router", b.replica)));
                    }
                }
            }
        }
        self.reload_router(ready_timeout).await?;
        if matches!(self.router_update, RouterUpdate::Runtime) {
            tracing::info!(
                replicas = want,
                "replicas started and added to the running router (Runtime API, no restart)"
            );
        }
        self.state.replicas = want;
        self.write_state();
        tracing::info!(
            replicas = want,
            "rebalance request done: the router knows every replica"
        );
        Ok(())
    }

    /// Takes replicas `want..have` away, once `rebalance` has moved every
    /// shard off them (refused while one still owns a shard): each leaves
    /// the running router first, its servers set to maintenance so HAProxy
    /// sends it nothing new while what it sent finishes; then it stops
    /// (SIGTERM: it drains what it accepted, SIGKILL after
    /// `drain_timeout`); then its servers are deleted from the router
    /// (Runtime API, no restart), and the configuration is written without
    /// it, its name kept as a spare so it may join again.
    async fn shrink(
        &mut self,
        have: usize,
        want: usize,
        ready_timeout: Duration,
        drain_timeout: Duration,
    ) -> Result<()> {
        let map = ShardMap::read(&self.dir.join(MAP_FILE))
            .with_context(|| format!("shard map {}", self.dir.join(MAP_FILE).display()))?;
        let leaving = ordinal_names("mcapi", have).map_err(anyhow::Error::msg)?[want..].to_vec();
        for r in &leaving {
            let owned = map.shards_of(r).len();
            if owned > 0 {
                bail!(
                    "{r} still owns {owned} shards: `mcapi cluster rebalance --replicas {want}` moves them off before it stops a replica"
                );
            }
        }
        let socket = self.state.admin_socket.clone();
        let runtime = matches!(self.router_update, RouterUpdate::Runtime);
        // The router may be restarting after an exit (its Runtime API
        // absent): it then reads the configuration written below, without
        // the leaving replicas.
        if runtime {
            for r in &leaving {
                match drain_backend(&socket, r) {
                    Err(e) if !router_absent(&e) => {
                        return Err(
                            anyhow::Error::new(e).context(format!("taking {r} out of the router"))
                        );
                    }
                    _ => {}
                }
            }
        }
        self.stop(want..have, drain_timeout).await;
        if runtime {
            let (socket, names) = (socket.clone(), leaving.clone());
            let removed = tokio::task::spawn_blocking(move || {
                for r in &names {
                    match remove_backend(&socket, r, Duration::from_secs(10)) {
                        Err(e) if !router_absent(&e) => {
                            return Err(anyhow::Error::new(e)
                                .context(format!("deleting {r} from the router")));
                        }
                        _ => {}
                    }
                }
                Ok(())
            })
            .await
            .context("the router update task")?;
            removed?;
        }
        self.processes.drain(want..have);
        self.spec.backends.retain(|b| !leaving.contains(&b.replica));
        self.spec.spare.extend(leaving.iter().cloned());
        write_router(&self.dir.join("router"), &map, &self.spec)?;
        check_router(&self.haproxy, &self.dir.join("router").join("haproxy.cfg"))?;
        self.reload_router(ready_timeout).await?;
        if runtime {
            tracing::info!(
                replicas = want,
                "replicas stopped and deleted from the running router (Runtime API, no restart)"
            );
        }
        self.state.replicas = want;
        self.write_state();
        tracing::info!(
            replicas = want,
            "rebalance request done: the leaving replicas are stopped and out of the router"
        );
        Ok(())
    }

    /// Has the running router take the configuration just written when it
    /// is not updated through its Runtime API: a master-worker reload, or
    /// a restart (the two ways kept to measure against the Runtime API,
    /// docs/cluster.md).
    async fn reload_router(&mut self, ready_timeout: Duration) -> Result<()> {
        let router = self.processes.len() - 1;
        match self.router_update {
            RouterUpdate::Runtime => {}
            RouterUpdate::Reload => {
                if let Some(pid) = self.processes[router].pid() {
                    send_signal(pid, libc::SIGUSR2);
                }
                tracing::info!("the router reloaded");
            }
            RouterUpdate::Restart => {
                tracing::info!("starting the router again");
                self.stop(router..router + 1, Duration::from_secs(10)).await;
                self.start(router..router + 1, ready_timeout).await?;
            }
        }
        Ok(())
    }

    /// Replicas first (they drain on SIGTERM), then the router.
    pub(super) async fn shutdown(&mut self, drain: Duration) {
        let replicas = self.processes.len().saturating_sub(1);
        self.stop(0..replicas, drain).await;
        self.stop(replicas..self.processes.len(), Duration::from_secs(10))
            .await;
        let _ = std::fs::remove_file(&self.state_file);
    }
}

/// The router's Runtime API does not answer because HAProxy is not
/// running (restarting after an exit): it reads the configuration when it
/// starts, so the update is not lost.
fn router_absent(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::NotFound | std::io::ErrorKind::ConnectionRefused
    )
}

pub(super) async fn supervise(setup: Setup, signal: impl Future<Output = ()> + Send) -> Result<()> {
    let Setup {
        dir,
        map,
        template,
        spec,
        haproxy,
        haproxy_cfg,
        admin_socket,
        http,
        grpc,
        processes,
        ready_timeout,
        drain_timeout,
        router_update,
    } = setup;
    let replicas = processes.len().saturating_sub(1);
    let mut cluster = Cluster {
        processes,
        template,
        spec,
        haproxy,
        dir: dir.clone(),
        state_file: dir.join(STATE_FILE),
        state: State {
            supervisor: std::process::id(),
            http: http.to_string(),
            grpc: grpc.to_string(),
            admin_socket: admin_socket.clone(),
            epoch: map.epoch(),
            replicas,
            processes: Vec::new(),
        },
        router_update,
    };
    tokio::pin!(signal);
    let started = tokio::select! {
        r = async {
            cluster.start(0..replicas, ready_timeout).await?;
            cluster.start(replicas..replicas + 1, ready_timeout).await
        } => r,
        () = &mut signal => Err(anyhow::anyhow!("interrupted while starting")),
    };
    if let Err(e) = started {
        cluster.shutdown(drain_timeout).await;
        return Err(e);
    }
    cluster.write_state();
    print_banner(&dir, &map, &cluster, &haproxy_cfg, &admin_socket);
    let mut hangup = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup())
        .context("installing the SIGHUP handler (rebalance requests)")?;
    loop {
        tokio::select! {
            () = cluster.watch(Backoff::DEFAULT) => break,
            () = &mut signal => break,
            _ = hangup.recv() => {
                if let Err(e) = cluster.resize(ready_timeout, drain_timeout).await {
                    tracing::error!(error = %format!("{e:#}"), "rebalance request refused");
                }
            }
        }
    }
    tracing::info!("shutdown requested: draining the replicas, then the router");
    cluster.shutdown(drain_timeout).await;
    tracing::info!("every process stopped");
    Ok(())
}

/// Where things listen, on stdout (this is a CLI).
pub(super) fn print_banner(
    dir: &Path,
    map: &ShardMap,
    cluster: &Cluster,
    cfg: &Path,
    socket: &Path,
) {
    let s = &cluster.state;
    let mut out = format!(
        "mcapi cluster local: {} replicas behind HAProxy, shard map epoch {} ({})\n\
         \x20 REST  http://{}\n\
         \x20 gRPC  http://{} (name the session in `x-mcapi-session` metadata)\n",
        map.replicas().len(),
        map.epoch(),
        dir.join(MAP_FILE).display(),
        s.http,
        s.grpc,
    );
    for p in &cluster.processes {
        let pid = p.pid().map_or_else(|| "-".to_string(), |p| p.to_string());
        match p.listen {
            Some((h, g)) => out.push_str(&format!(
                "  {:<10} REST {:<15}  gRPC {:<15}  pid {pid:<7}  log {}\n",
                p.name,
                h.to_string(),
                g.to_string(),
                p.log.display()
            )),
            None => out.push_str(&format!(
                "  {:<10} {}  pid {pid:<7}  log {}\n",
                p.name,
                cfg.display(),
                p.log.display()
            )),
        }
    }
    out.push_str(&format!(
        "  Runtime API {}\n  state {}\nCtrl-C or SIGTERM stops everything.\n",
        socket.display(),
        cluster.state_file.display()
    ));
    // Not `print!`, which panics when stdout is a closed pipe: the
    // cluster runs on whether or not anyone reads the banner.
    use std::io::Write;
    let mut stdout = std::io::stdout().lock();
    let _ = stdout.write_all(out.as_bytes());
    let _ = stdout.flush();
}
