//! The stimulus function Ξ (Algorithm 1, line 5) and the reward function
//! R = |Ξ Λ D| (line 8).
//!
//! Ξ has one row per valid pair and one column per stimulus dimension: the
//! agent's estimate of what taking a in s delivers. It starts optimistic,
//! Ξ ~ N(0, σ²) (docs/algorithm.md §3), so unexplored pairs promise something.

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
    /// A column with visit counts of its own (the curiosity column, §7);
    /// absent for agents without one.
    ///
    /// Not serialised: the durable store encodes snapshots with postcard, a
    /// format without field names, so a new field would change the encoding
    /// of every stored session. An in-memory snapshot keeps it; persisting a
    /// curious agent needs it added under a new store format version.
    #[serde(skip)]
    own_column: Option<OwnColumn>,
}

/// A column of Ξ learned at its own rate 1/n_col(s, a) (docs/algorithm.md §7:
/// the curiosity column restarts its counts at every module freeze).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OwnColumn {
    /// The stimulus dimension.
    pub dim: usize,
    /// n_col(p) since the column was last reset.
    pub visits: Vec<u32>,
}

impl StimulusFunction {
    /// Hints the CPU to load Ξ, which every plan reads whole, and the
    /// visit count of `pair`, the one the next observation updates unless
    /// it names another action (every count when there is no such pair yet;
    /// [`crate::prefetch`]). One line of counts instead of all of them: 9
    /// fewer lines of a hallway agent's ~100 to bring in.
    pub(crate) fn prefetch(&self, pair: Option<usize>) {
        crate::prefetch::slice(&self.xi);
        match pair.and_then(|p| self.visits.get(p)) {
            Some(count) => crate::prefetch::value(count),
            None => crate::prefetch::slice(&self.visits),
        }
    }

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
            own_column: None,
        }
    }

    /// Gives column `dim` visit counts of its own, starting at 0 (docs/algorithm.md
    /// §7: the curiosity column's rate is 1/n_cur). Ξ is unchanged.
    pub fn count_column_separately(&mut self, dim: usize) {
        debug_assert!(dim < self.n);
        self.own_column = Some(OwnColumn {
            dim,
            visits: vec![0; self.visits.len()],
        });
    }

    /// Re-initialises column `dim` optimistically, Ξ(·, dim) ~ N(0, sd²), and
    /// restarts its own visit counts at 0 (§7: at each module freeze the
    /// curiosity column is "initialised with optimistic values" again). The
    /// other columns and the pair counts n(s, a) are untouched.
    pub fn reset_column(&mut self, dim: usize, sd: f64, rng: &mut impl Rng) {
        debug_assert!(dim < self.n);
        let normal = Normal::new(0.0, sd).ok();
        for x in self.xi.iter_mut().skip(dim).step_by(self.n) {
            *x = normal.map_or(0.0, |d| d.sample(rng));
        }
        self.count_column_separately(dim);
    }

    /// Puts back the own column of a snapshot (whose encoding leaves it
    /// out); `Agent::restore` checks that it fits.
    pub fn restore_own_column(&mut self, column: Option<OwnColumn>) {
        self.own_column = column;
    }

    /// The column with its own visit counts, if any.
    pub fn own_column(&self) -> Option<&OwnColumn> {
        self.own_column.as_ref()
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
        let Some(own) = &mut self.own_column else {
            for (x, &obs) in row.iter_mut().zip(xi) {
                *x += eta * (obs - *x);
            }
            return;
        };
        // Column `own.dim` learns at its own rate 1/n_col(p).
        own.visits[p] = own.visits[p].saturating_add(1);
        let eta_own = match rate {
            StimulusRate::Constant(c) => c,
            StimulusRate::Named(_) => 1.0 / f64::from(own.visits[p]),
        };
        for (j, (x, &obs)) in row.iter_mut().zip(xi).enumerate() {
            let rate = if j == own.dim { eta_own } else { eta };
            *x += rate * (obs - *x);
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
    use crate::params::StimulusRateName;
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
            own_column: None,
        };
        let mut r = [0.0; 2];
        // Λ D = (0.5, 1, 2)
        f.rewards_into(&[0.5, 1.0, 2.0], &mut r);
        assert_eq!(r, [0.5, 0.0]);
        let g = StimulusFunction {
            n: 4,
            xi: vec![1.0, 1.0, 1.0, -1.0],
            visits: vec![0],
            own_column: None,
        };
        let mut r = [0.0; 1];
        g.rewards_into(&[1.0, 1.0, 1.0, 4.0], &mut r);
        assert_eq!(r, [1.0]);
        assert_eq!(g.constant_columns(), vec![0, 1, 2, 3]);
        assert_eq!(f.constant_columns(), Vec::<usize>::new());
    }

    #[test]
    fn an_own_column_restarts_its_mean_at_a_reset() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut f = StimulusFunction::new(2, 3, 0.3, &mut rng);
        let rate = StimulusRate::Named(StimulusRateName::SampleMean);
        f.count_column_separately(2);
        f.update(0, &[2.0, 0.0, 4.0], rate);
        f.update(0, &[4.0, 0.0, 8.0], rate);
        assert_eq!(f.row(0), &[3.0, 0.0, 6.0]);
        let before: Vec<f64> = f.table().to_vec();
        f.reset_column(2, 0.3, &mut rng);
        // Only column 2 is redrawn; the pair counts stay.
        for (i, (a, b)) in before.iter().zip(f.table()).enumerate() {
            assert_eq!(a == b, i % 3 != 2, "entry {i}");
        }
        assert_eq!(f.visits(), &[2, 0]);
        assert_eq!(f.own_column().map(|c| c.visits.clone()), Some(vec![0, 0]));
        // The first visit after the reset forgets the optimistic value
        // (n_cur = 1) while the other columns keep averaging (n = 3).
        f.update(0, &[6.0, 3.0, 1.0], rate);
        assert_eq!(f.row(0), &[4.0, 1.0, 1.0]);
        // The own column is not serialised (the store's encoding is unchanged).
        let json = serde_json::to_string(&f).expect("encode");
        assert!(!json.contains("own_column"), "{json}");
    }
}
