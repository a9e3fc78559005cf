//! The redb side of the store: the file's tables and format versions, the
//! bulk application of log frames (checkpoints), the replay of the
//! write-ahead log at open, and the health probe.
//!
//! Layout (format version [`FORMAT_VERSION`]):
//! - `meta`: `"format_version"` → u64; `"wal_lsn"` → the number of the
//!   last log frame applied (0: none);
//! - `sessions`: id → creation record;
//! - `snapshots`: id → (sequence number, snapshot);
//! - `log`: (session key, chunk number) → a chunk of up to [`CHUNK`]
//!   observation records (chunk c holds sequence numbers c·CHUNK to
//!   c·CHUNK + CHUNK − 1, each framed as sequence number, length, bytes).
//!   The session key is the 128-bit ULID of the session id. A snapshot at
//!   sequence number n drops the chunks that end at or before n.
//!
//! Upgrades at open, each in one transaction: format 2 → 3 prefixes every
//! record with [`RECORD_V2`]; 3 → 4 adds `wal_lsn` (an older file has no
//! log directory, or an empty one).

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use redb::{Database, Durability, ReadableTable, TableDefinition};

use crate::error::StoreError;
use crate::format::FORMAT_VERSION;
use crate::record::{log_key, push_entry, split_entry};
use crate::wal::{self, Frame};
use crate::write::Write;

/// The record-encoding byte given to records written under format 2.
pub const RECORD_V2: u8 = 2;

/// Observation records per log chunk.
pub const CHUNK: u64 = 64;

pub(super) const META: TableDefinition<&str, u64> = TableDefinition::new("meta");
pub(super) const SESSIONS: TableDefinition<&str, &[u8]> = TableDefinition::new("sessions");
pub(super) const SNAPSHOTS: TableDefinition<&str, (u64, &[u8])> = TableDefinition::new("snapshots");
pub(super) const LOG: TableDefinition<(u128, u64), &[u8]> = TableDefinition::new("log");
/// The health probe's scratch table (empty between probes).
const PROBE: TableDefinition<&str, &[u8]> = TableDefinition::new("probe");
/// The meta key of the last applied log frame.
const WAL_LSN: &str = "wal_lsn";

/// What the health probe writes (and removes again) after a reopen.
pub(super) const PROBE_BYTES: usize = 256 * 1024;

/// Whether a redb error leaves the `Database` unusable until it is closed and
/// opened again: an I/O error is latched (every later call answers
/// `PreviousIo`), and a failed commit may discard the allocator state (every
/// later write transaction answers `Corrupted`, "reopen the database to
/// repair it").
fn needs_reopen(e: &redb::Error) -> bool {
    matches!(
        e,
        redb::Error::Io(_)
            | redb::Error::PreviousIo
            | redb::Error::DatabaseClosed
            | redb::Error::Corrupted(_)
            | redb::Error::TransactionPoisoned
            | redb::Error::LockPoisoned(_)
            | redb::Error::Backend(_)
    )
}

/// A failure of the database while running, classified: a fault that needs
/// a reopen, or another failure.
#[derive(Debug)]
pub(super) struct DbFailure {
    pub reopen: bool,
    pub message: String,
}

impl DbFailure {
    pub fn of(e: impl Into<redb::Error>) -> Self {
        let e: redb::Error = e.into();
        Self {
            reopen: needs_reopen(&e),
            message: e.to_string(),
        }
    }
}

/// Opens (or creates) the database file, checking its integrity and format
/// version (upgrading formats 2 and 3); at start and at every reopen.
/// Returns the database and the number of the last log frame applied.
///
/// `cache_bytes` bounds redb's page cache (its own default is 1 GiB, which
/// a server writing a snapshot per evicted session would fill and keep).
pub(super) fn open_database(
    path: &Path,
    cache_bytes: usize,
) -> Result<(Database, u64), StoreError> {
    let corrupt = |reason: String| StoreError::Corrupt {
        path: path.to_path_buf(),
        reason,
    };
    // An I/O error (a full disk) is not damage: it is reported as such, at
    // start and at a reopen after a storage fault.
    let failed = |e: redb::Error| match e {
        redb::Error::Io(io)
            if !matches!(
                io.kind(),
                std::io::ErrorKind::InvalidData | std::io::ErrorKind::UnexpectedEof
            ) =>
        {
            StoreError::Io {
                path: path.to_path_buf(),
                reason: io.to_string(),
            }
        }
        redb::Error::PreviousIo => StoreError::Io {
            path: path.to_path_buf(),
            reason: e.to_string(),
        },
        other => corrupt(other.to_string()),
    };
    let existed = path.metadata().map(|m| m.len() > 0).unwrap_or(false);
    let db = Database::builder()
        .set_cache_size(cache_bytes)
        .set_check_integrity_on_open(true)
        .create(path)
        .map_err(|e| match e {
            redb::DatabaseError::DatabaseAlreadyOpen => StoreError::Io {
                path: path.to_path_buf(),
                reason: "already open in another process (is another mcapi running on this data directory?)".into(),
            },
            other => failed(other.into()),
        })?;
    let mut write = db.begin_write().map_err(|e| failed(e.into()))?;
    write.set_two_phase_commit(true);
    let applied;
    {
        let mut meta = write.open_table(META).map_err(|e| failed(e.into()))?;
        let found = meta
            .get("format_version")
            .map_err(|e| failed(e.into()))?
            .map(|v| v.value());
        match found {
            Some(v @ 2..=FORMAT_VERSION) => {
                if v == 2 {
                    let started = Instant::now();
                    let records = tag_format_2_records(&write)
                        .map_err(|e| corrupt(format!("upgrading from format version 2: {e}")))?;
                    tracing::info!(
                        path = %path.display(),
                        records,
                        seconds = started.elapsed().as_secs_f64(),
                        "store records tagged (format version 2 to 3)"
                    );
                }
                if v < FORMAT_VERSION {
                    meta.insert("format_version", FORMAT_VERSION)
                        .map_err(|e| failed(e.into()))?;
                    tracing::info!(path = %path.display(), "store upgraded from format version {v} to {FORMAT_VERSION}");
                }
            }
            Some(found) => {
                return Err(StoreError::Version {
                    path: path.to_path_buf(),
                    found,
                });
            }
            None if existed => {
                return Err(corrupt("the format version record is missing".into()));
            }
            None => {
                meta.insert("format_version", FORMAT_VERSION)
                    .map_err(|e| failed(e.into()))?;
            }
        }
        applied = meta
            .get(WAL_LSN)
            .map_err(|e| failed(e.into()))?
            .map_or(0, |v| v.value());
        write.open_table(SESSIONS).map_err(|e| failed(e.into()))?;
        write.open_table(SNAPSHOTS).map_err(|e| failed(e.into()))?;
        write.open_table(LOG).map_err(|e| failed(e.into()))?;
    }
    write.commit().map_err(|e| failed(e.into()))?;
    Ok((db, applied))
}

/// What [`replay_wal`] found.
#[derive(Debug, Default)]
pub(super) struct Replayed {
    /// The number the next frame gets.
    pub next_lsn: u64,
    /// Frames applied to the database.
    pub frames: u64,
    /// Whether the newest segment ended in a torn frame (cut).
    pub torn: bool,
}

/// At open: applies the log frames after `applied` to the database, one
/// transaction per segment, then deletes the segments (everything in them
/// is in the database). A torn tail of the newest segment is cut; any other
/// damage refuses the open, and nothing is deleted.
pub(super) fn replay_wal(
    db: &Database,
    wal_dir: &Path,
    applied: u64,
) -> Result<Replayed, StoreError> {
    let segments = wal::list_segments(wal_dir)?;
    let mut out = Replayed {
        next_lsn: applied + 1,
        ..Replayed::default()
    };
    let mut expected: Option<u64> = None;
    let mut spare = Spare::default();
    for (i, (first, path)) in segments.iter().enumerate() {
        let last = i + 1 == segments.len();
        if let Some(e) = expected
            && *first != e
        {
            return Err(StoreError::Corrupt {
                path: path.clone(),
                reason: format!(
                    "the log segment begins at frame {first}, its predecessor ends before {e}"
                ),
            });
        }
        let read = wal::read_segment(path, *first, last)?;
        out.torn |= read.torn;
        let next = *first + read.frames.len() as u64;
        expected = Some(next);
        let frames: Vec<&Frame> = read.frames.iter().filter(|f| f.lsn > applied).collect();
        if let Some(f) = frames.first()
            && f.lsn > out.next_lsn
        {
            return Err(StoreError::Corrupt {
                path: path.clone(),
                reason: format!(
                    "log frames {} to {} are missing (the database has applied up to {applied})",
                    out.next_lsn,
                    f.lsn - 1
                ),
            });
        }
        if let Some(f) = frames.last() {
            apply(db, frames.iter().flat_map(|f| &f.writes), f.lsn, &mut spare).map_err(|f| {
                StoreError::Io {
                    path: path.clone(),
                    reason: format!("applying the log to the database: {}", f.message),
                }
            })?;
            out.frames += frames.len() as u64;
        }
        out.next_lsn = out.next_lsn.max(next);
    }
    for (_, path) in &segments {
        std::fs::remove_file(path).map_err(|e| StoreError::Io {
            path: path.clone(),
            reason: format!("removing a replayed log segment: {e}"),
        })?;
    }
    if !segments.is_empty() {
        wal::sync_dir(wal_dir).map_err(|e| StoreError::Io {
            path: wal_dir.to_path_buf(),
            reason: e.to_string(),
        })?;
    }
    Ok(out)
}

/// The health probe: on a freshly opened handle, a durable commit of
/// [`PROBE_BYTES`] of new data, then a second one that removes it. A reopen
/// alone proves little: redb reuses the free pages inside its file, so a
/// small commit can succeed on a full disk while the next real one fails
/// again. Writing more than a small store's free pages needs the disk; a
/// large store whose free pages hold the probe can also take real commits
/// until they run out (and the fault, with a longer backoff, returns).
pub(super) fn probe(db: &Database) -> Result<(), DbFailure> {
    let blob = vec![0u8; PROBE_BYTES];
    for keep in [true, false] {
        let mut txn = db.begin_write().map_err(DbFailure::of)?;
        txn.set_durability(Durability::Immediate)
            .map_err(DbFailure::of)?;
        txn.set_two_phase_commit(true);
        {
            let mut table = txn.open_table(PROBE).map_err(DbFailure::of)?;
            if keep {
                table
                    .insert("probe", blob.as_slice())
                    .map_err(DbFailure::of)?;
            } else {
                table.remove("probe").map_err(DbFailure::of)?;
            }
        }
        txn.commit().map_err(DbFailure::of)?;
    }
    Ok(())
}

/// The 2 → 3 upgrade: prefixes every snapshot and log record with
/// [`RECORD_V2`]. Returns the number of records rewritten.
fn tag_format_2_records(write: &redb::WriteTransaction) -> Result<u64, String> {
    let e = |e: redb::Error| e.to_string();
    let tagged = |bytes: &[u8]| {
        let mut out = Vec::with_capacity(bytes.len() + 1);
        out.push(RECORD_V2);
        out.extend_from_slice(bytes);
        out
    };
    let mut n = 0u64;
    let mut snapshots = write.open_table(SNAPSHOTS).map_err(|x| e(x.into()))?;
    let mut rows = Vec::new();
    for row in snapshots.iter().map_err(|x| e(x.into()))? {
        let (id, v) = row.map_err(|x| e(x.into()))?;
        let (seq, bytes) = v.value();
        rows.push((id.value().to_string(), seq, tagged(bytes)));
    }
    for (id, seq, bytes) in &rows {
        snapshots
            .insert(id.as_str(), (*seq, bytes.as_slice()))
            .map_err(|x| e(x.into()))?;
        n += 1;
    }
    let mut log = write.open_table(LOG).map_err(|x| e(x.into()))?;
    let mut chunks = Vec::new();
    for row in log.iter().map_err(|x| e(x.into()))? {
        let (key, chunk) = row.map_err(|x| e(x.into()))?;
        let mut rest = chunk.value();
        let mut out = Vec::with_capacity(rest.len() + CHUNK as usize);
        while !rest.is_empty() {
            let (seq, entry, tail) =
                split_entry(rest).ok_or_else(|| "a log chunk is malformed".to_string())?;
            push_entry(&mut out, seq, &tagged(entry));
            n += 1;
            rest = tail;
        }
        chunks.push((key.value(), out));
    }
    for (key, chunk) in &chunks {
        log.insert(*key, chunk.as_slice())
            .map_err(|x| e(x.into()))?;
    }
    Ok(n)
}

/// Writes back the chunks a checkpoint appended to; their buffers go to
/// `spare`.
fn write_back(
    log: &mut redb::Table<'_, (u128, u64), &'static [u8]>,
    key: u128,
    chunks: Vec<(u64, Vec<u8>)>,
    spare: &mut Spare,
) -> Result<(), DbFailure> {
    for (c, bytes) in chunks {
        log.insert((key, c), bytes.as_slice())
            .map_err(DbFailure::of)?;
        spare.put(bytes);
    }
    Ok(())
}

/// The buffers of chunks a checkpoint wrote back, kept for the next one's:
/// a checkpoint of ten thousand sessions reads and extends ten thousand
/// chunks of a few KiB, and buffers taken fresh each time (grown as records
/// were appended, freed two seconds later) kept the kernel zeroing new
/// pages for them. Holds at most [`Spare::MAX_BYTES`] of capacity; the
/// checkpointer drops it when it goes idle.
#[derive(Debug, Default)]
pub(crate) struct Spare {
    buffers: Vec<Vec<u8>>,
    bytes: usize,
}

impl Spare {
    /// The most capacity kept.
    const MAX_BYTES: usize = 64 << 20;
    /// A chunk's buffer is made with room for a chunk of records of this
    /// size (a hallway record is about 60 bytes with its frame), so most
    /// chunks never grow.
    const RECORD_GUESS: usize = 80;

    /// An empty buffer, kept or new.
    fn take(&mut self) -> Vec<u8> {
        match self.buffers.pop() {
            Some(mut b) => {
                self.bytes -= b.capacity();
                b.clear();
                b
            }
            None => Vec::with_capacity(CHUNK as usize * Self::RECORD_GUESS),
        }
    }

    /// Keeps `buffer` if there is room for it.
    fn put(&mut self, buffer: Vec<u8>) {
        if self.bytes + buffer.capacity() <= Self::MAX_BYTES {
            self.bytes += buffer.capacity();
            self.buffers.push(buffer);
        }
    }
}

/// A session's log key as a hash key: the key is a ULID's bits or a
/// SHA-256 prefix, random enough as it is (no SipHash of it per record).
#[derive(Default)]
pub(crate) struct KeyHasher(u64);

impl std::hash::Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.0 = self.0.rotate_left(8) ^ u64::from(*b);
        }
    }
    fn write_u128(&mut self, key: u128) {
        // A ULID's low 80 bits are random, its high 48 a timestamp.
        self.0 = (key as u64) ^ ((key >> 64) as u64).rotate_left(29);
    }
}

/// Chunks with appended records not yet written back, by session key.
pub(crate) type Touched =
    HashMap<u128, Vec<(u64, Vec<u8>)>, std::hash::BuildHasherDefault<KeyHasher>>;

/// The chunk that record `seq` of session `key` is appended to: read from
/// the database the first time a checkpoint touches it.
fn chunk_for<'t>(
    touched: &'t mut Touched,
    log: &redb::Table<'_, (u128, u64), &'static [u8]>,
    key: u128,
    seq: u64,
    spare: &mut Spare,
) -> Result<&'t mut Vec<u8>, DbFailure> {
    let c = seq / CHUNK;
    let chunks = touched.entry(key).or_default();
    if chunks.last().is_none_or(|(last, _)| *last != c) {
        let mut bytes = spare.take();
        if let Some(v) = log.get((key, c)).map_err(DbFailure::of)? {
            bytes.extend_from_slice(v.value());
        }
        chunks.push((c, bytes));
    }
    let last = chunks.len() - 1;
    Ok(&mut chunks[last].1)
}

/// Applies writes to the database in one durable transaction that also
/// records `lsn` as the last applied log frame: a checkpoint, or the replay
/// of one segment at open. Appends to one chunk are gathered, so each chunk
/// a checkpoint touches is read and written once, however many of its
/// records arrive.
pub(super) fn apply<'a>(
    db: &Database,
    writes: impl Iterator<Item = &'a Write>,
    lsn: u64,
    spare: &mut Spare,
) -> Result<(), DbFailure> {
    let mut txn = db.begin_write().map_err(DbFailure::of)?;
    txn.set_durability(Durability::Immediate)
        .map_err(DbFailure::of)?;
    // Two-phase: a damaged newest commit is then reported as corruption
    // instead of being taken for a torn write and silently rolled back.
    // Costs a second sync, once per checkpoint.
    txn.set_two_phase_commit(true);
    {
        let mut meta = txn.open_table(META).map_err(DbFailure::of)?;
        let mut sessions = txn.open_table(SESSIONS).map_err(DbFailure::of)?;
        let mut snapshots = txn.open_table(SNAPSHOTS).map_err(DbFailure::of)?;
        let mut log = txn.open_table(LOG).map_err(DbFailure::of)?;
        let mut touched = Touched::default();
        for write in writes {
            match write {
                Write::Session { id, record } => {
                    sessions
                        .insert(&**id, record.as_slice())
                        .map_err(DbFailure::of)?;
                }
                Write::Append { id, seq, entry } => {
                    let bytes = chunk_for(&mut touched, &log, log_key(id), *seq, spare)?;
                    push_entry(bytes, *seq, entry);
                }
                Write::Appends(appends) => {
                    for (key, seq, framed) in appends.records() {
                        chunk_for(&mut touched, &log, key, seq, spare)?.extend_from_slice(framed);
                    }
                }
                Write::Snapshot { id, seq, snapshot } => {
                    let key = log_key(id);
                    if let Some(chunks) = touched.remove(&key) {
                        write_back(&mut log, key, chunks, spare)?;
                    }
                    snapshots
                        .insert(&**id, (*seq, snapshot.as_slice()))
                        .map_err(DbFailure::of)?;
                    // Chunks wholly at or before `seq`; a partial chunk
                    // stays, and reads skip its covered records.
                    let whole = (seq.saturating_add(1)) / CHUNK;
                    log.retain_in((key, 0)..(key, whole), |_, _| false)
                        .map_err(DbFailure::of)?;
                }
                Write::Resume { .. } => {}
                Write::Delete { id } => {
                    let key = log_key(id);
                    touched.remove(&key);
                    sessions.remove(&**id).map_err(DbFailure::of)?;
                    snapshots.remove(&**id).map_err(DbFailure::of)?;
                    log.retain_in((key, 0)..=(key, u64::MAX), |_, _| false)
                        .map_err(DbFailure::of)?;
                }
            }
        }
        for (key, chunks) in touched {
            write_back(&mut log, key, chunks, spare)?;
        }
        meta.insert(WAL_LSN, lsn).map_err(DbFailure::of)?;
    }
    txn.commit().map_err(DbFailure::of)
}

#[cfg(test)]
mod spare_tests {
    use super::Spare;

    #[test]
    fn a_spare_hands_back_empty_buffers_and_keeps_no_more_than_its_bound() {
        let mut spare = Spare::default();
        let fresh = spare.take();
        assert!(fresh.is_empty());
        assert!(fresh.capacity() >= super::CHUNK as usize * Spare::RECORD_GUESS);
        let mut used = fresh;
        used.extend_from_slice(&[7; 100]);
        let capacity = used.capacity();
        spare.put(used);
        let again = spare.take();
        assert!(again.is_empty(), "a kept buffer comes back cleared");
        assert_eq!(again.capacity(), capacity, "and is the one kept");
        assert_eq!(spare.bytes, 0);
        // Buffers beyond the bound are dropped, not kept.
        let big = Spare::MAX_BYTES / 4 + 1;
        for _ in 0..8 {
            spare.put(Vec::with_capacity(big));
        }
        assert_eq!(spare.buffers.len(), 3);
        assert!(spare.bytes <= Spare::MAX_BYTES);
    }
}
