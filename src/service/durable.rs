//! What the service keeps in the store (`crate::store`) and how it reads it
//! back: the creation record of a session, its snapshots and its log of
//! observations (DESIGN.md, "Durability").
//!
//! A log entry holds what the observation changed, resolved: the state, the
//! stimulus, the action that was actually taken (the advised one unless the
//! client reported another) and the action the reply advised. Replaying
//! entries through `Agent::observe` therefore rebuilds Ξ, the visit counts,
//! D and the tick exactly, whatever the policy did in between; the policy is
//! recomputed once at the end.

use serde::{Deserialize, Serialize};

use crate::algo::AgentSnapshot;

use super::error::ServiceError;
use super::session::HistoryEntry;
use super::spec::EffectiveConfig;

/// The creation record of a session (JSON: written once, read at start).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SessionRecord {
    /// The model as the client posted it (JSON text).
    pub model: String,
    /// The effective configuration, seed included.
    pub config: EffectiveConfig,
    /// SHA-256 of the API key that created it, if keys were in force.
    pub owner: Option<[u8; 32]>,
}

/// One observation as logged.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LogEntry {
    /// The state observed.
    pub state: u32,
    /// The stimulus (absent on a session's first observation).
    pub stimulus: Option<Vec<f64>>,
    /// The action whose pair the stimulus updated (absent on the first).
    pub taken: Option<u32>,
    /// The action the reply advised.
    pub advised: u32,
    /// The LSTDQ error the reply's history entry recorded.
    pub lstdq_error: f64,
    /// The policy version the reply reported.
    pub policy_version: u64,
}

/// A session snapshot.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SnapshotRecord {
    /// The agent.
    pub agent: AgentSnapshot,
    /// The history ring, oldest first.
    pub history: Vec<HistoryEntry>,
}

/// Binary encoding of log entries and snapshots.
pub fn encode<T: Serialize>(value: &T) -> Result<Vec<u8>, ServiceError> {
    postcard::to_stdvec(value)
        .map_err(|e| ServiceError::Internal(format!("encoding a record: {e}")))
}

/// Decodes a log entry or snapshot; `what` names it in the error.
pub fn decode<'a, T: Deserialize<'a>>(bytes: &'a [u8], what: &str) -> Result<T, String> {
    postcard::from_bytes(bytes).map_err(|e| format!("{what} does not decode: {e}"))
}

/// Applies one logged observation to a recovering agent and its history
/// ring: Ξ, visits, D and the tick change exactly as they did live.
pub fn replay(
    agent: &mut crate::algo::Agent,
    history: &mut std::collections::VecDeque<HistoryEntry>,
    history_cap: usize,
    entry: &LogEntry,
) -> Result<(), String> {
    let obs = crate::algo::Observation {
        state: entry.state as usize,
        stimulus: entry.stimulus.as_deref(),
        action_taken: entry.taken.map(|a| a as usize),
    };
    let out = agent.observe(&obs).map_err(|e| e.to_string())?;
    agent
        .set_advised_action(entry.advised as usize)
        .map_err(|e| e.to_string())?;
    if history_cap > 0 && entry.stimulus.is_some() {
        if history.len() >= history_cap {
            history.pop_front();
        }
        history.push_back(HistoryEntry {
            tick: out.tick,
            state: obs.state,
            action: entry.advised as usize,
            drive: agent.drive().vector().to_vec(),
            reward: out.reward,
            lstdq_error: entry.lstdq_error,
        });
    }
    agent.resume_policy_version(entry.policy_version);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_entries_round_trip_exactly() {
        let e = LogEntry {
            state: 7,
            stimulus: Some(vec![0.1 + 0.2, -1e-300, 6.0]),
            taken: Some(2),
            advised: 1,
            lstdq_error: 0.25,
            policy_version: 9,
        };
        let bytes = encode(&e).expect("encode");
        assert!(bytes.len() < 48, "{} bytes", bytes.len());
        assert_eq!(decode::<LogEntry>(&bytes, "entry").expect("decode"), e);
        assert!(decode::<LogEntry>(&bytes[..bytes.len() - 3], "entry").is_err());
    }
}
