//! Feature bases for LSTDQ (docs/algorithm.md §5).
//!
//! - `indicator`: one feature per valid pair (Φ = I); LSTDQ is then exact
//!   policy evaluation and never forms a matrix (see [`super::lstdq`]).
//! - `proto_value`: the k eigenvectors with the smallest eigenvalues of the
//!   normalised graph Laplacian I − D^{-1/2} W D^{-1/2} (Mahadevan's PVFs).
//! - `custom`: client-supplied state features.
//!
//! The last two are *state* features v(s) ∈ R^k lifted to state-action
//! features by one block per action: φ(s,a) = e_a ⊗ v(s), k·|A| features.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use nalgebra::{DMatrix, SymmetricEigen};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::error::{AlgoError, Result};
use super::model::EnvModel;
use super::spec::BasisSpec;

/// Pair counts up to this use the indicator basis by default (docs/sessions.md, "The model").
pub const INDICATOR_DEFAULT_MAX_PAIRS: usize = 2000;

/// Number of PVFs used when the default falls back to `proto_value`.
pub const DEFAULT_PVF_K: usize = 30;

impl BasisSpec {
    /// The default basis: indicator when |S||A| <= 2000, else 30 PVFs.
    pub fn default_for(model: &EnvModel) -> Self {
        if model.states() * model.n_actions() <= INDICATOR_DEFAULT_MAX_PAIRS {
            Self::Indicator
        } else {
            Self::ProtoValue {
                k: DEFAULT_PVF_K.min(model.states()),
            }
        }
    }
}

/// The largest magnitude of an entry of a `custom` basis: the planner's
/// Gram matrix ΦᵀΦ then has entries of at most |S|·1e12, and Φw, Q and
/// their differences stay far from overflowing f64.
pub const MAX_FEATURE: f64 = 1e6;

/// The largest condition number σ_max/σ_min of a `custom` basis's table V
/// (`states × k`) that [`Basis::build_checked`] accepts. The planner inverts
/// A = ΦᵀΦ − γ MᵀΨ_π and calls it singular when a pivot of its LU
/// factorisation is below 1e-12 of the largest; ΦᵀΦ's condition is V's
/// squared, so a limit of 1e5 leaves it at 1e10, two orders inside that.
/// The discount narrows the margin (A's smallest pivots shrink with 1 − γ),
/// which the server checks by running the first factorisation when it
/// creates the session. A table with linearly dependent columns (more
/// features than states, a zero or repeated column) has an infinite
/// condition number.
pub const MAX_FEATURE_CONDITION: f64 = 1e5;

/// State features v(s) ∈ R^k, stored row-major (`states × k`).
#[derive(Debug, Clone, PartialEq)]
pub struct StateFeatures {
    k: usize,
    values: Vec<f64>,
}

impl StateFeatures {
    /// Wraps a row-major `states × k` table.
    pub fn new(k: usize, values: Vec<f64>) -> Self {
        debug_assert!(k > 0 && values.len() % k == 0);
        Self { k, values }
    }

    /// Features per state.
    #[inline]
    pub fn k(&self) -> usize {
        self.k
    }

    /// v(s).
    #[inline]
    pub fn row(&self, s: usize) -> &[f64] {
        &self.values[s * self.k..(s + 1) * self.k]
    }

    /// The whole table, row-major `states × k`.
    pub fn as_slice(&self) -> &[f64] {
        &self.values
    }

    /// Number of states covered.
    pub fn states(&self) -> usize {
        self.values.len() / self.k
    }

    /// The condition number σ_max/σ_min of the table V, from the
    /// eigenvalues of VᵀV (k × k, so the cost is that of the planner's own
    /// Gram matrix); infinite when V's columns are linearly dependent.
    pub fn condition(&self) -> f64 {
        let (n, k) = (self.states(), self.k);
        if k > n {
            return f64::INFINITY;
        }
        let v = DMatrix::from_row_slice(n, k, &self.values);
        let eig = SymmetricEigen::new(v.tr_mul(&v));
        let max = eig.eigenvalues.max();
        let min = eig.eigenvalues.min();
        if !(min > 0.0 && max.is_finite()) {
            return f64::INFINITY;
        }
        (max / min).sqrt()
    }
}

/// When a basis build gives up: a deadline and a flag its caller sets when
/// it no longer wants the result, both optional. The sparse eigensolver
/// checks them between its block products (each a bounded amount of work),
/// so a stopped build frees its thread within one product. A build that
/// finishes has the same bits whatever its budget: the budget decides only
/// whether it finishes.
#[derive(Debug, Clone, Copy, Default)]
pub struct BuildBudget<'a> {
    /// Give up at this instant.
    pub deadline: Option<Instant>,
    /// Give up once this is set.
    pub cancelled: Option<&'a AtomicBool>,
}

impl BuildBudget<'_> {
    /// No deadline, never cancelled: recovery, tests, the experiments.
    pub const UNLIMITED: BuildBudget<'static> = BuildBudget {
        deadline: None,
        cancelled: None,
    };

    /// `Err(BuildStopped)` once the deadline has passed or the flag is set.
    pub fn check(&self) -> Result<()> {
        if self.cancelled.is_some_and(|c| c.load(Ordering::Relaxed)) {
            return Err(AlgoError::BuildStopped(
                "its request was abandoned".to_owned(),
            ));
        }
        if self.deadline.is_some_and(|d| Instant::now() >= d) {
            return Err(AlgoError::BuildStopped(
                "it ran past its time budget".to_owned(),
            ));
        }
        Ok(())
    }
}

/// A built basis.
#[derive(Debug, Clone, PartialEq)]
pub enum Basis {
    /// φ(s,a) = e_(s,a) over valid pairs.
    Indicator,
    /// φ(s,a) = e_a ⊗ v(s).
    StateBlocks(StateFeatures),
}

impl Basis {
    /// Builds the basis `spec` names for `model`.
    pub fn build(spec: &BasisSpec, model: &EnvModel) -> Result<Self> {
        Self::build_within(spec, model, BuildBudget::UNLIMITED)
    }

    /// [`Basis::build`], given up as `budget` says (a PVF basis is the one
    /// whose build can take long).
    pub fn build_within(
        spec: &BasisSpec,
        model: &EnvModel,
        budget: BuildBudget<'_>,
    ) -> Result<Self> {
        match spec {
            BasisSpec::Indicator => Ok(Self::Indicator),
            BasisSpec::ProtoValue { k } => Ok(Self::StateBlocks(proto_value_functions_within(
                model, *k, budget,
            )?)),
            BasisSpec::Custom { state_features } => {
                Ok(Self::StateBlocks(custom_features(model, state_features)?))
            }
        }
    }

    /// Builds the basis `spec` names, as [`Basis::build`], and refuses a
    /// `custom` table the planner could not work with: one whose condition
    /// number is beyond [`MAX_FEATURE_CONDITION`] (the check of a client's
    /// basis; the PVFs are orthonormal by construction).
    pub fn build_checked(spec: &BasisSpec, model: &EnvModel) -> Result<Self> {
        Self::build_checked_within(spec, model, BuildBudget::UNLIMITED)
    }

    /// [`Basis::build_checked`] within `budget`.
    pub fn build_checked_within(
        spec: &BasisSpec,
        model: &EnvModel,
        budget: BuildBudget<'_>,
    ) -> Result<Self> {
        let basis = Self::build_within(spec, model, budget)?;
        if let (BasisSpec::Custom { .. }, Self::StateBlocks(f)) = (spec, &basis) {
            let c = f.condition();
            if c > MAX_FEATURE_CONDITION {
                let c = if c.is_finite() {
                    format!("{c:.3e}")
                } else {
                    "infinite (its columns are linearly dependent)".to_owned()
                };
                return Err(AlgoError::InvalidBasis(format!(
                    "`state_features` is too badly conditioned for the planner: its condition number (largest over smallest singular value) is {c}, the limit is {MAX_FEATURE_CONDITION:e}; scale the features alike and drop dependent ones"
                )));
            }
        }
        Ok(basis)
    }

    /// Number of features (columns of Φ).
    pub fn n_features(&self, model: &EnvModel) -> usize {
        match self {
            Self::Indicator => model.n_pairs(),
            Self::StateBlocks(f) => f.k() * model.n_actions(),
        }
    }
}

/// Checks a client's `state_features` without building anything: one row
/// per state, every row as long as the first and not empty, every entry
/// finite and within ±[`MAX_FEATURE`]. O(entries) and no allocation, so a
/// server runs it before a build takes a place (the conditioning check,
/// an SVD, runs with the build: [`Basis::build_checked`]).
pub fn check_custom_rows(model: &EnvModel, rows: &[Vec<f64>]) -> Result<()> {
    let bad = |msg: String| AlgoError::InvalidBasis(msg);
    if rows.len() != model.states() {
        return Err(bad(format!(
            "`state_features` has {} rows, expected one per state ({})",
            rows.len(),
            model.states()
        )));
    }
    let k = rows[0].len();
    if k == 0 {
        return Err(bad("`state_features[0]` is empty".into()));
    }
    for (s, row) in rows.iter().enumerate() {
        if row.len() != k {
            return Err(bad(format!(
                "`state_features[{s}]` has {} features, expected {k} like row 0",
                row.len()
            )));
        }
        if row.iter().any(|x| !x.is_finite()) {
            return Err(bad(format!(
                "`state_features[{s}]` contains a non-finite number"
            )));
        }
        if let Some((j, x)) = row.iter().enumerate().find(|(_, x)| x.abs() > MAX_FEATURE) {
            return Err(bad(format!(
                "`state_features[{s}][{j}]` = {x:e} exceeds the limit of ±{MAX_FEATURE:e}"
            )));
        }
    }
    Ok(())
}

fn custom_features(model: &EnvModel, rows: &[Vec<f64>]) -> Result<StateFeatures> {
    check_custom_rows(model, rows)?;
    let k = rows[0].len();
    let mut values = Vec::with_capacity(rows.len() * k);
    for row in rows {
        values.extend_from_slice(row);
    }
    Ok(StateFeatures::new(k, values))
}

/// States up to which the PVFs come from the dense eigensolver
/// ([`SymmetricEigen`] of the whole Laplacian, O(|S|³)); larger graphs use
/// the sparse partial solver ([`sparse_pvfs`]).
///
/// 800 was the server's default cap on proto-value models while only the
/// dense solver existed, so every model accepted under the default limits
/// before the sparse solver keeps bit-identical features (and recovers
/// bit-identically from the log). The sparse solver is already about 50×
/// faster at 1,024 states (24 ms against 1.1-1.6 s, BENCHMARKS.md §9), and
/// agrees with the dense one there (`tests/pvf_sparse.rs`).
pub const DENSE_PVF_MAX_STATES: usize = 800;

/// The k eigenvectors of the normalised Laplacian with the smallest
/// eigenvalues (docs/algorithm.md §5). W_ss' = 1 when some action moves s to
/// s' ≠ s with p > 0, symmetrised, without self loops. A state without
/// neighbours has a zero row in D^{-1/2} W D^{-1/2}.
///
/// The eigenvectors are orthonormal; each is signed so that its entry of
/// largest magnitude is positive, which makes the basis reproducible.
/// Up to [`DENSE_PVF_MAX_STATES`] states they are exact (dense solver);
/// above, they come from [`sparse_pvfs`], deterministic for a given model.
pub fn proto_value_functions(model: &EnvModel, k: usize) -> Result<StateFeatures> {
    proto_value_functions_within(model, k, BuildBudget::UNLIMITED)
}

/// [`proto_value_functions`] within `budget` (checked before the dense
/// decomposition, which is bounded by [`DENSE_PVF_MAX_STATES`], and between
/// the sparse solver's block products).
pub fn proto_value_functions_within(
    model: &EnvModel,
    k: usize,
    budget: BuildBudget<'_>,
) -> Result<StateFeatures> {
    budget.check()?;
    let n = model.states();
    if k == 0 || k > n {
        return Err(AlgoError::InvalidBasis(format!(
            "`k` = {k} must be between 1 and the number of states ({n})"
        )));
    }
    if n <= DENSE_PVF_MAX_STATES {
        dense_pvfs(model, k)
    } else {
        sparse_pvfs_within(&StateGraph::of(model), k, budget).map(|(_, features)| features)
    }
}

/// The PVFs from a dense eigendecomposition of the whole Laplacian.
fn dense_pvfs(model: &EnvModel, k: usize) -> Result<StateFeatures> {
    let n = model.states();
    let mut w = DMatrix::<f64>::zeros(n, n);
    for p in 0..model.n_pairs() {
        let s = model.pair_state(p);
        for &t in model.successors(p).0 {
            let t = t as usize;
            if t != s {
                w[(s, t)] = 1.0;
                w[(t, s)] = 1.0;
            }
        }
    }
    let inv_sqrt_deg: Vec<f64> = (0..n)
        .map(|s| {
            let d: f64 = w.row(s).sum();
            if d > 0.0 { 1.0 / d.sqrt() } else { 0.0 }
        })
        .collect();
    let mut lap = DMatrix::<f64>::identity(n, n);
    for i in 0..n {
        for j in 0..n {
            if w[(i, j)] != 0.0 {
                lap[(i, j)] -= inv_sqrt_deg[i] * w[(i, j)] * inv_sqrt_deg[j];
            }
        }
    }
    let (_, values) = smallest_eigenpairs(lap, k);
    finite(values, k)
}

/// The k smallest eigenpairs of a symmetric matrix from a dense
/// decomposition (ties by index): the eigenvalues, and the vectors
/// row-major `n × k`, each signed so that its entry of largest magnitude is
/// positive (as the sparse solver signs them).
pub(crate) fn smallest_eigenpairs(m: DMatrix<f64>, k: usize) -> (Vec<f64>, Vec<f64>) {
    let n = m.nrows();
    let eig = SymmetricEigen::new(m);
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| {
        eig.eigenvalues[a]
            .total_cmp(&eig.eigenvalues[b])
            .then(a.cmp(&b))
    });
    let mut values = vec![0.0; n * k];
    for (j, &col) in order.iter().take(k).enumerate() {
        let v = eig.eigenvectors.column(col);
        let pivot = v
            .iter()
            .copied()
            .fold(0.0f64, |m, x| if x.abs() > m.abs() { x } else { m });
        let sign = if pivot < 0.0 { -1.0 } else { 1.0 };
        for s in 0..n {
            values[s * k + j] = sign * v[s];
        }
    }
    let theta = order.iter().take(k).map(|&c| eig.eigenvalues[c]).collect();
    (theta, values)
}

fn finite(values: Vec<f64>, k: usize) -> Result<StateFeatures> {
    if values.iter().any(|x| !x.is_finite()) {
        return Err(AlgoError::Numerical(
            "proto-value functions are not finite".into(),
        ));
    }
    Ok(StateFeatures::new(k, values))
}

/// The undirected state graph of docs/algorithm.md §5 as the sparse
/// normalised adjacency N = D^{-1/2} W D^{-1/2}, in compressed rows (each
/// row's neighbours ascending, no self loops): O(|S| + transitions) memory.
/// The normalised Laplacian is L = I − N.
#[derive(Debug, Clone)]
pub struct StateGraph {
    /// Row s is `idx[ptr[s]..ptr[s + 1]]`.
    ptr: Vec<usize>,
    idx: Vec<u32>,
    /// N_st = W_st/√(d_s d_t).
    val: Vec<f64>,
    /// d_s = Σ_t W_st.
    deg: Vec<f64>,
}

impl StateGraph {
    /// The graph of `model`: s ~ t when some action moves s to t ≠ s with
    /// p > 0, or t to s.
    pub fn of(model: &EnvModel) -> Self {
        let n = model.states();
        let mut edges: Vec<(u32, u32)> = Vec::new();
        for p in 0..model.n_pairs() {
            let s = model.pair_state(p) as u32;
            // Every stored successor has p > 0 (`EnvModel` keeps no zeros),
            // as in the dense solver.
            for &t in model.successors(p).0 {
                if t != s {
                    edges.push((s, t));
                    edges.push((t, s));
                }
            }
        }
        edges.sort_unstable();
        edges.dedup();
        let mut ptr = vec![0usize; n + 1];
        for &(s, _) in &edges {
            ptr[s as usize + 1] += 1;
        }
        for s in 0..n {
            ptr[s + 1] += ptr[s];
        }
        let weighted: Vec<(u32, u32, f64)> = edges.into_iter().map(|(s, t)| (s, t, 1.0)).collect();
        Self::from_sorted(n, &weighted, ptr)
    }

    /// A weighted graph on `n` nodes: `edges` lists (s, t, W_st > 0) with
    /// s ≠ t, both directions, sorted by (s, t) and without duplicates
    /// (the caller's contract; checked in debug builds).
    pub fn weighted(n: usize, edges: &[(u32, u32, f64)]) -> Self {
        debug_assert!(
            edges
                .windows(2)
                .all(|e| (e[0].0, e[0].1) < (e[1].0, e[1].1))
        );
        debug_assert!(
            edges
                .iter()
                .all(|e| e.0 != e.1 && e.2 > 0.0 && (e.1 as usize) < n)
        );
        let mut ptr = vec![0usize; n + 1];
        for &(s, _, _) in edges {
            ptr[s as usize + 1] += 1;
        }
        for s in 0..n {
            ptr[s + 1] += ptr[s];
        }
        Self::from_sorted(n, edges, ptr)
    }

    fn from_sorted(n: usize, edges: &[(u32, u32, f64)], ptr: Vec<usize>) -> Self {
        let deg: Vec<f64> = (0..n)
            .map(|s| edges[ptr[s]..ptr[s + 1]].iter().map(|e| e.2).sum())
            .collect();
        let inv_sqrt_deg: Vec<f64> = deg
            .iter()
            .map(|&d| if d > 0.0 { 1.0 / d.sqrt() } else { 0.0 })
            .collect();
        let val = edges
            .iter()
            .map(|&(s, t, w)| inv_sqrt_deg[s as usize] * w * inv_sqrt_deg[t as usize])
            .collect();
        let idx = edges.iter().map(|e| e.1).collect();
        Self { ptr, idx, val, deg }
    }

    /// Number of states.
    pub fn states(&self) -> usize {
        self.ptr.len() - 1
    }

    /// The (weighted) degree d_s.
    fn degree(&self, s: usize) -> f64 {
        self.deg[s]
    }

    /// The null space of L, component by component (depth-first, states of
    /// a component summed in ascending order).
    fn null_space(&self) -> NullSpace {
        let n = self.states();
        let mut comp = vec![usize::MAX; n];
        let mut weight = vec![0.0; n];
        let mut count = 0;
        let (mut stack, mut members) = (Vec::new(), Vec::new());
        for start in 0..n {
            if comp[start] != usize::MAX || self.degree(start) == 0.0 {
                continue;
            }
            members.clear();
            comp[start] = count;
            stack.push(start);
            while let Some(s) = stack.pop() {
                members.push(s);
                for &t in &self.idx[self.ptr[s]..self.ptr[s + 1]] {
                    if comp[t as usize] == usize::MAX {
                        comp[t as usize] = count;
                        stack.push(t as usize);
                    }
                }
            }
            members.sort_unstable();
            let norm = members.iter().map(|&s| self.degree(s)).sum::<f64>().sqrt();
            for &s in &members {
                weight[s] = self.degree(s).sqrt() / norm;
            }
            count += 1;
        }
        NullSpace {
            comp,
            weight,
            count,
        }
    }

    /// The dense Laplacian I − N (for tests and small graphs).
    pub fn dense_laplacian(&self) -> DMatrix<f64> {
        let n = self.states();
        let mut lap = DMatrix::identity(n, n);
        for s in 0..n {
            for e in self.ptr[s]..self.ptr[s + 1] {
                lap[(s, self.idx[e] as usize)] -= self.val[e];
            }
        }
        lap
    }

    /// `out = scale·(L − cI)·x + beta·prev` on blocks stored b × |S|
    /// column-major, so that column s (state s's b values) is contiguous.
    fn apply(
        &self,
        x: &DMatrix<f64>,
        c: f64,
        scale: f64,
        prev: Option<(&DMatrix<f64>, f64)>,
        out: &mut DMatrix<f64>,
    ) {
        let b = x.nrows();
        let xs = x.as_slice();
        let diag = (1.0 - c) * scale;
        for (s, o) in out.as_mut_slice().chunks_exact_mut(b).enumerate() {
            let xi = &xs[s * b..(s + 1) * b];
            match prev {
                Some((p, beta)) => {
                    let pi = &p.as_slice()[s * b..(s + 1) * b];
                    for ((o, &x), &p) in o.iter_mut().zip(xi).zip(pi) {
                        *o = diag * x + beta * p;
                    }
                }
                None => {
                    for (o, &x) in o.iter_mut().zip(xi) {
                        *o = diag * x;
                    }
                }
            }
            for e in self.ptr[s]..self.ptr[s + 1] {
                let w = self.val[e] * scale;
                let t = self.idx[e] as usize;
                for (o, &x) in o.iter_mut().zip(&xs[t * b..(t + 1) * b]) {
                    *o -= w * x;
                }
            }
        }
    }
}

/// Residual ‖L v − θ v‖₂ below which a Ritz pair of the sparse solver has
/// converged (‖L‖ ≤ 2). The subspace error is about this over the gap
/// λ_{k+1} − λ_k (Davis–Kahan).
pub const SPARSE_PVF_TOL: f64 = 1e-10;

/// Filtered iterations after which [`sparse_pvfs`] gives up: its work is
/// bounded by this many times (filter degree ≤ [`MAX_FILTER_DEGREE`]) block
/// products with the graph, plus one orthonormalisation each.
pub const SPARSE_PVF_MAX_ITERATIONS: usize = 60;

/// Highest degree of the Chebyshev filter of one iteration.
pub const MAX_FILTER_DEGREE: usize = 100;

/// Extra vectors the sparse solver carries beyond the k wanted ones.
pub fn sparse_pvf_block(k: usize, states: usize) -> usize {
    (k + (k / 2).max(10)).min(states)
}

/// Seed of the sparse solver's start block: fixed, so a model always gets
/// the same PVFs.
const SPARSE_PVF_SEED: u64 = 0x5056_4653; // "PVFS"

/// The k smallest eigenpairs of L = I − D^{-1/2} W D^{-1/2} (docs/algorithm.md
/// §5) without forming L: Chebyshev-filtered subspace iteration (Zhou & Saad,
/// "A Chebyshev–Davidson algorithm", 2007, the scaled filter of their Alg. 3.2)
/// on a block of b = k + max(k/2, 10) vectors.
///
/// Each iteration applies a Chebyshev polynomial of L that damps [cut, 2]
/// (2 bounds the spectrum of a normalised Laplacian, 0 is its smallest
/// eigenvalue; cut is the block's largest Ritz value) and keeps the value 1
/// at 0, so the smallest eigenvectors' share of the block grows. The block is
/// orthonormalised (Cholesky QR, twice) and rotated onto Ritz vectors
/// (Rayleigh–Ritz with [`SymmetricEigen`] of the b × b projection), until
/// the residual of each of the first k is at most [`SPARSE_PVF_TOL`].
///
/// A block method, unlike single-vector Lanczos, finds every copy of a
/// repeated eigenvalue (grids have many). The start block comes from a fixed
/// seed and every loop is sequential, so the result depends only on the
/// graph, never on threads. Eigenvalues ascending; vectors signed as in the
/// dense solver. Work: at most [`SPARSE_PVF_MAX_ITERATIONS`] iterations,
/// each O(degree · b · (|S| + edges) + |S| b²); memory O(|S| b).
pub fn sparse_pvfs(graph: &StateGraph, k: usize) -> Result<(Vec<f64>, StateFeatures)> {
    sparse_pvfs_within(graph, k, BuildBudget::UNLIMITED)
}

/// [`sparse_pvfs`] within `budget`, checked between block products.
pub fn sparse_pvfs_within(
    graph: &StateGraph,
    k: usize,
    budget: BuildBudget<'_>,
) -> Result<(Vec<f64>, StateFeatures)> {
    let n = graph.states();
    if k == 0 || k > n {
        return Err(AlgoError::InvalidBasis(format!(
            "`k` = {k} must be between 1 and the number of states ({n})"
        )));
    }
    match filtered_block(graph, k, None, budget) {
        Err(AlgoError::Numerical(_)) => deflated_pvfs(graph, k, budget),
        done => done,
    }
}

/// The second attempt of [`sparse_pvfs`], for graphs where the k-th
/// eigenvalue repeats across the whole block (docs/algorithm.md §5): many
/// components, whose null vectors D^{1/2}1_C are known exactly and are
/// taken first, and a cut kept above a Ritz cluster that fills the block.
fn deflated_pvfs(
    graph: &StateGraph,
    k: usize,
    budget: BuildBudget<'_>,
) -> Result<(Vec<f64>, StateFeatures)> {
    let n = graph.states();
    let null = graph.null_space();
    let c = null.count.min(k);
    let mut values = vec![0.0; n * k];
    for s in 0..n {
        if null.comp[s] < c {
            values[s * k + null.comp[s]] = null.weight[s];
        }
    }
    let mut theta = vec![0.0; c];
    if c < k {
        let (rest, features) = filtered_block(graph, k - c, Some(&null), budget)?;
        for s in 0..n {
            values[s * k + c..(s + 1) * k].copy_from_slice(features.row(s));
        }
        theta.extend(rest);
    }
    Ok((theta, finite(values, k)?))
}

/// The null space of L: one unit vector D^{1/2}1_C/‖D^{1/2}1_C‖ per connected
/// component C with an edge, numbered in the order of their first states.
struct NullSpace {
    /// The component of each state; `usize::MAX` for a state without edges
    /// (its row of L is that of I).
    comp: Vec<usize>,
    /// Each state's entry in its component's vector.
    weight: Vec<f64>,
    count: usize,
}

impl NullSpace {
    /// Removes the null space from every row of `x` (b × |S|), in a fixed
    /// order.
    fn project_out(&self, x: &mut DMatrix<f64>) {
        let b = x.nrows();
        let mut coef = vec![0.0; b * self.count];
        for (s, xs) in x.as_slice().chunks_exact(b).enumerate() {
            if let Some(c) = self.comp.get(s).copied().filter(|&c| c < self.count) {
                for (a, &v) in coef[c * b..(c + 1) * b].iter_mut().zip(xs) {
                    *a += v * self.weight[s];
                }
            }
        }
        for (s, xs) in x.as_mut_slice().chunks_exact_mut(b).enumerate() {
            if let Some(c) = self.comp.get(s).copied().filter(|&c| c < self.count) {
                for (v, &a) in xs.iter_mut().zip(&coef[c * b..(c + 1) * b]) {
                    *v -= a * self.weight[s];
                }
            }
        }
    }
}

/// The filtered block iteration of [`sparse_pvfs`] for the k smallest
/// eigenpairs; with `deflate`, in the complement of that null space and
/// with the cut kept above a Ritz cluster that fills the block.
fn filtered_block(
    graph: &StateGraph,
    k: usize,
    deflate: Option<&NullSpace>,
    budget: BuildBudget<'_>,
) -> Result<(Vec<f64>, StateFeatures)> {
    let n = graph.states();
    let room = n - deflate.map_or(0, |d| d.count);
    let b = sparse_pvf_block(k, room);
    let not_converged = || {
        AlgoError::Numerical(format!(
            "the sparse eigensolver did not find {k} proto-value functions of {n} states within {SPARSE_PVF_MAX_ITERATIONS} iterations"
        ))
    };
    let mut rng = ChaCha8Rng::seed_from_u64(SPARSE_PVF_SEED);
    let mut x = DMatrix::from_fn(b, n, |_, _| rng.random::<f64>() - 0.5);
    if let Some(d) = deflate {
        d.project_out(&mut x);
    }
    orthonormalise(&mut x).ok_or_else(not_converged)?;
    let mut lx = DMatrix::zeros(b, n);
    graph.apply(&x, 0.0, 1.0, None, &mut lx);
    let (mut theta, q) = rayleigh_ritz(&x, &lx);
    x = rotate(&q, &x);
    let mut y = DMatrix::zeros(b, n);
    let mut next = DMatrix::zeros(b, n);
    for _ in 0..SPARSE_PVF_MAX_ITERATIONS {
        // Damp [cut, 2], keep p(0) = 1 (Zhou & Saad's scaled recurrence).
        let mut cut = theta[b - 1];
        if deflate.is_some() && cut - theta[k - 1] <= 1e-8 {
            // The block lies in one eigenspace: the Ritz values say nothing
            // of the next eigenvalue, so damp from a little above it.
            cut = theta[k - 1] + 0.1 * (2.0 - theta[k - 1]);
        }
        let cut = cut.clamp(1e-9, 1.9);
        let (e, c) = ((2.0 - cut) / 2.0, (2.0 + cut) / 2.0);
        // The smallest eigenvalue is amplified about cosh(degree·acosh(c/e))
        // over the damped interval: at most e^10, so Cholesky QR keeps
        // its accuracy.
        let degree = ((10.0 / (c / e).acosh()).floor() as usize).clamp(4, MAX_FILTER_DEGREE);
        let sigma1 = -e / c;
        let tau = 2.0 / sigma1;
        let mut sigma = sigma1;
        budget.check()?;
        graph.apply(&x, c, sigma1 / e, None, &mut y);
        for _ in 2..=degree {
            budget.check()?;
            let sigma_next = 1.0 / (tau - sigma);
            graph.apply(
                &y,
                c,
                2.0 * sigma_next / e,
                Some((&x, -sigma * sigma_next)),
                &mut next,
            );
            std::mem::swap(&mut x, &mut y);
            std::mem::swap(&mut y, &mut next);
            sigma = sigma_next;
        }
        std::mem::swap(&mut x, &mut y);
        if let Some(d) = deflate {
            d.project_out(&mut x);
        }
        budget.check()?;
        orthonormalise(&mut x).ok_or_else(not_converged)?;
        budget.check()?;
        graph.apply(&x, 0.0, 1.0, None, &mut lx);
        let (ritz, q) = rayleigh_ritz(&x, &lx);
        theta = ritz;
        x = rotate(&q, &x);
        lx = rotate(&q, &lx);
        let converged = (0..k).all(|j| (lx.row(j) - x.row(j) * theta[j]).norm() <= SPARSE_PVF_TOL);
        if converged {
            let mut values = vec![0.0; n * k];
            for j in 0..k {
                let row = x.row(j);
                let pivot = row
                    .iter()
                    .copied()
                    .fold(0.0f64, |m, v| if v.abs() > m.abs() { v } else { m });
                let sign = if pivot < 0.0 { -1.0 } else { 1.0 };
                for s in 0..n {
                    values[s * k + j] = sign * row[s];
                }
            }
            theta.truncate(k);
            return Ok((theta, finite(values, k)?));
        }
    }
    Err(not_converged())
}

/// X Yᵀ (b × b) of two b × |S| blocks, summed state by state in a fixed
/// order. The solver's products are plain loops rather than nalgebra's
/// matrix product, whose kernels are chosen at run time by CPU features (FMA
/// or not): the PVFs must have the same bits on every machine, so that a
/// session replays identically wherever it is recovered.
fn cross(x: &DMatrix<f64>, y: &DMatrix<f64>) -> DMatrix<f64> {
    let b = x.nrows();
    let mut out = vec![0.0; b * b];
    for (xs, ys) in x
        .as_slice()
        .chunks_exact(b)
        .zip(y.as_slice().chunks_exact(b))
    {
        for (i, &xi) in xs.iter().enumerate() {
            for (o, &yj) in out[i * b..(i + 1) * b].iter_mut().zip(ys) {
                *o += xi * yj;
            }
        }
    }
    // Row i of `out` holds (X Yᵀ)[i, ·]; nalgebra is column-major.
    DMatrix::from_row_slice(b, b, &out)
}

/// Qᵀ X for a b × b `q` and a b × |S| block: each state's b values rotated,
/// in a fixed order (see [`cross`]).
fn rotate(q: &DMatrix<f64>, x: &DMatrix<f64>) -> DMatrix<f64> {
    let b = x.nrows();
    // Row i of Q, contiguous: (Qᵀ x)_j = Σ_i x_i Q[i, j].
    let rows: Vec<f64> = (0..b * b).map(|e| q[(e / b, e % b)]).collect();
    let mut out = DMatrix::zeros(b, x.ncols());
    for (o, xs) in out
        .as_mut_slice()
        .chunks_exact_mut(b)
        .zip(x.as_slice().chunks_exact(b))
    {
        for (&xi, row) in xs.iter().zip(rows.chunks_exact(b)) {
            for (oj, &qij) in o.iter_mut().zip(row) {
                *oj += xi * qij;
            }
        }
    }
    out
}

/// Makes the rows of `z` (b × |S|) orthonormal: Cholesky QR, twice
/// (Stathopoulos & Wu's CholQR2). `None` when the block is rank deficient.
fn orthonormalise(z: &mut DMatrix<f64>) -> Option<()> {
    let b = z.nrows();
    for _ in 0..2 {
        let gram = cross(z, z);
        let l = gram.cholesky()?.l();
        let l_inv = l.solve_lower_triangular(&DMatrix::identity(b, b))?;
        *z = rotate(&l_inv.transpose(), z);
    }
    Some(())
}

/// Ritz values (ascending, ties by index) and vectors (columns of Q) of L on
/// the row space of `x`, given `lx` = (L xᵀ)ᵀ.
fn rayleigh_ritz(x: &DMatrix<f64>, lx: &DMatrix<f64>) -> (Vec<f64>, DMatrix<f64>) {
    let h = cross(x, lx);
    let h = (&h + h.transpose()) * 0.5;
    let eig = SymmetricEigen::new(h);
    let b = eig.eigenvalues.len();
    let mut order: Vec<usize> = (0..b).collect();
    order.sort_by(|&i, &j| {
        eig.eigenvalues[i]
            .total_cmp(&eig.eigenvalues[j])
            .then(i.cmp(&j))
    });
    let theta = order.iter().map(|&i| eig.eigenvalues[i]).collect();
    let q = DMatrix::from_fn(b, b, |r, c| eig.eigenvectors[(r, order[c])]);
    (theta, q)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{hallway, three_room};

    #[test]
    fn pvfs_are_orthonormal_on_the_maze() {
        let m = three_room().model;
        let f = proto_value_functions(&m, 30).expect("pvf");
        for i in 0..30 {
            for j in 0..30 {
                let dot: f64 = (0..m.states()).map(|s| f.row(s)[i] * f.row(s)[j]).sum();
                let expected = if i == j { 1.0 } else { 0.0 };
                assert!((dot - expected).abs() < 1e-9, "<v{i}, v{j}> = {dot}");
            }
        }
    }

    #[test]
    fn smoothest_pvf_of_a_chain_is_proportional_to_sqrt_degree() {
        // The null vector of the normalised Laplacian is D^{1/2} 1.
        let m = hallway().model;
        let f = proto_value_functions(&m, 1).expect("pvf");
        let deg = |s: usize| if s == 0 || s == 49 { 1.0f64 } else { 2.0 };
        let ratio0 = f.row(0)[0] / deg(0).sqrt();
        for s in 0..50 {
            assert!((f.row(s)[0] / deg(s).sqrt() - ratio0).abs() < 1e-9);
        }
        assert!(ratio0 > 0.0, "sign convention makes it positive");
    }

    #[test]
    fn bad_bases_are_rejected() {
        let m = hallway().model;
        let e = Basis::build(&BasisSpec::ProtoValue { k: 51 }, &m).expect_err("k too big");
        assert!(
            e.to_string()
                .contains("between 1 and the number of states (50)")
        );
        let rows = vec![vec![1.0, 2.0]; 49];
        let e = Basis::build(
            &BasisSpec::Custom {
                state_features: rows,
            },
            &m,
        )
        .expect_err("rows");
        assert!(e.to_string().contains("has 49 rows"), "{e}");
        let mut rows = vec![vec![1.0, 2.0]; 50];
        rows[3] = vec![1.0];
        let e = Basis::build(
            &BasisSpec::Custom {
                state_features: rows,
            },
            &m,
        )
        .expect_err("ragged");
        assert!(
            e.to_string().contains("`state_features[3]` has 1 features"),
            "{e}"
        );
    }

    #[test]
    fn custom_bases_are_bounded_and_conditioned() {
        let m = EnvModel::chain(2, vec!["x".into()]).expect("chain");
        let custom = |rows: Vec<Vec<f64>>| BasisSpec::Custom {
            state_features: rows,
        };
        let e = Basis::build(&custom(vec![vec![1e200, 0.0], vec![0.0, 1.0]]), &m)
            .expect_err("too large");
        assert!(e.to_string().contains("`state_features[0][0]`"), "{e}");
        for (rows, what) in [
            (vec![vec![1e6, 0.0], vec![0.0, 1.0]], "1.000e6"),
            (vec![vec![1.0, 2.0], vec![2.0, 4.0]], "infinite"),
            (vec![vec![0.0], vec![0.0]], "infinite"),
            (vec![vec![1.0, 0.0, 1.0], vec![0.0, 1.0, 1.0]], "infinite"),
        ] {
            Basis::build(&custom(rows.clone()), &m).expect("the core builds it");
            let e = Basis::build_checked(&custom(rows), &m).expect_err("conditioning");
            assert!(
                matches!(e, AlgoError::InvalidBasis(_)) && e.to_string().contains(what),
                "{e}"
            );
        }
        for rows in [
            vec![vec![1e5, 0.0], vec![0.0, 1.0]],
            vec![vec![1e6, 1e6], vec![1e6, -1e6]],
            vec![vec![0.5], vec![-2.0]],
        ] {
            Basis::build_checked(&custom(rows.clone()), &m).expect("well conditioned");
        }
    }

    #[test]
    fn default_basis_depends_on_size() {
        assert_eq!(
            BasisSpec::default_for(&hallway().model),
            BasisSpec::Indicator
        );
        let big = EnvModel::chain(1000, vec!["x".into()]).expect("chain");
        assert_eq!(
            BasisSpec::default_for(&big),
            BasisSpec::ProtoValue { k: 30 }
        );
    }
}
