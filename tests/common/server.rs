//! Starting the real `mcapi serve` binary as a child process, waiting for
//! it to be ready, and killing or stopping it. Here and not in
//! mcapi-testkit: it names the binary with `env!("CARGO_BIN_EXE_mcapi")`,
//! which Cargo sets only for the root package's tests.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_testkit::ports::free_ports;
use mcapi_testkit::process::terminate;
use tonic::transport::Channel;

/// How to start `mcapi serve`.
#[derive(Debug, Clone, Default)]
pub struct Launch {
    /// `--data-dir`.
    pub data_dir: Option<PathBuf>,
    /// Extra flags.
    pub args: Vec<String>,
    /// Environment variables.
    pub env: Vec<(String, String)>,
}

impl Launch {
    /// `--data-dir dir --workers 2 --log-format json` and the given flags.
    pub fn new(data_dir: &Path, args: &[&str]) -> Self {
        Self {
            data_dir: Some(data_dir.to_path_buf()),
            args: args.iter().map(|s| s.to_string()).collect(),
            env: Vec::new(),
        }
    }

    /// Adds an environment variable.
    pub fn env(mut self, key: &str, value: &str) -> Self {
        self.env.push((key.into(), value.into()));
        self
    }
}

/// A running `mcapi serve` child, killed when dropped (a failing test
/// leaves no server behind).
pub struct Server {
    child: Option<Child>,
    /// REST port.
    pub http: u16,
    /// gRPC port.
    pub grpc: u16,
    /// The file its stderr (the log) goes to.
    pub log: PathBuf,
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Spawns `mcapi serve` on the given ports with its log in `log`.
pub fn spawn(launch: &Launch, http: u16, grpc: u16, log: &Path) -> Child {
    let log_file = std::fs::File::create(log).expect("log file");
    let mut args: Vec<OsString> = vec![
        "serve".into(),
        "--http".into(),
        format!("127.0.0.1:{http}").into(),
        "--grpc".into(),
        format!("127.0.0.1:{grpc}").into(),
        "--workers".into(),
        "2".into(),
        "--log-format".into(),
        "json".into(),
    ];
    if let Some(dir) = &launch.data_dir {
        args.push("--data-dir".into());
        args.push(dir.into());
    }
    args.extend(launch.args.iter().map(OsString::from));
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mcapi"));
    cmd.args(&args)
        .env_remove("MCAPI_API_KEYS")
        .env("RUST_LOG", "info")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::from(log_file));
    for (k, v) in &launch.env {
        cmd.env(k, v);
    }
    cmd.spawn().expect("mcapi serve starts")
}

impl Server {
    /// Starts the server on fresh ports and waits until `/readyz` answers
    /// 200 (recovery done); `log` names its log file.
    pub async fn start(launch: &Launch, log: PathBuf) -> Self {
        let (http, grpc) = free_ports();
        let child = spawn(launch, http, grpc, &log);
        let mut server = Self {
            child: Some(child),
            http,
            grpc,
            log,
        };
        server.wait_ready(Duration::from_secs(60)).await;
        server
    }

    /// Polls `/readyz` until 200; fails if the process exits first.
    pub async fn wait_ready(&mut self, timeout: Duration) {
        let client = reqwest::Client::builder()
            .timeout(Duration::from_secs(2))
            .build()
            .expect("client");
        let url = format!("{}/readyz", self.base());
        let started = Instant::now();
        loop {
            if let Some(status) = self.child_mut().try_wait().expect("try_wait") {
                panic!(
                    "mcapi serve exited with {status} before becoming ready; log:\n{}",
                    self.log_text()
                );
            }
            if let Ok(resp) = client.get(&url).send().await
                && resp.status() == 200
            {
                return;
            }
            assert!(
                started.elapsed() < timeout,
                "mcapi serve not ready after {timeout:?}; log:\n{}",
                self.log_text()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    fn child_mut(&mut self) -> &mut Child {
        self.child.as_mut().expect("the server is running")
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.as_ref().expect("the server is running").id()
    }

    /// `http://127.0.0.1:<http>`.
    pub fn base(&self) -> String {
        format!("http://127.0.0.1:{}", self.http)
    }

    /// `http://127.0.0.1:<grpc>`.
    pub fn grpc_url(&self) -> String {
        format!("http://127.0.0.1:{}", self.grpc)
    }

    /// A gRPC client.
    pub async fn grpc_client(&self) -> AgentsClient<Channel> {
        AgentsClient::connect(self.grpc_url())
            .await
            .expect("gRPC connects")
    }

    /// The log so far.
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// `kill -9`: no shutdown, no snapshot, nothing flushed by the server.
    pub fn kill9(&mut self) {
        if let Some(mut child) = self.child.take() {
            // `Child::kill` is SIGKILL on unix.
            child.kill().expect("SIGKILL");
            let status = child.wait().expect("wait");
            assert!(!status.success(), "a killed server cannot exit cleanly");
        }
    }

    /// SIGTERM, then waits (at most 30 s) for the exit status.
    pub fn terminate(&mut self) -> ExitStatus {
        let mut child = self.child.take().expect("the server is running");
        terminate(&mut child, Duration::from_secs(30), &|| self.log_text())
    }
}
