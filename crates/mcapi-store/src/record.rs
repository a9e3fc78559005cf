//! An observation record as the log keeps it: the key of its session's log
//! and its framing (sequence number, length, bytes), shared by the writes
//! that carry records ([`crate::write`]) and the chunks that keep them
//! ([`crate::db`]).

/// Bytes that frame a record before its entry: sequence number (u64) and
/// length (u32), little-endian.
pub(crate) const FRAME: usize = 8 + 4;

/// The log's key of a session: the 128 bits of the ULID in its id
/// (`s<shard>.<ULID>`), or a 128-bit hash of the id for other ids. A number
/// instead of the string keeps the log, which holds most of the file, small:
/// the store's size is what opening (integrity check) and recovery cost.
pub(crate) fn log_key(id: &str) -> u128 {
    if let Some((_, ulid)) = id.split_once('.')
        && let Ok(u) = ulid::Ulid::from_string(ulid)
    {
        return u.0;
    }
    use sha2::Digest;
    let d = sha2::Sha256::digest(id.as_bytes());
    let mut b = [0u8; 16];
    b.copy_from_slice(&d[..16]);
    u128::from_be_bytes(b)
}

/// Frames one record at the end of `out`: sequence number, length, bytes.
pub(crate) fn push_entry(out: &mut Vec<u8>, seq: u64, entry: &[u8]) {
    out.extend_from_slice(&seq.to_le_bytes());
    out.extend_from_slice(&(entry.len() as u32).to_le_bytes());
    out.extend_from_slice(entry);
}

/// The first framed record of `bytes` (its sequence number and entry) and
/// the rest; `None` if `bytes` does not begin with a whole record.
pub(crate) fn split_entry(bytes: &[u8]) -> Option<(u64, &[u8], &[u8])> {
    let (seq, rest) = bytes.split_first_chunk::<8>()?;
    let (len, rest) = rest.split_first_chunk::<4>()?;
    let len = u32::from_le_bytes(*len) as usize;
    (rest.len() >= len).then(|| (u64::from_le_bytes(*seq), &rest[..len], &rest[len..]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_framed_record_splits_back_and_a_torn_one_does_not() {
        let mut out = Vec::new();
        push_entry(&mut out, 7, b"abc");
        push_entry(&mut out, 8, b"");
        assert_eq!(out.len(), 2 * FRAME + 3);
        let (seq, entry, rest) = split_entry(&out).expect("first");
        assert_eq!((seq, entry), (7, &b"abc"[..]));
        let (seq, entry, rest) = split_entry(rest).expect("second");
        assert_eq!((seq, entry, rest), (8, &b""[..], &b""[..]));
        // Cut anywhere inside the first record: not a whole record.
        for cut in 0..FRAME + 3 {
            assert!(split_entry(&out[..cut]).is_none(), "cut at {cut}");
        }
    }

    #[test]
    fn a_ulid_id_keys_by_its_bits_and_any_other_by_a_hash() {
        let ulid = ulid::Ulid::from_parts(1_700_000_000_000, 42);
        assert_eq!(log_key(&format!("s03a7.{ulid}")), ulid.0);
        let (a, b) = (log_key("plain-a"), log_key("plain-b"));
        assert_ne!(a, b);
        assert_eq!(a, log_key("plain-a"));
    }
}
