//! The stimulus function Ξ of a continuous world (docs/algorithm.md
//! §9.3): a linear model of the stimulus in the state features of each
//! action, Ξ(s, a) = W_aᵀ v(s) ∈ R^n, fitted online by recursive least
//! squares. It replaces the discrete table of Algorithm 1, line 5.
//!
//! The discrete agent starts from Ξ ~ N(0, σ²) and a visited pair's row
//! becomes the sample mean of what it delivered. Here the draw becomes a
//! prior: W_a starts at a random M_a scaled so that Ξ(s, a) ~ N(0, σ²) at
//! a typical point, and RLS computes the ridge regression towards M_a,
//! W_a = (λI + Σ v vᵀ)⁻¹ (λ M_a + Σ v ξᵀ), with λ = E‖v‖² (one typical
//! observation's worth of prior). Where the agent has not been, Ξ keeps
//! its optimistic draw; where it has, Ξ follows what it received.
//!
//! One observation costs O(k² + k·n): one shared inverse per action.

use nalgebra::DMatrix;
use rand::Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use super::basis::FeatureMap;
use super::samples::SampleStore;

/// Ξ as per-action linear models.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LinearStimulus {
    k: usize,
    n: usize,
    /// W_a, row-major `actions × k × n`.
    w: Vec<f64>,
    /// P_a = (λI + Σ v vᵀ)⁻¹, row-major `actions × k × k` (symmetric).
    p: Vec<f64>,
    /// Scratch: P v.
    pv: Vec<f64>,
    /// Scratch: the prediction errors.
    err: Vec<f64>,
}

/// E‖v(s)‖² over the probe points ([`probe_features`]): the scale of a
/// typical feature vector, for the prior.
pub fn mean_sq_norm(map: &FeatureMap, d: usize) -> f64 {
    let probes = probe_features(map, d);
    let total: f64 = probes.iter().map(|x| x * x).sum();
    (total / PROBES as f64).max(f64::MIN_POSITIVE)
}

/// Number of probe points.
pub const PROBES: usize = 64;

/// v at [`PROBES`] fixed points of [0, 1]^d spread evenly (the Kronecker
/// sequence of the square roots of the first primes), row-major
/// `PROBES × k`: where the prior's scale is measured, and where the
/// planner looks for the best reward the agent can name.
pub fn probe_features(map: &FeatureMap, d: usize) -> Vec<f64> {
    const PRIMES: [f64; 16] = [
        2., 3., 5., 7., 11., 13., 17., 19., 23., 29., 31., 37., 41., 43., 47., 53.,
    ];
    let k = map.len();
    let mut out = vec![0.0; PROBES * k];
    let mut s = vec![0.0; d];
    for (i, v) in out.chunks_exact_mut(k).enumerate() {
        for (j, x) in s.iter_mut().enumerate() {
            let alpha = PRIMES[j % PRIMES.len()].sqrt() * (1 + j / PRIMES.len()) as f64;
            *x = ((i as f64 + 0.5) * alpha).fract();
        }
        map.features_into(&s, v);
    }
    out
}

impl LinearStimulus {
    /// W_a = M_a with entries N(0, sd² / E‖v‖²), drawn action by action,
    /// feature by feature; P_a = I / E‖v‖².
    pub fn new(
        actions: usize,
        k: usize,
        n: usize,
        sd: f64,
        typical_sq_norm: f64,
        rng: &mut impl Rng,
    ) -> Self {
        let entry_sd = sd / typical_sq_norm.sqrt();
        let w = match Normal::new(0.0, entry_sd) {
            Ok(normal) => (0..actions * k * n).map(|_| normal.sample(rng)).collect(),
            Err(_) => vec![0.0; actions * k * n],
        };
        let mut p = vec![0.0; actions * k * k];
        for a in 0..actions {
            for j in 0..k {
                p[a * k * k + j * k + j] = 1.0 / typical_sq_norm;
            }
        }
        Self {
            k,
            n,
            w,
            p,
            pv: vec![0.0; k],
            err: vec![0.0; n],
        }
    }

    /// Ξ fitted afresh on another basis (docs/algorithm.md §9.2, a PVF
    /// rebuild): a new prior M_a drawn as [`Self::new`] draws it, then the
    /// ridge regression towards it over the stored transitions, each
    /// standing for its weight ω in visits with its mean stimulus:
    /// P_a = (λI + Σ ω v vᵀ)⁻¹, W_a = P_a (λ M_a + Σ ω v ξᵀ). What RLS
    /// would hold had it seen the stored transitions' visits on this basis.
    /// O(N k² + |A| k³).
    pub fn fitted(
        actions: usize,
        k: usize,
        n: usize,
        sd: f64,
        typical_sq_norm: f64,
        rng: &mut impl Rng,
        samples: &SampleStore,
    ) -> Self {
        let mut xi = Self::new(actions, k, n, sd, typical_sq_norm, rng);
        let lambda = typical_sq_norm;
        for a in 0..actions {
            let mine = || {
                samples
                    .samples()
                    .iter()
                    .zip(samples.iter())
                    .filter(|(s, _)| s.a == a)
            };
            if mine().next().is_none() {
                continue;
            }
            let mut g = vec![0.0; k * k];
            for j in 0..k {
                g[j * k + j] = lambda;
            }
            let w = &mut xi.w[a * k * n..(a + 1) * k * n];
            let mut rhs: Vec<f64> = w.iter().map(|m| lambda * m).collect();
            for (s, features) in mine() {
                for (r, &vr) in features.v.iter().enumerate() {
                    let c = s.weight * vr;
                    if c == 0.0 {
                        continue;
                    }
                    for (gc, vc) in g[r * k..(r + 1) * k].iter_mut().zip(features.v) {
                        *gc += c * vc;
                    }
                    for (h, x) in rhs[r * n..(r + 1) * n].iter_mut().zip(&s.xi) {
                        *h += c * x;
                    }
                }
            }
            let g = DMatrix::from_row_slice(k, k, &g);
            let Some(p) = g
                .clone()
                .cholesky()
                .map(|c| c.inverse())
                .or_else(|| g.try_inverse())
            else {
                continue;
            };
            let p_block = &mut xi.p[a * k * k..(a + 1) * k * k];
            for r in 0..k {
                for c in 0..k {
                    p_block[r * k + c] = p[(r, c)];
                }
            }
            // W_a = P_a · rhs, in a fixed order.
            for r in 0..k {
                let out = &mut w[r * n..(r + 1) * n];
                out.iter_mut().for_each(|o| *o = 0.0);
                for c in 0..k {
                    let m = p_block[r * k + c];
                    if m != 0.0 {
                        for (o, h) in out.iter_mut().zip(&rhs[c * n..(c + 1) * n]) {
                            *o += m * h;
                        }
                    }
                }
            }
        }
        xi
    }

    /// Stimulus dimensions n.
    pub fn dims(&self) -> usize {
        self.n
    }

    /// Whether Ξ read from a snapshot has the shape of an agent with
    /// `actions` actions, `k` features and `n` stimuli.
    pub fn fits(&self, actions: usize, k: usize, n: usize) -> bool {
        self.k == k
            && self.n == n
            && self.w.len() == actions * k * n
            && self.p.len() == actions * k * k
            && self.pv.len() == k
            && self.err.len() == n
    }

    /// One RLS step for action `a` at features `v` with target ξ.
    pub fn update(&mut self, a: usize, v: &[f64], xi: &[f64]) {
        let (k, n) = (self.k, self.n);
        let p = &mut self.p[a * k * k..(a + 1) * k * k];
        let w = &mut self.w[a * k * n..(a + 1) * k * n];
        for (r, pv) in self.pv.iter_mut().enumerate() {
            *pv = p[r * k..(r + 1) * k]
                .iter()
                .zip(v)
                .map(|(p, v)| p * v)
                .sum();
        }
        let denom = 1.0 + v.iter().zip(&self.pv).map(|(v, pv)| v * pv).sum::<f64>();
        // Prediction errors ξ − W_aᵀ v, then W_a += (P v / denom) errᵀ.
        let err = &mut self.err;
        for (i, e) in err.iter_mut().enumerate() {
            let pred: f64 = (0..k).map(|j| w[j * n + i] * v[j]).sum();
            *e = xi[i] - pred;
        }
        for j in 0..k {
            let g = self.pv[j] / denom;
            if g != 0.0 {
                for (wi, e) in w[j * n..(j + 1) * n].iter_mut().zip(err.iter()) {
                    *wi += g * e;
                }
            }
        }
        // P −= (P v)(P v)ᵀ / denom.
        for r in 0..k {
            let gr = self.pv[r] / denom;
            if gr != 0.0 {
                for (pc, pvc) in p[r * k..(r + 1) * k].iter_mut().zip(&self.pv) {
                    *pc -= gr * pvc;
                }
            }
        }
    }

    /// Ξ(s, a) = W_aᵀ v into `out` (length n).
    pub fn predict_into(&self, a: usize, v: &[f64], out: &mut [f64]) {
        let (k, n) = (self.k, self.n);
        let w = &self.w[a * k * n..(a + 1) * k * n];
        out.iter_mut().for_each(|o| *o = 0.0);
        for (j, &vj) in v.iter().enumerate().take(k) {
            if vj != 0.0 {
                for (o, wi) in out.iter_mut().zip(&w[j * n..(j + 1) * n]) {
                    *o += wi * vj;
                }
            }
        }
    }

    /// u_a = W_a Λ D for every action (`actions × k`), so that the reward
    /// of Eq. 3 / line 8 at any (s, a) is R(s, a) = |v(s) · u_a|.
    pub fn reward_weights_into(&self, scaled_drive: &[f64], u: &mut [f64]) {
        debug_assert_eq!(u.len(), self.w.len() / self.n);
        for (row, out) in self.w.chunks_exact(self.n).zip(u.iter_mut()) {
            *out = row.iter().zip(scaled_drive).map(|(w, d)| w * d).sum();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::continuous::basis::ContinuousBasisSpec;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn rls_learns_a_local_source_and_keeps_the_prior_elsewhere() {
        let map = ContinuousBasisSpec::Rbf {
            centres_per_dim: 20,
            width: None,
        }
        .build(1, 2)
        .expect("basis");
        let k = map.len();
        let norm = mean_sq_norm(&map, 1);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut xi = LinearStimulus::new(2, k, 2, 0.3, norm, &mut rng);
        let mut v = vec![0.0; k];
        let mut out = [0.0; 2];
        map.features_into(&[0.9], &mut v);
        let mut far_before = [0.0; 2];
        xi.predict_into(0, &v, &mut far_before);
        // Food at x < 0.1 for action 0: ξ = [6, 0]; nothing elsewhere.
        for i in 0..400 {
            let x = (i % 40) as f64 / 80.0; // 0 .. 0.5
            map.features_into(&[x], &mut v);
            let target = if x < 0.1 { [6.0, 0.0] } else { [0.0, 0.0] };
            xi.update(0, &v, &target);
        }
        map.features_into(&[0.02], &mut v);
        xi.predict_into(0, &v, &mut out);
        assert!(
            (out[0] - 6.0).abs() < 1.0 && out[1].abs() < 0.5,
            "near the source: {out:?}"
        );
        map.features_into(&[0.3], &mut v);
        xi.predict_into(0, &v, &mut out);
        assert!(out[0].abs() < 0.5, "visited, empty: {out:?}");
        map.features_into(&[0.9], &mut v);
        xi.predict_into(0, &v, &mut out);
        for (a, b) in out.iter().zip(far_before) {
            assert!(
                (a - b).abs() < 0.1 * b.abs().max(0.05),
                "unvisited keeps the prior: {out:?} vs {far_before:?}"
            );
        }
    }
}
