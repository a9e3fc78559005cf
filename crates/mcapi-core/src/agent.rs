//! Algorithm 1 (MCA-PI) as an [`Agent`]: one observation in, one action out.
//!
//! A tick (docs/algorithm.md §2): the agent in s_t took a_t (the action it advised,
//! or the one the caller reports it took), arrived in s_{t+1} and received
//! ξ(t+1). [`Agent::observe`] applies line 5 (Ξ), lines 6-7 (D, Eqs. 1-2)
//! and Eq. 3 (r); [`Agent::plan`] applies line 8 (R = |ΞΛD|) and line 9 (one
//! LSTDQ evaluation and one greedy improvement); [`Agent::act`] returns
//! a_{t+1} = π_{t+1}(s_{t+1}), or a uniformly random valid action with
//! probability ε (exploration, our addition). [`Agent::step`] does all three,
//! Algorithm 1 to the letter. The split lets a server answer before planning.

use std::sync::Arc;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::drive::Drive;
use super::error::{AlgoError, Result, check_stimulus};
use super::learned::{LearnedModel, TransitionCounts, ValidLearnedParams};
use super::lstdq::{PlanOutcome, Planner, PlannerStats, PlanningModel};
use super::params::ValidParams;
use super::stimulus::StimulusFunction;

/// ChaCha streams `COLUMN_RESET_STREAMS | tick` of the agent's seed draw the
/// re-initialised stimulus columns (stream 0 is the agent's own RNG).
const COLUMN_RESET_STREAMS: u64 = 1 << 63;

/// What the caller reports at a tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation<'a> {
    /// s_{t+1}, the state the agent is in now.
    pub state: usize,
    /// ξ(t+1); absent on the first observation only.
    pub stimulus: Option<&'a [f64]>,
    /// a_t if it differs from the advised action (index into the model's actions).
    pub action_taken: Option<usize>,
}

impl<'a> Observation<'a> {
    /// The first observation: a state only.
    pub fn first(state: usize) -> Self {
        Self {
            state,
            stimulus: None,
            action_taken: None,
        }
    }

    /// A later observation with the stimulus received on arrival.
    pub fn new(state: usize, stimulus: &'a [f64]) -> Self {
        Self {
            state,
            stimulus: Some(stimulus),
            action_taken: None,
        }
    }
}

/// What [`Agent::observe`] did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObserveOutcome {
    /// Ticks so far (observations that carried a stimulus).
    pub tick: u64,
    /// |r| with r = D·Λξ (Eq. 3); 0 on the first observation.
    pub reward: f64,
}

/// The reply to one observation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step {
    /// Tick after this observation.
    pub tick: u64,
    /// Index of the next action a_{t+1}.
    pub action: usize,
    /// |r| of this tick (Eq. 3).
    pub reward: f64,
    /// The planning step this tick ran (None on the first observation).
    pub plan: Option<PlanOutcome>,
}

/// Position of a ChaCha8 stream: enough to resume it exactly.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RngState {
    /// The 32-byte key.
    pub seed: [u8; 32],
    /// Stream number.
    pub stream: u64,
    /// Words consumed so far.
    pub word_pos: u128,
}

impl RngState {
    pub(crate) fn of(rng: &ChaCha8Rng) -> Self {
        Self {
            seed: rng.get_seed(),
            stream: rng.get_stream(),
            word_pos: rng.get_word_pos(),
        }
    }

    pub(crate) fn resume(&self) -> ChaCha8Rng {
        let mut rng = ChaCha8Rng::from_seed(self.seed);
        rng.set_stream(self.stream);
        rng.set_word_pos(self.word_pos);
        rng
    }
}

/// Everything of an [`Agent`] that is not a function of its model and
/// parameters: what a durable store keeps to resume it (docs/sessions.md,
/// "Durability and recovery"). Ξ, the visit counts, D and its λ₁ statistics, the tick
/// and the RNG position come back bit for bit; so do π and Q.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AgentSnapshot {
    /// The RNG's position.
    pub rng: RngState,
    /// D and its running statistics (Eqs. 1-2, §4).
    pub drive: Drive,
    /// Ξ and n(s, a).
    pub stimulus: StimulusFunction,
    /// Chosen pair per state.
    pub policy: Vec<u32>,
    /// Q over valid pairs.
    pub q: Vec<f64>,
    /// R as of the last plan.
    pub rewards: Vec<f64>,
    /// Planner work counters.
    pub planner_stats: PlannerStats,
    /// s_t.
    pub state: Option<usize>,
    /// The pair advised by the last `act`.
    pub advised: Option<usize>,
    /// Ticks so far.
    pub tick: u64,
    /// |r| of the last tick.
    pub last_reward: f64,
    /// The last planning step.
    pub last_plan: PlanOutcome,
    /// Policy updates applied.
    pub policy_version: u64,
    /// R changed since the last plan.
    pub dirty: bool,
}

/// The resumable state of a learned-model agent: the agent's own snapshot
/// (policy and Q include the absorbing state when there is one) and the
/// counts, from which P̂ is rebuilt exactly. It lives here, beside
/// [`AgentSnapshot`], so that [`crate::learned`] needs nothing of the agent.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LearnedSnapshot {
    /// Everything an agent with a known model keeps.
    pub agent: AgentSnapshot,
    /// N(s, a, s′).
    pub counts: TransitionCounts,
}

/// [`AgentSnapshot`] borrowed from its agent: what a durable store encodes.
/// It has the owned type's name and fields in its order, and serde writes
/// a reference or a slice as what it points at, so it serialises to the
/// same bytes (tested), without a copy of Ξ, π, Q and R (for a world of
/// 100,000 states, megabytes held under the session's lock).
#[derive(Debug, Serialize)]
#[serde(rename = "AgentSnapshot")]
pub struct AgentSnapshotRef<'a> {
    /// The RNG's position.
    pub rng: RngState,
    /// D and its running statistics (its scratch is not serialised).
    pub drive: &'a Drive,
    /// Ξ and n(s, a).
    pub stimulus: &'a StimulusFunction,
    /// Chosen pair per state.
    pub policy: &'a [u32],
    /// Q over valid pairs.
    pub q: &'a [f64],
    /// R as of the last plan.
    pub rewards: &'a [f64],
    /// Planner work counters.
    pub planner_stats: PlannerStats,
    /// s_t.
    pub state: Option<usize>,
    /// The pair advised by the last `act`.
    pub advised: Option<usize>,
    /// Ticks so far.
    pub tick: u64,
    /// |r| of the last tick.
    pub last_reward: f64,
    /// The last planning step.
    pub last_plan: PlanOutcome,
    /// Policy updates applied.
    pub policy_version: u64,
    /// R changed since the last plan.
    pub dirty: bool,
}

/// [`LearnedSnapshot`] borrowed from its agent; serialises to its bytes
/// (the counts are one small vector per pair: a copy of them is an
/// allocation per pair).
#[derive(Debug, Serialize)]
#[serde(rename = "LearnedSnapshot")]
pub struct LearnedSnapshotRef<'a> {
    /// The agent, borrowed.
    pub agent: AgentSnapshotRef<'a>,
    /// N(s, a, s′).
    pub counts: &'a TransitionCounts,
}

/// One MCA-PI agent: its drive, stimulus function, policy and RNG.
#[derive(Debug, Clone)]
pub struct Agent {
    ctx: Arc<PlanningModel>,
    params: ValidParams,
    rng: ChaCha8Rng,
    drive: Drive,
    stimulus: StimulusFunction,
    planner: Planner,
    /// R = |ΞΛD| as of the last plan.
    rewards: Vec<f64>,
    scaled_drive: Vec<f64>,
    /// s_t: the state of the last observation.
    state: Option<usize>,
    /// The pair advised in `state` by the last `act`.
    advised: Option<usize>,
    tick: u64,
    last_reward: f64,
    last_plan: PlanOutcome,
    policy_version: u64,
    /// R changed since the last plan.
    dirty: bool,
    /// The learned transition model P̂, when the model has no posted P
    /// (docs/algorithm.md §8); `None` plans on the known P of `ctx`.
    learned: Option<Box<LearnedModel>>,
}

impl Agent {
    /// A fresh agent: Ξ ~ N(0, σ²), D = |N(0, I)| normalised, π₀ uniformly
    /// random over valid actions, drawn in that order from ChaCha8(seed) (§3).
    pub fn new(ctx: Arc<PlanningModel>, params: ValidParams) -> Self {
        Self::with_learned(ctx, params, None)
    }

    /// A fresh agent that learns P (docs/algorithm.md §8): `ctx` gives the states,
    /// actions, valid pairs and basis (its P is never read), the agent
    /// counts the transitions it makes and plans on P̂ (see
    /// [`crate::learned`]). Ξ, D and π₀ are drawn exactly as in
    /// [`Agent::new`], so a learned and a known agent with the same seed
    /// start alike.
    pub fn new_learned(
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        learned: ValidLearnedParams,
    ) -> Result<Self> {
        let learned = LearnedModel::new(&ctx, learned)?;
        Ok(Self::with_learned(ctx, params, Some(Box::new(learned))))
    }

    fn with_learned(
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        learned: Option<Box<LearnedModel>>,
    ) -> Self {
        let model = ctx.model();
        let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
        let stimulus = StimulusFunction::new(
            model.n_pairs(),
            model.n_stimuli(),
            params.optimistic_sd,
            &mut rng,
        );
        let drive = Drive::new(&params.priorities, params.eta, &mut rng);
        let mut policy: Vec<u32> = (0..model.states())
            .map(|s| {
                let range = model.pairs_of(s);
                rng.random_range(range) as u32
            })
            .collect();
        let plan_ctx = learned.as_ref().map_or(&*ctx, |l| l.planning_model());
        if plan_ctx.model().states() > model.states() {
            // The absorbing state s* has one pair, numbered last.
            policy.push(model.n_pairs() as u32);
        }
        let planner = Planner::new(plan_ctx, policy);
        let n_pairs = plan_ctx.model().n_pairs();
        let n = model.n_stimuli();
        Self {
            ctx,
            params,
            rng,
            drive,
            stimulus,
            planner,
            rewards: vec![0.0; n_pairs],
            scaled_drive: vec![0.0; n],
            state: None,
            advised: None,
            tick: 0,
            last_reward: 0.0,
            last_plan: PlanOutcome::default(),
            policy_version: 0,
            dirty: false,
            learned,
        }
    }

    /// Checks an observation against the model and the agent's state without
    /// changing anything; returns the pair (s_t, a_t) it will update, if any.
    pub fn validate(&self, obs: &Observation<'_>) -> Result<Option<usize>> {
        let model = self.ctx.model();
        if obs.state >= model.states() {
            return Err(AlgoError::StateOutOfRange {
                state: obs.state,
                states: model.states(),
            });
        }
        let Some(prev) = self.state else {
            if obs.stimulus.is_some() {
                return Err(AlgoError::FirstObservation { field: "stimulus" });
            }
            if obs.action_taken.is_some() {
                return Err(AlgoError::FirstObservation {
                    field: "action_taken",
                });
            }
            return Ok(None);
        };
        let xi = obs.stimulus.ok_or(AlgoError::MissingStimulus)?;
        check_stimulus(xi, model.n_stimuli())?;
        let pair = match obs.action_taken {
            None => self.advised,
            Some(a) if a >= model.n_actions() => {
                return Err(AlgoError::ActionOutOfRange {
                    action: a,
                    actions: model.n_actions(),
                });
            }
            Some(a) => Some(
                model
                    .pair(prev, a)
                    .ok_or_else(|| AlgoError::ActionNotAvailable {
                        state: prev,
                        action: model.actions()[a].clone(),
                    })?,
            ),
        };
        // `advised` is always set once `state` is (act follows every observe).
        pair.map(Some)
            .ok_or_else(|| AlgoError::Numerical("no advised action to update".into()))
    }

    /// Lines 5-7 and Eq. 3: learns Ξ(s_t, a_t) and updates D. Nothing changes on error.
    pub fn observe(&mut self, obs: &Observation<'_>) -> Result<ObserveOutcome> {
        let pair = self.validate(obs)?;
        if let (Some(p), Some(xi)) = (pair, obs.stimulus) {
            self.stimulus.update(p, xi, self.params.stimulus_rate);
            if let Some(learned) = &mut self.learned
                && learned.record(p, obs.state)
            {
                self.planner.model_changed(learned.planning_model());
            }
            self.last_reward = self.drive.update(xi).abs();
            debug_assert!((super::drive::norm(self.drive.vector()) - 1.0).abs() < 1e-9);
            self.tick += 1;
            self.dirty = true;
        }
        self.state = Some(obs.state);
        self.advised = None;
        Ok(ObserveOutcome {
            tick: self.tick,
            reward: if pair.is_some() {
                self.last_reward
            } else {
                0.0
            },
        })
    }

    /// Line 8 (R = |ΞΛD|) and line 9: one LSTDQ evaluation and one greedy
    /// improvement of π.
    pub fn plan(&mut self) -> Result<PlanOutcome> {
        self.refresh_rewards();
        let ctx = match &self.learned {
            Some(learned) => learned.planning_model(),
            None => &*self.ctx,
        };
        let outcome = self.planner.update(
            ctx,
            &self.rewards,
            self.params.gamma,
            self.params.ridge,
            &mut self.rng,
        )?;
        self.last_plan = outcome;
        self.policy_version += 1;
        self.dirty = false;
        Ok(outcome)
    }

    /// Recomputes R = |ΞΛD| from the current Ξ and D.
    fn refresh_rewards(&mut self) {
        for ((s, d), l) in self
            .scaled_drive
            .iter_mut()
            .zip(self.drive.vector())
            .zip(self.drive.inv_rho())
        {
            *s = d * l;
        }
        let pairs = self.ctx.model().n_pairs();
        let (real, absorbing) = self.rewards.split_at_mut(pairs);
        self.stimulus.rewards_into(&self.scaled_drive, real);
        if let Some(r_star) = absorbing.first_mut() {
            // R-max (docs/algorithm.md §8): s* earns the best reward of any valid pair.
            *r_star = real.iter().copied().fold(0.0, f64::max);
        }
    }

    /// a_{t+1}: π(s_{t+1}), or with probability ε a uniformly random valid
    /// action. The choice is remembered as the action the next observation
    /// updates. Returns `None` before the first observation.
    pub fn act(&mut self) -> Option<usize> {
        let s = self.state?;
        let mut pair = self.planner.chosen_pair(s);
        if self.params.epsilon > 0.0 && self.rng.random::<f64>() < self.params.epsilon {
            pair = self.rng.random_range(self.ctx.model().pairs_of(s));
        }
        self.advised = Some(pair);
        Some(self.ctx.model().pair_action(pair))
    }

    /// One tick of Algorithm 1: observe, plan (except on the first
    /// observation), act.
    pub fn step(&mut self, obs: &Observation<'_>) -> Result<Step> {
        let observed = self.observe(obs)?;
        let plan = self.dirty.then(|| self.plan());
        // Act even if planning failed, so the agent stays consistent.
        let action = self
            .act()
            .ok_or_else(|| AlgoError::Numerical("no state after an observation".into()))?;
        let plan = plan.transpose()?;
        Ok(Step {
            tick: observed.tick,
            action,
            reward: observed.reward,
            plan,
        })
    }

    /// Shared planning inputs (model and basis).
    pub fn planning_model(&self) -> &Arc<PlanningModel> {
        &self.ctx
    }

    /// Effective parameters.
    pub fn params(&self) -> &ValidParams {
        &self.params
    }

    /// The drive D.
    pub fn drive(&self) -> &Drive {
        &self.drive
    }

    /// The stimulus function Ξ.
    pub fn stimulus(&self) -> &StimulusFunction {
        &self.stimulus
    }

    /// The planner (Q, π).
    pub fn planner(&self) -> &Planner {
        &self.planner
    }

    /// R as of the last plan, one entry per valid pair.
    pub fn rewards(&self) -> &[f64] {
        &self.rewards[..self.ctx.model().n_pairs()]
    }

    /// True when [`Agent::restore`] of this agent's snapshot continues bit
    /// for bit as the agent itself would: a posted, deterministic model
    /// planned by the functional-graph engine ([`Planner::restores_exactly`]).
    /// A learned model may turn stochastic and then needs the engine's V.
    pub fn restores_exactly(&self) -> bool {
        self.learned.is_none() && self.planner.restores_exactly()
    }

    /// The learned transition model, for an agent created by
    /// [`Agent::new_learned`].
    pub fn learned(&self) -> Option<&LearnedModel> {
        self.learned.as_deref()
    }

    /// How much of the model is known: the fraction of valid pairs seen at
    /// least m times for a learned model, 1 for a known one.
    pub fn known_fraction(&self) -> f64 {
        self.learned.as_ref().map_or(1.0, |l| l.known_fraction())
    }

    /// Hints the CPU to start loading the tables this agent's next
    /// observation and plan touch: for a caller that steps many agents in
    /// turn, called on the next agent before stepping this one, so that its
    /// tables come from DRAM while this one computes. Changes nothing.
    pub fn prefetch(&self) {
        self.drive.prefetch();
        self.stimulus.prefetch(self.advised);
        self.planner.prefetch();
        crate::prefetch::slice(&self.rewards);
        crate::prefetch::slice(&self.scaled_drive);
    }

    /// Ticks so far.
    pub fn tick(&self) -> u64 {
        self.tick
    }

    /// The state of the last observation.
    pub fn state(&self) -> Option<usize> {
        self.state
    }

    /// Number of planning steps applied.
    pub fn policy_version(&self) -> u64 {
        self.policy_version
    }

    /// The last planning step.
    pub fn last_plan(&self) -> PlanOutcome {
        self.last_plan
    }

    /// True when R changed since the last plan.
    pub fn needs_plan(&self) -> bool {
        self.dirty
    }

    /// The greedy action of state `s` (no exploration).
    pub fn greedy_action(&self, s: usize) -> usize {
        self.ctx.model().pair_action(self.planner.chosen_pair(s))
    }

    /// The action advised by the last `act`: the one the next observation
    /// updates unless it reports another.
    pub fn advised_action(&self) -> Option<usize> {
        self.advised.map(|p| self.ctx.model().pair_action(p))
    }

    /// Sets the advised action of the current state, as a reply already
    /// sent to a client named it (used when replaying a log).
    pub fn set_advised_action(&mut self, action: usize) -> Result<()> {
        let state = self.state.ok_or_else(|| {
            AlgoError::InvalidSnapshot("an advised action before any state".into())
        })?;
        let pair = self.ctx.model().pair(state, action).ok_or_else(|| {
            AlgoError::InvalidSnapshot(format!("action {action} is not available in state {state}"))
        })?;
        self.advised = Some(pair);
        Ok(())
    }

    /// Raises the policy-version counter to at least `v` (a log replay
    /// restores the count the client was last told; the policy itself is
    /// recomputed once at the end of the replay).
    pub fn resume_policy_version(&mut self, v: u64) {
        self.policy_version = self.policy_version.max(v);
    }

    /// Gives stimulus column `dim` visit counts of its own (§7: the
    /// curiosity column's rate is 1/n_cur); see
    /// [`StimulusFunction::count_column_separately`].
    pub fn count_stimulus_column_separately(&mut self, dim: usize) -> Result<()> {
        self.check_dim(dim)?;
        self.stimulus.count_column_separately(dim);
        Ok(())
    }

    /// Re-initialises stimulus column `dim` optimistically, Ξ(·, dim) ~
    /// N(0, sd²), and restarts its own visit counts (§7: at each module
    /// freeze). R is recomputed at the next plan.
    ///
    /// The draws come from their own ChaCha stream, keyed by the agent's
    /// seed and the current tick, not from the agent's RNG: how many
    /// tie-break and exploration draws [`Agent::act`] made before (none when
    /// a store replays a log) must not change the learned Ξ, so a recovered
    /// session has the column it had live.
    pub fn reset_stimulus_column(&mut self, dim: usize, sd: f64) -> Result<()> {
        self.check_dim(dim)?;
        if !(sd.is_finite() && sd >= 0.0) {
            return Err(AlgoError::NonFinite { field: "sd" });
        }
        let mut rng = ChaCha8Rng::seed_from_u64(self.params.seed);
        rng.set_stream(COLUMN_RESET_STREAMS | self.tick);
        self.stimulus.reset_column(dim, sd, &mut rng);
        self.dirty = true;
        Ok(())
    }

    /// Sets drive component `dim` to `value` and renormalises (§7, condition
    /// (3)); see [`Drive::set_component`]. Returns whether D changed.
    pub fn set_drive_component(&mut self, dim: usize, value: f64) -> Result<bool> {
        self.check_dim(dim)?;
        if !value.is_finite() {
            return Err(AlgoError::NonFinite { field: "drive" });
        }
        let before = self.drive.vector()[dim];
        if before == value {
            return Ok(false);
        }
        let changed = self.drive.set_component(dim, value);
        self.dirty |= changed;
        Ok(changed)
    }

    fn check_dim(&self, dim: usize) -> Result<()> {
        let n = self.ctx.model().n_stimuli();
        if dim >= n {
            return Err(AlgoError::StimulusLength {
                got: dim + 1,
                expected: n,
            });
        }
        Ok(())
    }

    /// The agent's resumable state, borrowed: what a durable store encodes
    /// (the bytes of [`Agent::snapshot`], without copying it).
    pub fn snapshot_ref(&self) -> AgentSnapshotRef<'_> {
        AgentSnapshotRef {
            rng: RngState::of(&self.rng),
            drive: &self.drive,
            stimulus: &self.stimulus,
            policy: self.planner.policy(),
            q: self.planner.q(),
            rewards: &self.rewards,
            planner_stats: self.planner.stats(),
            state: self.state,
            advised: self.advised,
            tick: self.tick,
            last_reward: self.last_reward,
            last_plan: self.last_plan,
            policy_version: self.policy_version,
            dirty: self.dirty,
        }
    }

    /// The agent's resumable state, copied (what restores and in-memory
    /// snapshots take; a store encodes [`Agent::snapshot_ref`]).
    pub fn snapshot(&self) -> AgentSnapshot {
        AgentSnapshot {
            rng: RngState::of(&self.rng),
            drive: self.drive.without_scratch(),
            stimulus: self.stimulus.clone(),
            policy: self.planner.policy().to_vec(),
            q: self.planner.q().to_vec(),
            rewards: self.rewards.clone(),
            planner_stats: self.planner.stats(),
            state: self.state,
            advised: self.advised,
            tick: self.tick,
            last_reward: self.last_reward,
            last_plan: self.last_plan,
            policy_version: self.policy_version,
            dirty: self.dirty,
        }
    }

    /// An agent resumed from a snapshot taken of an agent with the same
    /// model and parameters; refuses a snapshot that does not fit them.
    pub fn restore(
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        snap: AgentSnapshot,
    ) -> Result<Self> {
        Self::restore_with(ctx, params, snap, None)
    }

    /// The resumable state of an agent with a learned model: its snapshot
    /// and the counts N(s, a, s′); `None` for a known model.
    pub fn learned_snapshot(&self) -> Option<LearnedSnapshot> {
        self.learned.as_ref().map(|l| LearnedSnapshot {
            agent: self.snapshot(),
            counts: l.counts().clone(),
        })
    }

    /// [`Agent::learned_snapshot`] borrowed: the same bytes, no copy.
    pub fn learned_snapshot_ref(&self) -> Option<LearnedSnapshotRef<'_>> {
        self.learned.as_ref().map(|l| LearnedSnapshotRef {
            agent: self.snapshot_ref(),
            counts: l.counts(),
        })
    }

    /// An agent with a learned model resumed from its snapshot: P̂ is
    /// rebuilt from the counts, so it continues exactly as the live agent
    /// would have.
    pub fn restore_learned(
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        learned: ValidLearnedParams,
        snap: LearnedSnapshot,
    ) -> Result<Self> {
        Self::restore_with(ctx, params, snap.agent, Some((learned, snap.counts)))
    }

    fn restore_with(
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        snap: AgentSnapshot,
        learned: Option<(ValidLearnedParams, TransitionCounts)>,
    ) -> Result<Self> {
        let learned = learned
            .map(|(p, counts)| LearnedModel::from_counts(&ctx, p, counts).map(Box::new))
            .transpose()?;
        let model = ctx.model();
        let (pairs, n) = (model.n_pairs(), model.n_stimuli());
        let plan_pairs = learned
            .as_ref()
            .map_or(pairs, |l| l.planning_model().model().n_pairs());
        let bad = |what: String| Err(AlgoError::InvalidSnapshot(what));
        if snap.drive.vector().len() != n || snap.drive.inv_rho().len() != n {
            return bad(format!(
                "D has {} components; the model has {n} stimuli",
                snap.drive.vector().len()
            ));
        }
        if snap.drive.vector().iter().any(|x| !x.is_finite())
            || (super::drive::norm(snap.drive.vector()) - 1.0).abs() > 1e-6
        {
            return bad("D is not a finite unit vector".into());
        }
        if snap.stimulus.dims() != n
            || snap.stimulus.table().len() != pairs * n
            || snap.stimulus.visits().len() != pairs
        {
            return bad(format!("Ξ does not have {pairs} pairs x {n} stimuli"));
        }
        if snap
            .stimulus
            .own_column()
            .is_some_and(|c| c.dim >= n || c.visits.len() != pairs)
        {
            return bad(format!(
                "Ξ's own column does not fit {pairs} pairs x {n} stimuli"
            ));
        }
        if snap.rewards.len() != plan_pairs {
            return bad(format!(
                "R has {} pairs; the model has {plan_pairs}",
                snap.rewards.len()
            ));
        }
        if snap.state.is_some_and(|s| s >= model.states()) {
            return bad("the current state is outside the model".into());
        }
        match (snap.state, snap.advised) {
            (None, Some(_)) => return bad("an advised pair without a state".into()),
            (Some(s), Some(p)) if !model.pairs_of(s).contains(&p) => {
                return bad(format!("advised pair {p} does not belong to state {s}"));
            }
            _ => {}
        }
        let plan_ctx = learned.as_ref().map_or(&*ctx, |l| l.planning_model());
        let planner = Planner::restore(plan_ctx, snap.policy, snap.q, snap.planner_stats)?;
        Ok(Self {
            rng: snap.rng.resume(),
            drive: snap.drive,
            stimulus: snap.stimulus,
            planner,
            rewards: snap.rewards,
            scaled_drive: vec![0.0; n],
            state: snap.state,
            advised: snap.advised,
            tick: snap.tick,
            last_reward: snap.last_reward,
            last_plan: snap.last_plan,
            policy_version: snap.policy_version,
            dirty: snap.dirty,
            learned,
            ctx,
            params,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::basis::Basis;
    use crate::drive::norm;
    use crate::model::hallway;
    use crate::params::AgentParams;

    fn hallway_agent(seed: u64) -> Agent {
        let preset = hallway();
        let params = AgentParams {
            seed: Some(seed),
            ..Default::default()
        }
        .check(2, 0)
        .expect("params");
        Agent::new(
            Arc::new(PlanningModel::new(preset.model, Basis::Indicator)),
            params,
        )
    }

    /// A borrowed snapshot encodes to its owned twin's bytes, in the
    /// store's format (postcard, no field names: order is all) and in JSON.
    fn assert_same_encoding(owned: &impl Serialize, borrowed: &impl Serialize) {
        assert_eq!(
            postcard::to_allocvec(borrowed).expect("encode"),
            postcard::to_allocvec(owned).expect("encode"),
            "postcard"
        );
        assert_eq!(
            serde_json::to_string(borrowed).expect("encode"),
            serde_json::to_string(owned).expect("encode"),
            "JSON"
        );
    }

    #[test]
    fn a_restored_agent_continues_exactly() {
        let mut a = hallway_agent(9);
        let mut state = 25;
        a.step(&Observation::first(state)).expect("first");
        walk(&mut a, &mut state, 300);
        let snap = a.snapshot();
        let bytes = serde_json::to_vec(&snap).expect("encode");
        let back: AgentSnapshot = serde_json::from_slice(&bytes).expect("decode");
        assert_eq!(back, snap);
        assert_same_encoding(&snap, &a.snapshot_ref());
        assert!(
            a.restores_exactly(),
            "the hallway plans on a functional graph"
        );
        let mut b = Agent::restore(Arc::clone(a.planning_model()), a.params().clone(), back)
            .expect("restore");
        let mut state_b = state;
        let ta = walk(&mut a, &mut state, 500);
        let tb = walk(&mut b, &mut state_b, 500);
        assert_eq!(ta, tb, "the restored agent must follow the same trajectory");
        assert!(
            a.snapshot() == b.snapshot(),
            "identical state after 500 ticks"
        );
    }

    #[test]
    fn only_the_functional_graph_engine_claims_an_exact_restore() {
        assert!(hallway_agent(3).restores_exactly());
        let learned = learned_hallway_agent(3, crate::learned::Optimism::Absorbing);
        assert!(
            !learned.restores_exactly(),
            "a learned P̂ may turn stochastic"
        );
        let preset = hallway();
        let spec = crate::spec::BasisSpec::ProtoValue { k: 4 };
        let basis = Basis::build(&spec, &preset.model).expect("PVFs");
        let params = AgentParams {
            seed: Some(3),
            ..Default::default()
        }
        .check(2, 0)
        .expect("params");
        let pvf = Agent::new(Arc::new(PlanningModel::new(preset.model, basis)), params);
        assert!(!pvf.restores_exactly(), "A⁻¹ is refactorised on restore");
    }

    fn learned_hallway_agent(seed: u64, optimism: crate::learned::Optimism) -> Agent {
        let params = AgentParams {
            seed: Some(seed),
            ..Default::default()
        }
        .check(2, 0)
        .expect("params");
        let learned = crate::learned::LearnedParams {
            optimism: Some(optimism),
            ..Default::default()
        }
        .check()
        .expect("learned params");
        Agent::new_learned(
            Arc::new(PlanningModel::new(hallway().model, Basis::Indicator)),
            params,
            learned,
        )
        .expect("learned agent")
    }

    /// Walks the hallway for `ticks` ticks following the agent's advice.
    fn walk(agent: &mut Agent, state: &mut usize, ticks: usize) -> Vec<(usize, Vec<f64>)> {
        let mut out = Vec::new();
        for _ in 0..ticks {
            let action = agent.advised_action().expect("advised");
            *state = match action {
                0 => state.saturating_sub(1),
                1 => (*state + 1).min(49),
                _ => *state,
            };
            let xi = [f64::from(*state == 10) * 6.0, f64::from(*state == 40) * 6.0];
            let step = agent.step(&Observation::new(*state, &xi)).expect("step");
            out.push((step.action, agent.drive().vector().to_vec()));
        }
        out
    }

    #[test]
    fn a_restored_learned_agent_continues_exactly() {
        for optimism in [
            crate::learned::Optimism::Absorbing,
            crate::learned::Optimism::Stimulus,
        ] {
            let mut a = learned_hallway_agent(9, optimism);
            let mut state = 25;
            a.step(&Observation::first(state)).expect("first");
            // Early, while part of the model is still unknown.
            walk(&mut a, &mut state, 40);
            let known = a.known_fraction();
            assert!(known > 0.0 && known < 1.0, "{optimism:?}: {known}");
            let snap = a.learned_snapshot().expect("learned");
            let bytes = serde_json::to_vec(&snap).expect("encode");
            let back: LearnedSnapshot = serde_json::from_slice(&bytes).expect("decode");
            assert_eq!(back, snap);
            assert_same_encoding(&snap, &a.learned_snapshot_ref().expect("learned"));
            let learned = a.learned().expect("learned").params();
            let mut b = Agent::restore_learned(
                Arc::clone(a.planning_model()),
                a.params().clone(),
                learned,
                back,
            )
            .expect("restore");
            assert_eq!(
                b.learned().expect("learned").planning_model().model(),
                a.learned().expect("learned").planning_model().model(),
                "P̂ is rebuilt exactly"
            );
            let mut state_b = state;
            let ta = walk(&mut a, &mut state, 500);
            let tb = walk(&mut b, &mut state_b, 500);
            assert_eq!(
                ta, tb,
                "{optimism:?}: the restored agent must follow the same path"
            );
            assert!(a.learned_snapshot() == b.learned_snapshot(), "{optimism:?}");
        }
    }

    #[test]
    fn unknown_pairs_are_worth_r_max_forever() {
        let mut a = learned_hallway_agent(4, crate::learned::Optimism::Absorbing);
        let mut state = 25;
        a.step(&Observation::first(state)).expect("first");
        walk(&mut a, &mut state, 20);
        let gamma = a.params().gamma;
        let r = a.rewards();
        let r_max = r.iter().copied().fold(0.0, f64::max);
        let q = a.planner().q();
        let learned = a.learned().expect("learned");
        assert_eq!(q.len(), 149, "Q has the absorbing pair last");
        assert!((q[148] - r_max / (1.0 - gamma)).abs() < 1e-9 * (1.0 + q[148]));
        let mut unknown = 0;
        for p in (0..148).filter(|&p| !learned.is_known(p)) {
            let expected = r[p] + gamma * r_max / (1.0 - gamma);
            assert!(
                (q[p] - expected).abs() < 1e-9 * (1.0 + expected),
                "pair {p}"
            );
            unknown += 1;
        }
        assert!(unknown > 100, "20 ticks leave most of the hallway unknown");
        assert_eq!(learned.known_pairs(), 148 - unknown);
    }

    #[test]
    fn a_snapshot_of_another_model_is_refused() {
        let a = hallway_agent(1);
        let mut snap = a.snapshot();
        snap.rewards.pop();
        let err = Agent::restore(Arc::clone(a.planning_model()), a.params().clone(), snap)
            .expect_err("short R");
        assert!(matches!(err, AlgoError::InvalidSnapshot(_)), "{err}");
        let mut snap = a.snapshot();
        snap.policy[0] = 9999;
        assert!(Agent::restore(Arc::clone(a.planning_model()), a.params().clone(), snap).is_err());
    }

    #[test]
    fn first_observation_carries_only_a_state() {
        let mut agent = hallway_agent(1);
        let err = agent
            .step(&Observation::new(3, &[0.0, 0.0]))
            .expect_err("stimulus on first");
        assert_eq!(err, AlgoError::FirstObservation { field: "stimulus" });
        let step = agent.step(&Observation::first(3)).expect("first");
        assert_eq!(step.tick, 0);
        assert!(step.plan.is_none());
        let err = agent
            .step(&Observation::first(4))
            .expect_err("missing stimulus");
        assert_eq!(err, AlgoError::MissingStimulus);
    }

    #[test]
    fn bad_observations_change_nothing() {
        let mut agent = hallway_agent(2);
        agent.step(&Observation::first(0)).expect("first");
        let before = agent.drive().vector().to_vec();
        let cases = [
            (
                Observation::new(50, &[0.0, 0.0]),
                "state 50 is out of range",
            ),
            (
                Observation::new(1, &[0.0]),
                "stimulus has 1 components, expected 2",
            ),
            (Observation::new(1, &[f64::NAN, 0.0]), "non-finite"),
            (
                Observation::new(1, &[0.0, -1e200]),
                "`stimulus[1]` = -1e200 exceeds the limit of ±1e12",
            ),
            (
                Observation {
                    state: 1,
                    stimulus: Some(&[0.0, 0.0]),
                    action_taken: Some(0),
                },
                "action `left` is not available in state 0",
            ),
            (
                Observation {
                    state: 1,
                    stimulus: Some(&[0.0, 0.0]),
                    action_taken: Some(7),
                },
                "action 7 is out of range",
            ),
        ];
        for (obs, msg) in cases {
            let err = agent.step(&obs).expect_err("invalid").to_string();
            assert!(err.contains(msg), "{err:?} should contain {msg:?}");
        }
        assert_eq!(agent.tick(), 0);
        assert_eq!(agent.drive().vector(), &before[..]);
    }

    #[test]
    fn action_taken_overrides_the_advice() {
        let mut agent = hallway_agent(3);
        agent.step(&Observation::first(20)).expect("first");
        let stay = agent.planning_model().model().pair(20, 2).expect("stay");
        let obs = Observation {
            state: 20,
            stimulus: Some(&[1.0, 0.0]),
            action_taken: Some(2),
        };
        agent.step(&obs).expect("step");
        assert_eq!(agent.stimulus().visits()[stay], 1);
        assert_eq!(agent.stimulus().row(stay), &[1.0, 0.0]);
    }

    #[test]
    fn same_seed_same_trajectory() {
        let run = |seed| {
            let mut agent = hallway_agent(seed);
            let mut s = agent.step(&Observation::first(25)).expect("first").action;
            let mut state = 25usize;
            let mut actions = Vec::new();
            for t in 0..300 {
                state = match s {
                    0 => state - 1,
                    1 => state + 1,
                    _ => state,
                };
                let xi = if state == 10 {
                    [6.0, 0.0]
                } else if state == 40 {
                    [0.0, 6.0]
                } else {
                    [0.0, 0.0]
                };
                let step = agent.step(&Observation::new(state, &xi)).expect("step");
                assert!(
                    (norm(agent.drive().vector()) - 1.0).abs() < 1e-12,
                    "tick {t}"
                );
                s = step.action;
                actions.push(s);
            }
            actions
        };
        assert_eq!(run(5), run(5));
        assert_ne!(run(5), run(6));
    }
}
