//! One hosted agent: the core `Agent` behind a brief lock, its history ring
//! and the synchronous operations the tick loop and handlers call.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

use parking_lot::Mutex;
use serde::{Deserialize, Serialize};

use crate::algo::model::ActionRef;
use crate::algo::{Agent, AlgoError, Observation};

use super::error::ServiceError;
use super::spec::{EffectiveConfig, ModelSummary, UpdateMode};

/// One observation as a client sends it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ObservationIn {
    /// The state the agent is in now.
    pub state: usize,
    /// The stimulus received on arrival; omitted on the first observation.
    #[serde(default)]
    pub stimulus: Option<Vec<f64>>,
    /// The action actually taken, by name or index, if not the advised one.
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    pub action_taken: Option<ActionRef>,
}

/// The reply to one observation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct StepOut {
    /// Ticks so far.
    pub tick: u64,
    /// Name of the next action.
    pub action: String,
    /// Index of the next action.
    pub action_index: usize,
    /// The drive D after this tick.
    pub drive: Vec<f64>,
    /// |r| of this tick (Eq. 3).
    pub reward: f64,
    /// Number of policy updates applied.
    pub policy_version: u64,
}

/// One tick of the history ring.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct HistoryEntry {
    /// Tick.
    pub tick: u64,
    /// State after the tick.
    pub state: usize,
    /// Action advised for that state.
    pub action: usize,
    /// Drive after the tick.
    pub drive: Vec<f64>,
    /// |r|.
    pub reward: f64,
    /// LSTDQ error of the newest policy update.
    pub lstdq_error: f64,
}

/// Mutable state of a session, behind its lock.
#[derive(Debug)]
pub struct SessionState {
    /// The MCA-PI agent.
    pub agent: Agent,
    history: VecDeque<HistoryEntry>,
}

/// A hosted session. Immutable parts live outside the lock.
#[derive(Debug)]
pub struct Session {
    /// The session id.
    pub id: String,
    /// Lockstep or async.
    pub mode: UpdateMode,
    /// Model summary.
    pub model: ModelSummary,
    /// Effective configuration.
    pub config: EffectiveConfig,
    /// Mutable state.
    pub state: Mutex<SessionState>,
    /// True while a plan job for this session waits in the tick queue.
    pub queued: AtomicBool,
    /// Moving average of one policy update's cost in nanoseconds;
    /// `u64::MAX` until the first update is measured.
    plan_cost_ns: AtomicU64,
    history_cap: usize,
}

impl Session {
    /// Wraps a fresh agent.
    pub fn new(id: String, agent: Agent, model: ModelSummary, config: EffectiveConfig) -> Self {
        Self {
            id,
            mode: config.update_mode,
            history_cap: config.history,
            model,
            config,
            state: Mutex::new(SessionState {
                agent,
                history: VecDeque::new(),
            }),
            queued: AtomicBool::new(false),
            plan_cost_ns: AtomicU64::new(u64::MAX),
        }
    }

    /// The measured cost of one policy update (a moving average over recent
    /// updates), or `u64::MAX` before the first.
    pub fn plan_cost_ns(&self) -> u64 {
        self.plan_cost_ns.load(Ordering::Relaxed)
    }

    fn record_plan_cost(&self, started: Instant, updates: usize) {
        if updates == 0 {
            return;
        }
        let x =
            u64::try_from(started.elapsed().as_nanos() / updates as u128).unwrap_or(u64::MAX - 1);
        let old = self.plan_cost_ns.load(Ordering::Relaxed);
        let new = if old == u64::MAX {
            x
        } else {
            (old.saturating_mul(3).saturating_add(x)) / 4
        };
        self.plan_cost_ns
            .store(new.min(u64::MAX - 1), Ordering::Relaxed);
    }

    /// Applies observations in order. With `plan` (lockstep) each is followed
    /// by exactly one LSTDQ update, as `Agent::step`; without (async) the
    /// reply uses the current policy and planning is left to the tick loop.
    ///
    /// On an error at observation i, the i earlier ones stay applied and the
    /// message says so.
    pub fn observe(
        &self,
        batch: &[ObservationIn],
        plan: bool,
    ) -> Result<Vec<StepOut>, ServiceError> {
        let mut st = self.state.lock();
        let started = Instant::now();
        let mut out = Vec::with_capacity(batch.len());
        let result = st.apply_all(batch, plan, self.history_cap, &mut out);
        drop(st);
        if plan {
            self.record_plan_cost(started, out.len());
        }
        result.map(|()| out)
    }

    /// One policy update if the reward changed since the last one (the tick
    /// loop's work for async sessions).
    pub fn plan_if_needed(&self) -> Result<bool, ServiceError> {
        let mut st = self.state.lock();
        if !st.agent.needs_plan() {
            return Ok(false);
        }
        let started = Instant::now();
        st.agent.plan()?;
        drop(st);
        self.record_plan_cost(started, 1);
        Ok(true)
    }

    /// Marks the session queued; true if it was not already.
    pub fn try_enqueue(&self) -> bool {
        !self.queued.swap(true, Ordering::AcqRel)
    }

    /// Clears the queued mark (before planning, so newer rewards re-queue).
    pub fn dequeued(&self) {
        self.queued.store(false, Ordering::Release);
    }

    /// The most recent `limit` history entries, oldest first.
    pub fn history(&self, limit: usize) -> Vec<HistoryEntry> {
        let st = self.state.lock();
        let skip = st.history.len().saturating_sub(limit);
        st.history.iter().skip(skip).cloned().collect()
    }
}

impl SessionState {
    fn apply_all(
        &mut self,
        batch: &[ObservationIn],
        plan: bool,
        history_cap: usize,
        out: &mut Vec<StepOut>,
    ) -> Result<(), ServiceError> {
        for (i, obs) in batch.iter().enumerate() {
            match self.apply(obs, plan, history_cap) {
                Ok(step) => out.push(step),
                Err(e) if batch.len() == 1 => return Err(e),
                Err(e) => {
                    return Err(match e {
                        ServiceError::Algo(AlgoError::Numerical(_)) | ServiceError::Internal(_) => {
                            e
                        }
                        e => ServiceError::BadRequest(format!(
                            "`observations[{i}]`: {e} (the {i} observations before it were applied)"
                        )),
                    });
                }
            }
        }
        Ok(())
    }

    fn apply(
        &mut self,
        obs: &ObservationIn,
        plan: bool,
        history_cap: usize,
    ) -> Result<StepOut, ServiceError> {
        let model = self.agent.planning_model().model();
        let action_taken = match &obs.action_taken {
            None => None,
            Some(ActionRef::Index(a)) => Some(*a),
            Some(ActionRef::Name(name)) => Some(
                model
                    .actions()
                    .iter()
                    .position(|a| a == name)
                    .ok_or_else(|| {
                        ServiceError::field(
                            "action_taken",
                            format!(
                                "unknown action `{name}` (actions: {})",
                                model.actions().join(", ")
                            ),
                        )
                    })?,
            ),
        };
        let observation = Observation {
            state: obs.state,
            stimulus: obs.stimulus.as_deref(),
            action_taken,
        };
        let step = if plan {
            self.agent.step(&observation)?
        } else {
            let observed = self.agent.observe(&observation)?;
            let action = self
                .agent
                .act()
                .ok_or_else(|| ServiceError::Internal("no state after an observation".into()))?;
            crate::algo::Step {
                tick: observed.tick,
                action,
                reward: observed.reward,
                plan: None,
            }
        };
        let agent = &self.agent;
        let drive = agent.drive().vector().to_vec();
        if history_cap > 0 && obs.stimulus.is_some() {
            if self.history.len() == history_cap {
                self.history.pop_front();
            }
            self.history.push_back(HistoryEntry {
                tick: step.tick,
                state: obs.state,
                action: step.action,
                drive: drive.clone(),
                reward: step.reward,
                lstdq_error: agent.last_plan().lstdq_error,
            });
        }
        Ok(StepOut {
            tick: step.tick,
            action: agent.planning_model().model().actions()[step.action].clone(),
            action_index: step.action,
            drive,
            reward: step.reward,
            policy_version: agent.policy_version(),
        })
    }
}

/// A shared handle.
pub type SessionRef = Arc<Session>;
