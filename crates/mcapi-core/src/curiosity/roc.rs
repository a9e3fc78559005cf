//! Robust Online Clustering of the scalar slow feature (Guedalia, London,
//! Werman 1999), §7 step 4: its error e is the distance to the nearest
//! centre.

use serde::{Deserialize, Serialize};

use super::params::ValidCuriosityParams;

/// One ROC centre: its position and weight (number of samples it stands for).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Centre {
    /// Position v.
    pub value: f64,
    /// Weight c.
    pub weight: f64,
}

/// Robust Online Clustering of the scalar slow feature (Guedalia, London,
/// Werman 1999), with the rules of §7 step 4.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Roc {
    pub(super) centres: Vec<Centre>,
    max_centres: usize,
    beta: f64,
}

impl Roc {
    /// An empty clustering with N_max = `max_centres` (≥ 2) and β.
    pub fn new(max_centres: usize, beta: f64) -> Self {
        Self {
            centres: Vec::with_capacity(max_centres),
            max_centres: max_centres.max(2),
            beta,
        }
    }

    /// An empty clustering with the parameters' N_max and β.
    pub fn with_params(params: &ValidCuriosityParams) -> Self {
        Self::new(params.max_centres, params.beta)
    }

    /// Clusters one sample y and returns its error e (§7 step 4, in order):
    ///
    /// 1. e = |y − v| for the nearest centre v, computed **before** the
    ///    update (0 if there is no centre yet);
    /// 2. the nearest centre gains weight, c += 1, and moves
    ///    v += max(1/c, β)(y − v), with the incremented c (so a centre is the
    ///    running mean of what it won until 1/c < β);
    /// 3. if N_max centres exist, the closest pair merges into one at their
    ///    weighted mean, weights adding;
    /// 4. a new centre of weight 1 is added at y.
    ///
    /// Ties (equal distances) go to the lowest index, resp. the
    /// lexicographically first pair.
    pub fn update(&mut self, y: f64) -> f64 {
        let nearest = self
            .centres
            .iter()
            .enumerate()
            .map(|(i, c)| (i, (y - c.value).abs()))
            .fold(None, |best: Option<(usize, f64)>, (i, dist)| match best {
                Some((_, b)) if b <= dist => best,
                _ => Some((i, dist)),
            });
        let error = match nearest {
            None => 0.0,
            Some((i, dist)) => {
                let c = &mut self.centres[i];
                c.weight += 1.0;
                c.value += (1.0 / c.weight).max(self.beta) * (y - c.value);
                dist
            }
        };
        if self.centres.len() >= self.max_centres {
            self.merge_closest_pair();
        }
        self.centres.push(Centre {
            value: y,
            weight: 1.0,
        });
        error
    }

    fn merge_closest_pair(&mut self) {
        let mut best: Option<(usize, usize, f64)> = None;
        for i in 0..self.centres.len() {
            for j in i + 1..self.centres.len() {
                let dist = (self.centres[i].value - self.centres[j].value).abs();
                if best.is_none_or(|(_, _, b)| dist < b) {
                    best = Some((i, j, dist));
                }
            }
        }
        if let Some((i, j, _)) = best {
            let (a, b) = (self.centres[i], self.centres[j]);
            let weight = a.weight + b.weight;
            self.centres[i] = Centre {
                value: (a.weight * a.value + b.weight * b.value) / weight,
                weight,
            };
            self.centres.remove(j);
        }
    }

    /// The centres, in insertion order (a merged pair takes the first's place).
    pub fn centres(&self) -> &[Centre] {
        &self.centres
    }
}
