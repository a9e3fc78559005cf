//! A session's value tables (`GET /v1/sessions/{id}/values`, gRPC
//! `GetValues`): which tables a caller asks for ([`ValueSelection`]), a
//! bound on their size checked before anything is built, and the tables
//! themselves (V, Q, the greedy policy, R and Ξ), read under the session's
//! lock.

use super::error::ServiceError;
use super::session::Session;
use super::wire::{CuriosityInfo, ModelSummary, Values};

/// Which value tables to return.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ValueSelection {
    /// V(s).
    pub v: bool,
    /// Q(s, a).
    pub q: bool,
    /// Greedy action per state.
    pub policy: bool,
    /// R(s, a).
    pub r: bool,
    /// Ξ(s, a).
    pub xi: bool,
}

impl ValueSelection {
    /// Parses `v,q,policy,r,xi` (any subset); empty means `v,policy`.
    pub fn parse(include: Option<&str>) -> Result<Self, ServiceError> {
        let Some(include) = include.filter(|s| !s.trim().is_empty()) else {
            return Ok(Self {
                v: true,
                policy: true,
                ..Self::default()
            });
        };
        let mut sel = Self::default();
        for part in include.split(',').map(str::trim) {
            match part {
                "v" => sel.v = true,
                "q" => sel.q = true,
                "policy" => sel.policy = true,
                "r" => sel.r = true,
                "xi" => sel.xi = true,
                "all" => {
                    sel = Self {
                        v: true,
                        q: true,
                        policy: true,
                        r: true,
                        xi: true,
                    }
                }
                other => {
                    return Err(ServiceError::field(
                        "include",
                        format!("unknown table `{other}` (choose from v, q, policy, r, xi, all)"),
                    ));
                }
            }
        }
        Ok(sel)
    }
}

impl ValueSelection {
    /// Refuses value tables whose JSON would exceed `limit`
    /// ([`Limits::max_response_bytes`](super::limits::Limits::max_response_bytes)),
    /// before anything is built (about 24 bytes per number, and per name
    /// for `policy`).
    pub fn check_size(self, model: &ModelSummary, limit: usize) -> Result<(), ServiceError> {
        let sel = self;
        let m = model;
        let cells = m.states.saturating_mul(m.actions.len());
        let longest = m.actions.iter().map(String::len).max().unwrap_or(0);
        let mut bytes = 0usize;
        if sel.v {
            bytes = bytes.saturating_add(m.states.saturating_mul(24));
        }
        if sel.policy {
            bytes = bytes.saturating_add(m.states.saturating_mul(longest + 4));
        }
        for table in [sel.q, sel.r] {
            if table {
                bytes = bytes.saturating_add(cells.saturating_mul(24));
            }
        }
        if sel.xi {
            bytes = bytes.saturating_add(cells.saturating_mul(m.stimuli.len() * 24 + 4));
        }
        if bytes > limit {
            return Err(ServiceError::LimitExceeded(format!(
                "the value tables asked for (`include`) would take about {bytes} bytes; the limit of one response is {} (--max-response-bytes): ask for fewer tables",
                limit
            )));
        }
        Ok(())
    }
}

/// The selected tables of a session, read under its lock.
pub fn tables(session: &Session, sel: ValueSelection) -> Values {
    let st = session.state.lock();
    let agent = st.learner.agent();
    let model = agent.planning_model().model();
    let per_pair = |f: &dyn Fn(usize) -> f64| -> Vec<Vec<Option<f64>>> {
        (0..model.states())
            .map(|s| {
                (0..model.n_actions())
                    .map(|a| model.pair(s, a).map(f))
                    .collect()
            })
            .collect()
    };
    let planner = agent.planner();
    Values {
        tick: agent.tick(),
        policy_version: agent.policy_version(),
        v: sel
            .v
            .then(|| (0..model.states()).map(|s| planner.value(s)).collect()),
        q: sel.q.then(|| per_pair(&|p| planner.q()[p])),
        policy: sel.policy.then(|| {
            (0..model.states())
                .map(|s| model.actions()[agent.greedy_action(s)].clone())
                .collect()
        }),
        r: sel.r.then(|| per_pair(&|p| agent.rewards()[p])),
        xi: sel.xi.then(|| {
            (0..model.states())
                .map(|s| {
                    (0..model.n_actions())
                        .map(|a| model.pair(s, a).map(|p| agent.stimulus().row(p).to_vec()))
                        .collect()
                })
                .collect()
        }),
        curiosity: st.learner.curious().map(CuriosityInfo::of),
        known_fraction: agent.learned().map(|l| l.known_fraction()),
    }
}
