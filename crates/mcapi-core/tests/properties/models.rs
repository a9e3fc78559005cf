//! Random environment models, in this suite's own representation, and the dense references built on them.

use super::*;

/// Successor states of a pair with their probabilities.
pub(crate) type Successors = Vec<(usize, f64)>;

/// `rows[s][a]` = successors of (s, a) with probabilities, `None` if unavailable.
#[derive(Debug, Clone)]
pub(crate) struct RawModel {
    pub(crate) states: usize,
    pub(crate) actions: usize,
    pub(crate) stochastic: bool,
    pub(crate) rows: Vec<Vec<Option<Successors>>>,
}

/// `m` distinct states of `0..states` (partial Fisher–Yates).
pub(crate) fn distinct_states(rng: &mut ChaCha8Rng, states: usize, m: usize) -> Vec<usize> {
    let mut all: Vec<usize> = (0..states).collect();
    for i in 0..m {
        let j = rng.random_range(i..states);
        all.swap(i, j);
    }
    all.truncate(m);
    all
}

/// A random sparse distribution over at least `min_support` states.
pub(crate) fn random_distribution(
    rng: &mut ChaCha8Rng,
    states: usize,
    min_support: usize,
) -> Vec<(usize, f64)> {
    let max_support = states.min(3).max(min_support);
    let m = rng.random_range(min_support..=max_support);
    let targets = distinct_states(rng, states, m);
    let weights: Vec<f64> = (0..m).map(|_| rng.random_range(0.05..1.0)).collect();
    let total: f64 = weights.iter().sum();
    targets
        .into_iter()
        .zip(weights.into_iter().map(|w| w / total))
        .collect()
}

impl RawModel {
    /// Each action is available with probability `p_available`; every state
    /// keeps at least one. Stochastic models have 1-3 successors per pair and
    /// (when there are two states or more) at least one pair with two.
    pub(crate) fn random(
        rng: &mut ChaCha8Rng,
        states: usize,
        actions: usize,
        stochastic: bool,
        p_available: f64,
    ) -> Self {
        let mut rows = Vec::with_capacity(states);
        let mut forced_branch = !stochastic || states < 2;
        for _ in 0..states {
            let mut available: Vec<bool> =
                (0..actions).map(|_| rng.random_bool(p_available)).collect();
            if !available.iter().any(|&x| x) {
                available[rng.random_range(0..actions)] = true;
            }
            let row = available
                .into_iter()
                .map(|avail| {
                    avail.then(|| {
                        if stochastic {
                            let min_support = if forced_branch { 1 } else { 2 };
                            forced_branch = true;
                            random_distribution(rng, states, min_support)
                        } else {
                            vec![(rng.random_range(0..states), 1.0)]
                        }
                    })
                })
                .collect();
            rows.push(row);
        }
        Self {
            states,
            actions,
            stochastic,
            rows,
        }
    }

    /// The posted form: `next` for deterministic models; for stochastic ones
    /// `transitions` in a shuffled order, actions by index or by name.
    pub(crate) fn spec(&self, rng: &mut ChaCha8Rng, n_stimuli: usize) -> ModelSpec {
        let action_names = names("act", self.actions);
        let (next, transitions) = if self.stochastic {
            let mut list = Vec::new();
            for (s, row) in self.rows.iter().enumerate() {
                for (a, succ) in row.iter().enumerate() {
                    if let Some(succ) = succ {
                        let action = if rng.random_bool(0.5) {
                            ActionRef::Index(a)
                        } else {
                            ActionRef::Name(action_names[a].clone())
                        };
                        list.push(TransitionSpec {
                            state: s,
                            action,
                            next: succ.clone(),
                        });
                    }
                }
            }
            for i in (1..list.len()).rev() {
                list.swap(i, rng.random_range(0..=i));
            }
            (None, Some(list))
        } else {
            let next = self
                .rows
                .iter()
                .map(|row| {
                    row.iter()
                        .map(|succ| succ.as_ref().map(|v| v[0].0))
                        .collect()
                })
                .collect();
            (Some(next), None)
        };
        ModelSpec {
            states: self.states,
            state_names: None,
            actions: action_names,
            next,
            transitions,
            stimuli: names("x", n_stimuli),
            basis: None,
        }
    }

    pub(crate) fn model(&self, rng: &mut ChaCha8Rng, n_stimuli: usize) -> TestResult<EnvModel> {
        EnvModel::from_spec(&self.spec(rng, n_stimuli))
            .map_err(|e| fail(format!("valid model refused: {e}")))
    }

    /// Pair numbering as documented: state-major, action-minor, valid pairs only.
    pub(crate) fn pair_index(&self) -> Vec<Vec<Option<usize>>> {
        let mut next = 0;
        self.rows
            .iter()
            .map(|row| {
                row.iter()
                    .map(|succ| {
                        succ.as_ref().map(|_| {
                            next += 1;
                            next - 1
                        })
                    })
                    .collect()
            })
            .collect()
    }

    pub(crate) fn n_pairs(&self) -> usize {
        self.rows.iter().flatten().filter(|x| x.is_some()).count()
    }

    pub(crate) fn available(&self, s: usize) -> Vec<usize> {
        (0..self.actions)
            .filter(|&a| self.rows[s][a].is_some())
            .collect()
    }

    /// A uniformly random available action per state.
    pub(crate) fn random_policy(&self, rng: &mut ChaCha8Rng) -> Vec<usize> {
        (0..self.states)
            .map(|s| {
                let avail = self.available(s);
                avail[rng.random_range(0..avail.len())]
            })
            .collect()
    }

    /// P^π over pairs: row (s,a), column (s', π(s')), entry P(s'|s,a).
    pub(crate) fn p_pi(&self, idx: &[Vec<Option<usize>>], pi: &[usize]) -> DMatrix<f64> {
        let n = self.n_pairs();
        let mut p = DMatrix::zeros(n, n);
        for s in 0..self.states {
            for a in 0..self.actions {
                let (Some(row), Some(succ)) = (idx[s][a], &self.rows[s][a]) else {
                    continue;
                };
                for &(t, prob) in succ {
                    let col =
                        idx[t][pi[t]].unwrap_or_else(|| unreachable!("π picks available actions"));
                    p[(row, col)] += prob;
                }
            }
        }
        p
    }

    /// Q^π = (I − γ P^π)⁻¹ R by a dense LU solve.
    pub(crate) fn dense_q(
        &self,
        idx: &[Vec<Option<usize>>],
        pi: &[usize],
        r: &[f64],
        gamma: f64,
    ) -> TestResult<Vec<f64>> {
        let n = self.n_pairs();
        let m = DMatrix::identity(n, n) - self.p_pi(idx, pi) * gamma;
        let q = m
            .lu()
            .solve(&DVector::from_column_slice(r))
            .ok_or_else(|| fail("I − γP^π is singular"))?;
        Ok(q.as_slice().to_vec())
    }
}

/// Actions of a planner policy given as pair indices.
pub(crate) fn policy_actions(model: &EnvModel, policy: &[u32]) -> Vec<usize> {
    policy
        .iter()
        .map(|&p| model.pair_action(p as usize))
        .collect()
}

pub(crate) fn policy_pairs(idx: &[Vec<Option<usize>>], pi: &[usize]) -> Vec<u32> {
    pi.iter()
        .enumerate()
        .map(|(s, &a)| {
            idx[s][a].unwrap_or_else(|| unreachable!("π picks available actions")) as u32
        })
        .collect()
}

/// Random rewards in [-5, 5], exactly zero on about a third of the pairs
/// (zeros create exact ties in Q, which exercise the tie rule).
pub(crate) fn random_rewards(rng: &mut ChaCha8Rng, n: usize) -> Vec<f64> {
    (0..n)
        .map(|_| {
            if rng.random_bool(0.35) {
                0.0
            } else {
                rng.random_range(-5.0..5.0)
            }
        })
        .collect()
}

/// π_{t+1} is greedy in Q with the tie rule of §2.6: a state keeps its
/// action when that action is within the tie tolerance of the max.
pub(crate) fn check_greedy(
    model: &EnvModel,
    before: &[u32],
    after: &[u32],
    q: &[f64],
    changes: usize,
) -> TestResult {
    let mut counted = 0;
    for s in 0..model.states() {
        let range = model.pairs_of(s);
        let max = q[range.clone()]
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        let floor = max - TIE_TOLERANCE * (1.0 + max.abs());
        let (old, new) = (before[s] as usize, after[s] as usize);
        prop_assert!(
            range.contains(&new),
            "state {}: pair {} is not one of its pairs",
            s,
            new
        );
        prop_assert!(
            q[new] >= floor,
            "state {}: Q(new) = {} is not maximal ({})",
            s,
            q[new],
            max
        );
        if q[old] >= floor {
            prop_assert_eq!(new, old, "state {}: a tied previous action must be kept", s);
        }
        counted += usize::from(new != old);
    }
    prop_assert_eq!(counted, changes, "reported policy changes");
    Ok(())
}
