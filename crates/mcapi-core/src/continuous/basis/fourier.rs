//! The Fourier basis (Konidaris, Osentoski & Thomas, AAAI 2011):
//! v_c(s) = cos(π c·s) for integer vectors c ∈ {0, …, n}^d, keeping only
//! the c with at most m non-zero entries (m = `max_coupling`), so that a
//! basis of d = 8 stays affordable: Σ_{j ≤ m} C(d, j) nʲ terms.

use super::MAX_STATE_FEATURES;

/// A Fourier basis: each term is its list of (dimension, frequency) pairs
/// with a non-zero frequency; the empty list is the constant term.
#[derive(Debug, Clone, PartialEq)]
pub struct Fourier {
    d: usize,
    /// Flattened terms: `starts[t]..starts[t + 1]` indexes `dims`/`freqs`.
    starts: Vec<usize>,
    dims: Vec<usize>,
    freqs: Vec<f64>,
}

/// The number of terms Σ_{j ≤ m} C(d, j) nʲ, or None beyond
/// [`MAX_STATE_FEATURES`].
pub fn count(d: usize, order: u32, coupling: u32) -> Option<usize> {
    let mut total = 1usize; // the constant term
    let mut binom = 1usize; // C(d, j)
    let mut power = 1usize; // order^j
    for j in 1..=(coupling as usize).min(d) {
        // C(d, j) = C(d, j − 1) (d + 1 − j) / j, exact at every step.
        binom = binom.checked_mul(d + 1 - j)? / j;
        power = power.checked_mul(order as usize)?;
        total = total.checked_add(binom.checked_mul(power)?)?;
        if total > MAX_STATE_FEATURES {
            return None;
        }
    }
    Some(total)
}

impl Fourier {
    /// The basis of order `order` on d dimensions with at most `coupling`
    /// coupled dimensions per term; the caller checked [`count`].
    pub fn new(d: usize, order: u32, coupling: u32) -> Self {
        let mut basis = Self {
            d,
            starts: vec![0],
            dims: Vec::new(),
            freqs: Vec::new(),
        };
        // The constant term, then terms by number of coupled dimensions,
        // each subset in lexicographic order, frequencies counting up.
        basis.starts.push(0);
        for m in 1..=(coupling as usize).min(d) {
            let mut subset: Vec<usize> = (0..m).collect();
            loop {
                let mut freq = vec![1u32; m];
                loop {
                    basis.dims.extend_from_slice(&subset);
                    basis.freqs.extend(freq.iter().map(|&f| f as f64));
                    basis.starts.push(basis.dims.len());
                    // Next frequency vector in 1..=order^m.
                    let Some(i) = (0..m).rev().find(|&i| freq[i] < order) else {
                        break;
                    };
                    freq[i] += 1;
                    freq[i + 1..].iter_mut().for_each(|f| *f = 1);
                }
                // Next subset of size m of 0..d.
                let Some(i) = (0..m).rev().find(|&i| subset[i] < d - m + i) else {
                    break;
                };
                subset[i] += 1;
                for j in i + 1..m {
                    subset[j] = subset[j - 1] + 1;
                }
            }
        }
        debug_assert_eq!(Some(basis.len()), count(d, order, coupling));
        basis
    }

    /// k, the number of terms.
    pub fn len(&self) -> usize {
        self.starts.len() - 1
    }

    /// Never empty: the constant term is always there.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// d.
    pub fn dim(&self) -> usize {
        self.d
    }

    /// Writes cos(π c·s) for every term.
    pub fn features_into(&self, s: &[f64], out: &mut [f64]) {
        for (t, o) in out.iter_mut().enumerate() {
            let (a, b) = (self.starts[t], self.starts[t + 1]);
            let dot: f64 = self.dims[a..b]
                .iter()
                .zip(&self.freqs[a..b])
                .map(|(&j, c)| c * s[j])
                .sum();
            *o = (std::f64::consts::PI * dot).cos();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_match_the_closed_form() {
        // Full coupling: (n + 1)^d.
        assert_eq!(count(2, 3, 2), Some(16));
        assert_eq!(Fourier::new(2, 3, 2).len(), 16);
        // Uncoupled: 1 + d·n.
        assert_eq!(count(8, 5, 1), Some(41));
        assert_eq!(Fourier::new(8, 5, 1).len(), 41);
        // Pairs on d = 8, order 3: 1 + 8·3 + 28·9.
        assert_eq!(count(8, 3, 2), Some(1 + 24 + 252));
        assert_eq!(Fourier::new(8, 3, 2).len(), 277);
        assert_eq!(count(64, 64, 64), None);
    }

    #[test]
    fn terms_are_distinct_cosines() {
        let f = Fourier::new(2, 2, 2);
        let mut out = vec![0.0; f.len()];
        f.features_into(&[0.0, 0.0], &mut out);
        assert!(
            out.iter().all(|v| (v - 1.0).abs() < 1e-15),
            "cos 0 = 1 for every term"
        );
        f.features_into(&[1.0, 0.0], &mut out);
        // The constant term, then (x:1), (x:2), (y:1), (y:2), then pairs.
        assert_eq!(out[0], 1.0);
        assert!((out[1] + 1.0).abs() < 1e-12 && (out[2] - 1.0).abs() < 1e-12);
        assert!((out[3] - 1.0).abs() < 1e-12);
    }
}
