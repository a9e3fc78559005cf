//! Damaged stores: a truncated, garbage, overwritten or changed store, a
//! damaged last commit or one of another format version is refused at start
//! with a message naming the file; a session that cannot be replayed is
//! skipped and left in the store; a second server on the same data directory
//! is refused.

use crate::common;

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::{
    Launch, Obs, Reply, Server, free_ports, http_client, log_events, params, rest, rest_create,
    rest_get, rest_list_all, step_state,
};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use redb::{ReadableDatabase, ReadableTable};
use reqwest::Method;
use serde_json::json;

use super::{STORE_FILE, Sim, log_path, logs};

/// A data directory with a few sessions, written by a server that stopped
/// cleanly; returns the store file's bytes.
async fn populated_store(dir: &Path, logs: &tempfile::TempDir) -> Vec<u8> {
    let mut server = Server::start(
        &Launch::new(dir, &["--snapshot-every", "40"]),
        log_path(logs, "populate"),
    )
    .await;
    let client = http_client();
    let base = server.base();
    for seed in 0..6 {
        let id = rest_create(&client, &base, None, json!({"seed": 300 + seed})).await;
        let mut sim = Sim::new(id, None, params(300 + seed, None), true);
        sim.rest_ticks(&client, &base, 100).await;
    }
    assert!(server.terminate().success());
    std::fs::read(dir.join(STORE_FILE)).expect("store file")
}

/// Starts `mcapi serve` on `dir` with both its ports held by this test, so
/// a server that got as far as binding would fail with a bind error, not
/// with the store's; returns the exit status and log.
fn start_refused(dir: &Path) -> (std::process::ExitStatus, String) {
    let http = TcpListener::bind("127.0.0.1:0").expect("bind");
    let grpc = TcpListener::bind("127.0.0.1:0").expect("bind");
    let (hp, gp) = (
        http.local_addr().expect("addr").port(),
        grpc.local_addr().expect("addr").port(),
    );
    let out = run_until_exit(dir, hp, gp);
    drop((http, grpc));
    out
}

/// Runs `mcapi serve` on `dir` until it exits (at most 20 s).
fn run_until_exit(dir: &Path, http: u16, grpc: u16) -> (std::process::ExitStatus, String) {
    let log = dir.join("serve.log");
    let mut child = common::spawn(&Launch::new(dir, &[]), http, grpc, &log);
    let deadline = Instant::now() + Duration::from_secs(20);
    let status = loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "mcapi serve kept running on a damaged store; log:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            );
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    (status, std::fs::read_to_string(&log).unwrap_or_default())
}

fn assert_refused_as_corrupt(dir: &Path, what: &str) {
    let (status, err) = start_refused(dir);
    assert!(!status.success(), "{what}: must not start; log:\n{err}");
    let file = dir.join(STORE_FILE);
    assert!(
        err.contains("corrupt"),
        "{what}: the message says the store is corrupt:\n{err}"
    );
    assert!(
        err.contains(&file.display().to_string()),
        "{what}: the message names {}:\n{err}",
        file.display()
    );
    assert!(
        !err.contains("binding"),
        "{what}: the store is checked before any port is bound:\n{err}"
    );
    assert!(
        !err.contains("mcapi serving"),
        "{what}: never served:\n{err}"
    );
}

/// Deterministic junk.
fn junk(len: usize, seed: u64) -> Vec<u8> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..len).map(|_| rng.random::<u8>()).collect()
}

fn write_store(root: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let dir = root.join(name);
    std::fs::create_dir_all(&dir).expect("dir");
    std::fs::write(dir.join(STORE_FILE), bytes).expect("write");
    dir
}

fn find_all(haystack: &[u8], needle: &[u8]) -> Vec<usize> {
    haystack
        .windows(needle.len())
        .enumerate()
        .filter(|(_, w)| *w == needle)
        .map(|(i, _)| i)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_store_is_refused_at_start_with_a_clear_message() {
    let root = tempfile::tempdir().expect("root");
    let logs = logs();
    let good_dir = root.path().join("good");
    let good = populated_store(&good_dir, &logs).await;
    let len = good.len();

    // Truncated to half.
    let dir = write_store(root.path(), "truncated", &good[..len / 2]);
    assert_refused_as_corrupt(&dir, "a store truncated to half");

    // Truncated to one page.
    let dir = write_store(root.path(), "one-page", &good[..4096.min(len)]);
    assert_refused_as_corrupt(&dir, "a store truncated to 4 KiB");

    // Garbage of the same length.
    let dir = write_store(root.path(), "garbage", &junk(len, 1));
    assert_refused_as_corrupt(&dir, "garbage");

    // The middle half overwritten.
    let mut bytes = good.clone();
    bytes[len / 4..3 * len / 4].copy_from_slice(&junk(3 * len / 4 - len / 4, 2));
    let dir = write_store(root.path(), "middle", &bytes);
    assert_refused_as_corrupt(&dir, "a store with its middle overwritten");

    // One byte changed inside every copy of the session records (live
    // data, in the tree of every commit): "hallway" becomes "hallwaz".
    let mut bytes = good.clone();
    let hits = find_all(&bytes, b"hallway");
    assert!(!hits.is_empty(), "the records name their preset");
    for i in hits {
        bytes[i + 6] = b'z';
    }
    let dir = write_store(root.path(), "record", &bytes);
    assert_refused_as_corrupt(&dir, "a store with a changed session record");

    // The untouched copy still starts, with every session (the damaged
    // ones above failed for their damage, not for a bad test setup).
    let dir = write_store(root.path(), "copy", &good);
    let mut server = Server::start(&Launch::new(&dir, &[]), log_path(&logs, "copy")).await;
    let listed = rest_list_all(&http_client(), &server.base(), None).await;
    assert_eq!(listed.len(), 6);
    assert!(server.terminate().success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_of_another_format_version_is_refused() {
    let root = tempfile::tempdir().expect("root");
    let logs = logs();
    let dir = root.path().join("data");
    populated_store(&dir, &logs).await;
    let file = dir.join(STORE_FILE);
    {
        const META: redb::TableDefinition<&str, u64> = redb::TableDefinition::new("meta");
        let db = redb::Database::open(&file).expect("open");
        let w = db.begin_write().expect("write");
        let found = w
            .open_table(META)
            .expect("meta")
            .insert("format_version", 99)
            .expect("insert")
            .map(|v| v.value());
        assert!(
            found.is_some_and(|v| v != 99),
            "the store records its format version: {found:?}"
        );
        w.commit().expect("commit");
    }
    let (status, err) = start_refused(&dir);
    assert!(!status.success(), "{err}");
    assert!(
        err.contains("format version 99") && err.contains(&file.display().to_string()),
        "{err}"
    );
    assert!(!err.contains("binding"), "{err}");
}

const SESSIONS: redb::TableDefinition<&str, &[u8]> = redb::TableDefinition::new("sessions");
const SNAPSHOTS: redb::TableDefinition<&str, (u64, &[u8])> =
    redb::TableDefinition::new("snapshots");
const LOG: redb::TableDefinition<(u128, u64), &[u8]> = redb::TableDefinition::new("log");

/// The log key of a session id (`s<shard>.<ULID>`): the ULID's 128 bits.
fn log_key(id: &str) -> u128 {
    let (_, ulid) = id.split_once('.').expect("s<shard>.<ULID>");
    ulid::Ulid::from_string(ulid).expect("a ULID").0
}

/// Everything the store holds of one session: its record, its snapshot
/// and its log chunks, as bytes.
type Stored = (
    Option<Vec<u8>>,
    Option<(u64, Vec<u8>)>,
    Vec<((u128, u64), Vec<u8>)>,
);

fn stored(file: &Path, id: &str) -> Stored {
    let db = redb::ReadOnlyDatabase::open(file).expect("the store opens read-only");
    let read = db.begin_read().expect("read");
    let record = read
        .open_table(SESSIONS)
        .expect("sessions")
        .get(id)
        .expect("get")
        .map(|v| v.value().to_vec());
    let snapshot = read
        .open_table(SNAPSHOTS)
        .expect("snapshots")
        .get(id)
        .expect("get")
        .map(|v| (v.value().0, v.value().1.to_vec()));
    let key = log_key(id);
    let log = read
        .open_table(LOG)
        .expect("log")
        .range((key, 0)..=(key, u64::MAX))
        .expect("range")
        .map(|row| {
            let (k, v) = row.expect("row");
            (k.value(), v.value().to_vec())
        })
        .collect();
    (record, snapshot, log)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_that_cannot_be_replayed_is_skipped_and_left_in_the_store() {
    // A store redb finds sound, holding one session whose record, snapshot
    // or log entry mcapi cannot decode: the server starts and serves the
    // other sessions; the bad one is reported (log, metric) and its data is
    // left in the store exactly as it was, for an operator to inspect.
    let root = tempfile::tempdir().expect("root");
    let logs = logs();
    let good = populated_store(&root.path().join("good"), &logs).await;
    for what in ["record", "snapshot", "log entry"] {
        let dir = write_store(root.path(), &what.replace(' ', "-"), &good);
        let file = dir.join(STORE_FILE);
        let (victim, others) = {
            let db = redb::Database::open(&file).expect("open");
            let w = db.begin_write().expect("write");
            let ids: Vec<String> = w
                .open_table(SESSIONS)
                .expect("sessions")
                .iter()
                .expect("iter")
                .map(|r| r.expect("row").0.value().to_string())
                .collect();
            assert_eq!(ids.len(), 6);
            let victim = ids[2].clone();
            let seq = w
                .open_table(SNAPSHOTS)
                .expect("snapshots")
                .get(victim.as_str())
                .expect("read")
                .expect("every session has a snapshot")
                .value()
                .0;
            match what {
                "record" => {
                    w.open_table(SESSIONS)
                        .expect("sessions")
                        .insert(victim.as_str(), &b"{not a record"[..])
                        .expect("insert");
                }
                "snapshot" => {
                    w.open_table(SNAPSHOTS)
                        .expect("snapshots")
                        .insert(victim.as_str(), (seq, &[0xffu8; 7][..]))
                        .expect("insert");
                }
                _ => {
                    // The next log entry after the snapshot, framed as the
                    // store frames it (sequence number, length, bytes), whose
                    // bytes are this version's tag and then garbage.
                    let next = seq + 1;
                    let at = (log_key(&victim), next / 64);
                    let mut log = w.open_table(LOG).expect("log");
                    let mut chunk = log
                        .get(at)
                        .expect("read")
                        .map(|v| v.value().to_vec())
                        .unwrap_or_default();
                    let entry = [3u8, 0xff, 0xff, 0xff, 0xff];
                    chunk.extend_from_slice(&next.to_le_bytes());
                    chunk.extend_from_slice(&(entry.len() as u32).to_le_bytes());
                    chunk.extend_from_slice(&entry);
                    log.insert(at, chunk.as_slice()).expect("insert");
                }
            }
            w.commit().expect("commit");
            let others: Vec<String> = ids.into_iter().filter(|id| *id != victim).collect();
            (victim, others)
        };
        let before = stored(&file, &victim);

        let mut server = Server::start(&Launch::new(&dir, &[]), log_path(&logs, what)).await;
        let client = http_client();
        let base = server.base();
        let mut listed = rest_list_all(&client, &base, None).await;
        listed.sort();
        assert_eq!(listed, others, "{what}: the other sessions are served");
        for id in &others {
            let (status, info) = rest_get(&client, &base, None, id).await;
            assert_eq!(status, 200, "{what}: {info}");
            assert_eq!(info["tick"], 99, "{what}: {id} recovered whole");
        }
        let (status, body) = rest_get(&client, &base, None, &victim).await;
        assert_eq!(
            status, 404,
            "{what}: the skipped session is not served: {body}"
        );
        let log = server.log_text();
        let skipped = log_events(
            &log,
            "a stored session cannot be recovered and is skipped; its data is left in the store untouched",
        );
        assert_eq!(skipped.len(), 1, "{what}: one session skipped:\n{log}");
        assert_eq!(skipped[0]["session"], victim.as_str(), "{what}");
        assert!(
            skipped[0]["reason"]
                .as_str()
                .is_some_and(|r| r.contains(what.split(' ').next().unwrap_or(what))),
            "{what}: the reason says what is wrong: {}",
            skipped[0]
        );
        let summary = log_events(&log, "stored sessions skipped at recovery");
        assert_eq!(summary.len(), 1, "{what}:\n{log}");
        assert_eq!(summary[0]["skipped"], 1, "{what}");
        assert!(
            summary[0]["ids"]
                .as_str()
                .is_some_and(|s| s.contains(&victim)),
            "{what}: {}",
            summary[0]
        );
        let metrics = client
            .get(format!("{base}/metrics"))
            .send()
            .await
            .expect("metrics")
            .text()
            .await
            .expect("body");
        assert!(
            metrics
                .lines()
                .any(|l| l.trim() == "mcapi_recovery_skipped_total 1"),
            "{what}: the metric counts it:\n{metrics}"
        );
        assert!(server.terminate().success());
        assert_eq!(
            stored(&file, &victim),
            before,
            "{what}: the skipped session's data is left untouched"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_last_commit_is_not_silently_rolled_back() {
    // The last commit holds the last acknowledged observation (no snapshot
    // after it: kill -9). Damage exactly that record: the server must not
    // start on the state before it as if nothing was acknowledged since.
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    let launch = Launch::new(data.path(), &[]);
    let mut server = Server::start(&launch, log_path(&logs, "first")).await;
    let client = http_client();
    let base = server.base();
    let id = rest_create(&client, &base, None, json!({"seed": 401})).await;
    let mut sim = Sim::new(id.clone(), None, params(401, None), true);
    sim.rest_ticks(&client, &base, 40).await;
    // One more observation whose stimulus is a value found nowhere else.
    let marker = 1.234_567_890_123_456_7_f64;
    let s = sim.state.expect("state");
    let a = sim.advised.expect("advised");
    let next = step_state(s, a);
    let obs = Obs {
        state: next,
        stimulus: Some([marker, 0.0]),
        taken: Some(a),
        report: None,
        by_name: false,
    };
    let (status, body) = rest(
        &client,
        Method::POST,
        &format!("{base}/v1/sessions/{id}/observations"),
        None,
        Some(&obs.json()),
    )
    .await;
    assert_eq!(status, 200, "{body}");
    sim.record(obs, Reply::from_json(&body));
    server.kill9();

    // The record is in the write-ahead log (acknowledged after the last
    // checkpoint) or in the database file (checkpointed before the kill):
    // damaged wherever it is.
    let mut files = vec![data.path().join(STORE_FILE)];
    for entry in std::fs::read_dir(data.path().join("wal")).expect("log dir") {
        files.push(entry.expect("entry").path());
    }
    let mut damaged = Vec::new();
    let mut hits = Vec::new();
    for file in files {
        let mut bytes = std::fs::read(&file).expect("store");
        let found = find_all(&bytes, &marker.to_le_bytes());
        if found.is_empty() {
            continue;
        }
        for i in &found {
            bytes[i + 3] ^= 0xff;
        }
        std::fs::write(&file, &bytes).expect("write");
        hits.extend(found);
        damaged.push(file);
    }
    assert!(
        !hits.is_empty(),
        "the logged stimulus is in the store's files"
    );

    let (port, gport) = free_ports();
    let log = log_path(&logs, "second");
    let mut child = common::spawn(&launch, port, gport, &log);
    let deadline = Instant::now() + Duration::from_secs(20);
    let client = http_client();
    let outcome = loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            break Err(status);
        }
        if let Ok(resp) = client
            .get(format!("http://127.0.0.1:{port}/readyz"))
            .send()
            .await
            && resp.status() == 200
        {
            break Ok(());
        }
        assert!(Instant::now() < deadline, "neither ready nor exited");
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let text = std::fs::read_to_string(&log).unwrap_or_default();
    match outcome {
        Err(status) => {
            let _ = child.wait();
            assert!(!status.success());
            assert!(
                text.contains("corrupt")
                    && damaged
                        .iter()
                        .any(|f| text.contains(&f.display().to_string())),
                "{text}"
            );
        }
        Ok(()) => {
            let base = format!("http://127.0.0.1:{port}");
            let (_, info) = rest_get(&client, &base, None, &id).await;
            let _ = child.kill();
            let _ = child.wait();
            let acked = sim
                .applied
                .iter()
                .filter(|(o, _)| o.stimulus.is_some())
                .count();
            panic!(
                "the server started on a store whose last commit is damaged ({} byte(s) changed \
                 in the record of the last acknowledged observation) without reporting it: \
                 session {id} has tick {} where {acked} ticks were acknowledged, so an \
                 acknowledged observation was silently rolled back",
                hits.len(),
                info["tick"],
            );
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_server_on_the_same_data_dir_is_refused() {
    let data = tempfile::tempdir().expect("data dir");
    let logs = logs();
    let launch = Launch::new(data.path(), &[]);
    let mut first = Server::start(&launch, log_path(&logs, "first")).await;
    let (status, err) = start_refused(data.path());
    assert!(!status.success(), "{err}");
    assert!(err.contains("already open"), "{err}");
    assert!(!err.contains("binding"), "{err}");
    // The first one is unharmed.
    let client = http_client();
    rest_create(&client, &first.base(), None, json!({})).await;
    assert!(first.terminate().success());
}
