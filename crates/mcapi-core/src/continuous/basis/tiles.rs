//! Tile coding (Sutton & Barto, 2nd ed., §9.5.4): T tilings, each a grid
//! of (t + 1)^d tiles of width 1/t, the i-th offset by i·(1, 3, 5, …)/T of
//! a tile (asymmetric offsets avoid diagonal artefacts). Exactly T
//! features are active per point, each 1/T, so Σ v = 1. When the exact
//! count T·(t + 1)^d exceeds the table, tile coordinates are hashed into
//! it (collisions share a feature).

/// A tile coder.
#[derive(Debug, Clone, PartialEq)]
pub struct Tiles {
    d: usize,
    tilings: usize,
    per_dim: usize,
    table: usize,
    /// The table holds every tile: indices are exact, not hashed.
    exact: bool,
}

impl Tiles {
    /// The caller checked the sizes (`exact`: T·(t + 1)^d == table).
    pub fn new(d: usize, tilings: usize, per_dim: usize, table: usize, exact: bool) -> Self {
        Self {
            d,
            tilings,
            per_dim,
            table,
            exact,
        }
    }

    /// k, the table size.
    pub fn len(&self) -> usize {
        self.table
    }

    /// Never empty.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// d.
    pub fn dim(&self) -> usize {
        self.d
    }

    /// T.
    pub fn tilings(&self) -> usize {
        self.tilings
    }

    /// The table index of each tiling's active tile at s.
    pub fn active(&self, s: &[f64], mut each: impl FnMut(usize)) {
        let t = self.per_dim as f64;
        let side = self.per_dim + 1;
        for i in 0..self.tilings {
            let mut exact = i;
            let mut hash: u64 = 0xcbf2_9ce4_8422_2325 ^ i as u64;
            for (j, &x) in s.iter().take(self.d).enumerate() {
                let offset = (i * (2 * j + 1)) as f64 / self.tilings as f64 / t;
                let cell = (((x + offset) * t).floor() as usize).min(self.per_dim);
                exact = exact * side + cell;
                hash = (hash ^ cell as u64).wrapping_mul(0x0000_0100_0000_01b3);
            }
            each(if self.exact {
                exact
            } else {
                (hash % self.table as u64) as usize
            });
        }
    }

    /// 1/T at each active tile, 0 elsewhere.
    pub fn features_into(&self, s: &[f64], out: &mut [f64]) {
        out.iter_mut().for_each(|v| *v = 0.0);
        let w = 1.0 / self.tilings as f64;
        self.active(s, |i| out[i] += w);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exactly_t_tiles_are_active_and_exact_indices_are_in_range() {
        let tiles = Tiles::new(2, 4, 5, 4 * 36, true);
        let mut out = vec![0.0; tiles.len()];
        for p in [[0.0, 0.0], [1.0, 1.0], [0.5, 0.2], [0.999, 0.001]] {
            tiles.features_into(&p, &mut out);
            assert_eq!(out.iter().filter(|v| **v > 0.0).count(), 4, "{p:?}");
            assert!((out.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        // Nearby points share most tiles, distant ones none.
        let (mut a, mut b) = (vec![0.0; tiles.len()], vec![0.0; tiles.len()]);
        tiles.features_into(&[0.5, 0.5], &mut a);
        tiles.features_into(&[0.51, 0.5], &mut b);
        let shared = a
            .iter()
            .zip(&b)
            .filter(|(x, y)| **x > 0.0 && **y > 0.0)
            .count();
        assert!(shared >= 2);
        tiles.features_into(&[0.0, 0.0], &mut b);
        assert_eq!(
            a.iter()
                .zip(&b)
                .filter(|(x, y)| **x > 0.0 && **y > 0.0)
                .count(),
            0
        );
    }
}
