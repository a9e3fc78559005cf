//! Durability and access control on the real binary (docs/operations.md,
//! "API keys" and "The store"; docs/sessions.md, "Durability and recovery"):
//! - a clean restart (SIGTERM) keeps every session exactly (Ξ, D, Q,
//!   policy, statistics, history) and the shutdown snapshot trims the log
//!   (nothing replayed); lockstep sessions then go on exactly as a core
//!   agent that never restarted;
//! - a deleted session stays deleted, after kill -9 and after a clean stop,
//!   and leaves no record in the store;
//! - after kill -9 the history ring comes back as it was served;
//! - a damaged store (truncated, garbage, overwritten, a changed record, a
//!   damaged last commit) or one of another format version is refused at
//!   start with a message naming the file, before any port is bound; a
//!   session whose record, snapshot or log entry mcapi cannot decode is
//!   skipped (logged with its id, counted, its data left in the store) and
//!   the others are served; a second server on the same data directory is
//!   refused;
//! - API keys over REST and gRPC: a missing, wrong or malformed key gets
//!   401 / UNAUTHENTICATED (`unauthenticated`, `WWW-Authenticate`) on every
//!   call; another key's session is 404 / NOT_FOUND on every call,
//!   indistinguishable from a missing one, and is never listed; health,
//!   readiness and metrics need no key; keys are never logged or echoed;
//! - `--store memory` with keys from `MCAPI_API_KEYS` touches no disk.
//!
//! One module per concern: [`restart`], [`damaged_store`], [`api_keys`];
//! the driven session ([`Sim`]) and the reads of a session and of a store
//! file they share are here. The session manager's handling of a failed
//! commit, a failed delete and a failed plan needs no binary: it is tested
//! in process with mcapi-server
//! (`crates/mcapi-server/tests/api/storage_failures.rs`).
// These tests still send the deprecated `model_json` (accepted for one
// more release, docs/grpc.md).
#![allow(deprecated)]

use crate::common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::{Obs, Reply, assert_bits_eq, check_session, core_agent, grpc_request, rest};
use mcapi_core::{Agent, AgentParams, Observation};
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use redb::{ReadableDatabase, ReadableTableMetadata, TableHandle};
use reqwest::Method;
use serde_json::{Value, json};
use tonic::transport::Channel;

mod api_keys;
mod continuous;
mod damaged_store;
mod groups;
mod restart;
mod seq;

const KEY_A: &str = "durability-key-alpha-0123456789";
const KEY_B: &str = "durability-key-bravo-9876543210";
/// Configured nowhere.
const KEY_WRONG: &str = "durability-key-wrong-000000000";
/// A well-formed id no session has.
const MISSING: &str = "s0000.01ARZ3NDEKTSV4RRFFQ69G5FAV";
const STORE_FILE: &str = "mcapi.redb";

// ------------------------------------------------------------------ driving

/// A session driven one observation at a time, with everything it applied
/// and, in lockstep mode, a core agent stepped alongside (`Agent::step`,
/// Algorithm 1 to the letter) that every reply must equal.
struct Sim {
    id: String,
    key: Option<&'static str>,
    params: AgentParams,
    applied: Vec<(Obs, Option<Reply>)>,
    state: Option<usize>,
    advised: Option<usize>,
    rng: ChaCha8Rng,
    core: Option<Agent>,
}

impl Sim {
    fn new(id: String, key: Option<&'static str>, params: AgentParams, lockstep: bool) -> Self {
        let seed = params.seed.expect("seeded");
        Self {
            id,
            key,
            core: lockstep.then(|| core_agent(&params)),
            params,
            applied: Vec::new(),
            state: None,
            advised: None,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0xd00d),
        }
    }

    fn next_obs(&mut self) -> Obs {
        common::next_hallway_obs(&mut self.rng, self.state, self.advised, true)
    }

    fn record(&mut self, obs: Obs, reply: Reply) {
        if let Some(core) = &mut self.core {
            let step = core
                .step(&Observation {
                    state: obs.state,
                    stimulus: obs.stimulus.as_ref().map(|x| &x[..]),
                    action_taken: obs.report,
                })
                .expect("core step");
            let t = step.tick;
            assert_eq!(reply.tick, t, "{}: tick", self.id);
            assert_eq!(reply.action, step.action, "{}: action at tick {t}", self.id);
            assert_bits_eq(
                &reply.drive,
                core.drive().vector(),
                &format!("{}: drive at tick {t}", self.id),
            );
            assert_eq!(reply.reward.to_bits(), step.reward.to_bits(), "reward");
        }
        self.state = Some(obs.state);
        self.advised = Some(reply.action);
        self.applied.push((obs, Some(reply)));
    }

    async fn rest_ticks(&mut self, client: &reqwest::Client, base: &str, n: usize) {
        for _ in 0..n {
            let obs = self.next_obs();
            let (status, body) = rest(
                client,
                Method::POST,
                &format!("{base}/v1/sessions/{}/observations", self.id),
                self.key,
                Some(&obs.json()),
            )
            .await;
            assert_eq!(status, 200, "{}: observe: {body}", self.id);
            self.record(obs, Reply::from_json(&body));
        }
    }

    async fn grpc_ticks(&mut self, client: &mut AgentsClient<Channel>, n: usize) {
        for _ in 0..n {
            let obs = self.next_obs();
            let steps = client
                .observe(grpc_request(
                    pb::ObserveRequest {
                        session_id: self.id.clone(),
                        observations: vec![obs.pb("")],
                    },
                    self.key,
                    Some(&self.id),
                ))
                .await
                .expect("observe over gRPC")
                .into_inner()
                .steps;
            assert_eq!(steps.len(), 1);
            self.record(obs, Reply::from_pb(&steps[0]));
        }
    }

    async fn check(&self, client: &reqwest::Client, base: &str, ctx: &str) {
        check_session(
            client,
            base,
            self.key,
            &self.id,
            &self.params,
            &self.applied,
            &format!("{ctx}: {}", self.id),
        )
        .await;
    }
}

/// A session's GET body, all its value tables and its history.
async fn everything(client: &reqwest::Client, base: &str, key: Option<&str>, id: &str) -> Value {
    let mut out = json!({});
    for (name, path) in [
        ("info", String::new()),
        ("values", "/values?include=all".into()),
        ("history", "/history".into()),
    ] {
        let (status, body) = rest(
            client,
            Method::GET,
            &format!("{base}/v1/sessions/{id}{path}"),
            key,
            None,
        )
        .await;
        assert_eq!(status, 200, "{id}{path}: {body}");
        out[name] = body;
    }
    out
}

/// [`everything`], once two reads 50 ms apart agree (no policy update of
/// an async session still pending).
async fn settled(client: &reqwest::Client, base: &str, key: Option<&str>, id: &str) -> Value {
    let started = Instant::now();
    let mut last = everything(client, base, key, id).await;
    loop {
        tokio::time::sleep(Duration::from_millis(50)).await;
        let now = everything(client, base, key, id).await;
        if now == last {
            return now;
        }
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "{id}: still changing"
        );
        last = now;
    }
}

/// Rows per table of a stopped server's store file (read-only).
fn table_rows(file: &Path) -> BTreeMap<String, u64> {
    let db = redb::ReadOnlyDatabase::open(file).expect("the store opens read-only");
    let read = db.begin_read().expect("read");
    read.list_tables()
        .expect("tables")
        .map(|t| {
            let name = t.name().to_string();
            let table = read.open_untyped_table(t).expect("table");
            (name, table.len().expect("len"))
        })
        .collect()
}

fn logs() -> tempfile::TempDir {
    tempfile::tempdir().expect("log dir")
}

fn log_path(dir: &tempfile::TempDir, name: &str) -> PathBuf {
    dir.path().join(format!("{name}.log"))
}
