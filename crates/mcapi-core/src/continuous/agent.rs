//! The MCA-PI agent of a continuous world (docs/algorithm.md §9): one
//! tick of Algorithm 1 with observation vectors instead of state numbers.
//!
//! - line 5: Ξ(s_t, a_t) learns ξ(t+1) by recursive least squares
//!   ([`super::stimulus`]);
//! - lines 6-7, Eq. 3: D is the discrete agent's [`Drive`], unchanged;
//! - the transition (s_t, a_t, s_{t+1}) goes into the sample store
//!   ([`super::samples`]);
//! - line 8: R = |Ξ Λ D| wherever the planner needs it;
//! - line 9: one LSTDQ evaluation on the stored transitions and one greedy
//!   improvement of their successor actions ([`super::planner`]);
//! - line 10: a_{t+1} = argmax_a Q(s_{t+1}, a), where an unknown
//!   (cell, action) pair is worth Q_opt = R + γ R_max / (1 − γ).

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod rebuild;
mod snapshot;

pub use snapshot::{
    ContinuousSnapshot, ContinuousSnapshotRef, ContinuousState, ContinuousStateRef, GridSnapshot,
    GridSnapshotRef,
};

use super::basis::{FeatureMap, PvfGraph};
use super::dot::{dot, rows_times};
use super::grid::GridPlanner;
use super::model::ContinuousModel;
use super::planner::SamplePlanner;
use super::samples::SampleStore;
use super::space::Placement;
use super::stimulus::{LinearStimulus, PROBES, mean_sq_norm, probe_features};
use crate::drive::Drive;
use crate::error::{AlgoError, Result, check_stimulus};
use crate::params::ValidParams;

/// The planner's ridge, as a fraction of one typical ‖v‖²: small enough
/// to leave LSTDQ's solution as it is, large enough that A⁻¹ starts well
/// conditioned for the rank-one updates.
const PLANNER_RIDGE: f64 = 1e-2;

/// Actions within this relative distance of the best Q are tied
/// (docs/algorithm.md §2.6).
const TIE: f64 = 1e-10;

/// Successor actions changed per tick, at most: the improvement of line 9
/// is bounded, the largest advantages first (docs/algorithm.md §9.5).
const MAX_SWITCHES: usize = 32;

/// One observation of a continuous world.
#[derive(Debug, Clone, Copy)]
pub struct ContinuousObservation<'a> {
    /// The observation vector, in the client's units.
    pub observation: &'a [f64],
    /// ξ(t+1); absent on the first observation.
    pub stimulus: Option<&'a [f64]>,
    /// The action the client took, if not the advised one.
    pub action_taken: Option<usize>,
}

/// What one tick did.
#[derive(Debug, Clone, PartialEq)]
pub struct ContinuousStep {
    /// Ticks so far (observations with a stimulus).
    pub tick: u64,
    /// The next action.
    pub action: usize,
    /// |r| of Eq. 3 (0 on the first observation).
    pub reward: f64,
    /// max_a Q at the new observation.
    pub value: f64,
    /// Whether the observation was outside the box and clipped.
    pub clipped: bool,
}

/// What [`ContinuousAgent::observe`] did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContinuousObserved {
    /// Ticks so far.
    pub tick: u64,
    /// |r| of Eq. 3 (0 on the first observation).
    pub reward: f64,
    /// Whether the observation was outside the box and clipped.
    pub clipped: bool,
}

/// Counters of a continuous agent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ContinuousStats {
    /// Observations clipped into the box.
    pub clipped: u64,
    /// Transitions stored now (on a grid: kept per (cell, action), a
    /// transition counting once for each pair it teaches).
    pub samples: usize,
    /// (cell, action) slots visited (on a grid: pairs with a successor).
    pub slots: usize,
    /// Rank-one updates of A⁻¹.
    pub updates: u64,
    /// Rebuilds of A⁻¹.
    pub rebuilds: u64,
    /// Builds of the basis (a PVF basis is rebuilt as its graph grows; 0
    /// for the others).
    pub basis_builds: u64,
}

/// The agent.
#[derive(Debug, Clone)]
pub struct ContinuousAgent {
    model: ContinuousModel,
    params: ValidParams,
    rng: ChaCha8Rng,
    drive: Drive,
    xi: LinearStimulus,
    store: SampleStore,
    planner: SamplePlanner,
    /// Per stored transition: bit a set when (cell of s′, a) is known.
    known_next: Vec<u64>,
    /// The current normalised observation and its features.
    s: Option<(Vec<f64>, Vec<f64>)>,
    /// The action advised at `s`.
    advised: Option<usize>,
    tick: u64,
    clipped: u64,
    /// An observation came since the last plan.
    needs_plan: bool,
    /// Plans so far.
    policy_version: u64,
    /// Scratch: u_a = W_a Λ D, `actions × k`.
    u: Vec<f64>,
    scaled_drive: Vec<f64>,
    targets: Vec<f64>,
    /// R(s′_i, a) of every stored transition i and action a, row-major,
    /// as of the last [`Self::refresh_reward_weights`]; 0 where (s′_i, a)
    /// is known (the planner's Q is used there, not R).
    next_rewards: Vec<f64>,
    r_max: f64,
    /// v at the probe points (`PROBES × k`).
    probes: Vec<f64>,
    /// The graph of a PVF basis, grown by every observation.
    graph: Option<PvfGraph>,
    /// The planner of a grid basis (docs/algorithm.md §9.8), which then
    /// replaces Ξ's linear model, the sample store and LSTDQ.
    grid: Option<Box<GridPlanner>>,
    /// Scratch: the successor actions to change (advantage, index, π, known).
    switches: Vec<(f64, usize, usize, bool)>,
    /// Scratch: per-action weights (u or w) transposed, `k × actions`.
    by_action: Vec<f64>,
    /// Scratch: Q(s′_i, a) = v(s′_i) · w_a, row-major, during a plan.
    next_q: Vec<f64>,
}

impl ContinuousAgent {
    /// D₀, then the prior of Ξ, from ChaCha8(seed), in that order.
    pub fn new(model: ContinuousModel, params: ValidParams) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
        let (d, k, na, n) = (
            model.dim(),
            model.features.len(),
            model.n_actions(),
            model.n_stimuli(),
        );
        let drive = Drive::new(&params.priorities, params.eta, &mut rng);
        // A grid plans without features: its prior is Ξ's (one draw per
        // cell and stimulus), and the feature machinery stays empty.
        let grid = match &model.features {
            FeatureMap::Grid(shape) => Some(Box::new(GridPlanner::new(
                d,
                shape.cells_per_dim,
                na,
                n,
                shape.neighbours,
                shape.reach,
                params.gamma,
                params.optimistic_sd,
                &mut rng,
            ))),
            _ => None,
        };
        let typical = if grid.is_some() {
            1.0
        } else {
            mean_sq_norm(&model.features, d)
        };
        let xi = LinearStimulus::new(na, k, n, params.optimistic_sd, typical, &mut rng);
        let sp = model.samples;
        let store = SampleStore::new(
            d,
            k,
            sp.cells_per_dim,
            sp.per_cell as usize,
            sp.max as usize,
            sp.known_after as u64,
        );
        let planner = SamplePlanner::new(k, na, params.gamma, PLANNER_RIDGE * typical);
        Self {
            params,
            rng,
            drive,
            xi,
            store,
            planner,
            known_next: Vec::new(),
            s: None,
            advised: None,
            tick: 0,
            clipped: 0,
            needs_plan: false,
            policy_version: 0,
            u: vec![0.0; na * k],
            scaled_drive: vec![0.0; n],
            targets: Vec::new(),
            next_rewards: Vec::new(),
            r_max: 0.0,
            probes: if grid.is_some() {
                Vec::new()
            } else {
                probe_features(&model.features, d)
            },
            grid,
            graph: match &model.features {
                FeatureMap::Pvf(p) => Some(PvfGraph::new(p)),
                _ => None,
            },
            switches: Vec::new(),
            by_action: Vec::new(),
            next_q: Vec::new(),
            model,
        }
    }

    /// The model.
    pub fn model(&self) -> &ContinuousModel {
        &self.model
    }

    /// The parameters.
    pub fn params(&self) -> &ValidParams {
        &self.params
    }

    /// The drive.
    pub fn drive(&self) -> &Drive {
        &self.drive
    }

    /// Ticks so far.
    pub fn tick(&self) -> u64 {
        self.tick
    }

    /// Counters.
    pub fn stats(&self) -> ContinuousStats {
        if let Some(grid) = &self.grid {
            let g = grid.stats();
            return ContinuousStats {
                clipped: self.clipped,
                samples: g.kept,
                slots: g.known,
                updates: 0,
                rebuilds: 0,
                basis_builds: 0,
            };
        }
        ContinuousStats {
            clipped: self.clipped,
            samples: self.store.len(),
            slots: self.store.slots(),
            updates: self.planner.updates,
            rebuilds: self.planner.rebuilds,
            basis_builds: self.graph.as_ref().map_or(0, |g| g.builds),
        }
    }

    /// Checks an observation without changing anything.
    pub fn validate(&self, obs: &ContinuousObservation<'_>) -> Result<()> {
        self.check(obs).map(drop)
    }

    /// [`Self::validate`], returning the normalised point and where it fell.
    fn check(&self, obs: &ContinuousObservation<'_>) -> Result<(Vec<f64>, Placement)> {
        let mut s = Vec::with_capacity(self.model.dim());
        let placement = self.model.spec.observation_space.normalise_into(
            obs.observation,
            self.model.spec.out_of_bounds,
            &mut s,
        )?;
        if self.s.is_none() {
            if obs.stimulus.is_some() {
                return Err(AlgoError::FirstObservation { field: "stimulus" });
            }
            if obs.action_taken.is_some() {
                return Err(AlgoError::FirstObservation {
                    field: "action_taken",
                });
            }
            return Ok((s, placement));
        }
        let xi = obs.stimulus.ok_or(AlgoError::MissingStimulus)?;
        check_stimulus(xi, self.model.n_stimuli())?;
        if let Some(a) = obs.action_taken
            && a >= self.model.n_actions()
        {
            return Err(AlgoError::ActionOutOfRange {
                action: a,
                actions: self.model.n_actions(),
            });
        }
        Ok((s, placement))
    }

    /// One tick: observe (lines 5-7), plan (lines 8-9), act (line 10).
    /// Nothing changes on error.
    pub fn step(&mut self, obs: &ContinuousObservation<'_>) -> Result<ContinuousStep> {
        let observed = self.observe(obs)?;
        self.plan();
        let (action, value) = self.act_now();
        Ok(ContinuousStep {
            tick: observed.tick,
            action,
            reward: observed.reward,
            value,
            clipped: observed.clipped,
        })
    }

    /// Algorithm 1 lines 5-7: Ξ learns ξ(t+1), D moves (Eq. 3), and the
    /// transition (s_t, a_t, s_{t+1}) is stored; no plan, no action.
    /// Nothing changes on error. [`Self::plan`] then [`Self::act`] finish
    /// the tick, as [`Self::step`] does; a server in async mode may plan
    /// later, after several observations.
    pub fn observe(&mut self, obs: &ContinuousObservation<'_>) -> Result<ContinuousObserved> {
        let (s, placement) = self.check(obs)?;
        let clipped = placement == Placement::Clipped;
        if clipped {
            self.clipped += 1;
        }
        if self.grid.is_some() {
            return Ok(self.observe_on_grid(s, obs, clipped));
        }
        if let Some(graph) = &mut self.graph {
            graph.observe(&s, self.s.is_some());
        }
        let mut v = vec![0.0; self.model.features.len()];
        self.model.features.features_into(&s, &mut v);
        let mut reward = 0.0;
        if let (Some((prev_s, prev_v)), Some(xi)) = (self.s.take(), obs.stimulus) {
            // `advised` is set whenever `s` is (act follows every observe).
            let a = obs.action_taken.or(self.advised).unwrap_or(0);
            self.xi.update(a, &prev_v, xi);
            reward = self.drive.update(xi).abs();
            debug_assert!((crate::drive::norm(self.drive.vector()) - 1.0).abs() < 1e-9);
            self.tick += 1;
            self.record(&prev_s, a, &s, &prev_v, &v, xi);
            self.needs_plan = true;
        } else {
            self.refresh_reward_weights(&v);
        }
        self.s = Some((s, v));
        Ok(ContinuousObserved {
            tick: self.tick,
            reward,
            clipped,
        })
    }

    /// [`Self::observe`] for a grid: the transition and ξ go to the grid
    /// planner; on the first observation, R is computed for the action.
    fn observe_on_grid(
        &mut self,
        s: Vec<f64>,
        obs: &ContinuousObservation<'_>,
        clipped: bool,
    ) -> ContinuousObserved {
        let mut reward = 0.0;
        if let (Some((prev_s, _)), Some(xi)) = (self.s.take(), obs.stimulus) {
            let a = obs.action_taken.or(self.advised).unwrap_or(0);
            if let Some(grid) = &mut self.grid {
                grid.observe(&prev_s, a, &s, xi);
            }
            reward = self.drive.update(xi).abs();
            debug_assert!((crate::drive::norm(self.drive.vector()) - 1.0).abs() < 1e-9);
            self.tick += 1;
            self.needs_plan = true;
        } else {
            self.scale_drive();
            if let Some(grid) = &mut self.grid {
                grid.rewards(&self.scaled_drive);
            }
        }
        self.s = Some((s, Vec::new()));
        ContinuousObserved {
            tick: self.tick,
            reward,
            clipped,
        }
    }

    /// `scaled_drive` = Λ D.
    fn scale_drive(&mut self) {
        for ((s, d), l) in self
            .scaled_drive
            .iter_mut()
            .zip(self.drive.vector())
            .zip(self.drive.inv_rho())
        {
            *s = d * l;
        }
    }

    /// Whether an observation was taken since the last [`Self::plan`].
    pub fn needs_plan(&self) -> bool {
        self.needs_plan
    }

    /// Lines 8-9, once, if an observation came since the last plan.
    pub fn plan(&mut self) {
        if !self.needs_plan {
            return;
        }
        if self.grid.is_some() {
            self.scale_drive();
            if let Some(grid) = &mut self.grid {
                grid.plan(&self.scaled_drive);
            }
            self.needs_plan = false;
            self.policy_version += 1;
            return;
        }
        self.maybe_rebuild_basis();
        if let Some((s, v)) = self.s.take() {
            self.plan_at(&v);
            self.s = Some((s, v));
        }
        self.needs_plan = false;
        self.policy_version += 1;
    }

    /// Line 10 at the current observation: the next action and
    /// max_a Q there; `None` before the first observation.
    pub fn act(&mut self) -> Option<(usize, f64)> {
        let (s, v) = self.s.take()?;
        let out = self.act_at(&s, &v);
        self.s = Some((s, v));
        Some(out)
    }

    fn act_now(&mut self) -> (usize, f64) {
        // `observe` succeeded, so `s` is set.
        self.act().unwrap_or((0, 0.0))
    }

    /// Policy updates so far.
    pub fn policy_version(&self) -> u64 {
        self.policy_version
    }

    /// The action advised at the current observation, if any.
    pub fn advised_action(&self) -> Option<usize> {
        self.advised
    }
    /// Stores (s, a, s′) and gives the planner its term.
    fn record(
        &mut self,
        s: &[f64],
        a: usize,
        s_next: &[f64],
        v: &[f64],
        v_next: &[f64],
        xi: &[f64],
    ) {
        let before = self.store.visits(s, a);
        let inserted = self.store.insert(self.tick, s, a, s_next, v, v_next, xi);
        if let Some(old) = &inserted.replaced {
            self.planner.remove(inserted.index, old.as_ref());
        }
        // A pair that just became known: every stored successor in its cell learns it.
        if before + 1 == self.model.samples.known_after as u64 {
            let cell = self.store.cell(s);
            for (i, sample) in self.store.samples().iter().enumerate() {
                if i != inserted.index && self.store.cell(&sample.s_next) == cell {
                    self.known_next[i] |= 1 << a;
                }
            }
        }
        let mask = (0..self.model.n_actions())
            .filter(|&b| self.store.is_known(s_next, b))
            .fold(0u64, |m, b| m | 1 << b);
        if inserted.index == self.known_next.len() {
            self.known_next.push(mask);
        } else {
            self.known_next[inserted.index] = mask;
        }
        let (pi, known, _) = self.greedy_successor(inserted.index, false);
        self.planner
            .add(inserted.index, self.store.get(inserted.index), pi, known);
    }

    /// u_a = W_a Λ D; R(s_i, a_i) of every stored transition into
    /// `targets`, R(s′_i, a) of its unknown successor pairs into
    /// `next_rewards`; and R_max: the best reward the agent can name, over
    /// the stored transitions, their unknown successor pairs, every action
    /// at the current point and at the probe points (where Ξ may still
    /// hold its optimistic prior).
    #[inline(always)]
    fn refresh_reward_weights(&mut self, v_now: &[f64]) {
        self.scale_drive();
        self.xi.reward_weights_into(&self.scaled_drive, &mut self.u);
        let mut r_max: f64 = 0.0;
        for a in 0..self.model.n_actions() {
            r_max = r_max.max(self.reward(v_now, a));
        }
        let k = v_now.len();
        for v in self.probes.chunks_exact(k).take(PROBES) {
            for a in 0..self.model.n_actions() {
                r_max = r_max.max(self.reward(v, a));
            }
        }
        // R(s′_i, a) for every action in one product over the store ...
        let na = self.model.n_actions();
        transpose_into(&self.u, k, na, &mut self.by_action);
        self.next_rewards.clear();
        self.next_rewards.resize(self.store.len() * na, 0.0);
        let rows = self.store.v_next_rows();
        rows_times(rows, k, &self.by_action, na, &mut self.next_rewards);
        self.targets.clear();
        let u = &self.u;
        for ((sample, &mask), next) in self
            .store
            .iter()
            .zip(&self.known_next)
            .zip(self.next_rewards.chunks_exact_mut(na))
        {
            let r = dot(sample.v, &u[sample.a * k..(sample.a + 1) * k]).abs();
            self.targets.push(r);
            r_max = r_max.max(r);
            // ... of which only unknown successor pairs need R (for
            // Q_opt); a known one's reward is among the stored
            // transitions' own.
            for (a, r) in next.iter_mut().enumerate() {
                *r = if mask >> a & 1 == 1 { 0.0 } else { r.abs() };
                r_max = r_max.max(*r);
            }
        }
        self.r_max = r_max;
    }

    /// R(s, a) = |v(s) · u_a| (line 8).
    #[inline(always)]
    fn reward(&self, v: &[f64], a: usize) -> f64 {
        let k = v.len();
        dot(v, &self.u[a * k..(a + 1) * k]).abs()
    }

    /// Q(s, a) as the agent acts on it: v(s) · w_a for a known pair, Q_opt
    /// for an unknown one.
    fn q_at(&self, s: &[f64], v: &[f64], a: usize) -> f64 {
        if let Some(grid) = &self.grid {
            return grid.q(grid.cell_of(s), a);
        }
        if self.store.is_known(s, a) {
            self.planner.q(v, a)
        } else {
            self.q_opt(v, a)
        }
    }

    /// Q_opt(s, a) = R(s, a) + γ R_max / (1 − γ): an unknown pair.
    #[inline(always)]
    fn q_opt(&self, v: &[f64], a: usize) -> f64 {
        let g = self.params.gamma;
        self.reward(v, a) + g * self.r_max / (1.0 - g)
    }

    /// The greedy action at transition i's successor, whether that pair
    /// is known, and its advantage over the action A holds for i (0 when
    /// they are the same or tied).
    /// `cached`: R(s′_i, ·) is in `next_rewards` and Q(s′_i, ·) in
    /// `next_q` (as they are in [`plan_kernel`] after the evaluation, for
    /// the transitions stored then).
    #[inline(always)]
    fn greedy_successor(&self, i: usize, cached: bool) -> (usize, bool, f64) {
        let sample = self.store.get(i);
        let mask = self.known_next[i];
        let previous = self.planner.successor(i).map(|(pi, _)| pi);
        let mut best = (f64::NEG_INFINITY, 0usize);
        let mut qs = [0.0f64; super::model::MAX_ACTIONS];
        let na = self.model.n_actions();
        let g = self.params.gamma;
        for (a, q) in qs.iter_mut().enumerate().take(na) {
            *q = if mask >> a & 1 == 1 {
                if cached {
                    self.next_q[i * na + a]
                } else {
                    self.planner.q(sample.v_next, a)
                }
            } else if cached {
                self.next_rewards[i * na + a] + g * self.r_max / (1.0 - g)
            } else {
                self.q_opt(sample.v_next, a)
            };
            if *q > best.0 {
                best = (*q, a);
            }
        }
        let tol = TIE * (1.0 + best.0.abs());
        let (pi, advantage) = match previous {
            Some(p) if qs[p] >= best.0 - tol => (p, 0.0),
            Some(p) => (best.1, best.0 - qs[p]),
            None => (best.1, 0.0),
        };
        (pi, mask >> pi & 1 == 1, advantage)
    }

    /// Line 8 and line 9: rewards of the stored transitions, one LSTDQ
    /// evaluation, one bounded greedy improvement of the successor actions.
    fn plan_at(&mut self, v_now: &[f64]) {
        plan_kernel(self, v_now);
    }

    /// Line 10: the greedy action at s (ties keep the previous action, else
    /// a uniform draw among the tied), or with probability ε a uniform one.
    fn act_at(&mut self, s: &[f64], v: &[f64]) -> (usize, f64) {
        let na = self.model.n_actions();
        let mut qs = [0.0f64; super::model::MAX_ACTIONS];
        let mut best = f64::NEG_INFINITY;
        for (a, q) in qs.iter_mut().enumerate().take(na) {
            *q = self.q_at(s, v, a);
            best = best.max(*q);
        }
        let tol = TIE * (1.0 + best.abs());
        let tied = |a: &usize| qs[*a] >= best - tol;
        let mut action = match self.advised.filter(tied) {
            Some(p) => p,
            None => {
                let count = (0..na).filter(tied).count();
                let pick = if count > 1 {
                    self.rng.random_range(0..count)
                } else {
                    0
                };
                (0..na).filter(tied).nth(pick).unwrap_or(0)
            }
        };
        if self.params.epsilon > 0.0 && self.rng.random::<f64>() < self.params.epsilon {
            action = self.rng.random_range(0..na);
        }
        self.advised = Some(action);
        (action, best)
    }

    /// Q(x, a) for every action at any observation (clipped into the box;
    /// unknown pairs optimistic, as the agent acts on them).
    pub fn q_values(&self, observation: &[f64]) -> Result<Vec<f64>> {
        let mut s = Vec::with_capacity(self.model.dim());
        self.model.spec.observation_space.normalise_into(
            observation,
            super::space::OutOfBounds::Clip,
            &mut s,
        )?;
        let mut v = vec![0.0; self.model.features.len()];
        self.model.features.features_into(&s, &mut v);
        Ok((0..self.model.n_actions())
            .map(|a| self.q_at(&s, &v, a))
            .collect())
    }

    /// V(x) = max_a Q(x, a) at any observation.
    pub fn value(&self, observation: &[f64]) -> Result<f64> {
        Ok(self
            .q_values(observation)?
            .into_iter()
            .fold(f64::NEG_INFINITY, f64::max))
    }
}

/// out (k × actions, row-major) = the `actions` blocks of k in `blocks`,
/// transposed.
#[inline(always)]
fn transpose_into(blocks: &[f64], k: usize, actions: usize, out: &mut Vec<f64>) {
    out.clear();
    out.resize(k * actions, 0.0);
    for (a, block) in blocks.chunks_exact(k).take(actions).enumerate() {
        for (j, &b) in block.iter().enumerate() {
            out[j * actions + a] = b;
        }
    }
}

/// [`ContinuousAgent::plan_at`]'s body, compiled for AVX-512, AVX2, AVX and
/// NEON as well and picked at run time: its passes over the sample store
/// are inner products ([`dot`]'s four fixed accumulators), products over
/// the store ([`rows_times`], each entry summed in order) and elementwise
/// sums, done in the same order whatever the vector width (no FMA
/// contraction), so every version gives the same bits.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx",
    "aarch64+neon"
))]
fn plan_kernel(agent: &mut ContinuousAgent, v_now: &[f64]) {
    agent.refresh_reward_weights(v_now);
    let g = agent.params.gamma;
    let na = agent.model.n_actions();
    let opt = g * agent.r_max / (1.0 - g);
    for i in 0..agent.store.len() {
        if let Some((pi, false)) = agent.planner.successor(i) {
            agent.targets[i] += g * (agent.next_rewards[i * na + pi] + opt);
        }
    }
    agent.planner.maybe_rebuild(&agent.store);
    agent.planner.evaluate(&agent.store, &agent.targets);
    // Q(s′_i, a) = v(s′_i) · w_a for every transition and action, in one
    // product over the store.
    let k = v_now.len();
    transpose_into(agent.planner.weights(), k, na, &mut agent.by_action);
    agent.next_q.clear();
    agent.next_q.resize(agent.store.len() * na, 0.0);
    let rows = agent.store.v_next_rows();
    rows_times(rows, k, &agent.by_action, na, &mut agent.next_q);
    // The improvement: every successor whose greedy action differs from
    // the one A holds is a candidate; at most MAX_SWITCHES of them, the
    // largest advantages first (ties by index), change this tick.
    agent.switches.clear();
    for i in 0..agent.store.len() {
        let (pi, known, advantage) = agent.greedy_successor(i, true);
        if agent.planner.successor(i) != Some((pi, known)) {
            agent.switches.push((advantage, i, pi, known));
        }
    }
    if agent.switches.len() > MAX_SWITCHES {
        agent
            .switches
            .select_nth_unstable_by(MAX_SWITCHES - 1, |x, y| {
                y.0.total_cmp(&x.0).then(x.1.cmp(&y.1))
            });
        agent.switches.truncate(MAX_SWITCHES);
        agent.switches.sort_unstable_by_key(|s| s.1);
    }
    for &(_, i, pi, known) in &agent.switches {
        agent
            .planner
            .set_successor(i, agent.store.get(i), pi, known);
    }
    agent.planner.flush();
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::AgentParams;
    use crate::continuous::{ContinuousSpec, ObservationSpace, OutOfBounds};

    fn spec(out_of_bounds: OutOfBounds) -> ContinuousSpec {
        ContinuousSpec {
            observation_space: ObservationSpace {
                low: vec![-1.0, 0.0],
                high: vec![1.0, 10.0],
            },
            actions: vec!["a".into(), "b".into(), "c".into()],
            stimuli: vec!["food".into(), "rest".into()],
            // The RBFs that were the default of d = 2 before the grid.
            basis: Some(crate::continuous::ContinuousBasisSpec::Rbf {
                centres_per_dim: 10,
                width: None,
            }),
            out_of_bounds,
            samples: Default::default(),
        }
    }

    fn agent(seed: u64, rule: OutOfBounds) -> ContinuousAgent {
        agent_on(seed, spec(rule))
    }

    fn agent_on(seed: u64, spec: ContinuousSpec) -> ContinuousAgent {
        let params = AgentParams {
            seed: Some(seed),
            ..Default::default()
        }
        .check(2, seed)
        .expect("params");
        ContinuousAgent::new(spec.build().expect("model"), params)
    }

    /// An agent on a PVF basis small enough to be rebuilt often.
    fn pvf_agent(seed: u64) -> ContinuousAgent {
        let mut s = spec(OutOfBounds::Clip);
        s.basis = Some(crate::continuous::ContinuousBasisSpec::Pvf {
            k: 12,
            nodes: Some(2048),
            neighbours: None,
        });
        agent_on(seed, s)
    }

    /// A deterministic little world: the action moves the point, food at one corner.
    fn drive(agent: &mut ContinuousAgent, ticks: usize) -> Vec<(usize, u64, u64)> {
        let mut x = vec![0.0, 5.0];
        let mut out = Vec::new();
        let first = agent.step(&ContinuousObservation {
            observation: &x,
            stimulus: None,
            action_taken: None,
        });
        let mut a = first.expect("first").action;
        for t in 0..ticks {
            x[0] =
                (x[0] + [-0.1, 0.1, 0.0][a] + 0.01 * ((t * 7 % 5) as f64 - 2.0)).clamp(-1.2, 1.2);
            x[1] = (x[1] + 0.3 * ((t % 3) as f64 - 1.0)).clamp(0.0, 10.0);
            let xi = [
                if x[0] < -0.8 { 6.0 } else { 0.0 },
                if x[0] > 0.8 { 6.0 } else { 0.0 },
            ];
            let step = agent
                .step(&ContinuousObservation {
                    observation: &x,
                    stimulus: Some(&xi),
                    action_taken: None,
                })
                .expect("step");
            assert!(step.value.is_finite() && step.reward.is_finite());
            let d = agent.drive().vector();
            assert!(
                (d.iter().map(|v| v * v).sum::<f64>().sqrt() - 1.0).abs() < 1e-9,
                "|D| = 1"
            );
            let value = agent.value(&x).expect("value");
            assert_eq!(
                value.to_bits(),
                step.value.to_bits(),
                "V at the observation is the step's"
            );
            out.push((step.action, step.value.to_bits(), step.reward.to_bits()));
            a = step.action;
        }
        out
    }

    #[test]
    fn the_same_seed_gives_the_same_bits_and_another_seed_does_not() {
        let (mut a, mut b, mut c) = (
            agent(3, OutOfBounds::Clip),
            agent(3, OutOfBounds::Clip),
            agent(4, OutOfBounds::Clip),
        );
        let (ra, rb, rc) = (drive(&mut a, 700), drive(&mut b, 700), drive(&mut c, 700));
        assert_eq!(ra, rb);
        assert_ne!(ra, rc);
        // Past a rebuild of A⁻¹ (every 256 ticks) and with observations clipped (x beyond ±1).
        assert!(a.stats().rebuilds >= 2, "{:?}", a.stats());
        assert!(a.stats().clipped > 0, "{:?}", a.stats());
    }

    /// The default basis of this space is a grid (docs/algorithm.md §9.8).
    #[test]
    fn a_grid_agent_gives_the_same_bits_for_the_same_seed() {
        let mut s = spec(OutOfBounds::Clip);
        s.basis = None;
        let (mut a, mut b, mut c) = (
            agent_on(3, s.clone()),
            agent_on(3, s.clone()),
            agent_on(4, s),
        );
        assert!(matches!(
            a.model().features,
            crate::continuous::FeatureMap::Grid(_)
        ));
        let (ra, rb, rc) = (drive(&mut a, 700), drive(&mut b, 700), drive(&mut c, 700));
        assert_eq!(ra, rb);
        assert_ne!(ra, rc);
        assert!(
            a.stats().slots > 0 && a.stats().clipped > 0,
            "{:?}",
            a.stats()
        );
    }

    /// A PVF basis is rebuilt as its graph grows; the rebuilds happen at
    /// the same ticks with the same bits for the same seed.
    #[test]
    fn a_pvf_basis_gives_the_same_bits_for_the_same_seed_across_rebuilds() {
        let (mut a, mut b, mut c) = (pvf_agent(3), pvf_agent(3), pvf_agent(4));
        let (ra, rb, rc) = (drive(&mut a, 700), drive(&mut b, 700), drive(&mut c, 700));
        assert_eq!(ra, rb);
        assert_ne!(ra, rc);
        let g = a.graph.as_ref().expect("graph");
        assert!(
            a.stats().basis_builds >= 2,
            "{:?} {} nodes {} edges",
            a.stats(),
            g.nodes(),
            g.edges()
        );
        assert_eq!(a.stats(), b.stats());
        let FeatureMap::Pvf(p) = &a.model().features else {
            panic!("a PVF basis");
        };
        assert!(p.nodes() >= 8, "{} nodes", p.nodes());
        assert_eq!(
            a.value(&[0.3, 4.0]).expect("v").to_bits(),
            b.value(&[0.3, 4.0]).expect("v").to_bits()
        );
    }

    /// `step` is `observe`, `plan`, `act`: an agent driven through the
    /// three calls gives the same bits; planning only every third
    /// observation (a server's async mode) is deterministic too.
    #[test]
    fn step_is_observe_plan_act() {
        step_is_observe_plan_act_on(|seed| agent(seed, OutOfBounds::Clip));
    }

    /// The same with a PVF basis, rebuilt along the way.
    #[test]
    fn step_is_observe_plan_act_with_a_pvf_basis() {
        step_is_observe_plan_act_on(pvf_agent);
    }

    fn step_is_observe_plan_act_on(make: impl Fn(u64) -> ContinuousAgent) {
        let mut whole = make(5);
        let expected = drive(&mut whole, 300);
        let run = |every: usize| {
            let mut a = make(5);
            let mut x = vec![0.0, 5.0];
            a.observe(&ContinuousObservation {
                observation: &x,
                stimulus: None,
                action_taken: None,
            })
            .expect("first");
            assert!(!a.needs_plan());
            let (mut act, _) = a.act().expect("an action");
            let mut out = Vec::new();
            for t in 0..300 {
                x[0] = (x[0] + [-0.1, 0.1, 0.0][act] + 0.01 * ((t * 7 % 5) as f64 - 2.0))
                    .clamp(-1.2, 1.2);
                x[1] = (x[1] + 0.3 * ((t % 3) as f64 - 1.0)).clamp(0.0, 10.0);
                let xi = [
                    if x[0] < -0.8 { 6.0 } else { 0.0 },
                    if x[0] > 0.8 { 6.0 } else { 0.0 },
                ];
                let o = a
                    .observe(&ContinuousObservation {
                        observation: &x,
                        stimulus: Some(&xi),
                        action_taken: None,
                    })
                    .expect("observe");
                assert!(a.needs_plan());
                if t % every == 0 {
                    a.plan();
                    assert!(!a.needs_plan());
                }
                let (next, value) = a.act().expect("an action");
                out.push((next, value.to_bits(), o.reward.to_bits()));
                act = next;
            }
            (out, a.policy_version())
        };
        let (lockstep, version) = run(1);
        assert_eq!(lockstep, expected);
        assert_eq!(version, 300);
        let (sparse, version) = run(3);
        assert_eq!(version, 100);
        assert_eq!(sparse, run(3).0, "deterministic");
        assert_ne!(sparse, expected, "planning less often is another run");
    }

    #[test]
    fn bad_observations_are_refused_and_change_nothing() {
        let mut agent = agent(1, OutOfBounds::Refuse);
        let obs = |x: &'static [f64], xi: Option<&'static [f64]>, a: Option<usize>| {
            ContinuousObservation {
                observation: x,
                stimulus: xi,
                action_taken: a,
            }
        };
        assert!(
            agent
                .step(&obs(&[0.0, 5.0], Some(&[0.0, 0.0]), None))
                .is_err(),
            "a stimulus on the first observation"
        );
        agent.step(&obs(&[0.0, 5.0], None, None)).expect("first");
        let before = agent.drive().clone();
        let absurd: [ContinuousObservation<'static>; 8] = [
            obs(&[0.0], Some(&[0.0, 0.0]), None),
            obs(&[0.0, 5.0, 1.0], Some(&[0.0, 0.0]), None),
            obs(&[f64::NAN, 5.0], Some(&[0.0, 0.0]), None),
            obs(&[0.0, f64::INFINITY], Some(&[0.0, 0.0]), None),
            obs(&[2.0, 5.0], Some(&[0.0, 0.0]), None),
            obs(&[0.0, 5.0], Some(&[1e300, 0.0]), None),
            obs(&[0.0, 5.0], Some(&[0.0]), None),
            obs(&[0.0, 5.0], Some(&[0.0, 0.0]), Some(usize::MAX)),
        ];
        for o in &absurd {
            assert!(agent.step(o).is_err(), "{o:?} was accepted");
        }
        assert!(
            agent.step(&obs(&[0.0, 5.0], None, None)).is_err(),
            "a later observation without stimulus"
        );
        assert_eq!(agent.drive(), &before);
        assert_eq!(agent.tick(), 0);
        agent
            .step(&obs(&[0.5, 5.0], Some(&[1.0, 0.0]), Some(2)))
            .expect("a good one after them");
        assert_eq!(agent.tick(), 1);
    }

    #[test]
    fn absurd_sample_parameters_are_refused() {
        for samples in [
            crate::continuous::SampleParams {
                max: Some(u32::MAX),
                ..Default::default()
            },
            crate::continuous::SampleParams {
                per_cell: Some(0),
                ..Default::default()
            },
            crate::continuous::SampleParams {
                cells_per_dim: Some(u32::MAX),
                ..Default::default()
            },
            crate::continuous::SampleParams {
                known_after: Some(u32::MAX),
                ..Default::default()
            },
        ] {
            let mut s = spec(OutOfBounds::Clip);
            s.samples = samples;
            assert!(s.build().is_err(), "{:?}", s.samples);
        }
        let mut s = spec(OutOfBounds::Clip);
        s.actions = (0..65).map(|i| format!("a{i}")).collect();
        assert!(s.build().is_err(), "65 actions");
        s.actions = vec!["x".into(), "x".into()];
        assert!(s.build().is_err(), "duplicate actions");
        let mut s = spec(OutOfBounds::Clip);
        s.stimuli.clear();
        assert!(s.build().is_err(), "no stimuli");
    }
}
