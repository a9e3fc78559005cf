//! Normalised radial basis functions on a grid of c^d centres μ_i:
//! v_i(s) = g_i(s) / Σ_j g_j(s), g_i(s) = exp(−‖s − μ_i‖² / (2σ²)), with
//! σ = `width` / (c − 1), the grid spacing times `width`.
//!
//! A Gaussian of a sum of squares is a product over dimensions, and so is
//! the normaliser, so v(s) is the tensor product of d one-dimensional
//! normalised profiles: d·c exponentials per point instead of c^d.

/// An RBF basis.
#[derive(Debug, Clone, PartialEq)]
pub struct Rbf {
    d: usize,
    c: usize,
    /// 1 / (2σ²).
    inv_two_var: f64,
}

impl Rbf {
    /// c ≥ 2 centres per dimension, σ = width / (c − 1); the caller
    /// checked that c^d is bounded.
    pub fn new(d: usize, c: usize, width: f64) -> Self {
        let sigma = width / (c - 1) as f64;
        Self {
            d,
            c,
            inv_two_var: 1.0 / (2.0 * sigma * sigma),
        }
    }

    /// k = c^d.
    pub fn len(&self) -> usize {
        self.c.pow(self.d as u32)
    }

    /// Never empty.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// d.
    pub fn dim(&self) -> usize {
        self.d
    }

    /// c.
    pub fn centres(&self) -> usize {
        self.c
    }

    /// The tensor product of the per-dimension normalised profiles; the
    /// first dimension varies slowest.
    pub fn features_into(&self, s: &[f64], out: &mut [f64]) {
        let c = self.c;
        let step = 1.0 / (c - 1) as f64;
        out[0] = 1.0;
        let mut filled = 1;
        let mut buf = [0.0f64; super::MAX_CENTRES_PER_DIM as usize];
        let profile = &mut buf[..c];
        for &x in s.iter().take(self.d) {
            // Centred on the nearest centre so the largest term is exp(0) = 1.
            let mut sum = 0.0;
            for (i, p) in profile.iter_mut().enumerate() {
                let dx = x - i as f64 * step;
                *p = (-dx * dx * self.inv_two_var).exp();
                sum += *p;
            }
            profile.iter_mut().for_each(|p| *p /= sum);
            // out[.. filled * c] = out[.. filled] ⊗ profile, in place from the end.
            for i in (0..filled).rev() {
                let v = out[i];
                for (j, p) in profile.iter().enumerate() {
                    out[i * c + j] = v * p;
                }
            }
            filled *= c;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn features_sum_to_one_and_peak_at_the_nearest_centre() {
        let rbf = Rbf::new(2, 5, 1.0);
        let mut out = vec![0.0; rbf.len()];
        for p in [[0.0, 0.0], [0.3, 0.9], [1.0, 0.5], [0.25, 0.75]] {
            rbf.features_into(&p, &mut out);
            let sum: f64 = out.iter().sum();
            assert!((sum - 1.0).abs() < 1e-12, "{p:?}: sum {sum}");
        }
        rbf.features_into(&[0.25, 0.75], &mut out);
        let best = (0..out.len()).max_by(|&a, &b| out[a].total_cmp(&out[b]));
        // Centre (1, 3) of the 5 × 5 grid: index 1·5 + 3.
        assert_eq!(best, Some(8));
    }
}
