//! LSTDQ on the sample store (docs/algorithm.md §9.5): Algorithm 1,
//! line 9, with the transition model replaced by the stored transitions,
//! as least-squares policy iteration evaluates policies (Lagoudakis &
//! Parr, JMLR 2003).
//!
//! With φ(s, a) = e_a ⊗ v(s) and the greedy successor action π_i of each
//! stored transition i,
//!
//!   A = λI + Σ_i ω_i u_i v_iᵀ,  u_i = φ(s_i, a_i),
//!   v_i = u_i − γ φ(s′_i, π_i)   (or u_i alone if (s′_i, π_i) is unknown),
//!   b = Σ_i ω_i u_i y_i,  y_i = R(s_i, a_i) (+ γ Q_opt(s′_i, π_i) if unknown),
//!   w = A⁻¹ b.
//!
//! ω_i is the number of visits transition i stands for
//! ([`Sample::weight`]), so the store is weighed as the whole history would
//! be: a pair tried a thousand times (a robot pushing into a wall) counts
//! a thousand times, and generalisation from its neighbours cannot hide
//! that it leads nowhere.
//!
//! An unknown successor pair leads to the absorbing optimistic state of
//! the discrete learned model: Q_opt(s, a) = R(s, a) + γ R_max / (1 − γ).
//!
//! **Cost per tick.** R changes every tick (D moves) but A does not: it
//! depends on the samples and the policy only. So A⁻¹ is kept up to date
//! by Sherman–Morrison, one rank-one update per transition stored,
//! replaced, or whose π_i changed, O((k|A|)²) each; b costs O(N·k) and
//! w = A⁻¹ b O((k|A|)²). Every [`REBUILD_EVERY`] ticks, or when an update
//! is ill-conditioned, A is rebuilt from the samples and inverted, which
//! bounds the rounding drift; the schedule depends only on the ticks and
//! the data, so a replay is bit-identical.

use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

use super::dot::dot;
use super::samples::{SampleRef, SampleStore};

/// Ticks between rebuilds of A⁻¹ from the samples.
pub const REBUILD_EVERY: u64 = 256;

/// |1 + vᵀA⁻¹u| below this makes a rank-one update a rebuild instead.
const MIN_PIVOT: f64 = 1e-8;

/// A term of a sparse state-action vector: coefficient × (e_block ⊗ v).
type Term<'a> = (usize, f64, &'a [f64]);

/// The inverse of A, the weights and the successor policy.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SamplePlanner {
    k: usize,
    actions: usize,
    gamma: f64,
    ridge: f64,
    /// A⁻¹, row-major (k|A|)².
    ainv: Vec<f64>,
    /// w = A⁻¹ b: block a holds the weights of action a.
    w: Vec<f64>,
    /// b of the last evaluation.
    b: Vec<f64>,
    /// π_i and whether (s′_i, π_i) is known, per stored transition, as
    /// A holds them.
    succ: Vec<(usize, bool)>,
    /// A must be rebuilt before the next evaluation.
    stale: bool,
    /// Ticks since the last rebuild.
    since_rebuild: u64,
    /// Rank-one updates applied since the agent started (a statistic).
    pub updates: u64,
    /// Rebuilds since the agent started (a statistic).
    pub rebuilds: u64,
    x: Vec<f64>,
    y: Vec<f64>,
}

impl SamplePlanner {
    /// A = λI, no samples, w = 0.
    pub fn new(k: usize, actions: usize, gamma: f64, ridge: f64) -> Self {
        let n = k * actions;
        let mut ainv = vec![0.0; n * n];
        for i in 0..n {
            ainv[i * n + i] = 1.0 / ridge;
        }
        Self {
            k,
            actions,
            gamma,
            ridge,
            ainv,
            w: vec![0.0; n],
            b: vec![0.0; n],
            succ: Vec::new(),
            stale: false,
            since_rebuild: 0,
            updates: 0,
            rebuilds: 0,
            x: vec![0.0; n],
            y: vec![0.0; n],
        }
    }

    /// Whether a planner read from a snapshot has the shape of one for `k`
    /// features, `actions` actions and `samples` stored transitions.
    pub fn fits(&self, k: usize, actions: usize, samples: usize) -> bool {
        let n = k * actions;
        self.k == k
            && self.actions == actions
            && self.ainv.len() == n * n
            && [&self.w, &self.b, &self.x, &self.y]
                .iter()
                .all(|v| v.len() == n)
            && self.succ.len() == samples
            && self.succ.iter().all(|&(pi, _)| pi < actions)
    }

    /// The weights w (block a: action a's weights on v(s)).
    pub fn weights(&self) -> &[f64] {
        &self.w
    }

    /// Q(s, a) = v(s) · w_a.
    pub fn q(&self, v: &[f64], a: usize) -> f64 {
        let k = self.k;
        dot(v, &self.w[a * k..(a + 1) * k])
    }

    /// The successor action and knownness A holds for transition i.
    pub fn successor(&self, i: usize) -> Option<(usize, bool)> {
        self.succ.get(i).copied()
    }

    fn terms<'a>(&self, sample: SampleRef<'a>, pi: usize, known: bool) -> ([Term<'a>; 2], usize) {
        let own = (sample.a, 1.0, sample.v);
        if known {
            ([own, (pi, -self.gamma, sample.v_next)], 2)
        } else {
            ([own, own], 1)
        }
    }

    /// A ← A + sign · u vᵀ with u = e_a ⊗ f and v = Σ terms, by
    /// Sherman–Morrison (`sign` also carries the transition's weight); marks A stale instead when the pivot is tiny.
    fn rank_one(&mut self, sign: f64, a: usize, f: &[f64], terms: &[Term<'_>]) {
        if self.stale {
            return;
        }
        let (k, n) = (self.k, self.k * self.actions);
        // x = A⁻¹ u: the columns of block a, weighted by f.
        for (r, x) in self.x.iter_mut().enumerate() {
            let row = &self.ainv[r * n + a * k..r * n + (a + 1) * k];
            *x = sign * dot(row, f);
        }
        // y = vᵀ A⁻¹, and vᵀx.
        self.y.iter_mut().for_each(|y| *y = 0.0);
        let mut vx = 0.0;
        for &(block, coef, g) in terms {
            for (j, &gj) in g.iter().enumerate() {
                let c = coef * gj;
                if c != 0.0 {
                    let r = block * k + j;
                    vx += c * self.x[r];
                    for (y, m) in self.y.iter_mut().zip(&self.ainv[r * n..(r + 1) * n]) {
                        *y += c * m;
                    }
                }
            }
        }
        let pivot = 1.0 + vx;
        if pivot.is_nan() || pivot.abs() < MIN_PIVOT {
            self.stale = true;
            return;
        }
        for (r, &xr) in self.x.iter().enumerate() {
            let s = xr / pivot;
            if s != 0.0 {
                for (m, y) in self.ainv[r * n..(r + 1) * n].iter_mut().zip(&self.y) {
                    *m -= s * y;
                }
            }
        }
        self.updates += 1;
    }

    /// Removes transition `old`'s term from A (it was at index i).
    pub fn remove(&mut self, i: usize, old: SampleRef<'_>) {
        let (pi, known) = self.succ[i];
        let (terms, len) = self.terms(old, pi, known);
        self.rank_one(-old.weight, old.a, old.v, &terms[..len]);
    }

    /// Adds transition i (already in `samples`) with successor action π.
    pub fn add(&mut self, i: usize, sample: SampleRef<'_>, pi: usize, known: bool) {
        if i == self.succ.len() {
            self.succ.push((pi, known));
        } else {
            self.succ[i] = (pi, known);
        }
        let (terms, len) = self.terms(sample, pi, known);
        self.rank_one(sample.weight, sample.a, sample.v, &terms[..len]);
    }

    /// Changes transition i's successor action (line 9's improvement at s′_i).
    pub fn set_successor(&mut self, i: usize, sample: SampleRef<'_>, pi: usize, known: bool) {
        let (old_pi, old_known) = self.succ[i];
        if (old_pi, old_known) == (pi, known) {
            return;
        }
        self.succ[i] = (pi, known);
        let g = sample.v_next;
        let mut terms: [Term<'_>; 2] = [(0, 0.0, g), (0, 0.0, g)];
        let mut len = 0;
        if known {
            terms[len] = (pi, -self.gamma, g);
            len += 1;
        }
        if old_known {
            terms[len] = (old_pi, self.gamma, g);
            len += 1;
        }
        if len > 0 {
            self.rank_one(sample.weight, sample.a, sample.v, &terms[..len]);
        }
    }

    /// The basis changed: the ridge is `ridge` from now on, and A must be
    /// rebuilt from the samples' new features before the next evaluation;
    /// the successor policy π is kept.
    pub fn rebase(&mut self, ridge: f64) {
        self.ridge = ridge;
        self.stale = true;
    }

    /// Rebuilds A from the samples and inverts it, when stale or due.
    /// Returns whether it rebuilt.
    pub fn maybe_rebuild(&mut self, store: &SampleStore) -> bool {
        self.since_rebuild += 1;
        if !self.stale && self.since_rebuild < REBUILD_EVERY {
            return false;
        }
        let (k, n) = (self.k, self.k * self.actions);
        // A, row-major while it is summed (each term adds k-long runs to a
        // row), then handed to nalgebra, which stores columns: so `a` below
        // is Aᵀ, inverted, and its inverse transposed back.
        let mut rows = vec![0.0; n * n];
        for i in 0..n {
            rows[i * n + i] = self.ridge;
        }
        for (sample, &(pi, known)) in store.iter().zip(&self.succ) {
            let (terms, len) = self.terms(sample, pi, known);
            for (j, &fj) in sample.v.iter().enumerate() {
                let fj = fj * sample.weight;
                if fj == 0.0 {
                    continue;
                }
                let row = &mut rows[(sample.a * k + j) * n..(sample.a * k + j + 1) * n];
                for &(block, coef, g) in &terms[..len] {
                    let c = fj * coef;
                    for (x, &gc) in row[block * k..(block + 1) * k].iter_mut().zip(g) {
                        *x += c * gc;
                    }
                }
            }
        }
        let a = DMatrix::from_vec(n, n, rows);
        let inv = a.clone().try_inverse().or_else(|| {
            // Singular even with the ridge: add a stronger one.
            let mut b = a;
            for i in 0..n {
                b[(i, i)] += 1e-6 * (1.0 + b[(i, i)].abs());
            }
            b.try_inverse()
        });
        if let Some(inv) = inv {
            // inv = (Aᵀ)⁻¹ = (A⁻¹)ᵀ in column-major order: A⁻¹ row-major.
            self.ainv.copy_from_slice(inv.as_slice());
        }
        self.stale = false;
        self.since_rebuild = 0;
        self.rebuilds += 1;
        true
    }

    /// b = Σ_i u_i y_i and w = A⁻¹ b (one evaluation of line 9).
    /// `targets[i]` is y_i.
    pub fn evaluate(&mut self, store: &SampleStore, targets: &[f64]) {
        let (k, n) = (self.k, self.k * self.actions);
        self.b.iter_mut().for_each(|b| *b = 0.0);
        for (sample, &y) in store.iter().zip(targets) {
            let y = y * sample.weight;
            let block = &mut self.b[sample.a * k..(sample.a + 1) * k];
            for (b, f) in block.iter_mut().zip(sample.v) {
                *b += f * y;
            }
        }
        for (r, w) in self.w.iter_mut().enumerate() {
            *w = dot(&self.ainv[r * n..(r + 1) * n], &self.b);
        }
        if self.w.iter().any(|w| !w.is_finite()) {
            // Never let a NaN reach Q: start over from A = λI next tick.
            self.w.iter_mut().for_each(|w| *w = 0.0);
            self.stale = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::continuous::samples::SampleStore;

    /// Sherman–Morrison updates agree with a rebuild from scratch.
    #[test]
    fn incremental_inverse_matches_a_rebuild() {
        let (k, actions) = (3, 2);
        let mut store = SampleStore::new(1, k, 8, 1, 6, 1);
        let mut planner = SamplePlanner::new(k, actions, 0.9, 0.1);
        let feats = |x: f64| vec![1.0, x, x * x];
        for t in 0..20u64 {
            let x = (t as f64 * 0.37).fract();
            let x2 = (x + 0.1).min(1.0);
            let ins = store.insert(
                t,
                &[x],
                (t % 2) as usize,
                &[x2],
                &feats(x),
                &feats(x2),
                &[0.0],
            );
            if let Some(old) = &ins.replaced {
                planner.remove(ins.index, old.as_ref());
            }
            planner.add(
                ins.index,
                store.get(ins.index),
                ((t / 3) % 2) as usize,
                t % 5 != 0,
            );
            if t % 4 == 0 {
                planner.set_successor(0, store.get(0), (t % 2) as usize, true);
            }
        }
        let incremental = planner.ainv.clone();
        planner.stale = true;
        assert!(planner.maybe_rebuild(&store));
        let max_err = incremental
            .iter()
            .zip(&planner.ainv)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let scale = planner.ainv.iter().map(|v| v.abs()).fold(0.0, f64::max);
        assert!(
            max_err <= 1e-8 * scale.max(1.0),
            "drift {max_err} at scale {scale}"
        );
    }
}
