//! A session's value tables (`GET /v1/sessions/{id}/values`, gRPC
//! `GetValues`): which tables a caller asks for ([`ValueSelection`]), a
//! bound on their size checked before anything is built, and the tables
//! themselves (V, Q, the greedy policy, R and Ξ), read under the session's
//! lock.

use super::error::ServiceError;
use super::session::Session;
use mcapi_core::continuous::{ContinuousAgent, ObservationSpace};

use super::wire::{CuriosityInfo, HistoryEntry, ModelSummary, Values};

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
    /// for `policy`); the estimate, when it fits.
    pub fn check_size(self, model: &ModelSummary, limit: usize) -> Result<usize, ServiceError> {
        let sel = self;
        let m = model;
        if let Some(spec) = &m.continuous {
            // `all` is every table the session has.
            let all = sel.v && sel.q && sel.policy && sel.r && sel.xi;
            if (sel.r || sel.xi) && !all {
                return Err(ServiceError::field(
                    "include",
                    "a continuous world has no table of R or Ξ to return; ask for v, q and policy, given at `points`",
                ));
            }
            let d = spec.observation_space.dim();
            let per_point = d * 24 + 24 + m.actions.len() * 24 + 64;
            let bytes = MAX_CONTINUOUS_POINTS.saturating_mul(per_point);
            if bytes > limit {
                return Err(ServiceError::LimitExceeded(format!(
                    "the value tables of this continuous session would take up to {bytes} bytes; the limit of one response is {limit} (--max-response-bytes)"
                )));
            }
            return Ok(bytes);
        }
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
        Ok(bytes)
    }
}

/// Most points a continuous session's tables are given at.
pub const MAX_CONTINUOUS_POINTS: usize = 1024;

/// Points per dimension of the grid a 1-D continuous session's tables are
/// given on (a 2-D one takes [`GRID_2D`]²).
const GRID_1D: usize = 101;
const GRID_2D: usize = 31;

/// Where a continuous session's tables are evaluated: a grid over the box
/// for d ≤ 2, else the observations of the history ring (the newest
/// [`MAX_CONTINUOUS_POINTS`]).
fn continuous_points(space: &ObservationSpace, history: Vec<HistoryEntry>) -> Vec<Vec<f64>> {
    let at = |i: usize, m: usize, j: usize| {
        let t = j as f64 / (m - 1) as f64;
        space.low[i] + t * (space.high[i] - space.low[i])
    };
    match space.dim() {
        1 => (0..GRID_1D).map(|j| vec![at(0, GRID_1D, j)]).collect(),
        2 => (0..GRID_2D)
            .flat_map(|r| (0..GRID_2D).map(move |c| (r, c)))
            .map(|(r, c)| vec![at(0, GRID_2D, c), at(1, GRID_2D, r)])
            .collect(),
        _ => history.into_iter().filter_map(|e| e.observation).collect(),
    }
}

fn continuous_tables(
    agent: &ContinuousAgent,
    sel: ValueSelection,
    history: Vec<HistoryEntry>,
) -> Values {
    let mut points = Vec::new();
    let mut qs = Vec::new();
    for x in continuous_points(&agent.model().spec.observation_space, history) {
        // The grid and logged observations are finite, so this holds.
        if let Ok(q) = agent.q_values(&x) {
            points.push(x);
            qs.push(q);
        }
    }
    let actions = &agent.model().spec.actions;
    let best = |q: &[f64]| {
        q.iter().enumerate().fold(
            (0, f64::NEG_INFINITY),
            |b, (a, &v)| if v > b.1 { (a, v) } else { b },
        )
    };
    Values {
        tick: agent.tick(),
        policy_version: agent.policy_version(),
        v: sel.v.then(|| qs.iter().map(|q| best(q).1).collect()),
        policy: sel
            .policy
            .then(|| qs.iter().map(|q| actions[best(q).0].clone()).collect()),
        q: sel.q.then(|| {
            qs.iter()
                .map(|q| q.iter().copied().map(Some).collect())
                .collect()
        }),
        points: Some(points),
        ..Values::default()
    }
}

/// The selected tables of a session, read under its lock.
pub fn tables(session: &Session, sel: ValueSelection) -> Values {
    if session.model.continuous.is_some() {
        let history = session.history(MAX_CONTINUOUS_POINTS);
        let st = session.state.lock();
        if let Some(agent) = st.learner.continuous() {
            return continuous_tables(agent, sel, history);
        }
    }
    let st = session.state.lock();
    let Some(agent) = st.learner.agent() else {
        return Values::default();
    };
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
        points: None,
    }
}
