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

use nalgebra::{DMatrix, SymmetricEigen};

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
        match spec {
            BasisSpec::Indicator => Ok(Self::Indicator),
            BasisSpec::ProtoValue { k } => Ok(Self::StateBlocks(proto_value_functions(model, *k)?)),
            BasisSpec::Custom { state_features } => {
                Ok(Self::StateBlocks(custom_features(model, state_features)?))
            }
        }
    }

    /// Number of features (columns of Φ).
    pub fn n_features(&self, model: &EnvModel) -> usize {
        match self {
            Self::Indicator => model.n_pairs(),
            Self::StateBlocks(f) => f.k() * model.n_actions(),
        }
    }
}

fn custom_features(model: &EnvModel, rows: &[Vec<f64>]) -> Result<StateFeatures> {
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
    let mut values = Vec::with_capacity(rows.len() * k);
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
        values.extend_from_slice(row);
    }
    Ok(StateFeatures::new(k, values))
}

/// The k eigenvectors of the normalised Laplacian with the smallest
/// eigenvalues (docs/algorithm.md §5). W_ss' = 1 when some action moves s to
/// s' ≠ s with p > 0, symmetrised, without self loops. A state without
/// neighbours has a zero row in D^{-1/2} W D^{-1/2}.
///
/// The eigenvectors are orthonormal; each is signed so that its entry of
/// largest magnitude is positive, which makes the basis reproducible.
pub fn proto_value_functions(model: &EnvModel, k: usize) -> Result<StateFeatures> {
    let n = model.states();
    if k == 0 || k > n {
        return Err(AlgoError::InvalidBasis(format!(
            "`k` = {k} must be between 1 and the number of states ({n})"
        )));
    }
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
    let eig = SymmetricEigen::new(lap);
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
    if values.iter().any(|x| !x.is_finite()) {
        return Err(AlgoError::Numerical(
            "proto-value functions are not finite".into(),
        ));
    }
    Ok(StateFeatures::new(k, values))
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
