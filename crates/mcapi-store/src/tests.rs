//! The store as a whole: reopening, trimming, group commit, damaged and
//! older files, broken sessions, the log's replay and its segments.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use redb::{Database, ReadableDatabase, ReadableTableMetadata};

use super::db::{LOG, META};
use super::*;
use std::time::Duration;

use crate::{checkpoint, wal};

fn id(s: &str) -> Arc<str> {
    Arc::from(s)
}

fn entries(store: &Store, s: &str, after: Option<u64>) -> Vec<(u64, Vec<u8>)> {
    let mut out = Vec::new();
    store
        .for_each_entry(s, after, |seq, e| {
            out.push((seq, e.to_vec()));
            Ok::<(), StoreError>(())
        })
        .expect("read log");
    out
}

#[test]
fn writes_survive_reopening_and_snapshots_trim_the_log() {
    let dir = tempfile::tempdir().expect("tempdir");
    {
        let store = Store::open(dir.path()).expect("open");
        let mut writes = vec![Write::Session {
            id: id("a"),
            record: b"ra".to_vec(),
        }];
        writes.extend((0..5).map(|seq| Write::Append {
            id: id("a"),
            seq,
            entry: vec![seq as u8],
        }));
        writes.push(Write::Session {
            id: id("ab"),
            record: b"rab".to_vec(),
        });
        writes.push(Write::Append {
            id: id("ab"),
            seq: 0,
            entry: vec![9],
        });
        store.submit(writes).wait_blocking().expect("commit");
        store
            .submit(vec![Write::Snapshot {
                id: id("a"),
                seq: 2,
                snapshot: b"snap".to_vec(),
            }])
            .wait_blocking()
            .expect("snapshot");
        store.close();
    }
    let store = Store::open(dir.path()).expect("reopen");
    let sessions = store.sessions().expect("sessions");
    assert_eq!(sessions.len(), 2);
    assert_eq!(sessions[0].id, "a");
    assert_eq!(sessions[0].record, b"ra");
    assert_eq!(sessions[0].snapshot, Some((2, b"snap".to_vec())));
    assert_eq!(sessions[1].snapshot, None);
    // Reads after the snapshot skip what it covers; "ab" is not mixed into "a".
    assert_eq!(
        entries(&store, "a", Some(2)),
        vec![(3, vec![3]), (4, vec![4])]
    );
    assert_eq!(entries(&store, "a", Some(3)), vec![(4, vec![4])]);
    assert_eq!(entries(&store, "ab", None), vec![(0, vec![9])]);
    store
        .submit(vec![Write::Delete { id: id("a") }])
        .wait_blocking()
        .expect("delete");
    assert_eq!(store.sessions().expect("sessions").len(), 1);
    assert!(entries(&store, "a", None).is_empty());
}

#[test]
fn chunks_are_trimmed_only_when_wholly_covered() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Store::open(dir.path()).expect("open");
    let n = 3 * CHUNK + 5;
    for seq in 0..n {
        store
            .submit(vec![Write::Append {
                id: id("s0001.01ARZ3NDEKTSV4RRFFQ69G5FAV"),
                seq,
                entry: seq.to_le_bytes().to_vec(),
            }])
            .wait_blocking()
            .expect("append");
    }
    let all = entries(&store, "s0001.01ARZ3NDEKTSV4RRFFQ69G5FAV", None);
    assert_eq!(all.len() as u64, n);
    assert!(all.iter().all(|(seq, e)| e == &seq.to_le_bytes().to_vec()));
    let cut = CHUNK + 3;
    store
        .submit(vec![Write::Snapshot {
            id: id("s0001.01ARZ3NDEKTSV4RRFFQ69G5FAV"),
            seq: cut,
            snapshot: vec![1],
        }])
        .wait_blocking()
        .expect("snapshot");
    let after = entries(&store, "s0001.01ARZ3NDEKTSV4RRFFQ69G5FAV", Some(cut));
    assert_eq!(after.first().map(|e| e.0), Some(cut + 1));
    assert_eq!(after.len() as u64, n - cut - 1);
    // The first chunk is gone; the second (partly covered) is kept.
    let read = store.db().expect("db").begin_read().expect("read");
    let log = read.open_table(LOG).expect("log");
    assert_eq!(log.len().expect("len"), 3);
}

#[test]
fn concurrent_submissions_share_commits_and_all_land() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Arc::new(Store::open(dir.path()).expect("open"));
    let threads: Vec<_> = (0..8)
        .map(|t| {
            let store = Arc::clone(&store);
            std::thread::spawn(move || {
                let sid = id(&format!("s{t}"));
                for seq in 0..50 {
                    store
                        .submit(vec![Write::Append {
                            id: Arc::clone(&sid),
                            seq,
                            entry: vec![t as u8],
                        }])
                        .wait_blocking()
                        .expect("commit");
                }
            })
        })
        .collect();
    for t in threads {
        t.join().expect("thread");
    }
    for t in 0..8 {
        let got = entries(&store, &format!("s{t}"), None);
        assert_eq!(got.len(), 50);
        assert!(got.iter().enumerate().all(|(i, (seq, _))| *seq == i as u64));
    }
}

#[test]
fn a_damaged_file_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    {
        let store = Store::open(dir.path()).expect("open");
        let writes = (0..2000)
            .map(|seq| Write::Append {
                id: id("a"),
                seq,
                entry: vec![7; 64],
            })
            .collect();
        store.submit(writes).wait_blocking().expect("commit");
    }
    let path = dir.path().join(FILE_NAME);
    let len = std::fs::metadata(&path).expect("meta").len();
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(&path)
        .expect("open file");
    file.set_len(len / 2).expect("truncate");
    drop(file);
    let err = Store::open(dir.path()).expect_err("a truncated store must not open");
    assert!(matches!(err, StoreError::Corrupt { .. }), "{err}");
}

#[test]
fn garbage_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join(FILE_NAME), vec![0x5a; 1 << 16]).expect("write");
    let err = Store::open(dir.path()).expect_err("garbage must not open");
    assert!(matches!(err, StoreError::Corrupt { .. }), "{err}");
}

#[test]
fn another_format_version_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    {
        let db = Database::create(dir.path().join(FILE_NAME)).expect("db");
        let w = db.begin_write().expect("write");
        w.open_table(META)
            .expect("meta")
            .insert("format_version", FORMAT_VERSION + 1)
            .expect("insert");
        w.commit().expect("commit");
    }
    let err = Store::open(dir.path()).expect_err("version");
    assert!(
        matches!(err, StoreError::Version { found, .. } if found == FORMAT_VERSION + 1),
        "{err}"
    );
}

fn set_version(dir: &Path, version: u64) {
    let db = Database::create(dir.join(FILE_NAME)).expect("db");
    let w = db.begin_write().expect("write");
    w.open_table(META)
        .expect("meta")
        .insert("format_version", version)
        .expect("insert");
    w.commit().expect("commit");
}

#[test]
fn a_format_2_file_is_upgraded_by_tagging_its_records() {
    let dir = tempfile::tempdir().expect("tempdir");
    let n = 2 * CHUNK + 7;
    {
        let store = Store::open(dir.path()).expect("open");
        let mut writes = vec![Write::Session {
            id: id("a"),
            record: b"ra".to_vec(),
        }];
        writes.extend((0..n).map(|seq| Write::Append {
            id: id("a"),
            seq,
            entry: vec![seq as u8, 0xAB],
        }));
        writes.push(Write::Snapshot {
            id: id("a"),
            seq: CHUNK + 1,
            snapshot: b"snap".to_vec(),
        });
        store.submit(writes).wait_blocking().expect("commit");
        store.close();
    }
    // The records above stand for untagged format-2 records.
    set_version(dir.path(), 2);
    let store = Store::open(dir.path()).expect("upgrade");
    let sessions = store.sessions().expect("sessions");
    assert_eq!(sessions[0].record, b"ra", "creation records are unchanged");
    assert_eq!(
        sessions[0].snapshot,
        Some((CHUNK + 1, vec![RECORD_V2, b's', b'n', b'a', b'p']))
    );
    let log = entries(&store, "a", Some(CHUNK + 1));
    let want: Vec<_> = (CHUNK + 2..n)
        .map(|seq| (seq, vec![RECORD_V2, seq as u8, 0xAB]))
        .collect();
    assert_eq!(log, want);
    store.close();
    drop(store);
    // Upgraded once: reopening does not tag again.
    let store = Store::open(dir.path()).expect("reopen");
    assert_eq!(entries(&store, "a", Some(CHUNK + 1)), want);
    let read = store.db().expect("db").begin_read().expect("read");
    let meta = read.open_table(META).expect("meta");
    let v = meta.get("format_version").expect("get").map(|v| v.value());
    assert_eq!(v, Some(FORMAT_VERSION));
}

#[test]
fn after_a_failed_commit_a_session_is_refused_until_resumed() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Store::open(dir.path()).expect("open");
    let append = |s: &str, seq: u64| Write::Append {
        id: id(s),
        seq,
        entry: vec![seq as u8],
    };
    store
        .submit(vec![append("a", 0), append("b", 0)])
        .wait_blocking()
        .expect("commit");
    store.fail_next_commits(1);
    let err = store
        .submit(vec![append("a", 1)])
        .wait_blocking()
        .expect_err("injected failure");
    assert!(matches!(err, StoreError::Failed(_)), "{err}");
    assert!(store.is_broken("a") && !store.is_broken("b"));
    // Writes after the hole are refused; other sessions go on.
    let err = store
        .submit(vec![append("a", 2)])
        .wait_blocking()
        .expect_err("a is broken");
    assert!(
        matches!(&err, StoreError::Broken(s) if &**s == "a"),
        "{err}"
    );
    store
        .submit(vec![append("b", 1)])
        .wait_blocking()
        .expect("b is fine");
    // A resume in the same queue readmits what follows it.
    let resumed = store.submit(vec![Write::Resume { id: id("a") }]);
    store
        .submit(vec![append("a", 1)])
        .wait_blocking()
        .expect("a after its resume");
    resumed.wait_blocking().expect("resume");
    assert!(!store.is_broken("a"));
    assert_eq!(entries(&store, "a", None), vec![(0, vec![0]), (1, vec![1])]);
    assert_eq!(entries(&store, "b", None), vec![(0, vec![0]), (1, vec![1])]);
}

fn appends(s: &str, seqs: std::ops::Range<u64>, bytes: usize) -> Vec<Write> {
    seqs.map(|seq| Write::Append {
        id: id(s),
        seq,
        entry: vec![seq as u8; bytes],
    })
    .collect()
}

fn segments(dir: &Path) -> Vec<(u64, PathBuf)> {
    wal::list_segments(&dir.join(wal::WAL_DIR)).expect("segments")
}

#[test]
fn a_clean_close_applies_the_log_and_leaves_it_empty() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Store::open(dir.path()).expect("open");
    store
        .submit(appends("a", 0..10, 8))
        .wait_blocking()
        .expect("commit");
    store.close();
    assert!(segments(dir.path()).is_empty());
    let read = Database::open(dir.path().join(FILE_NAME)).expect("db");
    let read = read.begin_read().expect("read");
    let meta = read.open_table(META).expect("meta");
    assert_eq!(
        meta.get("wal_lsn").expect("get").map(|v| v.value()),
        Some(1)
    );
    let log = read.open_table(LOG).expect("log");
    assert_eq!(log.len().expect("len"), 1);
}

#[test]
fn after_a_crash_the_log_is_replayed_into_the_database_exactly_once() {
    for durability in [Durability::Sync, Durability::Os] {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::open_with(dir.path(), durability).expect("open");
        for seq in 0..20 {
            store
                .submit(appends("a", seq..seq + 1, 4))
                .wait_blocking()
                .expect("commit");
        }
        // Half of it applied by a checkpoint before the crash.
        store.checkpoint().expect("checkpoint");
        for seq in 20..40 {
            store
                .submit(appends("a", seq..seq + 1, 4))
                .wait_blocking()
                .expect("commit");
        }
        store.crash();
        drop(store);
        assert!(
            !segments(dir.path()).is_empty(),
            "{durability}: the log stays"
        );
        for round in 0..2 {
            let store = Store::open_with(dir.path(), durability).expect("reopen");
            let got = entries(&store, "a", None);
            assert_eq!(
                got,
                (0..40).map(|s| (s, vec![s as u8; 4])).collect::<Vec<_>>(),
                "{durability}, round {round}: every acknowledged write, once"
            );
            store.crash();
        }
    }
}

#[test]
fn a_torn_tail_is_cut_and_a_damaged_frame_refuses_the_open() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Store::open(dir.path()).expect("open");
    // Frames of four 512-byte sectors each.
    let bytes = 2000;
    for seq in 0..3 {
        store
            .submit(appends("a", seq..seq + 1, bytes))
            .wait_blocking()
            .expect("commit");
    }
    store.crash();
    drop(store);
    let (_, path) = segments(dir.path()).pop().expect("segment");
    let whole = std::fs::read(&path).expect("bytes");
    // The last sector written: the end of the last frame.
    let last = whole
        .chunks_exact(512)
        .rposition(|s| s.iter().any(|&b| b != 0))
        .expect("frames")
        * 512;
    // Damage inside the last frame: refused, naming the segment.
    let mut damaged = whole.clone();
    damaged[last + 10] ^= 1;
    std::fs::write(&path, &damaged).expect("write");
    let err = Store::open(dir.path()).expect_err("damage");
    assert!(
        matches!(&err, StoreError::Corrupt { path: p, .. } if *p == path),
        "{err}"
    );
    // A sector of the last frame never written (a power cut mid-write):
    // cut, and the frames before it are kept.
    let mut torn = whole.clone();
    torn[last..last + 512].fill(0);
    std::fs::write(&path, &torn).expect("write");
    let store = Store::open(dir.path()).expect("a torn tail is not damage");
    assert_eq!(
        entries(&store, "a", None),
        vec![(0, vec![0; bytes]), (1, vec![1; bytes])]
    );
    // The next frame follows on and survives another crash.
    store
        .submit(appends("a", 2..3, bytes))
        .wait_blocking()
        .expect("commit");
    store.crash();
    drop(store);
    let store = Store::open(dir.path()).expect("reopen");
    assert_eq!(entries(&store, "a", None).len(), 3);
}

#[test]
fn a_version_1_log_left_by_a_crash_is_replayed_and_the_log_goes_on_in_version_2() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Store::open(dir.path()).expect("open");
    store
        .submit(appends("a", 0..2, 8))
        .wait_blocking()
        .expect("commit");
    store.close();
    drop(store);
    // What an older mcapi left when a power cut hit after two more
    // acknowledged commits: frames 2 to 4 in a version 1 segment, the
    // third torn (never acknowledged).
    let wal_dir = dir.path().join(wal::WAL_DIR);
    let path = wal::segment_path(&wal_dir, 2);
    let ends = wal::v1_segment(
        &path,
        2,
        &[
            appends("a", 2..3, 8),
            appends("a", 3..4, 8),
            appends("a", 4..5, 8),
        ],
    );
    let bytes = std::fs::read(&path).expect("bytes");
    std::fs::write(&path, &bytes[..ends[2] - 3]).expect("torn");
    let store = Store::open(dir.path()).expect("upgrade");
    assert_eq!(
        entries(&store, "a", None),
        (0..4).map(|s| (s, vec![s as u8; 8])).collect::<Vec<_>>()
    );
    store
        .submit(appends("a", 4..5, 8))
        .wait_blocking()
        .expect("commit");
    store.crash();
    drop(store);
    let (first, path) = segments(dir.path()).pop().expect("segment");
    assert_eq!(first, 4, "the log goes on after the replayed frames");
    let header = std::fs::read(&path).expect("bytes");
    assert_eq!(header[8..12], 2u32.to_le_bytes(), "a version 2 segment");
    let store = Store::open(dir.path()).expect("reopen");
    assert_eq!(entries(&store, "a", None).len(), 5);
}

#[test]
fn the_checkpointer_applies_frames_by_itself_round_after_round() {
    // Nobody asks for a checkpoint here: each round's first frame must
    // wake the checkpointer (it drains its frames only when woken or
    // due), or `applied` would stay behind until the close.
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Store::open(dir.path()).expect("open");
    let applied_all = |store: &Store| {
        let deadline = Instant::now() + 10 * checkpoint::CHECKPOINT_INTERVAL;
        while Instant::now() < deadline {
            let forwarded = store.shared.forwarded.load(Ordering::Acquire);
            if store.shared.applied.load(Ordering::Acquire) == forwarded {
                return true;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        false
    };
    for round in 0..3u64 {
        for seq in round * 5..round * 5 + 5 {
            store
                .submit(appends("a", seq..seq + 1, 16))
                .wait_blocking()
                .expect("commit");
        }
        assert!(applied_all(&store), "round {round} was applied");
        assert_eq!(store.shared.frame_bytes.load(Ordering::SeqCst), 0);
    }
    assert_eq!(entries(&store, "a", None).len(), 15);
}

#[test]
fn full_segments_are_closed_and_deleted_once_applied() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Store::open(dir.path()).expect("open");
    let frame = 1 << 20;
    let n = wal::SEGMENT_BYTES / frame as u64 + 2;
    for seq in 0..n {
        store
            .submit(appends("a", seq..seq + 1, frame))
            .wait_blocking()
            .expect("commit");
    }
    assert!(segments(dir.path()).len() >= 2, "a new segment was begun");
    store.checkpoint().expect("checkpoint");
    assert_eq!(
        segments(dir.path()).len(),
        1,
        "the closed segment is deleted"
    );
    assert_eq!(entries(&store, "a", None).len() as u64, n);
}

#[test]
fn a_format_3_file_is_upgraded_to_4() {
    let dir = tempfile::tempdir().expect("tempdir");
    {
        let store = Store::open(dir.path()).expect("open");
        store
            .submit(appends("a", 0..3, 2))
            .wait_blocking()
            .expect("commit");
        store.close();
    }
    // A format-3 file: no log directory, no `wal_lsn`.
    std::fs::remove_dir(dir.path().join(wal::WAL_DIR)).expect("rmdir");
    {
        let db = Database::create(dir.path().join(FILE_NAME)).expect("db");
        let w = db.begin_write().expect("write");
        {
            let mut meta = w.open_table(META).expect("meta");
            meta.insert("format_version", 3).expect("insert");
            meta.remove("wal_lsn").expect("remove");
        }
        w.commit().expect("commit");
    }
    let store = Store::open(dir.path()).expect("upgrade");
    assert_eq!(entries(&store, "a", None).len(), 3);
    store
        .submit(appends("a", 3..4, 2))
        .wait_blocking()
        .expect("commit");
    store.crash();
    drop(store);
    let store = Store::open(dir.path()).expect("reopen");
    assert_eq!(entries(&store, "a", None).len(), 4);
    let read = store.db().expect("db").begin_read().expect("read");
    let meta = read.open_table(META).expect("meta");
    let v = meta.get("format_version").expect("get").map(|v| v.value());
    assert_eq!(v, Some(FORMAT_VERSION));
}

/// Appends to `batch` a record for each of sessions `ids` at each of
/// `seqs`, as a group step per seq would: the entry is the id's first byte
/// and the seq.
fn fill(batch: &Batch, ids: &[Arc<str>], seqs: std::ops::Range<u64>) {
    for seq in seqs {
        for s in ids {
            batch
                .append(&LogId::new(Arc::clone(s)), seq, |out| {
                    out.extend_from_slice(&[s.as_bytes()[0], seq as u8]);
                    Ok::<(), StoreError>(())
                })
                .expect("append");
        }
    }
}

#[test]
fn batches_left_in_the_log_by_a_crash_are_replayed_into_each_sessions_log() {
    // A ULID id (the log key is its 128 bits) and any other id (a hash).
    let ids = [id("s0001.01ARZ3NDEKTSV4RRFFQ69G5FAV"), id("b"), id("c")];
    for durability in [Durability::Sync, Durability::Os] {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Arc::new(Store::open_with(dir.path(), durability).expect("open"));
        // Across a chunk's end, half of it applied by a checkpoint before
        // the crash; a lone append and a snapshot between batches.
        let first = Batch::new(Arc::clone(&store));
        fill(&first, &ids, 0..CHUNK - 2);
        first
            .finish()
            .wait_blocking()
            .of(0..3)
            .expect("first batch");
        store.checkpoint().expect("checkpoint");
        store
            .submit(vec![Write::Append {
                id: id("b"),
                seq: CHUNK - 2,
                entry: vec![b'b', (CHUNK - 2) as u8],
            }])
            .wait_blocking()
            .expect("lone append");
        // Sized for its records once the first is in (what a group
        // step's chunk does), across a snapshot and an early send.
        let second = Batch::expecting(Arc::clone(&store), 10);
        fill(&second, &ids[..1], CHUNK - 2..CHUNK + 5);
        second.push(Write::Snapshot {
            id: id("c"),
            seq: 3,
            snapshot: b"snap".to_vec(),
        });
        // Sent in two parts, as a write to one of its sessions would make it.
        second.send();
        fill(&second, &ids[2..], CHUNK - 2..CHUNK);
        let outcome = second.finish().wait_blocking();
        outcome.of(0..10).expect("second batch");
        store.crash();
        drop(store);
        assert!(
            !segments(dir.path()).is_empty(),
            "{durability}: the log stays"
        );
        for round in 0..2 {
            let store = Store::open_with(dir.path(), durability).expect("reopen");
            let want = |i: u8, seqs: std::ops::Range<u64>| {
                seqs.map(|s| (s, vec![i, s as u8])).collect::<Vec<_>>()
            };
            let what = format!("{durability}, round {round}");
            assert_eq!(
                entries(&store, &ids[0], None),
                want(b's', 0..CHUNK + 5),
                "{what}"
            );
            assert_eq!(
                entries(&store, "b", None),
                want(b'b', 0..CHUNK - 1),
                "{what}"
            );
            // Read after its snapshot, which a batch's part carried.
            assert_eq!(
                entries(&store, "c", Some(3)),
                want(b'c', 4..CHUNK),
                "{what}"
            );
            store.crash();
        }
    }
}

#[test]
fn a_batch_part_that_fails_or_is_refused_breaks_every_session_it_extends() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Arc::new(Store::open(dir.path()).expect("open"));
    let (a, b, c) = (id("a"), id("b"), id("c"));
    let batch = Batch::new(Arc::clone(&store));
    fill(&batch, &[Arc::clone(&a), Arc::clone(&b)], 0..1);
    store.fail_next_commits(1);
    batch.send();
    // Once this returns the first part is committed (or failed), so the
    // second is a commit of its own, not one group commit with it.
    let _ = store.submit(Vec::new()).wait_blocking();
    fill(&batch, std::slice::from_ref(&c), 0..1);
    let outcome = batch.finish().wait_blocking();
    // Positions 0 and 1 were the failed part, 2 the one after it.
    assert!(matches!(outcome.of(0..1), Err(StoreError::Failed(_))));
    assert!(outcome.of(1..3).is_err());
    outcome.of(2..3).expect("the second part");
    assert!(store.is_broken("a") && store.is_broken("b") && !store.is_broken("c"));
    // A part refused for one broken session leaves a hole in the others'.
    let batch = Batch::new(Arc::clone(&store));
    fill(&batch, &[Arc::clone(&c), Arc::clone(&a)], 1..2);
    let outcome = batch.finish().wait_blocking();
    assert!(matches!(outcome.of(0..1), Err(StoreError::Broken(_))));
    assert!(store.is_broken("c"));
    for s in ["a", "b", "c"] {
        store
            .submit(vec![Write::Resume { id: id(s) }])
            .wait_blocking()
            .expect("resume");
    }
    assert!(entries(&store, "a", None).is_empty());
    assert_eq!(entries(&store, "c", None), vec![(0, vec![b'c', 0])]);
}

#[test]
fn a_batch_dropped_unfinished_is_sent() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Arc::new(Store::open(dir.path()).expect("open"));
    let batch = Batch::new(Arc::clone(&store));
    fill(&batch, &[id("a")], 0..3);
    drop(batch);
    // Queued before this append, so committed before it returns.
    store
        .submit(appends("a", 3..4, 2))
        .wait_blocking()
        .expect("append");
    assert_eq!(entries(&store, "a", None).len(), 4);
}
