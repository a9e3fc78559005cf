//! The shard map (docs/cluster.md): which replica owns each of the 1024
//! virtual shards, at which epoch. One small text file is the one source of
//! truth for the replicas (`mcapi serve --shard-map`) and the router
//! (`mcapi cluster haproxy-config`):
//!
//! ```text
//! # comments and blank lines are ignored
//! epoch 3
//! s0000 mcapi-1
//! s0001 mcapi-0
//! ...            (every shard s0000..s03ff exactly once)
//! ```
//!
//! Everything read from a file is bounded before it is kept: the file's
//! size ([`MAX_MAP_BYTES`]), the length of a replica name
//! ([`MAX_REPLICA_NAME`]) and the number of replicas ([`MAX_REPLICAS`]).

use std::fmt;
use std::io::Read;
use std::path::Path;

use thiserror::Error;

/// Virtual shards: fixed forever (the first four hex digits of a session id).
pub const SHARDS: usize = 1024;

/// Largest map file read, in bytes: 1024 lines of a shard and a name of
/// [`MAX_REPLICA_NAME`] bytes take about 70 KiB; comments get the rest.
pub const MAX_MAP_BYTES: u64 = 256 * 1024;

/// Longest replica name, in bytes (a DNS label, as a Kubernetes pod name).
pub const MAX_REPLICA_NAME: usize = 63;

/// Most replicas in one map.
pub const MAX_REPLICAS: usize = 256;

/// A replica's name: a DNS label (lowercase letters, digits and `-`, not
/// at either end, 1 to 63 bytes), so it fits an HTTP header, an HAProxy
/// backend name and a Kubernetes pod name unchanged.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ReplicaName(String);

impl ReplicaName {
    /// Checks a name.
    pub fn parse(name: &str) -> Result<Self, String> {
        if name.is_empty() {
            return Err("a replica name must not be empty".into());
        }
        if name.len() > MAX_REPLICA_NAME {
            return Err(format!(
                "replica name of {} bytes; at most {MAX_REPLICA_NAME} are allowed",
                name.len()
            ));
        }
        if let Some(c) = name
            .chars()
            .find(|c| !(c.is_ascii_lowercase() || c.is_ascii_digit() || *c == '-'))
        {
            return Err(format!(
                "replica name `{}` has {c:?}; only a-z, 0-9 and `-` are allowed (a DNS label)",
                name.escape_debug()
            ));
        }
        if name.starts_with('-') || name.ends_with('-') {
            return Err(format!(
                "replica name `{name}` must not begin or end with `-`"
            ));
        }
        Ok(Self(name.to_string()))
    }

    /// The name.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl fmt::Display for ReplicaName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

/// A shard's key as in session ids, map files and the router: `s03a7`.
pub fn shard_key(shard: u16) -> String {
    format!("s{shard:04x}")
}

/// The shard of a session id `s<4 hex>.<ULID>`; `None` if the id does not
/// have that form or names a shard beyond [`SHARDS`] (then no replica can
/// hold it).
pub fn shard_of_id(id: &str) -> Option<u16> {
    let key = id.get(..5)?;
    if id.as_bytes().get(5) != Some(&b'.') {
        return None;
    }
    parse_shard_key(key).filter(|&s| usize::from(s) < SHARDS)
}

/// A shard key given alone (a path, a command line): `s0000`..`s03ff` to
/// the shard number, or why it is not one.
pub fn parse_shard(key: &str) -> Result<u16, String> {
    parse_shard_key(key)
        .filter(|&s| usize::from(s) < SHARDS)
        .ok_or_else(|| format!("`{}` is not a shard key s0000..s03ff", key.escape_debug()))
}

/// `s0000`..`s03ff` (four lowercase hex digits) to the shard number.
fn parse_shard_key(key: &str) -> Option<u16> {
    let hex = key.strip_prefix('s')?;
    if hex.len() != 4
        || !hex
            .bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
    {
        return None;
    }
    u16::from_str_radix(hex, 16).ok()
}

/// Why a shard map is refused. Line numbers count from 1.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum MapError {
    /// The file could not be read.
    #[error("reading the shard map {path}: {reason}")]
    Io {
        /// The file.
        path: String,
        /// The error.
        reason: String,
    },
    /// The file is larger than [`MAX_MAP_BYTES`].
    #[error(
        "the shard map is larger than {max} bytes; a map of 1024 shards needs well under 100 KiB"
    )]
    TooLarge {
        /// The limit.
        max: u64,
    },
    /// Not UTF-8 text.
    #[error("the shard map is not UTF-8 text")]
    NotText,
    /// No `epoch <n>` line before the first shard.
    #[error("the shard map has no `epoch <n>` line before its first shard line")]
    MissingEpoch,
    /// The epoch line is malformed.
    #[error("line {line}: {reason}")]
    Epoch {
        /// Its line.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// A line is not `<shard> <replica>`.
    #[error("line {line}: {reason}")]
    Syntax {
        /// Its line.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// A shard is assigned twice.
    #[error("line {line}: shard {shard} is assigned again (first on line {first})")]
    Duplicate {
        /// The second line.
        line: usize,
        /// The shard's key.
        shard: String,
        /// The first line.
        first: usize,
    },
    /// Shards without an owner.
    #[error("{count} of the 1024 shards have no owner: {listed}{more}")]
    Missing {
        /// How many.
        count: usize,
        /// The first few keys.
        listed: String,
        /// ", ..." when more than listed.
        more: &'static str,
    },
    /// More replicas than [`MAX_REPLICAS`].
    #[error("the shard map names more than {max} replicas")]
    TooManyReplicas {
        /// The limit.
        max: usize,
    },
}

/// Which replica owns each shard, at an epoch. Always complete: every
/// shard has exactly one owner.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ShardMap {
    epoch: u64,
    /// Distinct names, sorted.
    replicas: Vec<ReplicaName>,
    /// For each shard, an index into `replicas`.
    owner: Vec<u16>,
}

impl ShardMap {
    /// A map from each shard's owner (exactly [`SHARDS`] entries).
    pub fn from_owners(epoch: u64, owners: &[ReplicaName]) -> Result<Self, MapError> {
        if owners.len() != SHARDS {
            return Err(MapError::Missing {
                count: SHARDS.saturating_sub(owners.len()),
                listed: format!("{} owners given", owners.len()),
                more: "",
            });
        }
        check_epoch(epoch).map_err(|reason| MapError::Epoch { line: 0, reason })?;
        let mut replicas: Vec<ReplicaName> = owners.to_vec();
        replicas.sort();
        replicas.dedup();
        if replicas.len() > MAX_REPLICAS {
            return Err(MapError::TooManyReplicas { max: MAX_REPLICAS });
        }
        let owner = owners
            .iter()
            .map(|o| {
                // Found: `replicas` holds every owner; fewer than 2^16 of them.
                replicas.binary_search(o).map_or(0, |i| i as u16)
            })
            .collect();
        Ok(Self {
            epoch,
            replicas,
            owner,
        })
    }

    /// Reads and parses a map file, refusing one over [`MAX_MAP_BYTES`]
    /// before reading it whole.
    pub fn read(path: &Path) -> Result<Self, MapError> {
        let io = |e: std::io::Error| MapError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        };
        let file = std::fs::File::open(path).map_err(io)?;
        let mut bytes = Vec::new();
        file.take(MAX_MAP_BYTES + 1)
            .read_to_end(&mut bytes)
            .map_err(io)?;
        if bytes.len() as u64 > MAX_MAP_BYTES {
            return Err(MapError::TooLarge { max: MAX_MAP_BYTES });
        }
        let text = String::from_utf8(bytes).map_err(|_| MapError::NotText)?;
        Self::parse(&text)
    }

    /// Parses the text of a map file.
    pub fn parse(text: &str) -> Result<Self, MapError> {
        if text.len() as u64 > MAX_MAP_BYTES {
            return Err(MapError::TooLarge { max: MAX_MAP_BYTES });
        }
        let mut epoch = None;
        // For each shard: (owner index into `names`, line).
        let mut assigned: Vec<Option<(usize, usize)>> = vec![None; SHARDS];
        let mut names: Vec<ReplicaName> = Vec::new();
        for (i, raw) in text.lines().enumerate() {
            let line = i + 1;
            let content = raw.split('#').next().unwrap_or("").trim();
            if content.is_empty() {
                continue;
            }
            let mut words = content.split_ascii_whitespace();
            let (Some(first), second, third) = (words.next(), words.next(), words.next()) else {
                continue;
            };
            if first == "epoch" {
                if epoch.is_some() {
                    return Err(MapError::Epoch {
                        line,
                        reason: "a second `epoch` line".into(),
                    });
                }
                let value = match (second, third) {
                    (Some(v), None) => v,
                    _ => {
                        return Err(MapError::Epoch {
                            line,
                            reason: "expected `epoch <n>`".into(),
                        });
                    }
                };
                let n = value.parse::<u64>().map_err(|_| MapError::Epoch {
                    line,
                    reason: format!(
                        "the epoch `{}` is not a whole number",
                        clip(value).escape_debug()
                    ),
                })?;
                check_epoch(n).map_err(|reason| MapError::Epoch { line, reason })?;
                epoch = Some(n);
                continue;
            }
            if epoch.is_none() {
                return Err(MapError::MissingEpoch);
            }
            let (Some(name), None) = (second, third) else {
                return Err(MapError::Syntax {
                    line,
                    reason: format!(
                        "expected `<shard> <replica>` (e.g. `s03a7 mcapi-2`), found `{}`",
                        clip(content).escape_debug()
                    ),
                });
            };
            let shard = parse_shard_key(first).ok_or_else(|| MapError::Syntax {
                line,
                reason: format!(
                    "`{}` is not a shard: expected `s` and four lowercase hex digits, s0000 to s03ff",
                    clip(first).escape_debug()
                ),
            })?;
            if usize::from(shard) >= SHARDS {
                return Err(MapError::Syntax {
                    line,
                    reason: format!(
                        "shard {first} is out of range: there are 1024 shards, s0000 to s03ff"
                    ),
                });
            }
            let name =
                ReplicaName::parse(name).map_err(|reason| MapError::Syntax { line, reason })?;
            if let Some((_, first_line)) = assigned[usize::from(shard)] {
                return Err(MapError::Duplicate {
                    line,
                    shard: first.to_string(),
                    first: first_line,
                });
            }
            let index = match names.iter().position(|n| *n == name) {
                Some(i) => i,
                None => {
                    if names.len() >= MAX_REPLICAS {
                        return Err(MapError::TooManyReplicas { max: MAX_REPLICAS });
                    }
                    names.push(name);
                    names.len() - 1
                }
            };
            assigned[usize::from(shard)] = Some((index, line));
        }
        let Some(epoch) = epoch else {
            return Err(MapError::MissingEpoch);
        };
        let missing: Vec<usize> = (0..SHARDS).filter(|&s| assigned[s].is_none()).collect();
        if !missing.is_empty() {
            let listed: Vec<String> = missing
                .iter()
                .take(8)
                .map(|&s| shard_key(s as u16))
                .collect();
            return Err(MapError::Missing {
                count: missing.len(),
                listed: listed.join(", "),
                more: if missing.len() > 8 { ", ..." } else { "" },
            });
        }
        let owners: Vec<ReplicaName> = assigned
            .iter()
            .filter_map(|a| a.map(|(i, _)| names[i].clone()))
            .collect();
        Self::from_owners(epoch, &owners)
    }

    /// The map file's text: a header comment, the epoch, one line per shard.
    pub fn to_text(&self) -> String {
        let mut out = String::with_capacity(SHARDS * 16 + 128);
        out.push_str("# mcapi shard map: `<shard> <replica>` for each of the 1024 shards\n");
        out.push_str(&format!("epoch {}\n", self.epoch));
        for shard in 0..SHARDS as u16 {
            out.push_str(&format!("{} {}\n", shard_key(shard), self.owner(shard)));
        }
        out
    }

    /// This map with `shard` given to `owner`, at `epoch`.
    pub fn with_owner(
        &self,
        shard: u16,
        owner: &ReplicaName,
        epoch: u64,
    ) -> Result<Self, MapError> {
        let mut owners = self.owners();
        owners[usize::from(shard) % SHARDS] = owner.clone();
        Self::from_owners(epoch, &owners)
    }

    /// The epoch.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// The replicas owning at least one shard, sorted by name.
    pub fn replicas(&self) -> &[ReplicaName] {
        &self.replicas
    }

    /// The owner of a shard (`shard` taken modulo 1024).
    pub fn owner(&self, shard: u16) -> &ReplicaName {
        let i = self.owner[usize::from(shard) % SHARDS];
        &self.replicas[usize::from(i)]
    }

    /// Each shard's owner, shard 0 first.
    pub fn owners(&self) -> Vec<ReplicaName> {
        (0..SHARDS as u16).map(|s| self.owner(s).clone()).collect()
    }

    /// The shards a replica owns, ascending.
    pub fn shards_of(&self, replica: &ReplicaName) -> Vec<u16> {
        (0..SHARDS as u16)
            .filter(|&s| self.owner(s) == replica)
            .collect()
    }

    /// Whether the map names this replica.
    pub fn has_replica(&self, replica: &ReplicaName) -> bool {
        self.replicas.binary_search(replica).is_ok()
    }

    /// Shards per replica, in name order.
    pub fn counts(&self) -> Vec<(ReplicaName, usize)> {
        let mut counts = vec![0usize; self.replicas.len()];
        for &i in &self.owner {
            counts[usize::from(i)] += 1;
        }
        self.replicas.iter().cloned().zip(counts).collect()
    }
}

/// An epoch is at least 1 and below 2^63 (so `epoch + 1` never wraps).
fn check_epoch(epoch: u64) -> Result<(), String> {
    if epoch == 0 || epoch > i64::MAX as u64 {
        return Err(format!(
            "the epoch must be between 1 and {}, not {epoch}",
            i64::MAX
        ));
    }
    Ok(())
}

/// At most 64 bytes of a user's input, for an error message.
fn clip(s: &str) -> &str {
    let mut end = s.len().min(64);
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    &s[..end]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(n: usize) -> Vec<ReplicaName> {
        (0..n)
            .map(|i| ReplicaName::parse(&format!("mcapi-{i}")).expect("name"))
            .collect()
    }

    fn round_robin(epoch: u64, n: usize) -> ShardMap {
        let r = names(n);
        let owners: Vec<ReplicaName> = (0..SHARDS).map(|s| r[s % n].clone()).collect();
        ShardMap::from_owners(epoch, &owners).expect("map")
    }

    #[test]
    fn text_round_trips() {
        let map = round_robin(7, 3);
        let text = map.to_text();
        let back = ShardMap::parse(&text).expect("parses");
        assert_eq!(back, map);
        assert_eq!(back.epoch(), 7);
        assert_eq!(back.owner(5).as_str(), "mcapi-2");
        assert_eq!(
            back.counts().iter().map(|(_, c)| *c).collect::<Vec<_>>(),
            vec![342, 341, 341]
        );
        assert_eq!(back.shards_of(&names(3)[1])[..2], [1, 4]);
    }

    #[test]
    fn ids_carry_their_shard() {
        assert_eq!(shard_of_id("s03a7.01JDX4ABCDEF"), Some(0x3a7));
        assert_eq!(shard_of_id("s0000.x"), Some(0));
        assert_eq!(shard_of_id("s03A7.x"), None, "uppercase hex");
        assert_eq!(shard_of_id("s03a7x"), None);
        assert_eq!(shard_of_id("s03a"), None);
        assert_eq!(shard_of_id("é0000.x"), None);
        // Well formed, but beyond the shard count: no shard, so no panic
        // indexing the map with it.
        assert_eq!(shard_of_id("s03ff.x"), Some(0x3ff));
        assert_eq!(shard_of_id("s0400.x"), None);
        assert_eq!(shard_of_id("sffff.x"), None);
        assert_eq!(shard_key(0x3a7), "s03a7");
    }

    #[test]
    fn replica_names_are_dns_labels() {
        assert!(ReplicaName::parse("mcapi-0").is_ok());
        assert!(ReplicaName::parse(&"a".repeat(63)).is_ok());
        for bad in ["", "-a", "a-", "Mcapi", "a_b", "a b", "a.b", "é"] {
            assert!(ReplicaName::parse(bad).is_err(), "{bad:?} accepted");
        }
        let long = ReplicaName::parse(&"a".repeat(64)).expect_err("too long");
        assert!(long.contains("64 bytes"), "{long}");
    }

    fn error_of(text: &str) -> MapError {
        ShardMap::parse(text).expect_err("refused")
    }

    #[test]
    fn absurd_maps_are_refused_precisely() {
        let good = round_robin(3, 2).to_text();
        // Duplicate shard.
        let dup = format!("{good}s0007 mcapi-1\n");
        assert_eq!(
            error_of(&dup),
            MapError::Duplicate {
                line: 1027,
                shard: "s0007".into(),
                first: 10
            }
        );
        // Missing shards.
        let missing: String = good
            .lines()
            .filter(|l| !l.starts_with("s000") && !l.starts_with("s03ff"))
            .map(|l| format!("{l}\n"))
            .collect();
        let e = error_of(&missing);
        assert_eq!(
            e.to_string(),
            "17 of the 1024 shards have no owner: s0000, s0001, s0002, s0003, s0004, s0005, s0006, s0007, ..."
        );
        // Bad epochs.
        for (text, want) in [
            ("epoch x\n", "line 1: the epoch `x` is not a whole number"),
            ("epoch 0\n", "line 1: the epoch must be between 1"),
            ("epoch -3\n", "line 1: the epoch `-3` is not a whole number"),
            ("epoch 1 2\n", "line 1: expected `epoch <n>`"),
            ("epoch 99999999999999999999\n", "not a whole number"),
            ("epoch 1\nepoch 2\n", "line 2: a second `epoch` line"),
            ("s0000 mcapi-0\n", "no `epoch <n>` line"),
            ("", "no `epoch <n>` line"),
        ] {
            let e = error_of(text).to_string();
            assert!(e.contains(want), "{text:?}: {e}");
        }
        // Shard syntax and range.
        for (line, want) in [
            ("s0400 mcapi-0", "shard s0400 is out of range"),
            ("sffff mcapi-0", "out of range"),
            ("s3a7 mcapi-0", "`s3a7` is not a shard"),
            ("S0001 mcapi-0", "is not a shard"),
            ("s0001", "expected `<shard> <replica>`"),
            ("s0001 a b", "expected `<shard> <replica>`"),
            ("s0001 Mcapi", "only a-z, 0-9 and `-`"),
        ] {
            let e = error_of(&format!("epoch 1\n{line}\n")).to_string();
            assert!(e.starts_with("line 2: "), "{line}: {e}");
            assert!(e.contains(want), "{line}: {e}");
        }
        let long = format!("epoch 1\ns0000 {}\n", "a".repeat(100_000));
        assert!(error_of(&long).to_string().contains("at most 63"));
        // Huge.
        let huge = format!("epoch 1\n{}", "#".repeat(MAX_MAP_BYTES as usize));
        assert_eq!(error_of(&huge), MapError::TooLarge { max: MAX_MAP_BYTES });
        // Too many replicas (each shard its own name: 1024 > 256).
        let many: String = std::iter::once("epoch 1\n".to_string())
            .chain((0..SHARDS).map(|s| format!("{} r{s}\n", shard_key(s as u16))))
            .collect();
        assert_eq!(
            error_of(&many),
            MapError::TooManyReplicas { max: MAX_REPLICAS }
        );
    }

    #[test]
    fn comments_and_blank_lines_are_ignored() {
        let text = round_robin(2, 2)
            .to_text()
            .replace("s0001 mcapi-1", "  s0001   mcapi-1  # moved here\n\n");
        assert_eq!(ShardMap::parse(&text).expect("parses"), round_robin(2, 2));
    }

    #[test]
    fn reading_a_huge_file_stops_at_the_limit() {
        let dir = tempfile::tempdir().expect("dir");
        let path = dir.path().join("huge.map");
        std::fs::write(&path, vec![b'#'; 10 * 1024 * 1024]).expect("write");
        assert_eq!(
            ShardMap::read(&path),
            Err(MapError::TooLarge { max: MAX_MAP_BYTES })
        );
        std::fs::write(&path, [0xff, 0xfe]).expect("write");
        assert_eq!(ShardMap::read(&path), Err(MapError::NotText));
        let e = ShardMap::read(&dir.path().join("absent")).expect_err("missing");
        assert!(e.to_string().contains("absent"), "{e}");
    }
}
