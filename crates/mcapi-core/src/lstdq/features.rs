//! Engine 3: state-block features (proto-value functions, custom bases).
//! A = ΦᵀΦ − γ MᵀΨ_π with ΦᵀΦ and M shared by every session on the model
//! ([`FeatureCache`]); A⁻¹ kept and updated by Sherman–Morrison where π
//! changes, rebuilt every [`super::REFRESH_AFTER`] rank-one updates and when
//! a denominator is near zero (module docs of [`super`]).

use super::kernels::*;
use super::*;

/// ΦᵀΦ and M for a state-block basis (the factorisation inputs of §5).
#[derive(Debug, Clone)]
pub(super) struct FeatureCache {
    /// Features per state.
    pub(super) k: usize,
    /// ΦᵀΦ, K×K (block diagonal, one k×k block per action).
    pub(super) gram: DMatrix<f64>,
    /// Column s' is M[s'] = Σ_(s,a) P(s'|s,a) φ(s,a), K×|S|.
    pub(super) m: DMatrix<f64>,
    /// State features column-major (|S|×k): column j is v_j over states.
    pub(super) v_cols: Vec<f64>,
    /// k rounded up to a multiple of [`LANES`]: the row stride of
    /// `rows_padded`.
    pub(super) kp: usize,
    /// v(s) row-major with stride `kp`, zero-padded: the rows b = ΦᵀR reads.
    pub(super) rows_padded: Vec<f64>,
    /// Features that are zero on every valid pair (e.g. the block of an
    /// action no state offers): their rows and columns of A are zero.
    pub(super) unused: Vec<usize>,
}

impl FeatureCache {
    pub(super) fn new(model: &EnvModel, f: &StateFeatures) -> Self {
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

#[derive(Debug, Clone)]
pub(super) struct FeatureEngine {
    /// Scratch for rebuilding A = ΦᵀΦ − γ MᵀΨ_π (ridge included if used).
    pub(super) a: DMatrix<f64>,
    pub(super) a_inv: DMatrix<f64>,
    /// A⁻¹ must be rebuilt before the next solve.
    pub(super) stale: bool,
    pub(super) ridge_active: bool,
    pub(super) rank_one_since_refresh: usize,
    /// Policy changes not yet folded into A⁻¹: (state, old pair, new pair).
    pub(super) pending: Vec<(u32, u32, u32)>,
    pub(super) b: DVector<f64>,
    pub(super) w: DVector<f64>,
    pub(super) x: DVector<f64>,
    pub(super) y: DVector<f64>,
    pub(super) u: DVector<f64>,
    /// Scratch: Q(s, a) for every state and action, column-major |S|×|A|.
    pub(super) q_states: Vec<f64>,
    /// Scratch: b with each action block padded to `kp` entries.
    pub(super) b_wide: Vec<f64>,
    /// R of the last evaluation.
    pub(super) r_last: Vec<f64>,
    /// The planner's Q is Φ A⁻¹ Φᵀ `r_last` for the current A⁻¹, bit for bit.
    pub(super) evaluated: bool,
}

impl FeatureEngine {
    /// Brings A⁻¹ up to date with π; returns true when nothing had to change.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn prepare(
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
    pub(super) fn rebuild(
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
    pub(super) fn evaluate(
        &mut self,
        model: &EnvModel,
        cache: &FeatureCache,
        r: &[f64],
        q: &mut [f64],
    ) {
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
