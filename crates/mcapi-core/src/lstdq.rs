//! Model-based LSTDQ and greedy policy improvement (Algorithm 1, line 9;
//! docs/algorithm.md §2.6 and §5).
//!
//! One call of [`Planner::update`] is exactly one LSTDQ evaluation of the
//! current policy π_t on the current reward R followed by one greedy
//! improvement, giving π_{t+1}:
//!
//! A = Φᵀ(Φ − γ P^π Φ), b = Φᵀ R, w = A⁻¹ b, Q = Φ w,
//! π_{t+1}(s) = argmax_a Q(s, a) over valid a (ties: keep, else uniform).
//!
//! Three engines compute Q, all exact up to rounding:
//! - **indicator basis, deterministic model**: Φ = I, so Q = R + γ P^π Q is
//!   policy evaluation on a functional graph (each state has one successor
//!   under π): every component is a cycle with trees hanging off it, solved in
//!   O(|S|) by a closed form on the cycle and back-substitution on the trees;
//!   then Q(s,a) = R(s,a) + γ V(s'), O(|pairs|). No matrix is ever formed.
//! - **indicator basis, stochastic model**: the same equation is the sparse
//!   system (I − γ P_π) V = R_π over states, solved by Gauss–Seidel sweeps
//!   warm-started from the previous V until the a-posteriori error bound
//!   γ/(1−γ)·‖ΔV‖∞ is below 1e-12 (1 + ‖V‖∞); if γ is so close to 1 that
//!   this takes more than 20 000 sweeps, a dense LU solve takes over (up to
//!   2048 states; beyond, the update reports an error).
//! - **state-block features** (PVF, custom): A = ΦᵀΦ − γ MᵀΨ_π with
//!   M[s'] = Σ_(s,a) P(s'|s,a) φ(s,a) and Ψ_π[s'] = φ(s', π(s')) (§5). ΦᵀΦ and
//!   M depend only on the model and basis and are shared between sessions
//!   ([`PlanningModel`]). A changes only where π changes: a new action at one
//!   state s' is a rank-one change of A, so A⁻¹ is kept and updated by
//!   Sherman–Morrison; while π is unchanged the factorisation is reused as
//!   is. A is rebuilt and re-inverted from scratch after many changes, every
//!   [`REFRESH_AFTER`] rank-one updates (to bound rounding drift), and when a
//!   Sherman–Morrison denominator is near zero. Ridge λI is added only when A
//!   is singular. When neither A⁻¹ nor R changed since the last evaluation,
//!   Q_{t+1} = Q_t bit for bit and the evaluation is skipped (the outcome is
//!   the one it would give: error 0, no policy change).

use nalgebra::{DMatrix, DVector};
use rand::{Rng, RngExt};

use super::basis::{Basis, StateFeatures};
use super::error::{AlgoError, Result};
use super::model::EnvModel;

/// Ties: actions within `TIE_TOLERANCE (1 + |max Q|)` of the max are tied (§2.6).
pub const TIE_TOLERANCE: f64 = 1e-10;

/// Rank-one updates of A⁻¹ before it is recomputed from scratch.
pub const REFRESH_AFTER: usize = 256;

/// Gauss–Seidel sweep cap for stochastic models.
const MAX_SWEEPS: usize = 20_000;

/// Stochastic models up to this many states fall back to a dense solve when
/// Gauss–Seidel does not converge (γ very close to 1).
const DENSE_FALLBACK_MAX_STATES: usize = 2048;

/// The immutable parts of planning shared by every session on one model:
/// the model, the basis and, for feature bases, ΦᵀΦ and M.
#[derive(Debug, Clone)]
pub struct PlanningModel {
    model: EnvModel,
    basis: Basis,
    features: Option<FeatureCache>,
}

/// ΦᵀΦ and M for a state-block basis (the factorisation inputs of §5).
#[derive(Debug, Clone)]
struct FeatureCache {
    /// Features per state.
    k: usize,
    /// ΦᵀΦ, K×K (block diagonal, one k×k block per action).
    gram: DMatrix<f64>,
    /// Column s' is M[s'] = Σ_(s,a) P(s'|s,a) φ(s,a), K×|S|.
    m: DMatrix<f64>,
    /// State features column-major (|S|×k): column j is v_j over states.
    v_cols: Vec<f64>,
    /// k rounded up to a multiple of [`LANES`]: the row stride of
    /// `rows_padded`.
    kp: usize,
    /// v(s) row-major with stride `kp`, zero-padded: the rows b = ΦᵀR reads.
    rows_padded: Vec<f64>,
    /// Features that are zero on every valid pair (e.g. the block of an
    /// action no state offers): their rows and columns of A are zero.
    unused: Vec<usize>,
}

impl PlanningModel {
    /// Prepares a model and basis for planning.
    pub fn new(model: EnvModel, basis: Basis) -> Self {
        let features = match &basis {
            Basis::Indicator => None,
            Basis::StateBlocks(f) => Some(FeatureCache::new(&model, f)),
        };
        Self {
            model,
            basis,
            features,
        }
    }

    /// The same basis on another model with the same states and actions
    /// (a learned P̂, issue 17); ΦᵀΦ and M are computed for it.
    pub fn with_model(&self, model: EnvModel) -> Result<Self> {
        if let Basis::StateBlocks(f) = &self.basis
            && f.states() != model.states()
        {
            return Err(AlgoError::InvalidBasis(format!(
                "the basis has features for {} states; the model has {}",
                f.states(),
                model.states()
            )));
        }
        Ok(Self::new(model, self.basis.clone()))
    }

    /// Replaces P(·|p) by `next` (one row of a learned P̂) and keeps M in
    /// step: M[s'] loses P_old(s'|p) φ(p) and gains P_new(s'|p) φ(p), O(k)
    /// per successor (§5). A planner on this model must then be told with
    /// [`Planner::model_changed`].
    pub fn set_successors(&mut self, p: usize, next: &[(u32, f64)]) {
        if let (Some(cache), Basis::StateBlocks(f)) = (&mut self.features, &self.basis) {
            let (s, a) = (self.model.pair_state(p), self.model.pair_action(p));
            let (k, v) = (cache.k, f.row(s));
            let (old_next, old_prob) = self.model.successors(p);
            let moves = old_next
                .iter()
                .zip(old_prob)
                .map(|(&t, &q)| (t, -q))
                .chain(next.iter().copied());
            for (t, q) in moves {
                let mut col = cache.m.column_mut(t as usize);
                for i in 0..k {
                    col[a * k + i] += q * v[i];
                }
            }
        }
        self.model.set_successors(p, next);
    }

    /// The environment model.
    pub fn model(&self) -> &EnvModel {
        &self.model
    }

    /// The basis.
    pub fn basis(&self) -> &Basis {
        &self.basis
    }

    /// Number of features.
    pub fn n_features(&self) -> usize {
        self.basis.n_features(&self.model)
    }

    fn state_features(&self) -> Option<&StateFeatures> {
        match &self.basis {
            Basis::Indicator => None,
            Basis::StateBlocks(f) => Some(f),
        }
    }
}

impl FeatureCache {
    fn new(model: &EnvModel, f: &StateFeatures) -> Self {
        let k = f.k();
        let big_k = k * model.n_actions();
        let mut gram = DMatrix::zeros(big_k, big_k);
        let mut m = DMatrix::zeros(big_k, model.states());
        for p in 0..model.n_pairs() {
            let (s, a) = (model.pair_state(p), model.pair_action(p));
            let v = f.row(s);
            for i in 0..k {
                for j in 0..k {
                    gram[(a * k + i, a * k + j)] += v[i] * v[j];
                }
            }
            let (next, prob) = model.successors(p);
            for (&t, &q) in next.iter().zip(prob) {
                let mut col = m.column_mut(t as usize);
                for i in 0..k {
                    col[a * k + i] += q * v[i];
                }
            }
        }
        let unused = (0..big_k).filter(|&j| gram[(j, j)] == 0.0).collect();
        let n = model.states();
        let mut v_cols = vec![0.0; n * k];
        for s in 0..n {
            for (j, &x) in f.row(s).iter().enumerate() {
                v_cols[j * n + s] = x;
            }
        }
        let kp = k.div_ceil(LANES) * LANES;
        let mut rows_padded = vec![0.0; n * kp];
        for s in 0..n {
            rows_padded[s * kp..s * kp + k].copy_from_slice(f.row(s));
        }
        Self {
            k,
            gram,
            m,
            v_cols,
            unused,
            kp,
            rows_padded,
        }
    }
}

/// What one planning step did.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct PlanOutcome {
    /// ‖Q_t − Q_{t+1}‖₂ over valid pairs (Fig. 2d).
    pub lstdq_error: f64,
    /// States whose greedy action changed.
    pub policy_changes: usize,
    /// True when the evaluation reused the previous factorisation unchanged.
    pub reused_factorisation: bool,
}

/// Counters of the planner's work.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub struct PlannerStats {
    /// LSTDQ evaluations.
    pub updates: u64,
    /// Evaluations that reused the factorisation unchanged.
    pub reuses: u64,
    /// Full rebuilds and inversions of A.
    pub factorisations: u64,
    /// Rank-one updates of A⁻¹.
    pub rank_one_updates: u64,
    /// Rebuilds that needed the ridge.
    pub ridge_used: u64,
}

/// Per-agent planning state: Q, π and the engine's caches.
#[derive(Debug, Clone)]
pub struct Planner {
    q: Vec<f64>,
    /// Chosen pair per state (absolute pair index).
    policy: Vec<u32>,
    engine: Engine,
    stats: PlannerStats,
}

#[derive(Debug, Clone)]
enum Engine {
    FunctionalGraph(FunctionalGraph),
    GaussSeidel { v: Vec<f64> },
    Features(Box<FeatureEngine>),
}

#[derive(Debug, Clone)]
struct FunctionalGraph {
    /// V^π of the last evaluation (warm start of Gauss–Seidel when a
    /// learned P̂ stops being deterministic, [`Planner::model_changed`]).
    v: Vec<f64>,
}

/// Work space of [`Planner::update`] that no agent keeps between updates:
/// one per thread, so an idle session holds only Q, π and what its engine
/// must remember (about 1.3 KiB less per hallway session; BENCHMARKS.md §8).
/// Every update writes what it reads of it first, so which thread plans a
/// session does not change a bit of its results.
#[derive(Debug, Default)]
struct Scratch {
    /// Q_{t+1} while it is computed; after the swap, the agent's old Q.
    q_next: Vec<f64>,
    /// The states whose action is no longer greedy under Q_{t+1}, in
    /// state order ([`Planner::compare`]).
    outdated: Vec<u32>,
    /// The functional-graph walk's marks and path.
    mark: Vec<u8>,
    stack: Vec<u32>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

impl Scratch {
    /// Takes the thread's scratch, with `q_next` of exactly `pairs` entries
    /// (its capacity too: after the swap it is the agent's Q, and an agent
    /// keeps no spare room).
    fn take(pairs: usize) -> Self {
        let mut s = SCRATCH.with_borrow_mut(std::mem::take);
        if s.q_next.capacity() != pairs {
            s.q_next = vec![0.0; pairs];
        } else if s.q_next.len() != pairs {
            s.q_next.resize(pairs, 0.0);
        }
        s
    }

    /// Gives the scratch back to the thread.
    fn put_back(self) {
        SCRATCH.with_borrow_mut(|s| *s = self);
    }
}

#[derive(Debug, Clone)]
struct FeatureEngine {
    /// Scratch for rebuilding A = ΦᵀΦ − γ MᵀΨ_π (ridge included if used).
    a: DMatrix<f64>,
    a_inv: DMatrix<f64>,
    /// A⁻¹ must be rebuilt before the next solve.
    stale: bool,
    ridge_active: bool,
    rank_one_since_refresh: usize,
    /// Policy changes not yet folded into A⁻¹: (state, old pair, new pair).
    pending: Vec<(u32, u32, u32)>,
    b: DVector<f64>,
    w: DVector<f64>,
    x: DVector<f64>,
    y: DVector<f64>,
    u: DVector<f64>,
    /// Scratch: Q(s, a) for every state and action, column-major |S|×|A|.
    q_states: Vec<f64>,
    /// Scratch: b with each action block padded to `kp` entries.
    b_wide: Vec<f64>,
    /// R of the last evaluation.
    r_last: Vec<f64>,
    /// The planner's Q is Φ A⁻¹ Φᵀ `r_last` for the current A⁻¹, bit for bit.
    evaluated: bool,
}

impl Planner {
    /// A planner for the initial policy π₀ (`policy[s]` = chosen pair of s).
    pub fn new(ctx: &PlanningModel, policy: Vec<u32>) -> Self {
        let model = &ctx.model;
        debug_assert_eq!(policy.len(), model.states());
        let engine = match (&ctx.features, model.is_deterministic()) {
            (None, true) => Engine::FunctionalGraph(FunctionalGraph {
                v: vec![0.0; model.states()],
            }),
            (None, false) => Engine::GaussSeidel {
                v: vec![0.0; model.states()],
            },
            (Some(cache), _) => {
                let big_k = cache.gram.nrows();
                Engine::Features(Box::new(FeatureEngine {
                    a: DMatrix::zeros(big_k, big_k),
                    a_inv: DMatrix::zeros(big_k, big_k),
                    stale: true,
                    ridge_active: false,
                    rank_one_since_refresh: 0,
                    pending: Vec::new(),
                    b: DVector::zeros(big_k),
                    w: DVector::zeros(big_k),
                    x: DVector::zeros(big_k),
                    y: DVector::zeros(big_k),
                    u: DVector::zeros(big_k),
                    q_states: vec![0.0; model.states() * model.n_actions()],
                    b_wide: vec![0.0; cache.kp * model.n_actions()],
                    r_last: Vec::new(),
                    evaluated: false,
                }))
            }
        };
        Self {
            q: vec![0.0; model.n_pairs()],
            policy,
            engine,
            stats: PlannerStats::default(),
        }
    }

    /// A planner resumed from a stored policy, Q and counters. The engine's
    /// caches start cold (a feature basis refactorises A on the next
    /// update); a warm-started iterative solve starts from V(s) = Q(s, π(s)).
    pub fn restore(
        ctx: &PlanningModel,
        policy: Vec<u32>,
        q: Vec<f64>,
        stats: PlannerStats,
    ) -> Result<Self> {
        let model = &ctx.model;
        if policy.len() != model.states() {
            return Err(AlgoError::InvalidSnapshot(format!(
                "policy has {} states; the model has {}",
                policy.len(),
                model.states()
            )));
        }
        if let Some(s) =
            (0..model.states()).find(|&s| !model.pairs_of(s).contains(&(policy[s] as usize)))
        {
            return Err(AlgoError::InvalidSnapshot(format!(
                "policy of state {s} is pair {}, not one of its own",
                policy[s]
            )));
        }
        if q.len() != model.n_pairs() || q.iter().any(|x| !x.is_finite()) {
            return Err(AlgoError::InvalidSnapshot(format!(
                "Q must have {} finite entries",
                model.n_pairs()
            )));
        }
        let mut planner = Self::new(ctx, policy);
        if let Engine::GaussSeidel { v } = &mut planner.engine {
            for (s, v) in v.iter_mut().enumerate() {
                *v = q[planner.policy[s] as usize];
            }
        }
        planner.q = q;
        planner.stats = stats;
        Ok(planner)
    }

    /// Tells the planner that P changed (a learned P̂, issue 17): a model
    /// that is no longer deterministic moves the functional-graph engine to
    /// Gauss–Seidel, warm-started from its V; a feature basis rebuilds A
    /// (which holds P through M) at the next update.
    pub fn model_changed(&mut self, ctx: &PlanningModel) {
        match &mut self.engine {
            Engine::FunctionalGraph(fg) if !ctx.model.is_deterministic() => {
                let v = std::mem::take(&mut fg.v);
                self.engine = Engine::GaussSeidel { v };
            }
            Engine::Features(fe) => {
                fe.stale = true;
                fe.evaluated = false;
            }
            _ => {}
        }
    }

    /// Q over valid pairs.
    pub fn q(&self) -> &[f64] {
        &self.q
    }

    /// The greedy policy: chosen pair per state.
    pub fn policy(&self) -> &[u32] {
        &self.policy
    }

    /// The pair π chooses in state `s`.
    #[inline]
    pub fn chosen_pair(&self, s: usize) -> usize {
        self.policy[s] as usize
    }

    /// V(s) = Q(s, π(s)).
    pub fn value(&self, s: usize) -> f64 {
        self.q[self.policy[s] as usize]
    }

    /// Work counters.
    pub fn stats(&self) -> PlannerStats {
        self.stats
    }

    /// True when the next update depends only on π and Q, which a snapshot
    /// stores: the functional-graph engine solves each evaluation in closed
    /// form and keeps V only as a warm start for a model that stops being
    /// deterministic. A Gauss–Seidel solve warm-starts from its last V and
    /// a feature basis continues its rank-one updates of A⁻¹, so a restored
    /// planner of those engines agrees with the live one only to rounding.
    pub fn restores_exactly(&self) -> bool {
        matches!(self.engine, Engine::FunctionalGraph(_))
    }

    /// One LSTDQ evaluation of π on `r` and one greedy improvement.
    ///
    /// On a numerical failure Q and π are left as they were.
    pub fn update(
        &mut self,
        ctx: &PlanningModel,
        r: &[f64],
        gamma: f64,
        ridge: f64,
        rng: &mut impl Rng,
    ) -> Result<PlanOutcome> {
        let mut scratch = Scratch::take(ctx.model.n_pairs());
        let outcome = self.update_in(ctx, r, gamma, ridge, rng, &mut scratch);
        scratch.put_back();
        outcome
    }

    /// [`Planner::update`] with the thread's work space.
    fn update_in(
        &mut self,
        ctx: &PlanningModel,
        r: &[f64],
        gamma: f64,
        ridge: f64,
        rng: &mut impl Rng,
        scratch: &mut Scratch,
    ) -> Result<PlanOutcome> {
        let model = &ctx.model;
        debug_assert_eq!(r.len(), model.n_pairs());
        let mut reused = true;
        match &mut self.engine {
            Engine::FunctionalGraph(fg) => {
                fg.evaluate(model, &self.policy, r, gamma, scratch);
            }
            Engine::GaussSeidel { v } => {
                gauss_seidel(model, &self.policy, r, gamma, v, &mut scratch.q_next)?;
            }
            Engine::Features(fe) => {
                let cache = ctx.features.as_ref().ok_or_else(|| {
                    AlgoError::Numerical("feature engine without feature cache".into())
                })?;
                let f = ctx.state_features().ok_or_else(|| {
                    AlgoError::Numerical("feature engine without features".into())
                })?;
                reused =
                    fe.prepare(model, f, cache, &self.policy, gamma, ridge, &mut self.stats)?;
                if reused && fe.evaluated && same_bits(&fe.r_last, r) {
                    // Neither A⁻¹ nor R changed since the last evaluation, so
                    // Q_{t+1} = Q_t bit for bit: the LSTDQ error is 0 and π,
                    // already greedy in Q_t, stays (no outdated state, no
                    // RNG draw). Skipping the evaluation changes nothing.
                    self.stats.updates += 1;
                    self.stats.reuses += 1;
                    return Ok(PlanOutcome {
                        lstdq_error: 0.0,
                        policy_changes: 0,
                        reused_factorisation: true,
                    });
                }
                fe.evaluated = false;
                fe.evaluate(model, cache, r, &mut scratch.q_next);
            }
        }
        // ‖Q_t − Q_{t+1}‖₂; a non-finite Q makes it non-finite too.
        let err_sq = self.compare(model, scratch);
        if !err_sq.is_finite() {
            if let Engine::Features(fe) = &mut self.engine {
                fe.stale = true;
            }
            return Err(AlgoError::Numerical("LSTDQ produced a non-finite Q".into()));
        }
        if let Engine::Features(fe) = &mut self.engine {
            fe.r_last.clear();
            fe.r_last.extend_from_slice(r);
            fe.evaluated = true;
        }
        std::mem::swap(&mut self.q, &mut scratch.q_next);
        self.stats.updates += 1;
        self.stats.reuses += u64::from(reused);
        let changes = self.improve(model, rng, &scratch.outdated);
        Ok(PlanOutcome {
            lstdq_error: err_sq.sqrt(),
            policy_changes: changes,
            reused_factorisation: reused,
        })
    }

    /// ‖Q_t − Q_{t+1}‖² over the valid pairs (in pair order), and, in the
    /// same pass, the states whose current action is no longer within the
    /// tie tolerance of max_a Q_{t+1}(s, a) (§2.6) into `outdated`: the only
    /// states [`Planner::improve`] has to look at again.
    fn compare(&self, model: &EnvModel, scratch: &mut Scratch) -> f64 {
        let Scratch {
            q_next, outdated, ..
        } = scratch;
        outdated.clear();
        let mut err_sq = 0.0;
        for s in 0..model.states() {
            let range = model.pairs_of(s);
            let mut max = f64::NEG_INFINITY;
            for (old, &new) in self.q[range.clone()].iter().zip(&q_next[range]) {
                err_sq += (old - new) * (old - new);
                max = f64::max(max, new);
            }
            let floor = max - TIE_TOLERANCE * (1.0 + max.abs());
            if q_next[self.policy[s] as usize] >= floor {
                continue;
            }
            outdated.push(s as u32);
        }
        err_sq
    }

    /// Greedy improvement with the tie rule of §2.6 (Algorithm 1, line 9)
    /// over the states [`Planner::compare`] found outdated, in state order;
    /// returns the number of states whose action changed.
    fn improve(&mut self, model: &EnvModel, rng: &mut impl Rng, outdated: &[u32]) -> usize {
        for &s in outdated {
            let s = s as usize;
            let range = model.pairs_of(s);
            let qs = &self.q[range.clone()];
            let max = qs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let floor = max - TIE_TOLERANCE * (1.0 + max.abs());
            let current = self.policy[s] as usize;
            let tied = qs.iter().filter(|&&q| q >= floor).count();
            let pick = if tied > 1 {
                rng.random_range(0..tied)
            } else {
                0
            };
            let offset = qs
                .iter()
                .enumerate()
                .filter(|&(_, &q)| q >= floor)
                .nth(pick)
                .map_or(0, |(i, _)| i);
            let new = (range.start + offset) as u32;
            if let Engine::Features(fe) = &mut self.engine {
                fe.pending.push((s as u32, current as u32, new));
            }
            self.policy[s] = new;
        }
        outdated.len()
    }
}

impl FunctionalGraph {
    /// Exact Q^π for a deterministic model and Φ = I (see module docs).
    fn evaluate(
        &mut self,
        model: &EnvModel,
        policy: &[u32],
        r: &[f64],
        gamma: f64,
        scratch: &mut Scratch,
    ) {
        const UNSEEN: u8 = 0;
        const ON_PATH: u8 = 1;
        const DONE: u8 = 2;
        let n = model.states();
        let next = |s: usize| model.next_state(policy[s] as usize);
        let reward = |s: usize| r[policy[s] as usize];
        let Scratch {
            q_next: q,
            mark,
            stack,
            ..
        } = scratch;
        mark.clear();
        mark.resize(n, UNSEEN);
        let v = &mut self.v;
        for start in 0..n {
            if mark[start] == DONE {
                continue;
            }
            stack.clear();
            let mut s = start;
            while mark[s] == UNSEEN {
                mark[s] = ON_PATH;
                stack.push(s as u32);
                s = next(s);
            }
            if mark[s] == ON_PATH {
                // The walk closed a cycle c_0 = s, c_1, ..., c_{L-1} (the stack's tail):
                // V(c_0) = Σ_i γ^i r(c_i) / (1 − γ^L), summed backwards (Horner).
                let pos = stack.iter().rposition(|&x| x as usize == s).unwrap_or(0);
                let cycle = &stack[pos..];
                let len = cycle.len();
                let mut sum = 0.0;
                for &c in cycle.iter().rev() {
                    sum = reward(c as usize) + gamma * sum;
                }
                let v0 = sum / (1.0 - gamma.powi(len as i32));
                v[s] = v0;
                mark[s] = DONE;
                let mut after = v0;
                for &c in cycle[1..].iter().rev() {
                    let c = c as usize;
                    after = reward(c) + gamma * after;
                    v[c] = after;
                    mark[c] = DONE;
                }
                stack.truncate(pos);
            }
            // The rest of the path leads into solved states: back-substitute.
            while let Some(u) = stack.pop() {
                let u = u as usize;
                v[u] = reward(u) + gamma * v[next(u)];
                mark[u] = DONE;
            }
        }
        for (p, qp) in q.iter_mut().enumerate() {
            *qp = r[p] + gamma * v[model.next_state(p)];
        }
    }
}

/// `a` and `b` hold the same bits (so −0 ≠ 0 and NaN = NaN of the same payload).
fn same_bits(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

/// Exact Q^π for a stochastic model and Φ = I (see module docs).
fn gauss_seidel(
    model: &EnvModel,
    policy: &[u32],
    r: &[f64],
    gamma: f64,
    v: &mut [f64],
    q: &mut [f64],
) -> Result<()> {
    let expect = |p: usize, v: &[f64]| -> f64 {
        let (next, prob) = model.successors(p);
        next.iter()
            .zip(prob)
            .map(|(&t, &w)| w * v[t as usize])
            .sum()
    };
    let bound = if gamma > 0.0 {
        gamma / (1.0 - gamma)
    } else {
        0.0
    };
    let mut converged = false;
    for _ in 0..MAX_SWEEPS {
        let mut delta: f64 = 0.0;
        let mut scale: f64 = 0.0;
        for s in 0..model.states() {
            let p = policy[s] as usize;
            let new = r[p] + gamma * expect(p, v);
            delta = delta.max((new - v[s]).abs());
            scale = scale.max(new.abs());
            v[s] = new;
        }
        if bound * delta <= 1e-12 * (1.0 + scale) {
            converged = true;
            break;
        }
    }
    if !converged {
        // γ so close to 1 that the sweeps contract too slowly: solve
        // (I − γ P_π) V = R_π directly when the model is small enough.
        if model.states() > DENSE_FALLBACK_MAX_STATES {
            return Err(AlgoError::Numerical(format!(
                "policy evaluation did not converge in {MAX_SWEEPS} sweeps with gamma = {gamma}; use a smaller `gamma`"
            )));
        }
        dense_policy_values(model, policy, r, gamma, v)?;
    }
    for (p, qp) in q.iter_mut().enumerate() {
        *qp = r[p] + gamma * expect(p, v);
    }
    Ok(())
}

/// V = (I − γ P_π)⁻¹ R_π by dense LU (the exact fallback of [`gauss_seidel`]).
fn dense_policy_values(
    model: &EnvModel,
    policy: &[u32],
    r: &[f64],
    gamma: f64,
    v: &mut [f64],
) -> Result<()> {
    let n = model.states();
    let mut m = DMatrix::<f64>::identity(n, n);
    let mut rhs = DVector::<f64>::zeros(n);
    for s in 0..n {
        let p = policy[s] as usize;
        rhs[s] = r[p];
        let (next, prob) = model.successors(p);
        for (&t, &w) in next.iter().zip(prob) {
            m[(s, t as usize)] -= gamma * w;
        }
    }
    let sol = m
        .lu()
        .solve(&rhs)
        .ok_or_else(|| AlgoError::Numerical("I − γP_π is singular".into()))?;
    v.copy_from_slice(sol.as_slice());
    Ok(())
}

impl FeatureEngine {
    /// Brings A⁻¹ up to date with π; returns true when nothing had to change.
    #[allow(clippy::too_many_arguments)]
    fn prepare(
        &mut self,
        model: &EnvModel,
        f: &StateFeatures,
        cache: &FeatureCache,
        policy: &[u32],
        gamma: f64,
        ridge: f64,
        stats: &mut PlannerStats,
    ) -> Result<bool> {
        if !self.stale && self.pending.is_empty() {
            return Ok(true);
        }
        let big_k = cache.gram.nrows();
        let too_many = self.pending.len() * 3 > big_k;
        if self.stale
            || too_many
            || self.rank_one_since_refresh + self.pending.len() > REFRESH_AFTER
        {
            self.pending.clear();
            return self
                .rebuild(model, f, cache, policy, gamma, ridge, stats)
                .map(|()| false);
        }
        let k = cache.k;
        let pending = std::mem::take(&mut self.pending);
        for &(s, old, new) in &pending {
            let s = s as usize;
            let (b_old, b_new) = (
                model.pair_action(old as usize),
                model.pair_action(new as usize),
            );
            let v = f.row(s);
            // A' = A + u zᵀ with u = γ M[s'] and z = (e_old − e_new) ⊗ v(s').
            self.u.copy_from(&cache.m.column(s));
            self.u *= gamma;
            // Sherman–Morrison: A'⁻¹ = A⁻¹ − (A⁻¹u)(zᵀA⁻¹) / (1 + zᵀA⁻¹u).
            // z has only 2k non-zeros (blocks b_old and b_new), so zᵀA⁻¹ and
            // zᵀx read just those rows.
            let big_k = self.a_inv.nrows();
            mat_vec(
                self.a_inv.as_slice(),
                self.u.as_slice(),
                self.x.as_mut_slice(),
            );
            let z_dot = |col: &[f64]| -> f64 {
                v.iter()
                    .enumerate()
                    .map(|(t, vt)| vt * (col[b_old * k + t] - col[b_new * k + t]))
                    .sum()
            };
            let denom = 1.0 + z_dot(self.x.as_slice());
            if !denom.is_finite() || denom.abs() < 1e-8 {
                return self
                    .rebuild(model, f, cache, policy, gamma, ridge, stats)
                    .map(|()| false);
            }
            for (yj, col) in self
                .y
                .iter_mut()
                .zip(self.a_inv.as_slice().chunks_exact(big_k))
            {
                *yj = z_dot(col);
            }
            rank_one_update(
                self.a_inv.as_mut_slice(),
                -1.0 / denom,
                self.x.as_slice(),
                self.y.as_slice(),
            );
            self.rank_one_since_refresh += 1;
            stats.rank_one_updates += 1;
        }
        self.pending = pending;
        self.pending.clear();
        Ok(false)
    }

    /// A = ΦᵀΦ − γ MᵀΨ_π from scratch, then A⁻¹ (with ridge only if singular).
    #[allow(clippy::too_many_arguments)]
    fn rebuild(
        &mut self,
        model: &EnvModel,
        f: &StateFeatures,
        cache: &FeatureCache,
        policy: &[u32],
        gamma: f64,
        ridge: f64,
        stats: &mut PlannerStats,
    ) -> Result<()> {
        let k = cache.k;
        self.a.copy_from(&cache.gram);
        let big_k = self.a.nrows();
        let (a, m) = (self.a.as_mut_slice(), cache.m.as_slice());
        for (s, &p) in policy.iter().enumerate() {
            // Block column π(s) of A loses γ M[s] v(s)ᵀ.
            let b = model.pair_action(p as usize);
            let block = &mut a[b * k * big_k..(b + 1) * k * big_k];
            rank_one_update(block, -gamma, &m[s * big_k..(s + 1) * big_k], f.row(s));
        }
        // An unused feature has a zero row and column in A and b_j = 0, so
        // w_j = 0 whatever A_jj is: set it to 1 to take the feature out of the
        // system instead of regularising every feature (our choice).
        for &j in &cache.unused {
            self.a[(j, j)] = 1.0;
        }
        stats.factorisations += 1;
        self.rank_one_since_refresh = 0;
        self.pending.clear();
        self.ridge_active = false;
        if let Some(inv) = invert_if_regular(&self.a) {
            self.a_inv = inv;
            self.stale = false;
            return Ok(());
        }
        for i in 0..self.a.nrows() {
            self.a[(i, i)] += ridge;
        }
        stats.ridge_used += 1;
        self.ridge_active = true;
        match invert_if_regular(&self.a) {
            Some(inv) => {
                self.a_inv = inv;
                self.stale = false;
                Ok(())
            }
            None => {
                self.stale = true;
                Err(AlgoError::Numerical(format!(
                    "A is singular even with ridge {ridge}; increase `ridge`"
                )))
            }
        }
    }

    /// b = ΦᵀR, w = A⁻¹b, Q = Φw (see [`feature_kernel`]).
    fn evaluate(&mut self, model: &EnvModel, cache: &FeatureCache, r: &[f64], q: &mut [f64]) {
        feature_kernel(
            FeatureKernel {
                pair_state: model.pair_states(),
                pair_action: model.pair_actions(),
                rows_padded: &cache.rows_padded,
                kp: cache.kp,
                v_cols: &cache.v_cols,
                k: cache.k,
                a_inv: self.a_inv.as_slice(),
                r,
            },
            FeatureScratch {
                b_wide: &mut self.b_wide,
                b: self.b.as_mut_slice(),
                w: self.w.as_mut_slice(),
                q_states: &mut self.q_states,
            },
            q,
        );
    }
}

/// Read-only inputs of [`feature_kernel`].
struct FeatureKernel<'a> {
    pair_state: &'a [u32],
    pair_action: &'a [u32],
    /// v(s) row-major, |S|×kp, zero-padded.
    rows_padded: &'a [f64],
    /// Row stride of `rows_padded`, a multiple of [`LANES`] ≥ k.
    kp: usize,
    /// v_j column-major, |S|×k.
    v_cols: &'a [f64],
    k: usize,
    /// A⁻¹ column-major, K×K.
    a_inv: &'a [f64],
    r: &'a [f64],
}

/// Outputs and scratch of [`feature_kernel`].
struct FeatureScratch<'a> {
    /// b with each action block padded to kp entries (|A|·kp).
    b_wide: &'a mut [f64],
    b: &'a mut [f64],
    w: &'a mut [f64],
    /// Q(s, a) for every state and action, column-major |S|×|A|.
    q_states: &'a mut [f64],
}

/// Lanes of the widest vector register the kernels are compiled for (8
/// doubles with AVX-512): the rows b = ΦᵀR reads are padded to a multiple,
/// so their axpys have no scalar remainder.
const LANES: usize = 8;

/// Rows per block of [`combine_columns_into`].
const ROW_BLOCK: usize = 16;

/// b = ΦᵀR, w = A⁻¹b, Q = Φw with the block structure φ(s,a) = e_a ⊗ v(s)
/// (docs/algorithm.md §2.6; §5, engine 3).
///
/// b gains R(s,a) v(s) in block a, pair by pair, as axpys over padded rows
/// (consecutive pairs mostly belong to different actions, so the axpys do
/// not wait for each other); w is the sum of A⁻¹'s columns weighted by b and
/// Q(·, a) = Σ_j w_(a,j) v_j over states, both by [`combine_columns_into`],
/// which keeps a block of outputs in registers while it walks the columns.
/// Every output is summed in a fixed order, so the bits do not depend on the
/// vector width: the function is compiled for AVX-512, AVX2 and NEON as well
/// and picks the best version at run time, and every version gives the same
/// results (no FMA contraction).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx",
    "aarch64+neon"
))]
fn feature_kernel<'a>(x: FeatureKernel<'a>, out: FeatureScratch<'a>, q: &mut [f64]) {
    let (k, kp) = (x.k, x.kp);
    let n = x.v_cols.len() / k;
    out.b_wide.fill(0.0);
    for ((&rp, &s), &a) in x.r.iter().zip(x.pair_state).zip(x.pair_action) {
        let (s, a) = (s as usize, a as usize);
        let block = &mut out.b_wide[a * kp..(a + 1) * kp];
        for (bj, vj) in block.iter_mut().zip(&x.rows_padded[s * kp..(s + 1) * kp]) {
            *bj += rp * vj;
        }
    }
    for (bj, wide) in out.b.chunks_exact_mut(k).zip(out.b_wide.chunks_exact(kp)) {
        bj.copy_from_slice(&wide[..k]);
    }
    combine_columns_into(out.w, x.a_inv, out.b);
    for (col, wa) in out.q_states.chunks_exact_mut(n).zip(out.w.chunks_exact(k)) {
        combine_columns_into(col, x.v_cols, wa);
    }
    for ((qp, &s), &a) in q.iter_mut().zip(x.pair_state).zip(x.pair_action) {
        *qp = out.q_states[a as usize * n + s as usize];
    }
}

/// x = M u for a square column-major M, as a sum of M's columns (vectorised;
/// AVX-512, AVX2 and NEON versions picked at run time).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx",
    "aarch64+neon"
))]
fn mat_vec(m: &[f64], u: &[f64], x: &mut [f64]) {
    combine_columns_into(x, m, u);
}

/// out = Σ_j c_j · cols_j, where `cols` holds `c.len()` columns of
/// `out.len()` entries each.
///
/// Every entry is summed from 0 in the same order: the columns four at a
/// time, out_i += (c₀a₀ᵢ + c₁a₁ᵢ) + (c₂a₂ᵢ + c₃a₃ᵢ), then the columns left
/// over one at a time. So the bits do not depend on the vector width, nor on
/// the blocking: the rows are done [`ROW_BLOCK`] at a time (then 4, then 1),
/// each block summed in registers over all columns and stored once.
#[inline(always)]
fn combine_columns_into(out: &mut [f64], cols: &[f64], c: &[f64]) {
    let n = out.len();
    let mut i0 = 0;
    while n - i0 >= ROW_BLOCK {
        combine_rows::<ROW_BLOCK>(out, cols, c, i0);
        i0 += ROW_BLOCK;
    }
    while n - i0 >= 4 {
        combine_rows::<4>(out, cols, c, i0);
        i0 += 4;
    }
    while i0 < n {
        combine_rows::<1>(out, cols, c, i0);
        i0 += 1;
    }
}

/// Rows i0..i0+W of [`combine_columns_into`].
#[inline(always)]
fn combine_rows<const W: usize>(out: &mut [f64], cols: &[f64], c: &[f64], i0: usize) {
    let n = out.len();
    let mut acc = [0.0f64; W];
    let mut quads = c.chunks_exact(4);
    for (q, c4) in (&mut quads).enumerate() {
        let base = 4 * q * n + i0;
        let a0 = &cols[base..base + W];
        let a1 = &cols[base + n..base + n + W];
        let a2 = &cols[base + 2 * n..base + 2 * n + W];
        let a3 = &cols[base + 3 * n..base + 3 * n + W];
        let (c0, c1, c2, c3) = (c4[0], c4[1], c4[2], c4[3]);
        for ((((o, x0), x1), x2), x3) in acc.iter_mut().zip(a0).zip(a1).zip(a2).zip(a3) {
            *o += (c0 * x0 + c1 * x1) + (c2 * x2 + c3 * x3);
        }
    }
    let done = c.len() / 4 * 4;
    for (j, &cj) in c.iter().enumerate().skip(done) {
        let base = j * n + i0;
        for (o, x) in acc.iter_mut().zip(&cols[base..base + W]) {
            *o += cj * x;
        }
    }
    out[i0..i0 + W].copy_from_slice(&acc);
}

/// M += alpha x yᵀ for a column-major M with `x.len()` rows and `y.len()`
/// columns (vectorised like [`mat_vec`]).
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+avx", "aarch64+neon"))]
fn rank_one_update(m: &mut [f64], alpha: f64, x: &[f64], y: &[f64]) {
    for (&yj, col) in y.iter().zip(m.chunks_exact_mut(x.len())) {
        let c = alpha * yj;
        if c != 0.0 {
            for (mi, xi) in col.iter_mut().zip(x) {
                *mi += c * xi;
            }
        }
    }
}

/// A⁻¹ by LU with partial pivoting, or `None` when A is numerically singular
/// (a pivot below 1e-12 of the largest).
fn invert_if_regular(a: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let lu = a.clone().lu();
    let u = lu.u();
    let diag = u.diagonal();
    let max = diag.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let min = diag.iter().fold(f64::INFINITY, |m, x| m.min(x.abs()));
    if !(max.is_finite() && max > 0.0 && min > 1e-12 * max) {
        return None;
    }
    lu.try_inverse()
        .filter(|inv| inv.iter().all(|x| x.is_finite()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{hallway, names};
    use crate::spec::BasisSpec;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn first_action_policy(model: &EnvModel) -> Vec<u32> {
        (0..model.states())
            .map(|s| model.pairs_of(s).start as u32)
            .collect()
    }

    /// The axpy-form kernels the blocked ones replaced (commit 15aa12d):
    /// b gains R(s,a) v(s) pair by pair, w and Q are sums of columns four at
    /// a time. The blocked kernels must give the same bits.
    fn reference_kernel(
        model: &EnvModel,
        f: &StateFeatures,
        a_inv: &[f64],
        r: &[f64],
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        fn combine(out: &mut [f64], cols: &[f64], c: &[f64]) {
            let n = out.len();
            out.fill(0.0);
            let mut quads = cols.chunks_exact(4 * n).zip(c.chunks_exact(4));
            for (block, c4) in &mut quads {
                for (i, o) in out.iter_mut().enumerate() {
                    *o += (c4[0] * block[i] + c4[1] * block[n + i])
                        + (c4[2] * block[2 * n + i] + c4[3] * block[3 * n + i]);
                }
            }
            let done = c.len() / 4 * 4;
            for (&cj, col) in c[done..].iter().zip(cols[done * n..].chunks_exact(n)) {
                for (o, v) in out.iter_mut().zip(col) {
                    *o += cj * v;
                }
            }
        }
        let (k, n) = (f.k(), model.states());
        let big_k = k * model.n_actions();
        let mut b = vec![0.0; big_k];
        for (p, &rp) in r.iter().enumerate() {
            let (s, a) = (model.pair_state(p), model.pair_action(p));
            for (bj, vj) in b[a * k..(a + 1) * k].iter_mut().zip(f.row(s)) {
                *bj += rp * vj;
            }
        }
        let mut w = vec![0.0; big_k];
        combine(&mut w, a_inv, &b);
        let mut v_cols = vec![0.0; n * k];
        for s in 0..n {
            for (j, &x) in f.row(s).iter().enumerate() {
                v_cols[j * n + s] = x;
            }
        }
        let mut q_states = vec![0.0; n * model.n_actions()];
        for (col, wa) in q_states.chunks_exact_mut(n).zip(w.chunks_exact(k)) {
            combine(col, &v_cols, wa);
        }
        let q = (0..model.n_pairs())
            .map(|p| q_states[model.pair_action(p) * n + model.pair_state(p)])
            .collect();
        (b, w, q)
    }

    #[test]
    fn blocked_kernels_match_the_axpy_reference_bit_for_bit() {
        let model = hallway().model;
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut normal = || rng.random::<f64>() * 2.0 - 1.0;
        let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        for k in [1, 3, 4, 5, 7, 8, 9, 16, 17, 30, 33, 41, 50] {
            let rows: Vec<Vec<f64>> = (0..50)
                .map(|_| (0..k).map(|_| normal()).collect())
                .collect();
            let basis = Basis::build(
                &BasisSpec::Custom {
                    state_features: rows,
                },
                &model,
            )
            .expect("basis");
            let ctx = PlanningModel::new(model.clone(), basis);
            let (f, cache) = (
                ctx.state_features().expect("features"),
                ctx.features.as_ref().expect("cache"),
            );
            let big_k = 3 * k;
            let a_inv: Vec<f64> = (0..big_k * big_k).map(|_| normal()).collect();
            let r: Vec<f64> = (0..model.n_pairs()).map(|_| normal().abs()).collect();
            let (mut b, mut w, mut q) = (vec![0.0; big_k], vec![0.0; big_k], vec![0.0; 148]);
            let mut q_states = vec![0.0; 150];
            feature_kernel(
                FeatureKernel {
                    pair_state: model.pair_states(),
                    pair_action: model.pair_actions(),
                    rows_padded: &cache.rows_padded,
                    kp: cache.kp,
                    v_cols: &cache.v_cols,
                    k,
                    a_inv: &a_inv,
                    r: &r,
                },
                FeatureScratch {
                    b_wide: &mut vec![0.0; 3 * cache.kp],
                    b: &mut b,
                    w: &mut w,
                    q_states: &mut q_states,
                },
                &mut q,
            );
            let (b_ref, w_ref, q_ref) = reference_kernel(&model, f, &a_inv, &r);
            assert_eq!(bits(&b), bits(&b_ref), "b, k = {k}");
            assert_eq!(bits(&w), bits(&w_ref), "w, k = {k}");
            assert_eq!(bits(&q), bits(&q_ref), "Q, k = {k}");
            let mut x = vec![0.0; big_k];
            mat_vec(&a_inv, &b_ref, &mut x);
            assert_eq!(bits(&x), bits(&w_ref), "A⁻¹u, k = {k}");
        }
    }

    #[test]
    fn an_evaluation_with_nothing_changed_is_skipped_without_changing_results() {
        let model = hallway().model;
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let rows: Vec<Vec<f64>> = (0..50)
            .map(|_| (0..6).map(|_| rng.random::<f64>() - 0.5).collect())
            .collect();
        let basis = Basis::build(
            &BasisSpec::Custom {
                state_features: rows,
            },
            &model,
        )
        .expect("basis");
        let ctx = PlanningModel::new(model.clone(), basis);
        let mut r: Vec<f64> = (0..model.n_pairs()).map(|_| rng.random::<f64>()).collect();
        let mut memo = Planner::new(&ctx, first_action_policy(&model));
        let mut full = memo.clone();
        let mut skipped = 0;
        for t in 0..60 {
            if t == 30 {
                r[7] += 0.25;
            }
            // `full` evaluates every time, `memo` may skip.
            if let Engine::Features(fe) = &mut full.engine {
                fe.evaluated = false;
            }
            if let Engine::Features(fe) = &memo.engine {
                skipped += usize::from(
                    fe.evaluated && !fe.stale && fe.pending.is_empty() && fe.r_last == r,
                );
            }
            let mut rng_full = rng.clone();
            let a = memo.update(&ctx, &r, 0.9, 1e-6, &mut rng).expect("memo");
            let b = full
                .update(&ctx, &r, 0.9, 1e-6, &mut rng_full)
                .expect("full");
            assert_eq!(a, b, "tick {t}");
            assert_eq!(memo.policy(), full.policy(), "tick {t}");
            let bits = |p: &Planner| p.q().iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&memo), bits(&full), "tick {t}");
            assert_eq!(memo.stats(), full.stats(), "tick {t}");
        }
        assert!(skipped > 40, "only {skipped} evaluations skipped");
    }

    #[test]
    fn a_changed_row_of_p_updates_m_and_the_plan() {
        let model = hallway().model;
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let rows: Vec<Vec<f64>> = (0..50)
            .map(|_| (0..4).map(|_| rng.random::<f64>() - 0.5).collect())
            .collect();
        let spec = BasisSpec::Custom {
            state_features: rows,
        };
        let basis = Basis::build(&spec, &model).expect("basis");
        let mut ctx = PlanningModel::new(model.clone(), basis.clone());
        let r: Vec<f64> = (0..model.n_pairs()).map(|_| rng.random::<f64>()).collect();
        let mut planner = Planner::new(&ctx, first_action_policy(&model));
        planner.update(&ctx, &r, 0.9, 1e-6, &mut rng).expect("plan");
        // Pair (20, right) becomes slippery: 0.7 to 21, 0.3 stays.
        let p = model.pair(20, 1).expect("right");
        ctx.set_successors(p, &[(21, 0.7), (20, 0.3)]);
        planner.model_changed(&ctx);
        let fresh = PlanningModel::new(ctx.model().clone(), basis);
        let (m, m_ref) = (
            &ctx.features.as_ref().expect("cache").m,
            &fresh.features.as_ref().expect("cache").m,
        );
        assert!((m - m_ref).amax() < 1e-12, "M kept in step with P");
        let mut reference = Planner::new(&fresh, planner.policy().to_vec());
        let mut rng_ref = rng.clone();
        planner.update(&ctx, &r, 0.9, 1e-6, &mut rng).expect("plan");
        reference
            .update(&fresh, &r, 0.9, 1e-6, &mut rng_ref)
            .expect("reference plan");
        for (a, b) in planner.q().iter().zip(reference.q()) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        // The functional-graph engine moves to Gauss–Seidel.
        let mut ind = PlanningModel::new(model.clone(), Basis::Indicator);
        let mut fg = Planner::new(&ind, first_action_policy(&model));
        fg.update(&ind, &r, 0.9, 1e-6, &mut rng).expect("plan");
        ind.set_successors(p, &[(21, 0.7), (20, 0.3)]);
        fg.model_changed(&ind);
        assert!(matches!(fg.engine, Engine::GaussSeidel { .. }));
        fg.update(&ind, &r, 0.9, 1e-6, &mut rng)
            .expect("stochastic plan");
    }

    #[test]
    fn two_state_cycle_by_hand() {
        // 0 -go-> 1 -go-> 0, R = (1, 0), γ = 0.5: V0 = 1/(1−0.25) = 4/3, V1 = 0.5 V0.
        let model = EnvModel::deterministic(
            vec![vec![Some(1)], vec![Some(0)]],
            names(&["go"]),
            names(&["x"]),
        )
        .expect("model");
        let ctx = PlanningModel::new(model, Basis::Indicator);
        let mut planner = Planner::new(&ctx, vec![0, 1]);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let out = planner
            .update(&ctx, &[1.0, 0.0], 0.5, 1e-6, &mut rng)
            .expect("plan");
        assert!((planner.q()[0] - 4.0 / 3.0).abs() < 1e-15);
        assert!((planner.q()[1] - 2.0 / 3.0).abs() < 1e-15);
        assert!((out.lstdq_error - (16.0f64 / 9.0 + 4.0 / 9.0).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn hallway_policy_walks_to_the_reward() {
        let model = hallway().model;
        let ctx = PlanningModel::new(model.clone(), Basis::Indicator);
        let mut planner = Planner::new(&ctx, first_action_policy(&model));
        // Reward only for staying at 10.
        let mut r = vec![0.0; model.n_pairs()];
        r[model.pair(10, 2).expect("stay")] = 1.0;
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        for _ in 0..60 {
            planner
                .update(&ctx, &r, 0.95, 1e-6, &mut rng)
                .expect("plan");
        }
        for s in 0..50 {
            let a = model.pair_action(planner.chosen_pair(s));
            let expected = match s.cmp(&10) {
                std::cmp::Ordering::Less => 1,
                std::cmp::Ordering::Equal => 2,
                std::cmp::Ordering::Greater => 0,
            };
            assert_eq!(a, expected, "state {s}");
        }
        assert!((planner.value(10) - 20.0).abs() < 1e-9, "V(10) = 1/(1-γ)");
    }

    #[test]
    fn ties_keep_the_previous_action() {
        let model = hallway().model;
        let ctx = PlanningModel::new(model.clone(), Basis::Indicator);
        let policy: Vec<u32> = (0..50).map(|s| model.pairs_of(s).end as u32 - 1).collect();
        let mut planner = Planner::new(&ctx, policy.clone());
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let out = planner
            .update(&ctx, &vec![0.0; model.n_pairs()], 0.9, 1e-6, &mut rng)
            .expect("plan");
        assert_eq!(out.policy_changes, 0);
        assert_eq!(planner.policy(), &policy[..]);
    }

    #[test]
    fn feature_engine_matches_indicator_when_features_are_complete() {
        // With one-hot state features the block basis spans all pairs, so
        // LSTDQ is exact and must agree with the indicator engine.
        let model = hallway().model;
        let eye: Vec<Vec<f64>> = (0..50)
            .map(|s| (0..50).map(|j| f64::from(u8::from(s == j))).collect())
            .collect();
        let basis = Basis::build(
            &BasisSpec::Custom {
                state_features: eye,
            },
            &model,
        )
        .expect("basis");
        let feat = PlanningModel::new(model.clone(), basis);
        let ind = PlanningModel::new(model.clone(), Basis::Indicator);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let r: Vec<f64> = (0..model.n_pairs())
            .map(|p| ((p * 37) % 11) as f64 / 10.0)
            .collect();
        let mut pf = Planner::new(&feat, first_action_policy(&model));
        let mut pi = Planner::new(&ind, first_action_policy(&model));
        for _ in 0..30 {
            let mut rng_f = rng.clone();
            pf.update(&feat, &r, 0.9, 1e-6, &mut rng_f)
                .expect("feature plan");
            pi.update(&ind, &r, 0.9, 1e-6, &mut rng)
                .expect("indicator plan");
            for (a, b) in pf.q().iter().zip(pi.q()) {
                assert!((a - b).abs() < 1e-8, "{a} vs {b}");
            }
            assert_eq!(pf.policy(), pi.policy());
        }
        assert!(pf.stats().rank_one_updates > 0, "{:?}", pf.stats());
    }
}
