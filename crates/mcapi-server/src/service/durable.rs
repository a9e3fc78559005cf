//! What the service keeps in the store (`mcapi_store`) and how it reads it
//! back: the creation record of a session, its snapshots and its log of
//! observations (docs/sessions.md, "Durability and recovery").
//!
//! A log entry holds what the observation changed, resolved: the state, the
//! stimulus, the raw curiosity signal, the action that was actually taken
//! (the advised one unless the client reported another) and the action the
//! reply advised. Replaying entries through `Agent::observe` (or
//! `CuriousAgent::observe`) therefore rebuilds Ξ, the visit counts, D, the
//! curiosity channel and the tick exactly, whatever the policy did in
//! between; the policy is recomputed once at the end.
//!
//! A continuous world's session (docs/algorithm.md §9) logs the f64
//! observation vector instead of a state, and whether the tick loop ran a
//! policy update since the previous entry (async mode): its agent is
//! rebuilt by replaying every entry, plans included, and the advised action
//! of each entry must come out again, bit for bit.
//!
//! Each entry also keeps the digest of the observation as the client sent
//! it, and each snapshot's history entry the digest and the whole reply
//! (its policy version), so an observation resent with its `seq` after a
//! restart, an eviction or a shard move is answered with the reply it got
//! first, and a different one with the same seq is refused
//! (docs/sessions.md, "Delivery guarantees").
//!
//! Snapshots and log entries are postcard, a format without field names, so
//! each record begins with a byte naming its encoding: [`RECORD_V5`] for
//! what this version writes, [`RECORD_V4`] for the records before sequence
//! numbers (no digest, and history entries without their policy version:
//! they cannot be replayed), [`RECORD_V3`] for the log entries before
//! continuous worlds (snapshots are the same as in V4), [`RECORD_V2`] for
//! records written under store format 2 (which the store tags when it
//! upgrades the file). All four decode.

use serde::{Deserialize, Serialize};

use mcapi_core::continuous::{
    ContinuousSnapshot, ContinuousSnapshotRef, ContinuousStateRef, GridSnapshot, GridSnapshotRef,
};
use mcapi_core::{
    AgentSnapshot, AgentSnapshotRef, CuriousSnapshot, LearnedSnapshot, LearnedSnapshotRef,
};
pub use mcapi_store::RECORD_V2;

use super::agent_config::EffectiveConfig;
use super::error::{DecodeError, DecodeFault, ServiceError};
use super::wire::TickCuriosity;

/// The encoding byte of the records this version writes.
pub const RECORD_V5: u8 = 5;

/// The encoding byte of records written before sequence numbers.
pub const RECORD_V4: u8 = 4;

/// The encoding byte of records written before continuous worlds.
pub const RECORD_V3: u8 = 3;

/// The creation record of a session (JSON: written once, read at start).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SessionRecord {
    /// The model as the client posted it (JSON text).
    pub model: String,
    /// The effective configuration, seed (and curiosity channel) included.
    pub config: EffectiveConfig,
    /// SHA-256 of the API key that created it, if keys were in force.
    pub owner: Option<[u8; 32]>,
    /// The group it was created in, if any (docs/groups.md): the groups
    /// are rebuilt at start from their members' records.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub group: Option<super::membership::GroupTag>,
}

/// One observation as logged.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LogEntry {
    /// The state observed (0 for a continuous world).
    pub state: u32,
    /// A continuous world's observation, as the agent took it.
    pub observation: Option<Vec<f64>>,
    /// A continuous world's session in async mode: the tick loop ran a
    /// policy update between the previous entry and this one.
    pub planned_before: bool,
    /// The stimulus as the client sent it (for a curious session the
    /// extrinsic part; absent on a session's first observation).
    pub stimulus: Option<Vec<f64>>,
    /// The action whose pair the stimulus updated (absent on the first).
    pub taken: Option<u32>,
    /// The action the reply advised.
    pub advised: u32,
    /// The LSTDQ error the reply's history entry recorded.
    pub lstdq_error: f64,
    /// The policy version the reply reported.
    pub policy_version: u64,
    /// The raw curiosity signal and its source, if the observation had one.
    pub signal: Option<(u32, Vec<f64>)>,
    /// `history::digest` of the observation as the client sent it (what
    /// `seq_conflict` compares); 0 in entries written before it was kept.
    pub digest: u64,
}

/// A [`LogEntry`] borrowed from the observation it logs: encoded exactly as
/// the owned entry is (the same fields in the same order, and postcard
/// writes a borrowed slice as it writes a vector), without copying the
/// observation's vectors first. What the request path encodes.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LogEntryRef<'a> {
    /// [`LogEntry::state`].
    pub state: u32,
    /// [`LogEntry::observation`].
    pub observation: Option<&'a [f64]>,
    /// [`LogEntry::planned_before`].
    pub planned_before: bool,
    /// [`LogEntry::stimulus`].
    pub stimulus: Option<&'a [f64]>,
    /// [`LogEntry::taken`].
    pub taken: Option<u32>,
    /// [`LogEntry::advised`].
    pub advised: u32,
    /// [`LogEntry::lstdq_error`].
    pub lstdq_error: f64,
    /// [`LogEntry::policy_version`].
    pub policy_version: u64,
    /// [`LogEntry::signal`].
    pub signal: Option<(u32, &'a [f64])>,
    /// [`LogEntry::digest`].
    pub digest: u64,
}

impl LogEntryRef<'_> {
    /// Encodes the entry as [`encode`] encodes a [`LogEntry`], into a
    /// buffer sized for it up front (one allocation, no regrowth: the
    /// version byte and the fixed fields take at most 55 bytes, a vector's
    /// length one or two more, each f64 8).
    pub fn encode(&self) -> Result<Vec<u8>, ServiceError> {
        let len = |x: Option<&[f64]>| x.map_or(0, <[f64]>::len);
        let floats = len(self.observation) + len(self.stimulus) + len(self.signal.map(|(_, x)| x));
        let mut out = Vec::with_capacity(64 + 8 * floats);
        self.encode_into(&mut out)?;
        Ok(out)
    }

    /// Encodes the entry as [`Self::encode`] does, at the end of `out` (a
    /// batch's buffer, which many entries share).
    pub fn encode_into(&self, out: &mut Vec<u8>) -> Result<(), ServiceError> {
        /// The end of a buffer borrowed, as postcard's writer.
        struct Tail<'b>(&'b mut Vec<u8>);
        impl Extend<u8> for Tail<'_> {
            fn extend<I: IntoIterator<Item = u8>>(&mut self, bytes: I) {
                self.0.extend(bytes);
            }
        }
        out.push(RECORD_V5);
        postcard::to_extend(self, Tail(out))
            .map(drop)
            .map_err(|e| ServiceError::Internal(format!("encoding a record: {e}")))
    }
}

/// A log entry as [`RECORD_V4`] wrote it (no digest).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct LogEntryV4 {
    state: u32,
    observation: Option<Vec<f64>>,
    planned_before: bool,
    stimulus: Option<Vec<f64>>,
    taken: Option<u32>,
    advised: u32,
    lstdq_error: f64,
    policy_version: u64,
    signal: Option<(u32, Vec<f64>)>,
}

impl From<LogEntryV4> for LogEntry {
    /// Its digest is unknown (0): a resent observation of it is not
    /// compared.
    fn from(e: LogEntryV4) -> Self {
        Self {
            state: e.state,
            observation: e.observation,
            planned_before: e.planned_before,
            stimulus: e.stimulus,
            taken: e.taken,
            advised: e.advised,
            lstdq_error: e.lstdq_error,
            policy_version: e.policy_version,
            signal: e.signal,
            digest: 0,
        }
    }
}

/// A log entry as [`RECORD_V3`] wrote it (no observation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct LogEntryV3 {
    state: u32,
    stimulus: Option<Vec<f64>>,
    taken: Option<u32>,
    advised: u32,
    lstdq_error: f64,
    policy_version: u64,
    signal: Option<(u32, Vec<f64>)>,
}

impl From<LogEntryV3> for LogEntry {
    /// An entry of a model with numbered states: no observation vector, and
    /// no policy update recorded between entries.
    fn from(e: LogEntryV3) -> Self {
        Self {
            state: e.state,
            observation: None,
            planned_before: false,
            stimulus: e.stimulus,
            taken: e.taken,
            advised: e.advised,
            lstdq_error: e.lstdq_error,
            policy_version: e.policy_version,
            signal: e.signal,
            digest: 0,
        }
    }
}

/// A log entry as format 2 wrote it (no signal).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct LogEntryV2 {
    state: u32,
    stimulus: Option<Vec<f64>>,
    taken: Option<u32>,
    advised: u32,
    lstdq_error: f64,
    policy_version: u64,
}

/// The learner of a snapshot.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[expect(
    clippy::large_enum_variant,
    reason = "built once per snapshot write or recovery"
)]
pub enum LearnerSnapshot {
    /// An MCA-PI agent.
    Plain(AgentSnapshot),
    /// An agent with a curiosity channel.
    Curious(Box<CuriousSnapshot>),
    /// An agent that learns its transitions (docs/algorithm.md §8): its
    /// snapshot and the counts N(s, a, s′), from which P̂ is rebuilt. Last:
    /// postcard numbers variants by position, so stored snapshots of the
    /// variants above still decode.
    Learned(Box<LearnedRecord>),
    /// A continuous world's agent (docs/algorithm.md §9.7). After the
    /// variants above, for the same reason.
    Continuous(Box<ContinuousRecord>),
    /// A continuous world's agent on a grid (docs/algorithm.md §9.8).
    /// Last, for the same reason.
    ContinuousGrid(Box<ContinuousRecord<GridSnapshot>>),
}

impl LearnerSnapshot {
    /// The observations of a continuous world's history ring, if this is
    /// a continuous world's agent.
    pub fn history_observations_mut(&mut self) -> Option<&mut Vec<Option<Vec<f64>>>> {
        match self {
            Self::Continuous(c) => Some(&mut c.history_observations),
            Self::ContinuousGrid(c) => Some(&mut c.history_observations),
            Self::Plain(_) | Self::Curious(_) | Self::Learned(_) => None,
        }
    }
}

/// What a session writes as its learner ([`super::learner::Learner::snapshot`]):
/// the bytes of a [`LearnerSnapshot`], with the agent borrowed rather than
/// copied: a continuous world's ([`ContinuousStateRef`]; its A⁻¹ alone is
/// 32 MiB at k|A| = 2048), a plain agent's ([`AgentSnapshotRef`]: Ξ, π, Q
/// and R, megabytes in a world of 100,000 states) and a learned model's
/// with its counts ([`LearnedSnapshotRef`]: a vector per pair). The
/// variants are [`LearnerSnapshot`]'s, in its order and under its name; a
/// curious agent's (small worlds) is owned.
#[derive(Debug, Serialize)]
#[serde(rename = "LearnerSnapshot")]
pub enum LearnerSnapshotRef<'a> {
    /// [`LearnerSnapshot::Plain`].
    Plain(AgentSnapshotRef<'a>),
    /// [`LearnerSnapshot::Curious`].
    Curious(Box<CuriousSnapshot>),
    /// [`LearnerSnapshot::Learned`].
    Learned(Box<LearnedRecordRef<'a>>),
    /// [`LearnerSnapshot::Continuous`].
    Continuous(ContinuousRecord<ContinuousSnapshotRef<'a>>),
    /// [`LearnerSnapshot::ContinuousGrid`].
    ContinuousGrid(ContinuousRecord<GridSnapshotRef<'a>>),
}

impl<'a> LearnerSnapshotRef<'a> {
    /// A continuous world's agent, borrowed, with no ring observations yet
    /// (the session adds them).
    pub fn continuous(agent: ContinuousStateRef<'a>) -> Self {
        match agent {
            ContinuousStateRef::Features(agent) => Self::Continuous(ContinuousRecord {
                agent,
                history_observations: Vec::new(),
            }),
            ContinuousStateRef::Grid(agent) => Self::ContinuousGrid(ContinuousRecord {
                agent,
                history_observations: Vec::new(),
            }),
        }
    }

    /// As [`LearnerSnapshot::history_observations_mut`].
    pub fn history_observations_mut(&mut self) -> Option<&mut Vec<Option<Vec<f64>>>> {
        match self {
            Self::Continuous(c) => Some(&mut c.history_observations),
            Self::ContinuousGrid(c) => Some(&mut c.history_observations),
            Self::Plain(_) | Self::Curious(_) | Self::Learned(_) => None,
        }
    }
}

/// A continuous world's agent as a snapshot keeps it: on features
/// ([`ContinuousSnapshot`]) or on a grid ([`GridSnapshot`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContinuousRecord<A = ContinuousSnapshot> {
    /// The agent.
    pub agent: A,
    /// The observation of each tick of the history ring, oldest first
    /// ([`TickRecord`] has no field for it).
    pub history_observations: Vec<Option<Vec<f64>>>,
}

/// A learned agent as a snapshot keeps it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LearnedRecord {
    /// The agent and its counts.
    pub agent: LearnedSnapshot,
    /// The known fraction after each tick of the history ring, oldest
    /// first ([`TickRecord`] has no field for it; its layout is fixed by
    /// the record version).
    pub history_known: Vec<Option<f64>>,
}

/// [`LearnedRecord`], its agent borrowed; serialises to its bytes.
#[derive(Debug, Serialize)]
#[serde(rename = "LearnedRecord")]
pub struct LearnedRecordRef<'a> {
    /// The agent and its counts.
    pub agent: LearnedSnapshotRef<'a>,
    /// As [`LearnedRecord::history_known`].
    pub history_known: Vec<Option<f64>>,
}

/// A session snapshot.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SnapshotRecord {
    /// The learner.
    pub learner: LearnerSnapshot,
    /// The history ring, oldest first.
    pub history: Vec<TickRecord>,
}

/// A session snapshot as a session writes it: the bytes of a
/// [`SnapshotRecord`], its learner borrowed ([`LearnerSnapshotRef`]).
#[derive(Debug, Serialize)]
#[serde(rename = "SnapshotRecord")]
pub struct SnapshotRecordRef<'a> {
    /// The learner.
    pub learner: LearnerSnapshotRef<'a>,
    /// The history ring, oldest first.
    pub history: Vec<TickRecord>,
}

/// A snapshot as [`RECORD_V3`] and [`RECORD_V4`] wrote it.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct SnapshotRecordV4 {
    learner: LearnerSnapshot,
    history: Vec<TickRecordV4>,
}

/// A snapshot as format 2 wrote it.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct SnapshotRecordV2 {
    agent: AgentSnapshot,
    history: Vec<TickRecordV2>,
}

/// One history entry as a snapshot keeps it (the API type may change
/// shape; this one only under a new record version).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TickRecord {
    pub(super) tick: u64,
    pub(super) state: usize,
    pub(super) action: usize,
    pub(super) drive: Vec<f64>,
    pub(super) reward: f64,
    pub(super) lstdq_error: f64,
    pub(super) stimulus: Option<Vec<f64>>,
    pub(super) curiosity: Option<TickCuriosity>,
    /// The reply's policy version and the observation's digest; absent for
    /// entries restored from a [`RECORD_V4`] snapshot (not replayable).
    pub(super) reply: Option<(u64, u64)>,
    /// The entry of the session's first observation (not a tick).
    pub(super) first: bool,
}

/// A history entry as [`RECORD_V3`] and [`RECORD_V4`] kept it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct TickRecordV4 {
    tick: u64,
    state: usize,
    action: usize,
    drive: Vec<f64>,
    reward: f64,
    lstdq_error: f64,
    stimulus: Option<Vec<f64>>,
    curiosity: Option<TickCuriosity>,
}

/// A history entry as format 2 kept it (no stimulus).
#[derive(Debug, Clone, Serialize, Deserialize)]
struct TickRecordV2 {
    tick: u64,
    state: usize,
    action: usize,
    drive: Vec<f64>,
    reward: f64,
    lstdq_error: f64,
}

/// Encodes a log entry or snapshot: [`RECORD_V5`], then postcard.
///
/// The value is sized first (a pass that only counts), so that it is
/// written once into a buffer of its size: grown by doubling, a snapshot
/// of tens of megabytes was copied at each growth and its buffer could
/// reserve twice its size.
pub fn encode<T: Serialize>(value: &T) -> Result<Vec<u8>, ServiceError> {
    let failed = |e: postcard::Error| ServiceError::Internal(format!("encoding a record: {e}"));
    let len = postcard::serialize_with_flavor(value, postcard::ser_flavors::Size::default())
        .map_err(failed)?;
    let mut out = Vec::with_capacity(1 + len);
    out.push(RECORD_V5);
    let out = postcard::to_extend(value, out).map_err(failed)?;
    debug_assert_eq!(out.len(), 1 + len, "the sizing pass and the encoding agree");
    Ok(out)
}

fn split<'a>(bytes: &'a [u8], what: &str) -> Result<(u8, &'a [u8]), DecodeError> {
    let fault = match bytes.split_first() {
        Some((&v, rest)) if (RECORD_V2..=RECORD_V5).contains(&v) => return Ok((v, rest)),
        Some((&v, _)) => DecodeFault::Version(v),
        None => DecodeFault::Empty,
    };
    Err(DecodeError {
        what: what.to_string(),
        fault,
    })
}

fn postcard_decode<'a, T: Deserialize<'a>>(bytes: &'a [u8], what: &str) -> Result<T, DecodeError> {
    postcard::from_bytes(bytes).map_err(|e| DecodeError {
        what: what.to_string(),
        fault: e.into(),
    })
}

/// Decodes a log entry of either record version.
pub fn decode_entry(bytes: &[u8], what: &str) -> Result<LogEntry, DecodeError> {
    match split(bytes, what)? {
        (RECORD_V2, rest) => {
            let e: LogEntryV2 = postcard_decode(rest, what)?;
            Ok(LogEntryV3 {
                state: e.state,
                stimulus: e.stimulus,
                taken: e.taken,
                advised: e.advised,
                lstdq_error: e.lstdq_error,
                policy_version: e.policy_version,
                signal: None,
            }
            .into())
        }
        (RECORD_V3, rest) => postcard_decode::<LogEntryV3>(rest, what).map(LogEntry::from),
        (RECORD_V4, rest) => postcard_decode::<LogEntryV4>(rest, what).map(LogEntry::from),
        (_, rest) => postcard_decode(rest, what),
    }
}

/// Decodes a snapshot of either record version.
pub fn decode_snapshot(bytes: &[u8], what: &str) -> Result<SnapshotRecord, DecodeError> {
    match split(bytes, what)? {
        (RECORD_V2, rest) => {
            let s: SnapshotRecordV2 = postcard_decode(rest, what)?;
            Ok(SnapshotRecord {
                learner: LearnerSnapshot::Plain(s.agent),
                history: s
                    .history
                    .into_iter()
                    .map(|t| TickRecord {
                        tick: t.tick,
                        state: t.state,
                        action: t.action,
                        drive: t.drive,
                        reward: t.reward,
                        lstdq_error: t.lstdq_error,
                        stimulus: None,
                        curiosity: None,
                        reply: None,
                        first: false,
                    })
                    .collect(),
            })
        }
        (RECORD_V3 | RECORD_V4, rest) => {
            let s: SnapshotRecordV4 = postcard_decode(rest, what)?;
            Ok(SnapshotRecord {
                learner: s.learner,
                history: s
                    .history
                    .into_iter()
                    .map(|t| TickRecord {
                        tick: t.tick,
                        state: t.state,
                        action: t.action,
                        drive: t.drive,
                        reward: t.reward,
                        lstdq_error: t.lstdq_error,
                        stimulus: t.stimulus,
                        curiosity: t.curiosity,
                        reply: None,
                        first: false,
                    })
                    .collect(),
            })
        }
        (_, rest) => postcard_decode(rest, what),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::history::RingTick;

    fn entry(signal: Option<(u32, Vec<f64>)>) -> LogEntry {
        LogEntry {
            state: 7,
            observation: None,
            planned_before: false,
            stimulus: Some(vec![0.1 + 0.2, -1e-300, 6.0]),
            taken: Some(2),
            advised: 1,
            lstdq_error: 0.25,
            policy_version: 9,
            signal,
            digest: 0x1234_5678_9abc_def0,
        }
    }

    #[test]
    fn log_entries_round_trip_exactly() {
        for e in [entry(None), entry(Some((1, vec![0.5, -2.0])))] {
            let bytes = encode(&e).expect("encode");
            assert_eq!(bytes[0], RECORD_V5);
            assert_eq!(decode_entry(&bytes, "entry").expect("decode"), e);
            assert!(decode_entry(&bytes[..bytes.len() - 3], "entry").is_err());
        }
        assert!(encode(&entry(None)).expect("encode").len() < 56);
        // A continuous world's entry keeps its f64 observation bit for bit.
        let continuous = LogEntry {
            state: 0,
            observation: Some(vec![0.1 + 0.2, -0.0, f64::MIN_POSITIVE, 1e308]),
            planned_before: true,
            ..entry(None)
        };
        let back = decode_entry(&encode(&continuous).expect("encode"), "entry").expect("decode");
        let bits = |e: &LogEntry| {
            e.observation
                .iter()
                .flatten()
                .map(|x| x.to_bits())
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(&back), bits(&continuous));
        assert_eq!(back, continuous);
    }

    /// The borrowed entry the request path encodes is byte for byte the
    /// owned one, whatever its optional fields hold.
    #[test]
    fn borrowed_entries_encode_as_owned_ones() {
        let signals = [None, Some((1, vec![0.5, -2.0]))];
        let observations = [None, Some(vec![0.1 + 0.2, -0.0, 1e308])];
        for (signal, observation) in signals.iter().zip(&observations) {
            for stimulus in [None, Some(vec![6.0, f64::MIN_POSITIVE])] {
                let e = LogEntry {
                    observation: observation.clone(),
                    stimulus,
                    signal: signal.clone(),
                    ..entry(None)
                };
                let borrowed = LogEntryRef {
                    state: e.state,
                    observation: e.observation.as_deref(),
                    planned_before: e.planned_before,
                    stimulus: e.stimulus.as_deref(),
                    taken: e.taken,
                    advised: e.advised,
                    lstdq_error: e.lstdq_error,
                    policy_version: e.policy_version,
                    signal: e.signal.as_ref().map(|(s, x)| (*s, x.as_slice())),
                    digest: e.digest,
                };
                let bytes = borrowed.encode().expect("encode");
                assert_eq!(bytes, encode(&e).expect("encode"));
                assert!(bytes.len() <= bytes.capacity() && bytes.capacity() <= 64 + 8 * 9);
                assert_eq!(decode_entry(&bytes, "entry").expect("decode"), e);
            }
        }
        // The largest fixed fields still fit the buffer's 64 bytes.
        let widest = LogEntryRef {
            state: u32::MAX,
            observation: None,
            planned_before: true,
            stimulus: None,
            taken: Some(u32::MAX),
            advised: u32::MAX,
            lstdq_error: f64::MAX,
            policy_version: u64::MAX,
            signal: Some((u32::MAX, &[])),
            digest: u64::MAX,
        };
        let bytes = widest.encode().expect("encode");
        assert!(bytes.len() <= 64, "{}", bytes.len());
    }

    #[test]
    fn entries_before_sequence_numbers_decode_without_a_digest() {
        let e = entry(Some((1, vec![0.5])));
        let old = LogEntryV4 {
            state: e.state,
            observation: e.observation.clone(),
            planned_before: e.planned_before,
            stimulus: e.stimulus.clone(),
            taken: e.taken,
            advised: e.advised,
            lstdq_error: e.lstdq_error,
            policy_version: e.policy_version,
            signal: e.signal.clone(),
        };
        let bytes = postcard::to_extend(&old, vec![RECORD_V4]).expect("encode");
        assert_eq!(
            decode_entry(&bytes, "entry").expect("decode"),
            LogEntry { digest: 0, ..e }
        );
    }

    #[test]
    fn entries_before_continuous_worlds_decode() {
        let old = LogEntryV3 {
            state: 7,
            stimulus: Some(vec![0.1 + 0.2, -1e-300, 6.0]),
            taken: Some(2),
            advised: 1,
            lstdq_error: 0.25,
            policy_version: 9,
            signal: Some((1, vec![0.5])),
        };
        let bytes = postcard::to_extend(&old, vec![RECORD_V3]).expect("encode");
        assert_eq!(
            decode_entry(&bytes, "entry").expect("decode"),
            LogEntry {
                digest: 0,
                ..entry(Some((1, vec![0.5])))
            }
        );
    }

    #[test]
    fn format_2_entries_decode_and_unknown_versions_are_refused() {
        let old = LogEntryV2 {
            state: 7,
            stimulus: Some(vec![0.1 + 0.2, -1e-300, 6.0]),
            taken: Some(2),
            advised: 1,
            lstdq_error: 0.25,
            policy_version: 9,
        };
        let mut bytes = vec![RECORD_V2];
        bytes.extend(postcard::to_stdvec(&old).expect("encode"));
        assert_eq!(
            decode_entry(&bytes, "entry").expect("decode"),
            LogEntry {
                digest: 0,
                ..entry(None)
            }
        );
        bytes[0] = 9;
        let err = decode_entry(&bytes, "entry").expect_err("version 9");
        assert!(
            err.to_string().contains("unknown record version 9"),
            "{err}"
        );
        assert!(decode_entry(&[], "entry").is_err());
    }

    #[test]
    fn format_2_snapshots_decode_with_their_history() {
        use std::sync::Arc;

        use mcapi_core::{Agent, AgentParams, Basis, Observation, PlanningModel};
        let preset = mcapi_core::model::hallway();
        let params = AgentParams::default().check(2, 5).expect("params");
        let ctx = Arc::new(PlanningModel::new(preset.model, Basis::Indicator));
        let mut agent = Agent::new(ctx, params);
        agent.step(&Observation::first(3)).expect("first");
        agent.step(&Observation::new(4, &[1.0, 0.0])).expect("step");
        let old = SnapshotRecordV2 {
            agent: agent.snapshot(),
            history: vec![TickRecordV2 {
                tick: 1,
                state: 4,
                action: 2,
                drive: vec![0.6, 0.8],
                reward: 0.5,
                lstdq_error: 0.125,
            }],
        };
        let mut bytes = vec![RECORD_V2];
        bytes.extend(postcard::to_stdvec(&old).expect("encode"));
        let snap = decode_snapshot(&bytes, "snapshot").expect("decode");
        match snap.learner {
            LearnerSnapshot::Plain(a) => assert_eq!(a, agent.snapshot()),
            LearnerSnapshot::Curious(_)
            | LearnerSnapshot::Learned(_)
            | LearnerSnapshot::Continuous(_)
            | LearnerSnapshot::ContinuousGrid(_) => {
                panic!("a format-2 snapshot is a plain agent's")
            }
        }
        let h: Vec<_> = snap
            .history
            .iter()
            .map(|t| RingTick::from(t).entry())
            .collect();
        assert_eq!(h.len(), 1);
        assert_eq!((h[0].tick, h[0].reward), (1, 0.5));
        assert_eq!(h[0].stimulus, None, "format 2 kept no stimulus");
        // The same snapshot as this version writes it.
        let new = SnapshotRecord {
            learner: LearnerSnapshot::Plain(agent.snapshot()),
            history: vec![TickRecord::from(&RingTick::from(&snap.history[0]))],
        };
        let bytes = encode(&new).expect("encode");
        let back = decode_snapshot(&bytes, "snapshot").expect("decode");
        assert_eq!(back.history, new.history);
    }

    /// A snapshot before sequence numbers decodes, its history entries
    /// without a reply (they cannot be replayed); this version's keeps the
    /// reply, the digest and the first observation's entry.
    #[test]
    fn v4_snapshots_decode_and_v5_keeps_the_reply() {
        use std::sync::Arc;

        use mcapi_core::{Agent, AgentParams, Basis, PlanningModel};
        let preset = mcapi_core::model::hallway();
        let params = AgentParams::default().check(2, 5).expect("params");
        let ctx = Arc::new(PlanningModel::new(preset.model, Basis::Indicator));
        let agent = Agent::new(ctx, params);
        let tick = TickRecordV4 {
            tick: 1,
            state: 4,
            action: 2,
            drive: vec![0.6, 0.8],
            reward: 0.5,
            lstdq_error: 0.125,
            stimulus: Some(vec![1.0, 0.0]),
            curiosity: None,
        };
        let old = SnapshotRecordV4 {
            learner: LearnerSnapshot::Plain(agent.snapshot()),
            history: vec![tick.clone()],
        };
        let bytes = postcard::to_extend(&old, vec![RECORD_V4]).expect("encode");
        let snap = decode_snapshot(&bytes, "snapshot").expect("decode");
        assert_eq!(snap.history[0].reply, None);
        assert_eq!(RingTick::from(&snap.history[0]).replay(&[]), None);
        let actions: Vec<String> = ["left", "right", "stay"].map(String::from).to_vec();
        let first = RingTick::new(0, 3, 1, &[0.6, 0.8], None, None, 0.0, 0.0, None, None)
            .with_reply(1, 77)
            .as_first();
        let new = SnapshotRecord {
            learner: LearnerSnapshot::Plain(agent.snapshot()),
            history: vec![TickRecord::from(&first)],
        };
        let back = decode_snapshot(&encode(&new).expect("encode"), "snapshot").expect("decode");
        assert_eq!(back.history, new.history);
        let ring = RingTick::from(&back.history[0]);
        assert_eq!(ring, first);
        assert!(ring.is_first() && ring.matches(77) && !ring.matches(78));
        let step = ring.replay(&actions).expect("replayable");
        assert_eq!(
            (step.tick, step.action.as_str(), step.policy_version),
            (0, "right", 1)
        );
        assert!(step.replayed);
    }

    /// The learned variant is appended: the tags of the stored variants do
    /// not move (postcard numbers variants by position), and a learned
    /// agent's snapshot, counts included, round-trips exactly.
    #[test]
    fn learned_snapshots_round_trip_and_old_tags_stay() {
        use std::sync::Arc;

        use mcapi_core::{Agent, AgentParams, Basis, LearnedParams, Observation, PlanningModel};
        let preset = mcapi_core::model::hallway();
        let params = AgentParams::default().check(2, 5).expect("params");
        let ctx = Arc::new(PlanningModel::new(preset.model, Basis::Indicator));
        let plain = Agent::new(Arc::clone(&ctx), params.clone());
        let bytes = encode(&LearnerSnapshot::Plain(plain.snapshot())).expect("encode");
        assert_eq!(bytes[1], 0, "Plain keeps tag 0");
        assert!(
            encode(&LearnerSnapshotRef::Plain(plain.snapshot_ref())).expect("encode") == bytes,
            "what a session writes for a plain agent is the owned record's bytes"
        );
        let learned = LearnedParams::default().check().expect("learned params");
        let mut agent = Agent::new_learned(ctx, params, learned).expect("learned agent");
        agent.step(&Observation::first(3)).expect("first");
        for s in [4, 5, 5, 6] {
            agent.step(&Observation::new(s, &[1.0, 0.0])).expect("step");
        }
        let snap = LearnedRecord {
            agent: agent.learned_snapshot().expect("a learned agent"),
            history_known: vec![Some(0.25), None],
        };
        let bytes = encode(&LearnerSnapshot::Learned(Box::new(snap.clone()))).expect("encode");
        assert_eq!(bytes[1], 2, "Learned is the third variant");
        let borrowed = LearnerSnapshotRef::Learned(Box::new(LearnedRecordRef {
            agent: agent.learned_snapshot_ref().expect("a learned agent"),
            history_known: snap.history_known.clone(),
        }));
        assert!(
            encode(&borrowed).expect("encode") == bytes,
            "what a session writes for a learned agent is the owned record's bytes"
        );
        let back: LearnerSnapshot = postcard::from_bytes(&bytes[1..]).expect("decode");
        match back {
            LearnerSnapshot::Learned(s) => assert_eq!(*s, snap),
            LearnerSnapshot::Plain(_)
            | LearnerSnapshot::Curious(_)
            | LearnerSnapshot::Continuous(_)
            | LearnerSnapshot::ContinuousGrid(_) => {
                panic!("decoded as another variant")
            }
        }
    }

    /// An agent on the unit square with two actions and one stimulus, on
    /// `basis`, after four observations.
    fn stepped_continuous_agent(
        basis: serde_json::Value,
    ) -> mcapi_core::continuous::ContinuousAgent {
        let spec: mcapi_core::continuous::ContinuousSpec =
            serde_json::from_value(serde_json::json!({
                "observation_space": {"low": [0, 0], "high": [1, 1]},
                "actions": ["north", "south"],
                "stimuli": ["food"],
                "basis": basis,
            }))
            .expect("spec");
        let params = mcapi_core::AgentParams::default()
            .check(1, 7)
            .expect("params");
        let mut agent =
            mcapi_core::continuous::ContinuousAgent::new(spec.build().expect("model"), params);
        for (i, x) in [0.1, 0.2, 0.3, 0.2].into_iter().enumerate() {
            agent
                .step(&mcapi_core::continuous::ContinuousObservation {
                    observation: &[x, 0.5],
                    stimulus: (i > 0).then_some(&[1.0][..]),
                    action_taken: None,
                })
                .expect("step");
        }
        agent
    }

    /// What a session writes for `agent` with the ring's `observations`
    /// (its learner borrowed, [`LearnerSnapshotRef`]) is `bytes`, the owned
    /// record's encoding.
    fn assert_written_as(
        agent: &mcapi_core::continuous::ContinuousAgent,
        observations: &[Option<Vec<f64>>],
        bytes: &[u8],
    ) {
        let mut borrowed = LearnerSnapshotRef::continuous(agent.snapshot_ref());
        *borrowed
            .history_observations_mut()
            .expect("a continuous record") = observations.to_vec();
        assert!(
            encode(&borrowed).expect("encode") == bytes,
            "what a session writes is the owned record's bytes"
        );
    }

    /// A continuous world's snapshot is the fourth variant, after those
    /// that stores already hold, and keeps the ring's observations.
    #[test]
    fn continuous_snapshots_decode_as_written() {
        let agent = stepped_continuous_agent(serde_json::json!({"kind": "fourier", "order": 2}));
        let record = ContinuousRecord {
            agent: agent.snapshot().features().expect("a feature basis"),
            history_observations: vec![Some(vec![0.2, 0.5]), None],
        };
        let bytes = encode(&LearnerSnapshot::Continuous(Box::new(record.clone()))).expect("encode");
        assert_eq!(bytes[1], 3, "Continuous is the fourth variant");
        assert_written_as(&agent, &record.history_observations, &bytes);
        match postcard::from_bytes::<LearnerSnapshot>(&bytes[1..]).expect("decode") {
            LearnerSnapshot::Continuous(back) => {
                assert_eq!(back.history_observations, record.history_observations);
                // Through the store, the agent's scratch buffers come back empty.
                let again = encode(&LearnerSnapshot::Continuous(back)).expect("encode");
                assert_eq!(again.len(), bytes.len());
            }
            LearnerSnapshot::Plain(_)
            | LearnerSnapshot::Curious(_)
            | LearnerSnapshot::Learned(_)
            | LearnerSnapshot::ContinuousGrid(_) => {
                panic!("decoded as another variant")
            }
        }
    }

    /// A grid agent's snapshot is a variant of its own, after the others,
    /// so that the snapshots stored before it still decode.
    #[test]
    fn a_grid_snapshot_round_trips_as_the_last_variant() {
        let agent =
            stepped_continuous_agent(serde_json::json!({"kind": "grid", "cells_per_dim": 8}));
        let mcapi_core::continuous::ContinuousState::Grid(grid) = agent.snapshot() else {
            panic!("a grid agent's snapshot is a grid snapshot");
        };
        let record = ContinuousRecord {
            agent: *grid,
            history_observations: vec![Some(vec![0.2, 0.5])],
        };
        let bytes =
            encode(&LearnerSnapshot::ContinuousGrid(Box::new(record.clone()))).expect("encode");
        assert_eq!(bytes[1], 4, "ContinuousGrid is the fifth variant");
        assert_written_as(&agent, &record.history_observations, &bytes);
        let back = postcard::from_bytes::<LearnerSnapshot>(&bytes[1..]).expect("decode");
        let again = encode(&back).expect("encode");
        assert_eq!(again, bytes);
    }
}
