//! Proto-value functions of a sample graph, extended to any point by the
//! Nyström formula (Mahadevan & Maggioni, JMLR 2007; docs/algorithm.md
//! §9.2): the basis of a continuous world that respects its walls.
//!
//! The graph ([`super::pvf_graph`]) has as nodes a subsampled set of the
//! observations seen so far, x_1 … x_n ∈ [0, 1]^d, and as edges the
//! pairs of nodes the agent was seen to move between, with Gaussian
//! weights W_ij = exp(−‖x_i − x_j‖² / σ), σ the mean squared edge length.
//! The k eigenvectors v_1 … v_k of the normalised Laplacian
//! L = I − D^-½ W D^-½ with the smallest eigenvalues are the PVFs on the
//! nodes (exact dense eigendecomposition up to [`DENSE_PVF_NODES`] nodes,
//! the discrete core's sparse solver above).
//!
//! The Nyström extension to any point x, in its random-walk form:
//! ψ_k = D^-½ v_k are the eigenvectors of P = D⁻¹W with eigenvalue
//! μ_k = 1 − λ_k, and
//!
//!   ψ_k(x) = (1/μ_k) Σ_j [w_j(x) / d(x)] ψ_k(j),
//!   w_j(x) = exp(−‖x − x_j‖² / σ), d(x) = Σ_j w_j(x),
//!
//! the sum over x's nearest node and that node's graph neighbours (not
//! its nearest nodes in the box, which may lie behind a wall). 1/μ_k is a
//! constant per feature and is absorbed by scaling each ψ_k to unit root
//! mean square over the nodes. The first feature (λ = 0 on a connected
//! graph) is then the constant 1.
//!
//! Before the first build (no nodes yet) the basis is the constant
//! feature e_1: the agent explores on the optimism of unknown pairs alone
//! until the graph has [`super::pvf_graph::FIRST_BUILD_NODES`] nodes.

use serde::{Deserialize, Serialize};

use crate::basis::{StateGraph, sparse_pvfs};
use crate::error::{AlgoError, Result};

/// Graphs of at most this many nodes are decomposed densely (exact, and
/// faster than the sparse solver at this size: docs/algorithm.md §9.2).
pub const DENSE_PVF_NODES: usize = 300;

/// A built PVF basis: the nodes, their neighbours and ψ at each.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pvf {
    d: usize,
    k: usize,
    /// The largest node set (the spec's `nodes`).
    max_nodes: usize,
    /// The most edges per node (the spec's `neighbours`).
    neighbours: usize,
    /// 1/σ of the Gaussian weights.
    inv_sigma: f64,
    /// Node points, row-major `n × d`.
    nodes: Vec<f64>,
    /// Node j's neighbours are `idx[ptr[j]..ptr[j + 1]]`.
    ptr: Vec<usize>,
    idx: Vec<u32>,
    /// ψ at the nodes, row-major `n × k` (zero columns beyond n).
    psi: Vec<f64>,
    /// The smallest Laplacian eigenvalues found (ascending).
    eigenvalues: Vec<f64>,
}

impl Pvf {
    /// The basis before any node: the constant feature.
    pub fn empty(d: usize, k: usize, max_nodes: usize, neighbours: usize) -> Self {
        Self {
            d,
            k,
            max_nodes,
            neighbours,
            inv_sigma: 1.0,
            nodes: Vec::new(),
            ptr: vec![0],
            idx: Vec::new(),
            psi: Vec::new(),
            eigenvalues: Vec::new(),
        }
    }

    /// k.
    pub fn len(&self) -> usize {
        self.k
    }

    /// Never empty.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// d.
    pub fn dim(&self) -> usize {
        self.d
    }

    /// Whether a basis read from a snapshot is one of dimension `d` with
    /// `k` features, and every index in it points inside it.
    pub fn fits(&self, d: usize, k: usize) -> bool {
        let n = self.nodes.len() / d.max(1);
        self.d == d
            && self.k == k
            && self.nodes.len() == n * d
            && self.ptr.len() == n + 1
            && self.ptr.first() == Some(&0)
            && self.ptr.windows(2).all(|w| w[0] <= w[1])
            && self.ptr.last() == Some(&self.idx.len())
            && self.idx.iter().all(|&j| (j as usize) < n)
            && self.psi.len() == n * k
            && self.inv_sigma.is_finite()
    }

    /// The largest node set.
    pub fn max_nodes(&self) -> usize {
        self.max_nodes
    }

    /// The most edges per node.
    pub fn neighbours(&self) -> usize {
        self.neighbours
    }

    /// Nodes of the built graph (0 before the first build).
    pub fn nodes(&self) -> usize {
        self.nodes.len() / self.d.max(1)
    }

    /// The Laplacian eigenvalues of the features, ascending.
    pub fn eigenvalues(&self) -> &[f64] {
        &self.eigenvalues
    }

    /// Builds the PVFs of the graph on `nodes` (row-major `n × d`) with the
    /// undirected `edges` (each pair once or twice, any order).
    pub fn build(&self, nodes: &[f64], edges: &[(u32, u32)]) -> Result<Self> {
        let (d, k) = (self.d, self.k);
        let n = nodes.len() / d;
        if n == 0 {
            return Ok(Self::empty(d, k, self.max_nodes, self.neighbours));
        }
        let dist2 = |i: u32, j: u32| sq_dist(row(nodes, d, i as usize), row(nodes, d, j as usize));
        let mut both: Vec<(u32, u32)> = edges
            .iter()
            .filter(|(i, j)| i != j && (*i as usize) < n && (*j as usize) < n)
            .flat_map(|&(i, j)| [(i, j), (j, i)])
            .collect();
        both.sort_unstable();
        both.dedup();
        let sigma = if both.is_empty() {
            1.0
        } else {
            (both.iter().map(|&(i, j)| dist2(i, j)).sum::<f64>() / both.len() as f64).max(1e-12)
        };
        let inv_sigma = 1.0 / sigma;
        let weighted: Vec<(u32, u32, f64)> = both
            .iter()
            .map(|&(i, j)| (i, j, (-dist2(i, j) * inv_sigma).exp().max(1e-300)))
            .collect();
        let graph = StateGraph::weighted(n, &weighted);
        let k_eff = k.min(n);
        let (eigenvalues, v) = if n <= DENSE_PVF_NODES {
            dense(&graph, k_eff)
        } else {
            let (theta, f) = sparse_pvfs(&graph, k_eff)?;
            (theta, f.as_slice().to_vec())
        };
        // ψ = D^-½ v, each column scaled to unit root mean square.
        let mut deg = vec![0.0; n];
        for &(i, _, w) in &weighted {
            deg[i as usize] += w;
        }
        let mut psi = vec![0.0; n * k];
        for j in 0..n {
            let s = if deg[j] > 0.0 {
                1.0 / deg[j].sqrt()
            } else {
                1.0
            };
            for c in 0..k_eff {
                psi[j * k + c] = v[j * k_eff + c] * s;
            }
        }
        for c in 0..k_eff {
            let ms = (0..n).map(|j| psi[j * k + c].powi(2)).sum::<f64>() / n as f64;
            if ms > 0.0 {
                let scale = 1.0 / ms.sqrt();
                (0..n).for_each(|j| psi[j * k + c] *= scale);
            }
        }
        if psi.iter().any(|x| !x.is_finite()) {
            return Err(AlgoError::Numerical(
                "proto-value functions are not finite".into(),
            ));
        }
        let mut ptr = vec![0usize; n + 1];
        for &(i, _) in &both {
            ptr[i as usize + 1] += 1;
        }
        for j in 0..n {
            ptr[j + 1] += ptr[j];
        }
        let idx = both.iter().map(|&(_, j)| j).collect();
        Ok(Self {
            d,
            k,
            max_nodes: self.max_nodes,
            neighbours: self.neighbours,
            inv_sigma,
            nodes: nodes[..n * d].to_vec(),
            ptr,
            idx,
            psi,
            eigenvalues,
        })
    }

    /// v(s): the Nyström extension over s's nearest node and its neighbours.
    pub fn features_into(&self, s: &[f64], out: &mut [f64]) {
        out.iter_mut().for_each(|v| *v = 0.0);
        let n = self.nodes();
        if n == 0 {
            out[0] = 1.0;
            return;
        }
        let nearest = nearest(&self.nodes, self.d, s).0;
        let k = self.k;
        let mut total = 0.0;
        let mut add = |j: usize| {
            let w = (-sq_dist(s, row(&self.nodes, self.d, j)) * self.inv_sigma).exp();
            total += w;
            for (o, p) in out.iter_mut().zip(&self.psi[j * k..(j + 1) * k]) {
                *o += w * p;
            }
        };
        add(nearest);
        for &j in &self.idx[self.ptr[nearest]..self.ptr[nearest + 1]] {
            add(j as usize);
        }
        if total > 0.0 {
            out.iter_mut().for_each(|o| *o /= total);
        } else {
            // Far beyond σ from every node: the nearest node's values.
            out.copy_from_slice(&self.psi[nearest * k..(nearest + 1) * k]);
        }
    }

    /// Floating-point operations of one evaluation.
    pub fn eval_cost(&self) -> usize {
        let n = self.nodes();
        let deg = self.idx.len().checked_div(n).unwrap_or(0);
        n * self.d * 3 + (deg + 1) * (2 * self.k + 3 * self.d + 20)
    }
}

/// Row j of a row-major table of width d.
fn row(t: &[f64], d: usize, j: usize) -> &[f64] {
    &t[j * d..(j + 1) * d]
}

/// ‖a − b‖².
pub(crate) fn sq_dist(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// The nearest node to s (the lowest index among equals) and its squared
/// distance; `nodes` is row-major `n × d` with n ≥ 1.
pub(crate) fn nearest(nodes: &[f64], d: usize, s: &[f64]) -> (usize, f64) {
    let mut best = (0usize, f64::INFINITY);
    for (j, x) in nodes.chunks_exact(d).enumerate() {
        let e = sq_dist(s, x);
        if e < best.1 {
            best = (j, e);
        }
    }
    best
}

/// The k smallest eigenpairs of the graph's normalised Laplacian from a
/// dense decomposition; vectors row-major `n × k`, each signed so that
/// its entry of largest magnitude is positive (as the sparse solver).
fn dense(graph: &StateGraph, k: usize) -> (Vec<f64>, Vec<f64>) {
    crate::basis::smallest_eigenpairs(graph.dense_laplacian(), k)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 1-D chain of nodes with edges between consecutive ones.
    fn chain(n: usize) -> (Vec<f64>, Vec<(u32, u32)>) {
        let nodes = (0..n).map(|i| i as f64 / (n - 1) as f64).collect();
        let edges = (1..n as u32).map(|i| (i - 1, i)).collect();
        (nodes, edges)
    }

    #[test]
    fn the_first_feature_is_constant_and_the_second_changes_sign_along_a_chain() {
        for n in [20, DENSE_PVF_NODES + 40] {
            let (nodes, edges) = chain(n);
            let pvf = Pvf::empty(1, 4, 1000, 8)
                .build(&nodes, &edges)
                .expect("pvf");
            assert_eq!(pvf.nodes(), n);
            assert!(pvf.eigenvalues()[0].abs() < 1e-9, "{:?}", pvf.eigenvalues());
            let mut v = vec![0.0; 4];
            for i in 0..=50 {
                pvf.features_into(&[i as f64 / 50.0], &mut v);
                assert!((v[0] - 1.0).abs() < 1e-6, "n={n}: {v:?}");
                assert!(v.iter().all(|x| x.is_finite()));
            }
            // The second PVF of a chain is a half cosine: opposite signs at the ends.
            let (mut a, mut b) = (vec![0.0; 4], vec![0.0; 4]);
            pvf.features_into(&[0.0], &mut a);
            pvf.features_into(&[1.0], &mut b);
            assert!(a[1] * b[1] < 0.0, "{a:?} {b:?}");
        }
    }

    #[test]
    fn before_any_node_the_basis_is_the_constant_feature() {
        let pvf = Pvf::empty(2, 5, 100, 8);
        let mut v = vec![9.0; 5];
        pvf.features_into(&[0.3, 0.7], &mut v);
        assert_eq!(v, vec![1.0, 0.0, 0.0, 0.0, 0.0]);
    }

    /// Two rows of nodes close in the box but joined only at one end (a
    /// wall between them): the PVFs separate them, as distances cannot.
    #[test]
    fn features_follow_the_graph_not_the_distance() {
        let n = 20;
        let mut nodes = Vec::new();
        for y in [0.0, 0.1] {
            for i in 0..n {
                nodes.extend_from_slice(&[i as f64 / (n - 1) as f64, y]);
            }
        }
        let mut edges: Vec<(u32, u32)> = Vec::new();
        for r in 0..2u32 {
            for i in 1..n as u32 {
                edges.push((r * n as u32 + i - 1, r * n as u32 + i));
            }
        }
        edges.push((0, n as u32)); // the door, at x = 0
        let pvf = Pvf::empty(2, 3, 100, 8).build(&nodes, &edges).expect("pvf");
        let (mut a, mut b) = (vec![0.0; 3], vec![0.0; 3]);
        // Across the wall at the far end, 0.1 apart but 2 rows' length apart on the graph.
        pvf.features_into(&[1.0, 0.0], &mut a);
        pvf.features_into(&[1.0, 0.1], &mut b);
        assert!((a[1] - b[1]).abs() > 1.0, "{a:?} {b:?}");
    }
}
