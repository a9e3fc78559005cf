//! The stimulus function Ξ (Algorithm 1, line 5) and the reward function
//! R = |Ξ Λ D| (line 8).
//!
//! Ξ has one row per valid pair and one column per stimulus dimension: the
//! agent's estimate of what taking a in s delivers. It starts optimistic,
//! Ξ ~ N(0, σ²) (ALGORITHM.md §3), so unexplored pairs promise something.

use rand::Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use super::params::StimulusRate;

/// Ξ and the visit counts n(s, a).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StimulusFunction {
    n: usize,
    /// Row-major `pairs × n`.
    xi: Vec<f64>,
    visits: Vec<u32>,
}

impl StimulusFunction {
    /// Ξ ~ N(0, sd²) per entry, zero visits.
    pub fn new(pairs: usize, n: usize, sd: f64, rng: &mut impl Rng) -> Self {
        let xi = match Normal::new(0.0, sd) {
            Ok(normal) => (0..pairs * n).map(|_| normal.sample(rng)).collect(),
            // sd is checked finite and non-negative; this arm is unreachable in practice.
            Err(_) => vec![0.0; pairs * n],
        };
        Self {
            n,
            xi,
            visits: vec![0; pairs],
        }
    }

    /// Number of stimulus dimensions.
    pub fn dims(&self) -> usize {
        self.n
    }

    /// Ξ(p, ·).
    #[inline]
    pub fn row(&self, p: usize) -> &[f64] {
        &self.xi[p * self.n..(p + 1) * self.n]
    }

    /// The whole table, row-major `pairs × n`.
    pub fn table(&self) -> &[f64] {
        &self.xi
    }

    /// Visits n(p).
    pub fn visits(&self) -> &[u32] {
        &self.visits
    }

    /// Line 5: Ξ(p) += η_stim (ξ − Ξ(p)), η_stim = 1/n(p) or a constant.
    pub fn update(&mut self, p: usize, xi: &[f64], rate: StimulusRate) {
        self.visits[p] = self.visits[p].saturating_add(1);
        let eta = match rate {
            StimulusRate::Constant(c) => c,
            StimulusRate::Named(_) => 1.0 / f64::from(self.visits[p]),
        };
        let row = &mut self.xi[p * self.n..(p + 1) * self.n];
        for (x, &obs) in row.iter_mut().zip(xi) {
            *x += eta * (obs - *x);
        }
    }

    /// Line 8: R = |Ξ Λ D| elementwise, written into `r` (one entry per pair).
    /// `scaled_drive` is Λ D.
    pub fn rewards_into(&self, scaled_drive: &[f64], r: &mut [f64]) {
        let n = self.n;
        debug_assert_eq!(scaled_drive.len(), n);
        debug_assert_eq!(r.len() * n, self.xi.len());
        match n {
            2 => {
                let (d0, d1) = (scaled_drive[0], scaled_drive[1]);
                for (out, row) in r.iter_mut().zip(self.xi.chunks_exact(2)) {
                    *out = (row[0] * d0 + row[1] * d1).abs();
                }
            }
            3 => {
                let (d0, d1, d2) = (scaled_drive[0], scaled_drive[1], scaled_drive[2]);
                for (out, row) in r.iter_mut().zip(self.xi.chunks_exact(3)) {
                    *out = (row[0] * d0 + row[1] * d1 + row[2] * d2).abs();
                }
            }
            _ => {
                for (out, row) in r.iter_mut().zip(self.xi.chunks_exact(n)) {
                    *out = row
                        .iter()
                        .zip(scaled_drive)
                        .map(|(x, d)| x * d)
                        .sum::<f64>()
                        .abs();
                }
            }
        }
    }

    /// Condition (3) of Sec. 3.1: the stimulus dimensions whose column of Ξ
    /// is constant across all pairs (they need no planning).
    pub fn constant_columns(&self) -> Vec<usize> {
        (0..self.n)
            .filter(|&j| {
                let first = self.xi[j];
                self.xi.iter().skip(j).step_by(self.n).all(|&x| x == first)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::params::StimulusRateName;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn sample_mean_rate_gives_the_mean() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut f = StimulusFunction::new(3, 2, 0.3, &mut rng);
        let rate = StimulusRate::Named(StimulusRateName::SampleMean);
        for x in [1.0, 2.0, 6.0] {
            f.update(1, &[x, -x], rate);
        }
        // The optimistic start is forgotten at the first visit (η = 1).
        assert!((f.row(1)[0] - 3.0).abs() < 1e-15);
        assert!((f.row(1)[1] + 3.0).abs() < 1e-15);
        assert_eq!(f.visits(), &[0, 3, 0]);
    }

    #[test]
    fn constant_rate_is_an_exponential_average() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut f = StimulusFunction::new(1, 1, 0.0, &mut rng);
        f.update(0, &[4.0], StimulusRate::Constant(0.25));
        assert_eq!(f.row(0), &[1.0]);
        f.update(0, &[4.0], StimulusRate::Constant(0.25));
        assert_eq!(f.row(0), &[1.75]);
    }

    #[test]
    fn rewards_are_abs_of_xi_lambda_d() {
        let f = StimulusFunction {
            n: 3,
            xi: vec![1.0, 0.0, 0.0, 0.0, -2.0, 1.0],
            visits: vec![0, 0],
        };
        let mut r = [0.0; 2];
        // Λ D = (0.5, 1, 2)
        f.rewards_into(&[0.5, 1.0, 2.0], &mut r);
        assert_eq!(r, [0.5, 0.0]);
        let g = StimulusFunction {
            n: 4,
            xi: vec![1.0, 1.0, 1.0, -1.0],
            visits: vec![0],
        };
        let mut r = [0.0; 1];
        g.rewards_into(&[1.0, 1.0, 1.0, 4.0], &mut r);
        assert_eq!(r, [1.0]);
        assert_eq!(g.constant_columns(), vec![0, 1, 2, 3]);
        assert_eq!(f.constant_columns(), Vec::<usize>::new());
    }
}
