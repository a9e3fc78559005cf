//! The drive vector D: Peng's anti-Hebbian Minor Component Analysis rule
//! (Eqs. 1-2, Algorithm 1 lines 6-7), and the scalar reward of Eq. 3.
//!
//! D tracks the minor eigenvector of C = E[Λξ ξᵀΛ], so it points at the
//! stimuli the agent received least.

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// The drive, its MCA rate and the running estimate of λ₁ (docs/algorithm.md §4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Drive {
    d: Vec<f64>,
    /// 1/ρ per dimension: the diagonal of Λ.
    inv_rho: Vec<f64>,
    eta: f64,
    /// Running mean of Λξ ξᵀΛ (row-major n×n), for the λ₁ estimate.
    second_moment: Vec<f64>,
    samples: u64,
    max_sq_norm: f64,
    /// Scratch: Λξ of the last update.
    #[serde(skip)]
    scaled: Vec<f64>,
    /// Scratch: D before normalisation.
    #[serde(skip)]
    next: Vec<f64>,
}

/// Euclidean norm.
#[inline]
pub fn norm(x: &[f64]) -> f64 {
    x.iter().map(|v| v * v).sum::<f64>().sqrt()
}

impl Drive {
    /// Hints the CPU to load what [`Drive::update`] touches ([`crate::prefetch`]).
    pub(crate) fn prefetch(&self) {
        crate::prefetch::slice(&self.d);
        crate::prefetch::slice(&self.inv_rho);
        crate::prefetch::slice(&self.second_moment);
        crate::prefetch::slice(&self.scaled);
        crate::prefetch::slice(&self.next);
    }

    /// D₀ = |N(0, I)| normalised (docs/algorithm.md §3).
    pub fn new(priorities: &[f64], eta: f64, rng: &mut impl Rng) -> Self {
        let n = priorities.len();
        let d: Vec<f64> = (0..n)
            .map(|_| StandardNormal.sample(rng))
            .map(|x: f64| x.abs())
            .collect();
        Self::from_parts(d, priorities, eta)
    }

    /// A drive with a given direction (normalised here; a zero or
    /// non-finite vector becomes the uniform direction).
    pub fn from_parts(mut d: Vec<f64>, priorities: &[f64], eta: f64) -> Self {
        let n = d.len();
        assert_eq!(priorities.len(), n, "one priority per drive component");
        let len = norm(&d);
        if len > 0.0 && len.is_finite() {
            d.iter_mut().for_each(|x| *x /= len);
        } else {
            d.iter_mut().for_each(|x| *x = 1.0 / (n as f64).sqrt());
        }
        Self {
            d,
            inv_rho: priorities.iter().map(|r| 1.0 / r).collect(),
            eta,
            second_moment: vec![0.0; n * n],
            samples: 0,
            max_sq_norm: 0.0,
            scaled: vec![0.0; n],
            next: vec![0.0; n],
        }
    }

    /// A copy without the scratch buffers (what a snapshot keeps).
    pub fn without_scratch(&self) -> Self {
        Self {
            scaled: Vec::new(),
            next: Vec::new(),
            ..self.clone()
        }
    }

    /// The unit drive vector D.
    #[inline]
    pub fn vector(&self) -> &[f64] {
        &self.d
    }

    /// The diagonal of Λ = diag(1/ρ).
    #[inline]
    pub fn inv_rho(&self) -> &[f64] {
        &self.inv_rho
    }

    /// One MCA step on stimulus ξ, returning r = D·Λξ with the new D.
    ///
    /// Eq. 1: D ← (1−η) D − η (D·Λξ) Λξ; Eq. 2: D ← D/‖D‖; Eq. 3: r = D·Λξ.
    /// If Eq. 1 ever produced a zero or non-finite vector (a measure-zero
    /// event: D ∥ Λξ with η‖Λξ‖² = 1−η) D is left unchanged rather than
    /// letting NaN escape; this is our guard, not the paper's.
    pub fn update(&mut self, xi: &[f64]) -> f64 {
        debug_assert_eq!(xi.len(), self.d.len());
        let n = self.d.len();
        self.scaled.resize(n, 0.0);
        for ((s, x), l) in self.scaled.iter_mut().zip(xi).zip(&self.inv_rho) {
            *s = x * l;
        }
        let u = &self.scaled;
        let proj: f64 = self.d.iter().zip(u).map(|(d, u)| d * u).sum();
        let eta = self.eta;
        self.next.resize(n, 0.0);
        for ((x, d), u) in self.next.iter_mut().zip(&self.d).zip(u) {
            *x = (1.0 - eta) * d - eta * proj * u;
        }
        let len = norm(&self.next);
        if len > f64::MIN_POSITIVE && len.is_finite() {
            for (d, x) in self.d.iter_mut().zip(&self.next) {
                *d = x / len;
            }
        }
        debug_assert!((norm(&self.d) - 1.0).abs() < 1e-9, "|D| = 1 after Eq. 2");
        self.track(n);
        self.d.iter().zip(&self.scaled).map(|(d, u)| d * u).sum()
    }

    /// Sets component `dim` of D to `value` and renormalises, |D| = 1
    /// (docs/algorithm.md §7, condition (3): D\[cur\] = 0 while every known signal
    /// source is explained, 1/√n when one becomes unexplained again). Sets
    /// nothing and returns false if the result would not be a finite
    /// non-zero vector; a component already equal to `value` is left as it
    /// is, bit for bit.
    pub fn set_component(&mut self, dim: usize, value: f64) -> bool {
        let Some(&old) = self.d.get(dim) else {
            return false;
        };
        if old == value {
            return true;
        }
        self.d[dim] = value;
        let len = norm(&self.d);
        if len > f64::MIN_POSITIVE && len.is_finite() {
            self.d.iter_mut().for_each(|x| *x /= len);
            true
        } else {
            self.d[dim] = old;
            false
        }
    }

    /// Updates the running second moment of Λξ and max ‖Λξ‖².
    fn track(&mut self, n: usize) {
        self.samples += 1;
        let a = 1.0 / self.samples as f64;
        let u = &self.scaled;
        let mut sq = 0.0;
        for i in 0..n {
            sq += u[i] * u[i];
            let row = &mut self.second_moment[i * n..(i + 1) * n];
            for j in 0..n {
                row[j] += a * (u[i] * u[j] - row[j]);
            }
        }
        self.max_sq_norm = self.max_sq_norm.max(sq);
    }

    /// Number of stimuli seen.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// max ‖Λξ‖² seen so far.
    pub fn max_sq_norm(&self) -> f64 {
        self.max_sq_norm
    }

    /// Estimate of λ₁, the largest eigenvalue of C = E[Λξ ξᵀΛ], from the
    /// running second moment (an exact symmetric eigendecomposition of the
    /// small n×n matrix).
    pub fn lambda1_estimate(&self) -> f64 {
        let n = self.d.len();
        let c = nalgebra::DMatrix::from_row_slice(n, n, &self.second_moment);
        nalgebra::SymmetricEigen::new(c)
            .eigenvalues
            .iter()
            .copied()
            .fold(0.0, f64::max)
    }

    /// Condition (1) of Sec. 3.1: η λ₁ < 0.5, with the running λ₁ estimate.
    pub fn condition_holds(&self) -> bool {
        self.eta * self.lambda1_estimate() < 0.5
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn eq1_by_hand() {
        // D = (1, 0), ξ = (1, 1), η = 0.1, Λ = I:
        // D·ξ = 1, D' = 0.9 (1,0) − 0.1 (1,1) = (0.8, −0.1), normalised.
        let mut drive = Drive::from_parts(vec![1.0, 0.0], &[1.0, 1.0], 0.1);
        let r = drive.update(&[1.0, 1.0]);
        let len = (0.8f64 * 0.8 + 0.01).sqrt();
        assert!((drive.vector()[0] - 0.8 / len).abs() < 1e-15);
        assert!((drive.vector()[1] + 0.1 / len).abs() < 1e-15);
        // Eq. 3 with the updated D.
        assert!((r - (0.8 - 0.1) / len).abs() < 1e-15);
    }

    #[test]
    fn priorities_scale_the_stimulus() {
        // ρ = (0.5, 1): Λξ = (2, 0) for ξ = (1, 0).
        let mut drive = Drive::from_parts(vec![1.0, 1.0], &[0.5, 1.0], 0.1);
        let r = drive.update(&[1.0, 0.0]);
        let s = std::f64::consts::FRAC_1_SQRT_2;
        // D·Λξ = 2s; D' = 0.9 (s, s) − 0.1·2s·(2, 0) = (0.5s, 0.9s).
        let (a, b) = (0.5 * s, 0.9 * s);
        let len = (a * a + b * b).sqrt();
        assert!((drive.vector()[0] - a / len).abs() < 1e-15);
        assert!((r - 2.0 * a / len).abs() < 1e-15);
    }

    #[test]
    fn receiving_food_turns_the_drive_to_rest() {
        let mut drive = Drive::from_parts(vec![0.8, 0.6], &[1.0, 1.0], 0.01);
        for _ in 0..500 {
            drive.update(&[6.0, 0.0]);
        }
        assert!(drive.vector()[1].abs() > 0.99, "{:?}", drive.vector());
    }

    #[test]
    fn initial_drive_is_a_positive_unit_vector() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let d = Drive::new(&[1.0; 4], 0.01, &mut rng);
        assert!((norm(d.vector()) - 1.0).abs() < 1e-12);
        assert!(d.vector().iter().all(|&x| x >= 0.0));
    }

    #[test]
    fn lambda1_tracks_the_second_moment() {
        let mut drive = Drive::from_parts(vec![1.0, 0.0], &[1.0, 1.0], 0.01);
        drive.update(&[2.0, 0.0]);
        drive.update(&[0.0, 0.0]);
        // C = diag(2, 0).
        assert!((drive.lambda1_estimate() - 2.0).abs() < 1e-9);
        assert_eq!(drive.max_sq_norm(), 4.0);
        assert!(drive.condition_holds());
    }

    #[test]
    fn set_component_renormalises() {
        let mut drive = Drive::from_parts(vec![0.6, 0.0, 0.8], &[1.0; 3], 0.01);
        assert!(drive.set_component(2, 0.0));
        assert_eq!(drive.vector(), &[1.0, 0.0, 0.0]);
        let s = 1.0 / 3f64.sqrt();
        assert!(drive.set_component(2, s));
        let len = (1.0 + s * s).sqrt();
        assert!((drive.vector()[0] - 1.0 / len).abs() < 1e-15);
        assert!((drive.vector()[2] - s / len).abs() < 1e-15);
        let mut lone = Drive::from_parts(vec![0.0, 1.0], &[1.0; 2], 0.01);
        assert!(!lone.set_component(1, 0.0), "a zero drive is refused");
        assert_eq!(lone.vector(), &[0.0, 1.0]);
        assert!(!lone.set_component(5, 0.0));
    }
}
