//! The write-ahead log: the store's hot path (docs/sessions.md,
//! "Durability and recovery").
//!
//! Every group commit is one frame appended to the active segment file and,
//! under [`Durability::Sync`], one `fdatasync`. redb is updated later, in
//! bulk, by the checkpointer (`checkpoint.rs`), which records in redb the
//! last frame it applied; segments wholly applied are deleted.
//!
//! Files: `wal/<first frame number, 20 digits>.wal` in the data directory.
//! A segment begins with a 16-byte header ([`MAGIC`], the segment format
//! version, reserved). A frame is:
//!
//! | bytes | field |
//! |---|---|
//! | 4 | payload length, little-endian |
//! | 8 | frame number (LSN), little-endian; consecutive across segments |
//! | 4 | CRC-32 of the 12 bytes above |
//! | 4 | CRC-32 of the payload |
//! | n | payload: the group's writes ([`encode_write`]) |
//!
//! A frame is written with one `write` call, so a killed process leaves
//! either all of it or none. After a power cut the last frame may be cut
//! short: a frame whose header or payload runs past the end of the last
//! segment is a *torn tail* and is cut. Anything else that does not check
//! (a header or payload checksum, a frame number out of sequence, a torn
//! frame that is not at the very end) is damage, and the store refuses to
//! open rather than lose what was acknowledged.

use std::fs::{File, OpenOptions};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::{StoreError, Write};

/// The log's directory inside the data directory.
pub const WAL_DIR: &str = "wal";
/// The first bytes of every segment.
const MAGIC: &[u8; 8] = b"MCAPIWAL";
/// Version of the segment and frame layout.
const SEGMENT_VERSION: u32 = 1;
/// Bytes of the segment header.
const HEADER_LEN: u64 = 16;
/// Bytes of a frame's header.
const FRAME_HEADER: usize = 20;
/// A segment is closed (and a new one begun) once it holds this much.
pub const SEGMENT_BYTES: u64 = 16 << 20;
/// The largest payload a frame may declare: a larger length is damage.
const MAX_PAYLOAD: u32 = 1 << 30;

/// When a commit is acknowledged: the durability knob (`--durability`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Durability {
    /// After the frame is on disk (`fdatasync`): survives a crash of the
    /// process and of the machine (a power cut).
    #[default]
    Sync,
    /// After the frame reaches the kernel (`write`): survives a crash of
    /// the process (`kill -9`), not of the machine; the log is synced in
    /// the background every [`OS_SYNC_INTERVAL`](super::OS_SYNC_INTERVAL).
    Os,
}

impl std::fmt::Display for Durability {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Sync => "sync",
            Self::Os => "os",
        })
    }
}

const KIND_SESSION: u8 = 1;
const KIND_APPEND: u8 = 2;
const KIND_SNAPSHOT: u8 = 3;
const KIND_DELETE: u8 = 4;

/// Appends one write to a frame's payload. `Resume` is not logged: it
/// changes what the writer accepts, not what is stored.
fn encode_write(w: &Write, out: &mut Vec<u8>) {
    let id = |out: &mut Vec<u8>, id: &str| {
        out.extend_from_slice(&(id.len() as u32).to_le_bytes());
        out.extend_from_slice(id.as_bytes());
    };
    let bytes = |out: &mut Vec<u8>, b: &[u8]| {
        out.extend_from_slice(&(b.len() as u32).to_le_bytes());
        out.extend_from_slice(b);
    };
    match w {
        Write::Session { id: i, record } => {
            out.push(KIND_SESSION);
            id(out, i);
            bytes(out, record);
        }
        Write::Append { id: i, seq, entry } => {
            out.push(KIND_APPEND);
            id(out, i);
            out.extend_from_slice(&seq.to_le_bytes());
            bytes(out, entry);
        }
        Write::Snapshot {
            id: i,
            seq,
            snapshot,
        } => {
            out.push(KIND_SNAPSHOT);
            id(out, i);
            out.extend_from_slice(&seq.to_le_bytes());
            bytes(out, snapshot);
        }
        Write::Delete { id: i } => {
            out.push(KIND_DELETE);
            id(out, i);
        }
        Write::Resume { .. } => {}
    }
}

/// A reader over a payload.
struct Cursor<'a>(&'a [u8]);

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let (head, rest) = self.0.split_at_checked(n)?;
        self.0 = rest;
        Some(head)
    }
    fn u8(&mut self) -> Option<u8> {
        self.take(1).map(|b| b[0])
    }
    fn u32(&mut self) -> Option<u32> {
        self.take(4)
            .map(|b| u32::from_le_bytes(b.try_into().unwrap_or([0; 4])))
    }
    fn u64(&mut self) -> Option<u64> {
        self.take(8)
            .map(|b| u64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
    }
    fn bytes(&mut self) -> Option<&'a [u8]> {
        let n = self.u32()? as usize;
        self.take(n)
    }
    fn id(&mut self) -> Option<Arc<str>> {
        std::str::from_utf8(self.bytes()?).ok().map(Arc::from)
    }
}

/// The writes of one frame's payload, or `None` if it does not decode.
fn decode_payload(payload: &[u8]) -> Option<Vec<Write>> {
    let mut c = Cursor(payload);
    let mut out = Vec::new();
    while !c.0.is_empty() {
        let w = match c.u8()? {
            KIND_SESSION => Write::Session {
                id: c.id()?,
                record: c.bytes()?.to_vec(),
            },
            KIND_APPEND => Write::Append {
                id: c.id()?,
                seq: c.u64()?,
                entry: c.bytes()?.to_vec(),
            },
            KIND_SNAPSHOT => Write::Snapshot {
                id: c.id()?,
                seq: c.u64()?,
                snapshot: c.bytes()?.to_vec(),
            },
            KIND_DELETE => Write::Delete { id: c.id()? },
            _ => return None,
        };
        out.push(w);
    }
    Some(out)
}

/// Encodes one frame (header and payload) into `out`, which is cleared
/// first.
fn encode_frame<'a>(lsn: u64, writes: impl Iterator<Item = &'a Write>, out: &mut Vec<u8>) {
    out.clear();
    out.resize(FRAME_HEADER, 0);
    for w in writes {
        encode_write(w, out);
    }
    let len = (out.len() - FRAME_HEADER) as u32;
    out[0..4].copy_from_slice(&len.to_le_bytes());
    out[4..12].copy_from_slice(&lsn.to_le_bytes());
    let header_crc = crc32fast::hash(&out[0..12]);
    out[12..16].copy_from_slice(&header_crc.to_le_bytes());
    let payload_crc = crc32fast::hash(&out[FRAME_HEADER..]);
    out[16..20].copy_from_slice(&payload_crc.to_le_bytes());
}

/// One frame read back: its number and writes.
#[derive(Debug)]
pub struct Frame {
    /// The frame number.
    pub lsn: u64,
    /// The group's writes, in order.
    pub writes: Vec<Write>,
}

/// A segment read back.
#[derive(Debug)]
pub struct SegmentRead {
    /// Its frames, in order.
    pub frames: Vec<Frame>,
    /// Whether it ends in a torn frame (cut short by a crash).
    pub torn: bool,
}

/// The path of the segment whose first frame is `first`.
pub fn segment_path(dir: &Path, first: u64) -> PathBuf {
    dir.join(format!("{first:020}.wal"))
}

/// The segments in `dir` by first frame number, in order. A file there
/// that is not a segment is refused (it is not ours to delete or skip).
pub fn list_segments(dir: &Path) -> Result<Vec<(u64, PathBuf)>, StoreError> {
    let io = |e: std::io::Error| StoreError::Io {
        path: dir.to_path_buf(),
        reason: e.to_string(),
    };
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let path = entry.map_err(io)?.path();
        let first = path
            .file_name()
            .and_then(|n| n.to_str())
            .and_then(|n| n.strip_suffix(".wal"))
            .filter(|n| n.len() == 20)
            .and_then(|n| n.parse::<u64>().ok());
        match first {
            Some(first) => out.push((first, path)),
            None => {
                return Err(StoreError::Corrupt {
                    path,
                    reason: "a file in the log directory that is not a log segment".into(),
                });
            }
        }
    }
    out.sort_unstable_by_key(|(first, _)| *first);
    Ok(out)
}

/// Reads one segment. `first` is the frame number its name promises;
/// `last` whether it is the newest segment (the only one that may end torn).
pub fn read_segment(path: &Path, first: u64, last: bool) -> Result<SegmentRead, StoreError> {
    let corrupt = |reason: String| StoreError::Corrupt {
        path: path.to_path_buf(),
        reason,
    };
    let bytes = std::fs::read(path).map_err(|e| StoreError::Io {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    let (header, mut rest) = match bytes.split_at_checked(HEADER_LEN as usize) {
        // A header cut short: the segment was being created at the crash.
        None if last => {
            return Ok(SegmentRead {
                frames: Vec::new(),
                torn: true,
            });
        }
        None => return Err(corrupt("the segment header is cut short".into())),
        Some(split) => split,
    };
    if &header[0..8] != MAGIC {
        return Err(corrupt("not a log segment (wrong magic bytes)".into()));
    }
    let version = u32::from_le_bytes(header[8..12].try_into().unwrap_or([0; 4]));
    if header[12..16] != [0; 4] {
        return Err(corrupt(
            "the segment header's reserved bytes are not zero".into(),
        ));
    }
    if version != SEGMENT_VERSION {
        return Err(corrupt(format!(
            "log segment version {version}; this mcapi reads version {SEGMENT_VERSION}"
        )));
    }
    let mut frames = Vec::new();
    let mut offset = HEADER_LEN;
    let mut expected = first;
    while !rest.is_empty() {
        let at = |what: &str| format!("frame {expected} at byte {offset}: {what}");
        let Some((head, tail)) = rest.split_at_checked(FRAME_HEADER) else {
            if last {
                return Ok(SegmentRead { frames, torn: true });
            }
            return Err(corrupt(at("cut short in a segment that is not the last")));
        };
        let len = u32::from_le_bytes(head[0..4].try_into().unwrap_or([0; 4]));
        let lsn = u64::from_le_bytes(head[4..12].try_into().unwrap_or([0; 8]));
        let header_crc = u32::from_le_bytes(head[12..16].try_into().unwrap_or([0; 4]));
        let payload_crc = u32::from_le_bytes(head[16..20].try_into().unwrap_or([0; 4]));
        if crc32fast::hash(&head[0..12]) != header_crc || len > MAX_PAYLOAD {
            return Err(corrupt(at("the frame header does not check")));
        }
        if lsn != expected {
            return Err(corrupt(at(&format!("it is numbered {lsn}"))));
        }
        let Some((payload, tail)) = tail.split_at_checked(len as usize) else {
            if last {
                return Ok(SegmentRead { frames, torn: true });
            }
            return Err(corrupt(at("cut short in a segment that is not the last")));
        };
        if crc32fast::hash(payload) != payload_crc {
            return Err(corrupt(at("the payload checksum does not match")));
        }
        let writes =
            decode_payload(payload).ok_or_else(|| corrupt(at("the payload does not decode")))?;
        frames.push(Frame { lsn, writes });
        offset += (FRAME_HEADER + len as usize) as u64;
        expected += 1;
        rest = tail;
    }
    Ok(SegmentRead {
        frames,
        torn: false,
    })
}

/// Syncs a directory, so that files created or removed in it stay so.
pub fn sync_dir(dir: &Path) -> std::io::Result<()> {
    File::open(dir)?.sync_all()
}

/// The active segment, as the writer thread sees it.
#[derive(Debug)]
pub struct Wal {
    dir: PathBuf,
    file: File,
    /// The active segment's first frame number.
    first: u64,
    /// Bytes of the active segment that hold whole, acknowledged frames.
    len: u64,
    /// The next frame's number.
    next: u64,
    /// Frames written since the last sync.
    unsynced: bool,
    /// The frame being written (kept to reuse its allocation).
    buf: Vec<u8>,
}

impl Wal {
    /// Begins a new segment whose first frame is `next`.
    pub fn create(dir: &Path, next: u64) -> std::io::Result<Self> {
        let path = segment_path(dir, next);
        let mut file = OpenOptions::new()
            .create_new(true)
            .append(true)
            .open(&path)?;
        let mut header = [0u8; HEADER_LEN as usize];
        header[0..8].copy_from_slice(MAGIC);
        header[8..12].copy_from_slice(&SEGMENT_VERSION.to_le_bytes());
        file.write_all(&header)?;
        file.sync_data()?;
        sync_dir(dir)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            file,
            first: next,
            len: HEADER_LEN,
            next,
            unsynced: false,
            buf: Vec::new(),
        })
    }

    /// The next frame's number.
    pub fn next_lsn(&self) -> u64 {
        self.next
    }

    /// Whether frames were written since the last sync.
    pub fn unsynced(&self) -> bool {
        self.unsynced
    }

    /// Appends one frame holding `writes` (one `write` call) and returns its
    /// number. On failure the segment is cut back to its last whole frame,
    /// so the failed frame can never be read back; if even that fails the
    /// error says so ([`AppendError::Dirty`]) and nothing may be appended
    /// until [`Wal::repair`] succeeds.
    pub fn append<'a>(
        &mut self,
        writes: impl Iterator<Item = &'a Write>,
    ) -> Result<u64, AppendError> {
        let lsn = self.next;
        encode_frame(lsn, writes, &mut self.buf);
        if let Err(e) = self.file.write_all(&self.buf) {
            return Err(self.cut(e));
        }
        self.len += self.buf.len() as u64;
        self.next += 1;
        self.unsynced = true;
        Ok(lsn)
    }

    /// Cuts the segment back to its last whole frame after a failed write.
    fn cut(&mut self, cause: std::io::Error) -> AppendError {
        match self
            .file
            .set_len(self.len)
            .and_then(|()| self.file.sync_data())
        {
            Ok(()) => AppendError::Clean(cause),
            Err(e) => AppendError::Dirty(format!("{cause}; then cutting the segment back: {e}")),
        }
    }

    /// Makes everything appended durable (`fdatasync`). On failure the
    /// frames since the last sync may or may not be on disk: the caller
    /// treats them as failed and cuts them off ([`Wal::truncate`]).
    pub fn sync(&mut self) -> std::io::Result<()> {
        self.file.sync_data()?;
        self.unsynced = false;
        Ok(())
    }

    /// Bytes of the active segment.
    pub fn bytes(&self) -> u64 {
        self.len
    }

    /// Cuts the segment back to `len` bytes (forgetting the frames after
    /// it) and syncs: after a failed sync, so that frames never
    /// acknowledged cannot be read back.
    pub fn truncate(&mut self, len: u64, next: u64) -> Result<(), String> {
        self.file
            .set_len(len)
            .and_then(|()| self.file.sync_data())
            .map_err(|e| e.to_string())?;
        self.len = len;
        self.next = next;
        self.unsynced = false;
        Ok(())
    }

    /// After a [`AppendError::Dirty`] failure: cut the segment back to its
    /// last whole frame again.
    pub fn repair(&mut self) -> Result<(), String> {
        let (len, next) = (self.len, self.next);
        self.truncate(len, next)
    }

    /// Whether the active segment is full.
    pub fn full(&self) -> bool {
        self.len >= SEGMENT_BYTES
    }

    /// Closes the active segment (synced) and begins the next. Returns the
    /// closed segment's first and last frame numbers and its path.
    pub fn roll(&mut self) -> std::io::Result<(u64, u64, PathBuf)> {
        self.sync()?;
        let closed = (
            self.first,
            self.next - 1,
            segment_path(&self.dir, self.first),
        );
        *self = Self::create(&self.dir, self.next)?;
        Ok(closed)
    }

    /// The active segment's first frame number and path.
    pub fn active(&self) -> (u64, PathBuf) {
        (self.first, segment_path(&self.dir, self.first))
    }
}

/// A failed append.
#[derive(Debug)]
pub enum AppendError {
    /// The write failed and the segment was cut back: nothing of the frame
    /// remains.
    Clean(std::io::Error),
    /// The write failed and the segment could not be cut back: part of the
    /// frame may remain until [`Wal::repair`] succeeds.
    Dirty(String),
}

impl std::fmt::Display for AppendError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Clean(e) => write!(f, "{e}"),
            Self::Dirty(e) => f.write_str(e),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn writes() -> Vec<Write> {
        vec![
            Write::Session {
                id: Arc::from("s0001.x"),
                record: b"record".to_vec(),
            },
            Write::Append {
                id: Arc::from("s0001.x"),
                seq: 7,
                entry: vec![1, 2, 3],
            },
            Write::Snapshot {
                id: Arc::from("s0001.x"),
                seq: 7,
                snapshot: vec![9; 100],
            },
            Write::Resume {
                id: Arc::from("s0001.x"),
            },
            Write::Delete {
                id: Arc::from("s0001.x"),
            },
        ]
    }

    fn same(a: &[Write], b: &[Write]) -> bool {
        let logged = a.iter().filter(|w| !matches!(w, Write::Resume { .. }));
        format!("{:?}", logged.collect::<Vec<_>>()) == format!("{b:?}")
    }

    #[test]
    fn frames_read_back_as_written_and_a_cut_tail_is_torn() {
        let dir = tempfile::tempdir().expect("dir");
        let mut wal = Wal::create(dir.path(), 5).expect("create");
        let w = writes();
        assert_eq!(wal.append(w.iter()).expect("append"), 5);
        assert_eq!(wal.append(w[1..2].iter()).expect("append"), 6);
        wal.sync().expect("sync");
        let (first, path) = wal.active();
        let read = read_segment(&path, first, true).expect("read");
        assert!(!read.torn);
        assert_eq!(read.frames.len(), 2);
        assert!(same(&w, &read.frames[0].writes));
        assert_eq!(read.frames[1].lsn, 6);
        // Every cut inside the last frame is a torn tail, and only there.
        let full = std::fs::read(&path).expect("bytes");
        let second = full.len() - (FRAME_HEADER + read_len(&w[1..2]));
        for cut in second + 1..full.len() {
            std::fs::write(&path, &full[..cut]).expect("cut");
            let read = read_segment(&path, first, true).expect("torn is not damage");
            assert!(read.torn, "cut at {cut}");
            assert_eq!(read.frames.len(), 1);
            let err = read_segment(&path, first, false).expect_err("torn inside a closed segment");
            assert!(matches!(err, StoreError::Corrupt { .. }));
        }
    }

    fn read_len(w: &[Write]) -> usize {
        let mut out = Vec::new();
        for w in w {
            encode_write(w, &mut out);
        }
        out.len()
    }

    #[test]
    fn any_flipped_byte_of_a_whole_frame_is_damage_not_a_torn_tail() {
        let dir = tempfile::tempdir().expect("dir");
        let mut wal = Wal::create(dir.path(), 1).expect("create");
        wal.append(writes().iter()).expect("append");
        let (first, path) = wal.active();
        let full = std::fs::read(&path).expect("bytes");
        for i in 0..full.len() {
            let mut bytes = full.clone();
            bytes[i] ^= 0x40;
            std::fs::write(&path, &bytes).expect("write");
            match read_segment(&path, first, true) {
                Err(StoreError::Corrupt { .. }) => {}
                // A flipped high bit of the length may make the frame run
                // past the end: only then may it read as torn... which
                // the header checksum rules out.
                other => panic!("byte {i} flipped: {other:?}"),
            }
        }
    }

    #[test]
    fn frame_numbers_must_follow_on() {
        let dir = tempfile::tempdir().expect("dir");
        let mut wal = Wal::create(dir.path(), 10).expect("create");
        wal.append(writes().iter()).expect("append");
        let (_, path) = wal.active();
        let err = read_segment(&path, 11, true).expect_err("numbered 10, expected 11");
        assert!(err.to_string().contains("numbered 10"), "{err}");
    }

    #[test]
    fn a_failed_frame_is_cut_back_and_roll_begins_the_next_segment() {
        let dir = tempfile::tempdir().expect("dir");
        let mut wal = Wal::create(dir.path(), 1).expect("create");
        wal.append(writes().iter()).expect("append");
        let len = wal.bytes();
        wal.append(writes().iter()).expect("append");
        wal.truncate(len, 2).expect("truncate");
        let (first, path) = wal.active();
        assert_eq!(
            read_segment(&path, first, true).expect("read").frames.len(),
            1
        );
        assert_eq!(wal.append(writes().iter()).expect("append"), 2);
        let (a, b, closed) = wal.roll().expect("roll");
        assert_eq!((a, b), (1, 2));
        assert_eq!(wal.next_lsn(), 3);
        let listed = list_segments(dir.path()).expect("list");
        assert_eq!(listed, vec![(1, closed), (3, segment_path(dir.path(), 3))]);
    }

    #[test]
    fn strangers_in_the_log_directory_are_refused() {
        let dir = tempfile::tempdir().expect("dir");
        std::fs::write(dir.path().join("notes.txt"), b"hi").expect("write");
        assert!(matches!(
            list_segments(dir.path()),
            Err(StoreError::Corrupt { .. })
        ));
    }
}
