//! Incremental slow feature analysis (IncSFA, Kompella et al. 2012), §7 "A
//! module" steps 1-3: quadratic expansion, exact running centring and
//! whitening, backward differences, MCA on the differences, the slow
//! feature y.

use nalgebra::{DMatrix, SymmetricEigen};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use super::params::ValidCuriosityParams;
use crate::drive::norm;

/// Dimension of the quadratic expansion of an m-dimensional signal:
/// m linear, m squares and m(m−1)/2 cross products.
pub const fn expanded_dim(m: usize) -> usize {
    m * (m + 3) / 2
}

/// §7 step 1: z = [x_i …, x_i² …, x_i x_j for i < j] (for m = 2:
/// [x1, x2, x1², x2², x1x2]). Writes into `z`, replacing its contents.
pub fn expand_quadratic(x: &[f64], z: &mut Vec<f64>) {
    z.clear();
    z.extend_from_slice(x);
    z.extend(x.iter().map(|v| v * v));
    for i in 0..x.len() {
        for j in i + 1..x.len() {
            z.push(x[i] * x[j]);
        }
    }
}

pub(super) fn expand(x: &[f64]) -> Vec<f64> {
    let mut z = Vec::with_capacity(expanded_dim(x.len()));
    expand_quadratic(x, &mut z);
    z
}

/// y = A v for a row-major d×d matrix A.
fn mat_vec(a: &[f64], v: &[f64], out: &mut [f64]) {
    let d = v.len();
    for (i, o) in out.iter_mut().enumerate() {
        *o = a[i * d..(i + 1) * d]
            .iter()
            .zip(v)
            .map(|(a, v)| a * v)
            .sum();
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(a, b)| a * b).sum()
}

/// A random unit vector of dimension d: w₀ of a module (§7 step 3).
fn random_unit(d: usize, rng: &mut impl Rng) -> Vec<f64> {
    loop {
        let w: Vec<f64> = (0..d).map(|_| StandardNormal.sample(rng)).collect();
        let len = norm(&w);
        // A zero draw has probability 0; redraw rather than divide by it.
        if len > 1e-12 && len.is_finite() {
            return w.into_iter().map(|x| x / len).collect();
        }
    }
}

/// One incremental slow-feature learner (IncSFA, Kompella et al. 2012) with
/// a single output: the slow feature y = w·S(z − m).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SfaModule {
    /// Signal dimension m.
    m: usize,
    /// Samples learned from, n.
    n: u64,
    /// Running mean of z.
    mean: Vec<f64>,
    /// Running covariance of z, row-major d×d.
    cov: Vec<f64>,
    /// Whitening matrix S = C^(−1/2) (floored), row-major d×d.
    whitening: Vec<f64>,
    /// The unit feature direction w in whitened space.
    w: Vec<f64>,
    /// z of the previous learned sample, for the backward difference.
    z_prev: Option<Vec<f64>>,
    eta_c: f64,
    floor_rel: f64,
    floor_abs: f64,
}

impl SfaModule {
    /// A fresh module for m-dimensional signals with initial direction w₀
    /// (normalised here; it must have [`expanded_dim`]`(m)` entries and a
    /// nonzero finite norm, else the first basis vector is used). The
    /// whitening starts as the identity, the mean at 0.
    pub fn new(m: usize, w0: Vec<f64>, params: &ValidCuriosityParams) -> Self {
        let d = expanded_dim(m);
        let len = norm(&w0);
        let w = if w0.len() == d && len > 0.0 && len.is_finite() {
            w0.into_iter().map(|x| x / len).collect()
        } else {
            let mut e = vec![0.0; d];
            if let Some(first) = e.first_mut() {
                *first = 1.0;
            }
            e
        };
        let mut identity = vec![0.0; d * d];
        for i in 0..d {
            identity[i * d + i] = 1.0;
        }
        Self {
            m,
            n: 0,
            mean: vec![0.0; d],
            cov: vec![0.0; d * d],
            whitening: identity,
            w,
            z_prev: None,
            eta_c: params.eta_c,
            floor_rel: params.floor_rel,
            floor_abs: params.floor_abs,
        }
    }

    /// A fresh module with w₀ drawn from `rng`.
    pub fn random(m: usize, params: &ValidCuriosityParams, rng: &mut impl Rng) -> Self {
        let w0 = random_unit(expanded_dim(m), rng);
        Self::new(m, w0, params)
    }

    /// Learns from one sample and returns its slow feature y (§7 steps 1-3):
    ///
    /// - d = z − m; m += a·d; C = (1−a)(C + a·d dᵀ) with a = 1/n (the exact
    ///   running mean and population covariance);
    /// - S = C^(−1/2) by symmetric eigendecomposition, eigenvalues floored
    ///   at `floor_rel`·λ_max + `floor_abs`;
    /// - du = S(z − z_prev) with the current S, and MCA on du,
    ///   w ← normalise((1−η_c) w − η_c (w·du) du); no MCA step on the first
    ///   sample;
    /// - y = w·S(z − m).
    ///
    /// `x` must have m entries (the channel checks it).
    pub fn learn(&mut self, x: &[f64]) -> f64 {
        debug_assert_eq!(x.len(), self.m);
        let z = expand(x);
        let d = z.len();
        self.n += 1;
        let a = 1.0 / self.n as f64;
        let diff: Vec<f64> = z.iter().zip(&self.mean).map(|(z, m)| z - m).collect();
        for (m, dz) in self.mean.iter_mut().zip(&diff) {
            *m += a * dz;
        }
        for i in 0..d {
            for j in 0..d {
                let c = &mut self.cov[i * d + j];
                *c = (1.0 - a) * (*c + a * diff[i] * diff[j]);
            }
        }
        self.update_whitening();
        if let Some(prev) = &self.z_prev {
            let dz: Vec<f64> = z.iter().zip(prev).map(|(z, p)| z - p).collect();
            let mut du = vec![0.0; d];
            mat_vec(&self.whitening, &dz, &mut du);
            self.mca_step(&du);
        }
        let y = self.feature_of_expanded(&z);
        self.z_prev = Some(z);
        y
    }

    /// The slow feature y = w·S(z − m) of a sample, without learning.
    pub fn output(&self, x: &[f64]) -> f64 {
        debug_assert_eq!(x.len(), self.m);
        self.feature_of_expanded(&expand(x))
    }

    fn feature_of_expanded(&self, z: &[f64]) -> f64 {
        let centred: Vec<f64> = z.iter().zip(&self.mean).map(|(z, m)| z - m).collect();
        let mut white = vec![0.0; z.len()];
        mat_vec(&self.whitening, &centred, &mut white);
        dot(&self.w, &white)
    }

    /// S = C^(−1/2) with the floor of §7 step 2. If the eigensolver does not
    /// converge (not seen on finite input) the previous S is kept.
    fn update_whitening(&mut self) {
        let d = self.mean.len();
        let c = DMatrix::from_row_slice(d, d, &self.cov);
        let Some(eig) = SymmetricEigen::try_new(c, f64::EPSILON, 10_000) else {
            return;
        };
        let lambda_max = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
        let floor = self.floor_rel * lambda_max + self.floor_abs;
        let inv_sqrt: Vec<f64> = eig
            .eigenvalues
            .iter()
            .map(|&l| 1.0 / l.max(floor).sqrt())
            .collect();
        let v = &eig.eigenvectors;
        for i in 0..d {
            for j in i..d {
                let s: f64 = (0..d).map(|k| v[(i, k)] * inv_sqrt[k] * v[(j, k)]).sum();
                self.whitening[i * d + j] = s;
                self.whitening[j * d + i] = s;
            }
        }
    }

    /// Peng's MCA rule on the whitened difference (§7 step 3). If the step
    /// produced a zero or non-finite vector w is left unchanged (our guard,
    /// as in [`super::drive::Drive::update`]).
    fn mca_step(&mut self, du: &[f64]) {
        let proj = dot(&self.w, du);
        let eta = self.eta_c;
        let next: Vec<f64> = self
            .w
            .iter()
            .zip(du)
            .map(|(w, u)| (1.0 - eta) * w - eta * proj * u)
            .collect();
        let len = norm(&next);
        if len > f64::MIN_POSITIVE && len.is_finite() {
            self.w = next.into_iter().map(|x| x / len).collect();
        }
    }

    /// Signal dimension m.
    pub fn signal_dim(&self) -> usize {
        self.m
    }

    /// Samples learned from.
    pub fn samples(&self) -> u64 {
        self.n
    }

    /// The unit feature direction w (in whitened, expanded space).
    pub fn direction(&self) -> &[f64] {
        &self.w
    }

    /// The running mean of z.
    pub fn mean(&self) -> &[f64] {
        &self.mean
    }

    /// The running covariance C of z, row-major d×d.
    pub fn covariance(&self) -> &[f64] {
        &self.cov
    }

    /// The whitening matrix S, row-major d×d.
    pub fn whitening(&self) -> &[f64] {
        &self.whitening
    }

    /// S C Sᵀ, the covariance of S(z − m) over the samples learned from
    /// (≈ I wherever C's eigenvalues are above the floor); a check of step 2.
    pub fn whitened_covariance(&self) -> Vec<f64> {
        let d = self.mean.len();
        let s = DMatrix::from_row_slice(d, d, &self.whitening);
        let c = DMatrix::from_row_slice(d, d, &self.cov);
        let w = &s * c * s.transpose();
        (0..d * d).map(|k| w[(k / d, k % d)]).collect()
    }
}
