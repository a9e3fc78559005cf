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

/// Rank-one terms of A held back and applied to A⁻¹ in one pass: a tick's
/// successor changes ([`crate::continuous::agent`] bounds them to 32) and
/// a few more.
pub const MAX_PENDING: usize = 40;

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
    /// The rows of A⁻¹ a rank-one update weighs (scratch, empty between
    /// updates).
    #[serde(skip)]
    weighed: Vec<(usize, f64)>,
    /// Pending rank-one terms, x_i then y_i of each, k|A| entries each:
    /// the inverse of A is A⁻¹ − Σ_i x_i y_iᵀ until [`Self::flush`]. Empty
    /// between the agent's steps (a snapshot never holds any).
    #[serde(skip)]
    pending_x: Vec<f64>,
    #[serde(skip)]
    pending_y: Vec<f64>,
    /// The pending x_i transposed, while they are applied (scratch).
    #[serde(skip)]
    pending_t: Vec<f64>,
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
            weighed: Vec::new(),
            pending_x: Vec::new(),
            pending_y: Vec::new(),
            pending_t: Vec::new(),
        }
    }

    /// Whether a planner read from a snapshot has the shape of one for `k`
    /// features, `actions` actions and `samples` stored transitions.
    pub fn fits(&self, k: usize, actions: usize, samples: usize) -> bool {
        let n = k * actions;
        self.k == k
            && self.actions == actions
            && self.ainv.len() == n * n
            && self.w.len() == n
            && self.b.len() == n
            && self.succ.len() == samples
            && self.succ.iter().all(|&(pi, _)| pi < actions)
    }

    /// The weights w (block a: action a's weights on v(s)).
    pub fn weights(&self) -> &[f64] {
        &self.w
    }

    /// Q(s, a) = v(s) · w_a.
    #[inline(always)]
    pub fn q(&self, v: &[f64], a: usize) -> f64 {
        let k = self.k;
        dot(v, &self.w[a * k..(a + 1) * k])
    }

    /// The successor action and knownness A holds for transition i.
    #[inline(always)]
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
    /// Sherman–Morrison (`sign` also carries the transition's weight),
    /// deferred: the term joins the pending ones, applied to A⁻¹ together
    /// by [`Self::flush`]. Marks A stale instead when the pivot is tiny.
    fn rank_one(&mut self, sign: f64, a: usize, f: &[f64], terms: &[Term<'_>]) {
        if self.stale {
            return;
        }
        let n = self.k * self.actions;
        if self.pending_x.len() >= MAX_PENDING * n {
            self.flush();
        }
        let update = RankOne { sign, a, f, terms };
        let pending = (&mut self.pending_x, &mut self.pending_y);
        let done = defer_rank_one(&self.ainv, (self.k, n), update, pending, &mut self.weighed);
        self.weighed.clear();
        if done {
            self.updates += 1;
        } else {
            self.stale = true;
            self.drop_pending();
        }
    }

    /// Forgets the pending terms: A is stale, or rebuilt from the samples
    /// (which hold them already).
    fn drop_pending(&mut self) {
        self.pending_x.clear();
        self.pending_y.clear();
    }

    /// Applies the pending rank-one terms to A⁻¹, in one pass over it.
    pub fn flush(&mut self) {
        if self.pending_x.is_empty() {
            return;
        }
        let n = self.k * self.actions;
        let pending = (self.pending_x.as_slice(), self.pending_y.as_slice());
        apply_pending(&mut self.ainv, n, pending, &mut self.pending_t);
        self.drop_pending();
        self.pending_t.clear();
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
        self.flush();
    }

    /// Changes transition i's successor action (line 9's improvement at
    /// s′_i). The change is pending until [`Self::flush`] (or the next
    /// evaluation) applies it.
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
        self.drop_pending();
    }

    /// Rebuilds A from the samples and inverts it, when stale or due.
    /// Returns whether it rebuilt.
    pub fn maybe_rebuild(&mut self, store: &SampleStore) -> bool {
        self.since_rebuild += 1;
        if !self.stale && self.since_rebuild < REBUILD_EVERY {
            return false;
        }
        self.drop_pending();
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
    #[inline(always)]
    pub fn evaluate(&mut self, store: &SampleStore, targets: &[f64]) {
        self.flush();
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

/// One rank-one term u vᵀ of A, u = e_a ⊗ f scaled by `sign`, v = Σ terms.
#[derive(Clone, Copy)]
struct RankOne<'a, 't> {
    sign: f64,
    a: usize,
    f: &'a [f64],
    terms: &'t [Term<'a>],
}

/// Sherman–Morrison for one more term u vᵀ of A, deferred: with the
/// pending terms (x_i, y_i) so far, A⁻¹ stands for M = A⁻¹ − Σ_i x_i y_iᵀ,
/// and the new term's x = M u and y = vᵀM / (1 + vᵀMu) are appended to
/// them, so that (A + u vᵀ)⁻¹ = M − x yᵀ. `ainv` is row-major of `shape` =
/// (k, k|A|); `pending` holds the x_i and the y_i, k|A| entries each.
/// Returns false, appending nothing, when the pivot is tiny or NaN.
///
/// Every entry is computed by the same operations in the same order
/// whatever the vector width (elementwise products and differences, and
/// [`dot`]'s four fixed accumulators; no FMA contraction), so the versions
/// compiled for AVX-512, AVX2, AVX and NEON, picked at run time, give the
/// same bits as the baseline one.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx",
    "aarch64+neon"
))]
fn defer_rank_one<'a, 't>(
    ainv: &[f64],
    shape: (usize, usize),
    update: RankOne<'a, 't>,
    pending: (&mut Vec<f64>, &mut Vec<f64>),
    rows: &mut Vec<(usize, f64)>,
) -> bool {
    let (k, n) = shape;
    let RankOne { sign, a, f, terms } = update;
    let (pending_x, pending_y) = pending;
    let p = pending_x.len() / n;
    pending_x.resize((p + 1) * n, 0.0);
    pending_y.resize((p + 1) * n, 0.0);
    let (xs, x) = pending_x.split_at_mut(p * n);
    let (ys, y) = pending_y.split_at_mut(p * n);
    // x = A⁻¹u: the columns of block a, weighted by f ...
    for (r, x) in x.iter_mut().enumerate() {
        *x = sign * dot(&ainv[r * n + a * k..r * n + (a + 1) * k], f);
    }
    // ... minus Σ_i x_i (y_i · u).
    for (xi, yi) in xs.chunks_exact(n).zip(ys.chunks_exact(n)) {
        let c = sign * dot(&yi[a * k..(a + 1) * k], f);
        if c != 0.0 {
            for (x, xi) in x.iter_mut().zip(xi) {
                *x -= c * xi;
            }
        }
    }
    // vᵀx, and the rows of A⁻¹ that v weighs, with their weights.
    let mut vx = 0.0;
    rows.clear();
    for &(block, coef, g) in terms {
        for (j, &gj) in g.iter().enumerate() {
            let c = coef * gj;
            if c != 0.0 {
                let r = block * k + j;
                vx += c * x[r];
                rows.push((r, c));
            }
        }
    }
    let pivot = 1.0 + vx;
    if pivot.is_nan() || pivot.abs() < MIN_PIVOT {
        pending_x.truncate(p * n);
        pending_y.truncate(p * n);
        return false;
    }
    // y = vᵀA⁻¹, four rows at a time, (c₀m₀ + c₁m₁) + (c₂m₂ + c₃m₃) ...
    y.iter_mut().for_each(|y| *y = 0.0);
    let row = |r: usize| &ainv[r * n..(r + 1) * n];
    let mut quads = rows.chunks_exact(4);
    for q in &mut quads {
        let [(r0, c0), (r1, c1), (r2, c2), (r3, c3)] = [q[0], q[1], q[2], q[3]];
        let m = row(r0).iter().zip(row(r1)).zip(row(r2)).zip(row(r3));
        for (y, (((m0, m1), m2), m3)) in y.iter_mut().zip(m) {
            *y += (c0 * m0 + c1 * m1) + (c2 * m2 + c3 * m3);
        }
    }
    for &(r, c) in quads.remainder() {
        for (y, m) in y.iter_mut().zip(row(r)) {
            *y += c * m;
        }
    }
    // ... minus Σ_i (v · x_i) y_i, over the pivot.
    for (xi, yi) in xs.chunks_exact(n).zip(ys.chunks_exact(n)) {
        let c: f64 = terms
            .iter()
            .map(|&(block, coef, g)| coef * dot(g, &xi[block * k..(block + 1) * k]))
            .sum();
        if c != 0.0 {
            for (y, yi) in y.iter_mut().zip(yi) {
                *y -= c * yi;
            }
        }
    }
    y.iter_mut().for_each(|y| *y /= pivot);
    true
}

/// Columns of A⁻¹ updated at once in registers by [`apply_pending`].
const APPLY_COLS: usize = 32;

/// A⁻¹ ← A⁻¹ − Σ_i x_i y_iᵀ for the pending terms (x_i, y_i), in one pass:
/// A⁻¹ in blocks of [`APPLY_COLS`] columns, each row's block kept in
/// registers while every term is taken from it in order (so each entry is
/// m − c₀y₀ − c₁y₁ − …, whatever the vector width). `xt` is scratch for
/// the x_i transposed.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx",
    "aarch64+neon"
))]
fn apply_pending(ainv: &mut [f64], n: usize, pending: (&[f64], &[f64]), xt: &mut Vec<f64>) {
    let (xs, ys) = pending;
    let p = xs.len() / n;
    xt.clear();
    xt.resize(n * p, 0.0);
    for (i, xi) in xs.chunks_exact(n).enumerate() {
        for (r, &x) in xi.iter().enumerate() {
            xt[r * p + i] = x;
        }
    }
    // The y_i's columns of one block, packed together (y_i of k|A| = 2^m
    // entries apart would fall into the same few cache sets).
    let mut packed = [0.0f64; MAX_PENDING * APPLY_COLS];
    let mut c0 = 0;
    while n - c0 >= APPLY_COLS {
        for (pack, yi) in packed.chunks_exact_mut(APPLY_COLS).zip(ys.chunks_exact(n)) {
            pack.copy_from_slice(&yi[c0..c0 + APPLY_COLS]);
        }
        for (row, c) in ainv.chunks_exact_mut(n).zip(xt.chunks_exact(p)) {
            let block = &mut row[c0..c0 + APPLY_COLS];
            let mut acc = [0.0f64; APPLY_COLS];
            acc.copy_from_slice(block);
            for (&ci, yi) in c.iter().zip(packed.chunks_exact(APPLY_COLS)) {
                if ci != 0.0 {
                    for (m, y) in acc.iter_mut().zip(yi) {
                        *m -= ci * y;
                    }
                }
            }
            block.copy_from_slice(&acc);
        }
        c0 += APPLY_COLS;
    }
    if c0 < n {
        for (row, c) in ainv.chunks_exact_mut(n).zip(xt.chunks_exact(p)) {
            for (&ci, yi) in c.iter().zip(ys.chunks_exact(n)) {
                if ci != 0.0 {
                    for (m, y) in row[c0..].iter_mut().zip(&yi[c0..]) {
                        *m -= ci * y;
                    }
                }
            }
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
        planner.flush();
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

    /// Successor changes held back (more of them than [`MAX_PENDING`], so
    /// that some are applied on the way) give the inverse of a rebuild, and
    /// so do the rank-one updates applied one at a time.
    #[test]
    fn pending_changes_applied_together_match_a_rebuild() {
        let (k, actions) = (5, 3);
        let samples = 24;
        let mut store = SampleStore::new(1, k, 8, 4, samples, 1);
        let feats = |x: f64| -> Vec<f64> {
            (0..k)
                .map(|j| (-(x - j as f64 / 4.0).powi(2) * 8.0).exp())
                .collect()
        };
        let mut planner = SamplePlanner::new(k, actions, 0.9, 0.1);
        for t in 0..samples as u64 {
            let x = (t as f64 * 0.29).fract();
            let x2 = (x + 0.05).min(1.0);
            let ins = store.insert(
                t,
                &[x],
                (t % 3) as usize,
                &[x2],
                &feats(x),
                &feats(x2),
                &[0.0],
            );
            assert!(ins.replaced.is_none());
            planner.add(ins.index, store.get(ins.index), 0, t % 4 != 0);
        }
        let mut one_at_a_time = planner.clone();
        let mut changes = 0;
        for round in 1..4 {
            for i in 0..samples {
                let pi = (i + round) % actions;
                let known = (i + round) % 5 != 0;
                planner.set_successor(i, store.get(i), pi, known);
                one_at_a_time.set_successor(i, store.get(i), pi, known);
                one_at_a_time.flush();
                changes += 1;
            }
        }
        assert!(changes > MAX_PENDING);
        assert!(!planner.pending_x.is_empty(), "some changes still pending");
        planner.flush();
        assert!(planner.pending_x.is_empty() && planner.pending_y.is_empty());
        let mut rebuilt = planner.clone();
        rebuilt.stale = true;
        assert!(rebuilt.maybe_rebuild(&store));
        let scale = rebuilt.ainv.iter().map(|v| v.abs()).fold(0.0, f64::max);
        for (name, got) in [("together", &planner), ("one at a time", &one_at_a_time)] {
            assert!(!got.stale, "{name}: no update was refused");
            let err = got
                .ainv
                .iter()
                .zip(&rebuilt.ainv)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(
                err <= 1e-9 * scale.max(1.0),
                "{name}: drift {err} at scale {scale}"
            );
        }
    }
}
