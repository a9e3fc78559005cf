//! The write-ahead log: the store's hot path (docs/sessions.md,
//! "Durability and recovery").
//!
//! Every group commit is one frame written into the active segment file
//! and, under [`Durability::Sync`], one `fdatasync`. redb is updated later,
//! in bulk, by the checkpointer (`checkpoint.rs`), which records in redb the
//! last frame it applied; segments wholly applied are deleted.
//!
//! Files: `wal/<first frame number, 20 digits>.wal` in the data directory,
//! and at most two temporaries (`*.tmp`, segments being zero-filled; any left
//! by a crash are deleted at open).
//!
//! ## Segment format, version 2 (what the log writes; version 1 is still read)
//!
//! A segment is a file of a fixed size, a whole number of 512-byte
//! sectors, **filled with zeros before it is used** (by a background thread
//! while the previous segment fills) and renamed into place. Frames are then
//! written over the zeros, so the file never grows: a sync writes the frame
//! and nothing else, where a growing file also needs its inode written (on
//! this project's test machine an append's `fdatasync` took 1.8-2.2× as long
//! as an overwrite's; BENCHMARKS.md §8).
//!
//! The first sector is the header (`MAGIC`, the version, four reserved
//! zero bytes, zeros). Each frame begins on a sector boundary:
//!
//! | bytes | field |
//! |---|---|
//! | 4 | payload length, little-endian |
//! | 8 | frame number (LSN), little-endian; consecutive across segments |
//! | 4 | CRC-32 of the 12 bytes above |
//! | 4 | CRC-32 of the payload |
//! | n | payload: the group's writes (`encode_write`) |
//! | | zeros to the next sector boundary |
//!
//! The frames end at the first blank (all-zero) sector where a frame would
//! begin; everything after it must be blank too.
//!
//! **Torn tails.** A killed process leaves a frame whole or absent (one
//! `pwrite`). A power cut during a frame's write may leave any of its
//! sectors unwritten, that is still zero (a sector is the unit a disk writes
//! whole). Reading the newest segment, a frame is a *torn tail*, and is cut,
//! when nothing is written after it and either its first sector is blank or
//! its payload does not check and one of its sectors is blank: the rule
//! etcd's log uses. Anything else that does not check (a header on a
//! written sector, a payload with no blank sector, a frame number out of
//! sequence, padding that is not zero, bytes written after the end, any
//! fault in a segment that is not the newest) is damage, and the store
//! refuses to open rather than lose what was acknowledged. What this cannot
//! tell apart: damage that zeroes whole sectors of the newest frame, or
//! flips bytes in the newest frame *and* that frame's own data happens to
//! hold a sector-aligned run of 512 zero bytes; such a frame is cut as torn.
//!
//! ## Version 1 (read, never written)
//!
//! Version 1 segments (a 16-byte header, frames back to back, the file
//! growing with each append; a torn tail is a frame running past the end of
//! the file) are still read at open: a store written by an older mcapi
//! replays its log and continues in version 2 segments.

use std::fs::{File, OpenOptions};
use std::io::Write as _;
use std::os::unix::fs::FileExt as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::thread::JoinHandle;

use crate::error::StoreError;
use crate::write::{Appends, Write};

/// Under [`Durability::Os`], how long a frame may stay unsynced.
pub const OS_SYNC_INTERVAL: std::time::Duration = std::time::Duration::from_millis(5);

/// The log's directory inside the data directory.
pub const WAL_DIR: &str = "wal";
/// The first bytes of every segment.
const MAGIC: &[u8; 8] = b"MCAPIWAL";
/// Version of the segment and frame layout written.
const SEGMENT_VERSION: u32 = 2;
/// The unit frames are aligned to and a disk writes whole.
const SECTOR: usize = 512;
/// Bytes of a version 1 segment's header.
const V1_HEADER_LEN: usize = 16;
/// Bytes of a frame's header.
const FRAME_HEADER: usize = 20;
/// Size of the segments prepared ahead of the writer (a frame larger than
/// this gets a segment of its own size).
pub const SEGMENT_BYTES: u64 = 16 << 20;
/// Size of the segment begun at open: small, so that opening a store (and
/// each test that does) writes 1 MiB of zeros, not 16; the next one is a
/// full [`SEGMENT_BYTES`], prepared in the background.
const FIRST_SEGMENT_BYTES: u64 = 1 << 20;
/// The largest payload a frame may declare: a larger length is damage.
const MAX_PAYLOAD: u32 = 1 << 30;
/// The spare segment being prepared for the next roll.
const SPARE: &str = "spare.tmp";
/// A segment being prepared while the writer waits.
const NEW: &str = "new.tmp";

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
    /// the background every 5 ms (`OS_SYNC_INTERVAL`).
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
/// Records appended to many sessions' logs in one write ([`Appends`]):
/// their bytes as they are, session keys included (a group step's; added
/// after the four above, which keep their bytes).
const KIND_APPENDS: u8 = 5;

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
        Write::Appends(a) => {
            out.push(KIND_APPENDS);
            bytes(out, &a.records);
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
            KIND_APPENDS => Write::Appends(Appends::decoded(c.bytes()?.to_vec())?),
            _ => return None,
        };
        out.push(w);
    }
    Some(out)
}

/// Encodes one frame (header and payload, no padding) into `out`, which is
/// cleared first.
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

/// A frame's header, parsed but not yet checked.
struct FrameHeader {
    len: u32,
    lsn: u64,
    header_crc: u32,
    payload_crc: u32,
}

impl FrameHeader {
    fn parse(head: &[u8; FRAME_HEADER]) -> Self {
        let u32_at =
            |i: usize| u32::from_le_bytes([head[i], head[i + 1], head[i + 2], head[i + 3]]);
        let mut lsn = [0u8; 8];
        lsn.copy_from_slice(&head[4..12]);
        Self {
            len: u32_at(0),
            lsn: u64::from_le_bytes(lsn),
            header_crc: u32_at(12),
            payload_crc: u32_at(16),
        }
    }

    /// Whether the header's own checksum holds and its length is possible.
    fn checks(&self, head: &[u8; FRAME_HEADER]) -> bool {
        crc32fast::hash(&head[0..12]) == self.header_crc && self.len <= MAX_PAYLOAD
    }
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

/// The segments in `dir` by first frame number, in order. Temporaries
/// (`*.tmp`, segments being prepared) are skipped; any other file there
/// that is not a segment is refused (it is not ours to delete or skip).
pub fn list_segments(dir: &Path) -> Result<Vec<(u64, PathBuf)>, StoreError> {
    let io = |e: std::io::Error| StoreError::Io {
        path: dir.to_path_buf(),
        reason: e.to_string(),
    };
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let path = entry.map_err(io)?.path();
        let name = path.file_name().and_then(|n| n.to_str());
        if name.is_some_and(|n| n.ends_with(".tmp")) {
            continue;
        }
        let first = name
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

/// Reads one segment, of either version. `first` is the frame number its
/// name promises; `last` whether it is the newest segment (the only one
/// that may end torn).
pub fn read_segment(path: &Path, first: u64, last: bool) -> Result<SegmentRead, StoreError> {
    let corrupt = |reason: String| StoreError::Corrupt {
        path: path.to_path_buf(),
        reason,
    };
    let bytes = std::fs::read(path).map_err(|e| StoreError::Io {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    let Some(header) = bytes.get(..V1_HEADER_LEN) else {
        // A version 1 header cut short: the segment was being created at
        // the crash (version 2 segments are renamed in whole).
        if last {
            return Ok(SegmentRead {
                frames: Vec::new(),
                torn: true,
            });
        }
        return Err(corrupt("the segment header is cut short".into()));
    };
    if &header[0..8] != MAGIC {
        return Err(corrupt("not a log segment (wrong magic bytes)".into()));
    }
    if header[12..16] != [0; 4] {
        return Err(corrupt(
            "the segment header's reserved bytes are not zero".into(),
        ));
    }
    match u32::from_le_bytes([header[8], header[9], header[10], header[11]]) {
        1 => read_v1(&bytes, first, last).map_err(corrupt),
        2 => read_v2(&bytes, first, last).map_err(corrupt),
        version => Err(corrupt(format!(
            "log segment version {version}; this mcapi reads versions 1 and {SEGMENT_VERSION}"
        ))),
    }
}

/// Whether every byte is zero.
fn blank(bytes: &[u8]) -> bool {
    bytes.iter().all(|&b| b == 0)
}

/// Reads a version 2 segment's frames (see the module docs); the error is
/// the reason it is damaged.
fn read_v2(bytes: &[u8], first: u64, last: bool) -> Result<SegmentRead, String> {
    if bytes.len() % SECTOR != 0 || bytes.len() < SECTOR {
        return Err(format!(
            "{} bytes is not a whole number of {SECTOR}-byte sectors",
            bytes.len()
        ));
    }
    if !blank(&bytes[V1_HEADER_LEN..SECTOR]) {
        return Err("the segment header's padding is not zero".into());
    }
    let mut frames = Vec::new();
    let mut offset = SECTOR;
    let mut expected = first;
    // The first byte written at or after `from`, if any.
    let written_after = |from: usize| bytes[from..].iter().position(|&b| b != 0).map(|i| from + i);
    while offset < bytes.len() {
        let at = |what: &str| format!("frame {expected} at byte {offset}: {what}");
        let sector = &bytes[offset..offset + SECTOR];
        if blank(sector) {
            // No frame begins here. Anything written after it is the rest of
            // a frame whose first sector never reached the disk (torn), or
            // damage where no frame can be.
            return match written_after(offset) {
                None => Ok(SegmentRead {
                    frames,
                    torn: false,
                }),
                Some(_) if last => Ok(SegmentRead { frames, torn: true }),
                Some(b) => Err(at(&format!(
                    "the log ends here, but byte {b} is written after it"
                ))),
            };
        }
        let mut head = [0u8; FRAME_HEADER];
        head.copy_from_slice(&sector[..FRAME_HEADER]);
        let h = FrameHeader::parse(&head);
        // The first sector is written (not blank), and a sector is written
        // whole: a header that does not check is damage, never a tear.
        if !h.checks(&head) {
            return Err(at("the frame header does not check"));
        }
        if h.lsn != expected {
            return Err(at(&format!("it is numbered {}", h.lsn)));
        }
        let used = FRAME_HEADER + h.len as usize;
        let span = used.next_multiple_of(SECTOR);
        let Some(frame) = bytes.get(offset..offset + span) else {
            return Err(at("it runs past the end of the segment"));
        };
        let payload = &frame[FRAME_HEADER..used];
        if crc32fast::hash(payload) != h.payload_crc {
            // Torn only if a sector of it never reached the disk, nothing
            // was written after it, and it is the newest segment.
            if !frame.chunks_exact(SECTOR).any(blank) {
                return Err(at("the payload checksum does not match"));
            }
            if let Some(b) = written_after(offset + span) {
                return Err(at(&format!(
                    "a sector of it is blank, but byte {b} is written after it"
                )));
            }
            if !last {
                return Err(at("cut short in a segment that is not the last"));
            }
            return Ok(SegmentRead { frames, torn: true });
        }
        if !blank(&frame[used..]) {
            return Err(at("the padding after the payload is not zero"));
        }
        let writes = decode_payload(payload).ok_or_else(|| at("the payload does not decode"))?;
        frames.push(Frame { lsn: h.lsn, writes });
        offset += span;
        expected += 1;
    }
    Ok(SegmentRead {
        frames,
        torn: false,
    })
}

/// Reads a version 1 segment's frames: back to back after a 16-byte
/// header, a torn tail being a frame that runs past the end of the file.
fn read_v1(bytes: &[u8], first: u64, last: bool) -> Result<SegmentRead, String> {
    let mut rest = &bytes[V1_HEADER_LEN..];
    let mut frames = Vec::new();
    let mut offset = V1_HEADER_LEN;
    let mut expected = first;
    let torn = |frames: Vec<Frame>, at: String| {
        if last {
            Ok(SegmentRead { frames, torn: true })
        } else {
            Err(at)
        }
    };
    while !rest.is_empty() {
        let at = |what: &str| format!("frame {expected} at byte {offset}: {what}");
        let Some((head, tail)) = rest.split_first_chunk::<FRAME_HEADER>() else {
            return torn(frames, at("cut short in a segment that is not the last"));
        };
        let h = FrameHeader::parse(head);
        if !h.checks(head) {
            return Err(at("the frame header does not check"));
        }
        if h.lsn != expected {
            return Err(at(&format!("it is numbered {}", h.lsn)));
        }
        let Some((payload, tail)) = tail.split_at_checked(h.len as usize) else {
            return torn(frames, at("cut short in a segment that is not the last"));
        };
        if crc32fast::hash(payload) != h.payload_crc {
            return Err(at("the payload checksum does not match"));
        }
        let writes = decode_payload(payload).ok_or_else(|| at("the payload does not decode"))?;
        frames.push(Frame { lsn: h.lsn, writes });
        offset += FRAME_HEADER + h.len as usize;
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

/// Segment sizes tried in turn when a new segment is needed now: the full
/// size, then smaller ones, so that a nearly full disk (one that has just
/// had some room freed) still takes frames. Each is raised to the room the
/// frame needs.
const FALLBACK_SIZES: [u64; 4] = [SEGMENT_BYTES, FIRST_SEGMENT_BYTES, 64 << 10, 0];

/// Writes a zero-filled version 2 segment of `size` bytes to `path`
/// (replaced if present) and syncs it: one `write` per MiB, then
/// `fdatasync`. On failure the file is removed, so that a full disk is
/// not kept full by half a segment.
fn prepare(path: &Path, size: u64) -> std::io::Result<()> {
    let written = write_zeroed(path, size);
    if written.is_err() {
        let _ = std::fs::remove_file(path);
    }
    written
}

/// Prepares a segment at `path` of the first of `sizes` (each at least
/// `need`) that the disk takes; returns its size.
fn prepare_fitting(path: &Path, need: u64, sizes: &[u64]) -> std::io::Result<u64> {
    let mut failed = None;
    for &size in sizes {
        let size = size.max(need);
        match prepare(path, size) {
            Ok(()) => return Ok(size),
            Err(e) => failed = Some(e),
        }
        if size == need {
            break;
        }
    }
    Err(failed.unwrap_or_else(|| std::io::Error::other("no segment size to try")))
}

fn write_zeroed(path: &Path, size: u64) -> std::io::Result<()> {
    let mut file = OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .open(path)?;
    let zeros = vec![0u8; 1 << 20];
    let mut header = [0u8; SECTOR];
    header[0..8].copy_from_slice(MAGIC);
    header[8..12].copy_from_slice(&SEGMENT_VERSION.to_le_bytes());
    file.write_all(&header)?;
    let mut left = size - SECTOR as u64;
    while left > 0 {
        let n = left.min(zeros.len() as u64) as usize;
        file.write_all(&zeros[..n])?;
        left -= n as u64;
    }
    file.sync_data()
}

/// The spare segment for the next roll.
#[derive(Debug, Default)]
enum Spare {
    /// None yet (the active segment is less than half full).
    #[default]
    None,
    /// Being zero-filled by a thread of its own; it returns the size.
    Preparing(JoinHandle<std::io::Result<u64>>),
    /// Ready at [`SPARE`], this many bytes.
    Ready(u64),
}

/// The active segment, as the writer thread sees it.
#[derive(Debug)]
pub struct Wal {
    dir: PathBuf,
    file: File,
    /// The active segment's first frame number.
    first: u64,
    /// The active segment's size (all of it written, zeros after `len`).
    size: u64,
    /// Bytes of the active segment that hold the header and whole frames.
    len: u64,
    /// The next frame's number.
    next: u64,
    /// `len` and `next` at the last successful sync.
    synced: (u64, u64),
    /// How far the active segment may hold frame bytes: past `len` after a
    /// failed write, until it is zeroed again.
    written: u64,
    /// Frames written since the last sync.
    unsynced: bool,
    /// The frame being written (kept to reuse its allocation).
    buf: Vec<u8>,
    /// Segments closed by a roll, for [`Wal::take_closed`].
    closed: Vec<(u64, u64, PathBuf)>,
    spare: Spare,
}

impl Wal {
    /// Begins the log at open: deletes temporaries a crash may have left
    /// and begins a new segment whose first frame is `next`.
    pub fn create(dir: &Path, next: u64) -> std::io::Result<Self> {
        for entry in std::fs::read_dir(dir)? {
            let path = entry?.path();
            if path.extension().is_some_and(|e| e == "tmp") {
                std::fs::remove_file(&path)?;
            }
        }
        let path = segment_path(dir, next);
        if path.exists() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                format!("{} exists", path.display()),
            ));
        }
        let size = prepare_fitting(&dir.join(NEW), 2 * SECTOR as u64, &FALLBACK_SIZES[1..])?;
        let file = install_prepared(dir, &dir.join(NEW), &path)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            file,
            first: next,
            size,
            len: SECTOR as u64,
            next,
            synced: (SECTOR as u64, next),
            written: SECTOR as u64,
            unsynced: false,
            buf: Vec::new(),
            closed: Vec::new(),
            spare: Spare::None,
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

    /// Writes one frame holding `writes` (one `pwrite` over the zeros) and
    /// returns its number. A frame that does not fit the active segment
    /// first closes it (synced) and begins the next ([`Wal::take_closed`]
    /// lists it). On failure the frame's bytes are zeroed again, so it can
    /// never be read back; if even that fails the error says so
    /// ([`AppendError::Dirty`]) and nothing may be written until
    /// [`Wal::repair`] succeeds.
    pub fn append<'a>(
        &mut self,
        writes: impl Iterator<Item = &'a Write>,
    ) -> Result<u64, AppendError> {
        let lsn = self.next;
        encode_frame(lsn, writes, &mut self.buf);
        let span = self.buf.len().next_multiple_of(SECTOR);
        self.buf.resize(span, 0);
        if self.len + span as u64 > self.size {
            self.roll(span as u64).map_err(AppendError::Clean)?;
        }
        self.written = self.written.max(self.len + span as u64);
        if let Err(e) = self.file.write_all_at(&self.buf, self.len) {
            return Err(self.cut(e));
        }
        self.len += span as u64;
        self.next += 1;
        self.unsynced = true;
        if matches!(self.spare, Spare::None) && self.len > self.size / 2 {
            let path = self.dir.join(SPARE);
            self.spare = Spare::Preparing(std::thread::spawn(move || {
                prepare(&path, SEGMENT_BYTES).map(|()| SEGMENT_BYTES)
            }));
        }
        Ok(lsn)
    }

    /// Zeroes the active segment from byte `from` to the furthest byte
    /// written, and syncs.
    fn zero_from(&mut self, from: u64) -> std::io::Result<()> {
        let zeros = vec![0u8; (self.written.saturating_sub(from)).min(1 << 20) as usize];
        let mut at = from;
        while at < self.written {
            let n = (self.written - at).min(zeros.len() as u64) as usize;
            self.file.write_all_at(&zeros[..n], at)?;
            at += n as u64;
        }
        self.file.sync_data()?;
        self.written = from;
        Ok(())
    }

    /// Zeroes what a failed write may have left after the last whole frame.
    fn cut(&mut self, cause: std::io::Error) -> AppendError {
        match self.zero_from(self.len) {
            Ok(()) => AppendError::Clean(cause),
            Err(e) => AppendError::Dirty(format!("{cause}; then zeroing the failed frame: {e}")),
        }
    }

    /// Closes the active segment (synced) and begins the next, of room for
    /// a frame of `span` bytes: the spare if it is ready (or being
    /// prepared: this waits for it) and large enough, else one zero-filled
    /// now ([`FALLBACK_SIZES`]). An active segment without frames is
    /// replaced, not closed.
    fn roll(&mut self, span: u64) -> std::io::Result<()> {
        let empty = self.next == self.first;
        if !empty {
            self.sync()?;
        }
        let need = span + SECTOR as u64;
        if let Spare::Preparing(handle) = std::mem::take(&mut self.spare) {
            self.spare = match handle.join() {
                Ok(Ok(size)) => Spare::Ready(size),
                Ok(Err(e)) => {
                    tracing::warn!(error = %e, "preparing a log segment in the background");
                    Spare::None
                }
                Err(_) => Spare::None,
            };
        }
        let (from, size) = match self.spare {
            Spare::Ready(size) if size >= need => (self.dir.join(SPARE), size),
            _ => {
                let size = prepare_fitting(&self.dir.join(NEW), need, &FALLBACK_SIZES)?;
                (self.dir.join(NEW), size)
            }
        };
        let path = segment_path(&self.dir, self.next);
        let file = install_prepared(&self.dir, &from, &path)?;
        if from.ends_with(SPARE) {
            self.spare = Spare::None;
        }
        if !empty {
            self.closed.push((
                self.first,
                self.next - 1,
                segment_path(&self.dir, self.first),
            ));
        }
        self.file = file;
        self.first = self.next;
        self.size = size;
        self.len = SECTOR as u64;
        self.written = self.len;
        self.synced = (self.len, self.next);
        self.unsynced = false;
        Ok(())
    }

    /// The segments closed since the last call: first and last frame
    /// numbers and path of each.
    pub fn take_closed(&mut self) -> Vec<(u64, u64, PathBuf)> {
        std::mem::take(&mut self.closed)
    }

    /// Makes everything written durable (`fdatasync`). On failure the
    /// frames since the last sync may or may not be on disk: the caller
    /// treats them as failed and cuts them off ([`Wal::cut_unsynced`]).
    pub fn sync(&mut self) -> std::io::Result<()> {
        self.file.sync_data()?;
        self.unsynced = false;
        self.synced = (self.len, self.next);
        Ok(())
    }

    /// Forgets the frames written since the last successful sync (zeroed,
    /// then synced): after a failed sync, so that frames never
    /// acknowledged cannot be read back.
    pub fn cut_unsynced(&mut self) -> Result<(), String> {
        let (len, next) = self.synced;
        self.zero_from(len).map_err(|e| e.to_string())?;
        self.len = len;
        self.next = next;
        self.unsynced = false;
        Ok(())
    }

    /// After a [`AppendError::Dirty`] failure: zero what follows the last
    /// whole frame again.
    pub fn repair(&mut self) -> Result<(), String> {
        self.zero_from(self.len).map_err(|e| e.to_string())
    }

    /// The active segment's first frame number and path.
    pub fn active(&self) -> (u64, PathBuf) {
        (self.first, segment_path(&self.dir, self.first))
    }
}

impl Drop for Wal {
    /// Waits for a spare being prepared and deletes it: the data directory
    /// keeps no 16 MiB of zeros while the server is stopped.
    fn drop(&mut self) {
        if let Spare::Preparing(handle) = std::mem::take(&mut self.spare) {
            let _ = handle.join();
        }
        let _ = std::fs::remove_file(self.dir.join(SPARE));
    }
}

/// Renames a prepared segment into place (replacing an empty active one of
/// the same name), syncs the directory so that the name stays, and opens
/// it for writing.
fn install_prepared(dir: &Path, from: &Path, path: &Path) -> std::io::Result<File> {
    std::fs::rename(from, path)?;
    sync_dir(dir)?;
    OpenOptions::new().read(true).write(true).open(path)
}

/// A failed append.
#[derive(Debug)]
pub enum AppendError {
    /// The write failed and its bytes were zeroed again (or it failed
    /// before writing): nothing of the frame remains.
    Clean(std::io::Error),
    /// The write failed and its bytes could not be zeroed: part of the
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
/// A version 1 segment, as mcapi wrote them before: 16-byte header,
/// frames back to back. Returns where each frame ends.
pub(super) fn v1_segment(path: &Path, first: u64, frames: &[Vec<Write>]) -> Vec<usize> {
    let mut bytes = Vec::new();
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&1u32.to_le_bytes());
    bytes.extend_from_slice(&[0; 4]);
    let mut ends = Vec::new();
    let mut buf = Vec::new();
    for (i, w) in frames.iter().enumerate() {
        encode_frame(first + i as u64, w.iter(), &mut buf);
        bytes.extend_from_slice(&buf);
        ends.push(bytes.len());
    }
    std::fs::write(path, &bytes).expect("write");
    ends
}

#[cfg(test)]
mod tests {
    use super::*;

    fn writes() -> Vec<Write> {
        let mut appends = Appends::default();
        for (id, seq) in [("s0001.x", 8), ("s0001.z", 0)] {
            appends
                .push(&crate::LogId::new(Arc::from(id)), seq, |out| {
                    out.extend_from_slice(&[4, 5, 6]);
                    Ok::<(), ()>(())
                })
                .expect("push");
        }
        // The log keeps the records' keys, not their ids.
        appends.ids.clear();
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
            Write::Appends(appends),
            Write::Delete {
                id: Arc::from("s0001.x"),
            },
        ]
    }

    /// A write whose frame spans `sectors` sectors, with no blank sector of
    /// its own.
    fn large(sectors: usize) -> Vec<Write> {
        vec![Write::Append {
            id: Arc::from("s0002.y"),
            seq: 1,
            entry: (0..sectors * SECTOR - 64)
                .map(|i| (i % 251 + 1) as u8)
                .collect(),
        }]
    }

    fn same(a: &[Write], b: &[Write]) -> bool {
        let logged = a.iter().filter(|w| !matches!(w, Write::Resume { .. }));
        format!("{:?}", logged.collect::<Vec<_>>()) == format!("{b:?}")
    }

    fn sector_count(w: &[Write]) -> usize {
        let mut out = Vec::new();
        encode_frame(0, w.iter(), &mut out);
        out.len().div_ceil(SECTOR)
    }

    #[test]
    fn frames_read_back_as_written_in_a_zero_filled_segment_that_never_grows() {
        let dir = tempfile::tempdir().expect("dir");
        let mut wal = Wal::create(dir.path(), 5).expect("create");
        let (first, path) = wal.active();
        let size = std::fs::metadata(&path).expect("meta").len();
        assert_eq!(size, FIRST_SEGMENT_BYTES);
        let w = writes();
        assert_eq!(wal.append(w.iter()).expect("append"), 5);
        assert_eq!(wal.append(w[1..2].iter()).expect("append"), 6);
        wal.sync().expect("sync");
        assert_eq!(std::fs::metadata(&path).expect("meta").len(), size);
        let read = read_segment(&path, first, true).expect("read");
        assert!(!read.torn);
        assert_eq!(read.frames.len(), 2);
        assert!(same(&w, &read.frames[0].writes));
        assert_eq!(read.frames[1].lsn, 6);
        // Frames begin on sector boundaries.
        let bytes = std::fs::read(&path).expect("bytes");
        let second = SECTOR * (1 + sector_count(&w));
        assert_eq!(bytes[second + 4..second + 12], 6u64.to_le_bytes());
    }

    #[test]
    fn a_frame_with_unwritten_sectors_is_torn_at_the_end_and_damage_elsewhere() {
        let dir = tempfile::tempdir().expect("dir");
        let mut wal = Wal::create(dir.path(), 1).expect("create");
        let big = large(4);
        let k = sector_count(&big);
        assert_eq!(k, 4);
        wal.append(writes().iter()).expect("append");
        wal.append(big.iter()).expect("append");
        wal.sync().expect("sync");
        let (first, path) = wal.active();
        let whole = std::fs::read(&path).expect("bytes");
        let start = SECTOR * (1 + sector_count(&writes()));
        // Every way a power cut can leave the last frame: any proper,
        // nonempty subset of its sectors unwritten.
        for mask in 1..(1u32 << k) - 1 {
            let mut bytes = whole.clone();
            for s in 0..k {
                if mask & (1 << s) != 0 {
                    let at = start + s * SECTOR;
                    bytes[at..at + SECTOR].fill(0);
                }
            }
            std::fs::write(&path, &bytes).expect("write");
            let read = read_segment(&path, first, true).expect("torn is not damage");
            assert!(read.torn, "mask {mask:b}");
            assert_eq!(read.frames.len(), 1, "mask {mask:b}");
            let err = read_segment(&path, first, false).expect_err("torn inside a closed segment");
            assert!(matches!(err, StoreError::Corrupt { .. }), "mask {mask:b}");
            // Torn, but something was written after it: damage. (With its
            // first sector unwritten, the frame's extent is unknown, and
            // whatever follows is taken for the rest of it.)
            if mask & 1 == 0 {
                bytes[start + k * SECTOR + 7] = 1;
                std::fs::write(&path, &bytes).expect("write");
                let err = read_segment(&path, first, true).expect_err("written after a torn frame");
                assert!(
                    err.to_string().contains("written after"),
                    "mask {mask:b}: {err}"
                );
            }
        }
        // The whole frame unwritten: it was never there.
        let mut bytes = whole.clone();
        bytes[start..start + k * SECTOR].fill(0);
        std::fs::write(&path, &bytes).expect("write");
        let read = read_segment(&path, first, true).expect("read");
        assert!(!read.torn);
        assert_eq!(read.frames.len(), 1);
        // Bytes after the end of a closed segment's frames: damage.
        bytes[start + SECTOR + 3] = 1;
        std::fs::write(&path, &bytes).expect("write");
        assert!(read_segment(&path, first, true).expect("torn").torn);
        let err = read_segment(&path, first, false).expect_err("closed segment");
        assert!(err.to_string().contains("written after"), "{err}");
    }

    #[test]
    fn any_flipped_byte_of_a_whole_frame_is_damage_not_a_torn_tail() {
        let dir = tempfile::tempdir().expect("dir");
        let mut wal = Wal::create(dir.path(), 1).expect("create");
        wal.append(writes().iter()).expect("append");
        wal.append(large(3).iter()).expect("append");
        let (first, path) = wal.active();
        let full = std::fs::read(&path).expect("bytes");
        // The header sector and both frames, padding included.
        let end = SECTOR * (1 + sector_count(&writes()) + 3);
        for i in 0..end {
            let mut bytes = full.clone();
            bytes[i] ^= 0x40;
            std::fs::write(&path, &bytes).expect("write");
            for last in [true, false] {
                match read_segment(&path, first, last) {
                    Err(StoreError::Corrupt { .. }) => {}
                    other => panic!("byte {i} flipped (last: {last}): {other:?}"),
                }
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
    fn unsynced_frames_are_cut_and_a_frame_that_does_not_fit_rolls_the_segment() {
        let dir = tempfile::tempdir().expect("dir");
        let mut wal = Wal::create(dir.path(), 1).expect("create");
        wal.append(writes().iter()).expect("append");
        wal.sync().expect("sync");
        wal.append(writes().iter()).expect("append");
        wal.append(writes().iter()).expect("append");
        wal.cut_unsynced().expect("cut");
        let (first, path) = wal.active();
        let read = read_segment(&path, first, true).expect("read");
        assert_eq!((read.frames.len(), read.torn), (1, false));
        assert_eq!(wal.append(writes().iter()).expect("append"), 2);
        // Fill the first (1 MiB) segment: past half of it the spare is
        // prepared; the frame that does not fit goes into it.
        let per = sector_count(&large(64)) * SECTOR;
        let fit = (FIRST_SEGMENT_BYTES as usize - SECTOR * 3) / per;
        for _ in 0..fit {
            wal.append(large(64).iter()).expect("append");
        }
        assert!(wal.take_closed().is_empty());
        let lsn = wal.append(large(64).iter()).expect("append");
        let closed = wal.take_closed();
        assert_eq!(closed, vec![(1, lsn - 1, path.clone())]);
        let (second, active) = wal.active();
        assert_eq!(second, lsn);
        assert_eq!(
            std::fs::metadata(&active).expect("meta").len(),
            SEGMENT_BYTES
        );
        assert!(!dir.path().join(SPARE).exists(), "the spare was used");
        let listed = list_segments(dir.path()).expect("list");
        assert_eq!(listed, vec![(1, path.clone()), (lsn, active.clone())]);
        let read = read_segment(&path, 1, false).expect("closed segment");
        assert_eq!(read.frames.len() as u64, lsn - 1);
        // A frame larger than a spare gets a segment of its own size.
        let giant = vec![Write::Append {
            id: Arc::from("g"),
            seq: 0,
            entry: vec![7; SEGMENT_BYTES as usize],
        }];
        let g = wal.append(giant.iter()).expect("append");
        assert_eq!(wal.take_closed().len(), 1);
        let (_, active) = wal.active();
        let size = std::fs::metadata(&active).expect("meta").len();
        assert!(size > SEGMENT_BYTES && size % SECTOR as u64 == 0, "{size}");
        wal.sync().expect("sync");
        let read = read_segment(&active, g, true).expect("read");
        assert!(same(&giant, &read.frames[0].writes));
    }

    #[test]
    fn an_empty_segment_too_small_for_a_frame_is_replaced_not_closed() {
        let dir = tempfile::tempdir().expect("dir");
        let mut wal = Wal::create(dir.path(), 3).expect("create");
        let big = large((FIRST_SEGMENT_BYTES as usize) / SECTOR);
        assert_eq!(wal.append(big.iter()).expect("append"), 3);
        assert!(wal.take_closed().is_empty());
        let listed = list_segments(dir.path()).expect("list");
        assert_eq!(listed.len(), 1);
        let read = read_segment(&listed[0].1, 3, true).expect("read");
        assert_eq!(read.frames.len(), 1);
    }

    #[test]
    fn temporaries_are_skipped_and_deleted_at_open_strangers_refused() {
        let dir = tempfile::tempdir().expect("dir");
        std::fs::write(dir.path().join(SPARE), b"half a spare").expect("write");
        assert!(list_segments(dir.path()).expect("list").is_empty());
        let wal = Wal::create(dir.path(), 1).expect("create");
        assert!(!dir.path().join(SPARE).exists());
        drop(wal);
        std::fs::write(dir.path().join("notes.txt"), b"hi").expect("write");
        assert!(matches!(
            list_segments(dir.path()),
            Err(StoreError::Corrupt { .. })
        ));
    }

    #[test]
    fn version_1_segments_are_read_with_their_own_torn_tail_rule() {
        let dir = tempfile::tempdir().expect("dir");
        let path = segment_path(dir.path(), 5);
        let w = writes();
        let ends = v1_segment(&path, 5, &[w.clone(), w[1..2].to_vec()]);
        let read = read_segment(&path, 5, true).expect("read");
        assert_eq!((read.frames.len(), read.torn), (2, false));
        assert!(same(&w, &read.frames[0].writes));
        let full = std::fs::read(&path).expect("bytes");
        for cut in ends[0] + 1..full.len() {
            std::fs::write(&path, &full[..cut]).expect("cut");
            let read = read_segment(&path, 5, true).expect("torn is not damage");
            assert!(read.torn, "cut at {cut}");
            assert_eq!(read.frames.len(), 1);
            assert!(read_segment(&path, 5, false).is_err());
        }
        for i in V1_HEADER_LEN..full.len() {
            let mut bytes = full.clone();
            bytes[i] ^= 0x40;
            std::fs::write(&path, &bytes).expect("write");
            assert!(read_segment(&path, 5, true).is_err(), "byte {i} flipped");
        }
    }
}
