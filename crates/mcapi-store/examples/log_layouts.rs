//! What redb costs for the sessions' log under the durable group step's
//! load, by the layout of the log's values and the size of redb's page
//! cache (BENCHMARKS.md §14, "What a durable group step's checkpoints
//! cost, and where redb sets the floor").
//!
//! ```text
//! cargo run --release -p mcapi-store --example log_layouts -- LAYOUT [CACHE_MIB] [CHECKPOINTS]
//! ```
//!
//! Each transaction stands for one checkpoint of the durable row of
//! `benches/vector.sh`: 3,000 bytes of records for each of 10,000
//! sessions (two seconds of their steps), and, for a sixteenth of the
//! sessions in turn, the deletion of their older records (a snapshot every
//! sixteen checkpoints). The transactions are committed as the store's
//! checkpoints are (`Durability::Immediate`, two-phase). `LAYOUT` is one of:
//!
//! - `chunks`: the store's layout (`db.rs`): values keyed (session, chunk
//!   number), each chunk read, extended and written back;
//! - `session`: one new value per session and checkpoint, keyed
//!   (session, checkpoint), never read back;
//! - `checkpoint`: the same values keyed (checkpoint, session), so that a
//!   checkpoint's inserts land together at the end of the tree, with an
//!   index (session, checkpoint) to find a session's values.
//!
//! Prints the CPU time per checkpoint over the last sixteen (the steady
//! state), the wall time, and the bytes the process read and wrote in all
//! (`/proc/self/io`). The database is a temporary file, removed at exit.

use std::time::Instant;

use redb::{Database, Durability, ReadableTable, TableDefinition};

/// The sessions' log, keyed (session, chunk or checkpoint).
const BY_SESSION: TableDefinition<(u128, u64), &[u8]> = TableDefinition::new("log");
/// The log keyed (checkpoint, session).
const BY_CHECKPOINT: TableDefinition<(u64, u128), &[u8]> = TableDefinition::new("by_checkpoint");
/// For `checkpoint`: which checkpoints hold a session's values.
const INDEX: TableDefinition<(u128, u64), ()> = TableDefinition::new("index");

/// Sessions written to per checkpoint.
const SESSIONS: u64 = 10_000;
/// Bytes of records a session gains per checkpoint.
const GAINED: usize = 3_000;
/// The size of the store's chunks (`CHUNK` records of about 60 bytes).
const CHUNK_BYTES: usize = 3_840;
/// Each session deletes its older records once per this many checkpoints.
const SNAPSHOT_EVERY: u64 = 16;

#[derive(Clone, Copy, PartialEq)]
enum Layout {
    Chunks,
    Session,
    Checkpoint,
}

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let layout = match args.next().as_deref() {
        Some("chunks") => Layout::Chunks,
        Some("session") => Layout::Session,
        Some("checkpoint") => Layout::Checkpoint,
        other => anyhow::bail!("LAYOUT must be chunks, session or checkpoint, not {other:?}"),
    };
    let cache_mib: usize = args.next().map_or(Ok(64), |a| a.parse())?;
    let checkpoints: u64 = args.next().map_or(Ok(40), |a| a.parse())?;
    anyhow::ensure!(
        (1..=65_536).contains(&cache_mib),
        "CACHE_MIB must be between 1 and 65536, as --store-cache-mib"
    );
    anyhow::ensure!(
        checkpoints >= SNAPSHOT_EVERY,
        "CHECKPOINTS must be at least {SNAPSHOT_EVERY}"
    );
    let dir = tempfile::tempdir()?;
    let db = Database::builder()
        .set_cache_size(cache_mib << 20)
        .create(dir.path().join("log.redb"))?;
    // Spread over the key space as ULIDs are.
    let sessions: Vec<u128> = (1..=u128::from(SESSIONS))
        .map(|i| i.wrapping_mul(0x9E37_79B9_7F4A_7C15_F39C_C060_5CED_C835))
        .collect();
    let records = vec![7u8; GAINED];
    let (mut cpu, mut wall) = (0.0, 0.0);
    for round in 0..checkpoints {
        let started = (Instant::now(), cpu_seconds()?);
        let mut txn = db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        txn.set_two_phase_commit(true);
        {
            let mut by_session = txn.open_table(BY_SESSION)?;
            let mut by_checkpoint = txn.open_table(BY_CHECKPOINT)?;
            let mut index = txn.open_table(INDEX)?;
            for (i, &key) in (0..).zip(&sessions) {
                let snapshot = i % SNAPSHOT_EVERY == round % SNAPSHOT_EVERY;
                match layout {
                    Layout::Chunks => {
                        let first = round * GAINED as u64;
                        let chunk = first / CHUNK_BYTES as u64;
                        if snapshot {
                            by_session.retain_in((key, 0)..(key, chunk), |_, _| false)?;
                        }
                        let mut bytes = by_session
                            .get((key, chunk))?
                            .map(|v| v.value().to_vec())
                            .unwrap_or_default();
                        let room = CHUNK_BYTES.saturating_sub(bytes.len()).min(GAINED);
                        bytes.extend_from_slice(&records[..room]);
                        by_session.insert((key, chunk), bytes.as_slice())?;
                        if room < GAINED {
                            by_session.insert((key, chunk + 1), &records[room..])?;
                        }
                    }
                    Layout::Session => {
                        if snapshot {
                            by_session.retain_in((key, 0)..(key, round), |_, _| false)?;
                        }
                        by_session.insert((key, round), records.as_slice())?;
                    }
                    Layout::Checkpoint => {
                        if snapshot {
                            let older = index
                                .range((key, 0)..(key, round))?
                                .map(|row| row.map(|(k, _)| k.value().1))
                                .collect::<Result<Vec<u64>, _>>()?;
                            for c in older {
                                by_checkpoint.remove((c, key))?;
                                index.remove((key, c))?;
                            }
                        }
                        by_checkpoint.insert((round, key), records.as_slice())?;
                        index.insert((key, round), ())?;
                    }
                }
            }
        }
        txn.commit()?;
        if round >= checkpoints - SNAPSHOT_EVERY {
            cpu += cpu_seconds()? - started.1;
            wall += started.0.elapsed().as_secs_f64();
        }
    }
    let (read, written) = io_bytes()?;
    let per = |s: f64| s * 1000.0 / SNAPSHOT_EVERY as f64;
    println!(
        "{layout} cache {cache_mib} MiB: CPU {:.0} ms and wall {:.0} ms per checkpoint (the last {SNAPSHOT_EVERY}); \
         {:.2} GB written, {:.2} GB read for {:.2} GB of records",
        per(cpu),
        per(wall),
        written as f64 / 1e9,
        read as f64 / 1e9,
        (checkpoints * SESSIONS) as f64 * GAINED as f64 / 1e9,
        layout = match layout {
            Layout::Chunks => "chunks",
            Layout::Session => "session",
            Layout::Checkpoint => "checkpoint",
        },
    );
    Ok(())
}

/// The CPU time this process has run, in seconds: its one thread's
/// (`/proc/self/schedstat`, in nanoseconds; redb starts no threads).
fn cpu_seconds() -> anyhow::Result<f64> {
    let stat = std::fs::read_to_string("/proc/self/schedstat")?;
    let ns: u64 = stat
        .split_whitespace()
        .next()
        .ok_or_else(|| anyhow::anyhow!("/proc/self/schedstat is empty"))?
        .parse()?;
    Ok(ns as f64 / 1e9)
}

/// Bytes read and written by this process's system calls (`rchar`, `wchar`).
fn io_bytes() -> anyhow::Result<(u64, u64)> {
    let io = std::fs::read_to_string("/proc/self/io")?;
    let field = |name: &str| -> anyhow::Result<u64> {
        io.lines()
            .find_map(|l| l.strip_prefix(name))
            .ok_or_else(|| anyhow::anyhow!("/proc/self/io has no {name}"))?
            .trim()
            .parse()
            .map_err(Into::into)
    };
    Ok((field("rchar:")?, field("wchar:")?))
}
