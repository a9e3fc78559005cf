//! Learned transition models (docs/algorithm.md §8): the agent estimates P from what it
//! sees instead of being given it.
//!
//! The agent keeps sparse counts N(s, a, s′) of the transitions it made
//! (previous state, action taken, new state) and plans with the same LSTDQ
//! (Algorithm 1, line 9; docs/algorithm.md §2.6) on the estimate
//!
//! P̂(s′|s, a) = N(s, a, s′) / N(s, a)   for pairs seen at least m times.
//!
//! A pair seen fewer than m times is **unknown** and optimistic, in one of
//! two ways ([`Optimism`]):
//! - `absorbing` (R-max, the default): an unknown pair leads to one extra
//!   absorbing state s* whose only pair earns R_max = max over the valid
//!   pairs of R = |ΞΛD| every tick, so Q(s, a) = R(s, a) + γ R_max / (1 − γ):
//!   trying it is worth as much as the best reward the agent can name.
//! - `stimulus` (optimistic Ξ only): an unknown pair stays where it is, and
//!   its reward is the one Ξ gives it; Ξ's optimistic initialisation
//!   (docs/algorithm.md §3) is the only optimism, as with a known model.
//!
//! Counts only grow, so a row of P̂ that has two successors keeps them; an
//! observation changes the row of one pair, in O(successors of the pair).

use serde::{Deserialize, Serialize};

use super::basis::Basis;
use super::error::{AlgoError, Result};
use super::lstdq::PlanningModel;
use super::model::EnvModel;

/// Default m: a pair is known after three visits. One visit is enough in
/// a deterministic world, but in a stochastic one a single unlucky slip
/// makes a doorway look like a wall for good (the pair is known, so nothing
/// draws the agent back to it); on the three-room maze with slip 0.2, m = 1
/// leaves sources unfound in half the trials, m = 3 finds them all and
/// still costs little in the deterministic maze (BENCHMARKS.md §9).
pub const DEFAULT_KNOWN_AFTER: u32 = 3;

/// Largest m accepted.
pub const MAX_KNOWN_AFTER: u32 = 1_000_000;

/// How unknown pairs are made optimistic.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Optimism {
    /// R-max: unknown pairs lead to an absorbing state worth R_max forever.
    #[default]
    Absorbing,
    /// Unknown pairs loop on their state; the optimism is Ξ's initialisation.
    Stimulus,
}

/// Parameters of a learned model as a client sends them; every field optional.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LearnedParams {
    /// m: visits after which a pair's row of P̂ is trusted (1..=1 000 000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub known_after: Option<u32>,
    /// How unknown pairs are optimistic.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub optimism: Option<Optimism>,
}

/// Checked learned-model parameters; only [`LearnedParams::check`] makes them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ValidLearnedParams {
    /// m.
    pub known_after: u32,
    /// The optimism rule.
    pub optimism: Optimism,
}

impl LearnedParams {
    /// Validates the parameters.
    pub fn check(&self) -> Result<ValidLearnedParams> {
        let known_after = self.known_after.unwrap_or(DEFAULT_KNOWN_AFTER);
        if !(1..=MAX_KNOWN_AFTER).contains(&known_after) {
            return Err(AlgoError::InvalidParameter {
                name: "known_after",
                reason: format!("{known_after} is not in 1..={MAX_KNOWN_AFTER}"),
            });
        }
        Ok(ValidLearnedParams {
            known_after,
            optimism: self.optimism.unwrap_or_default(),
        })
    }
}

impl ValidLearnedParams {
    /// Back to the optional form, every field set.
    pub fn to_params(&self) -> LearnedParams {
        LearnedParams {
            known_after: Some(self.known_after),
            optimism: Some(self.optimism),
        }
    }
}

/// The sparse counts N(s, a, s′) and N(s, a), one list per valid pair.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TransitionCounts {
    /// N(s, a) per pair.
    visits: Vec<u64>,
    /// Per pair: (s′, N(s, a, s′)) in the order the successors were first seen.
    next: Vec<Vec<(u32, u64)>>,
}

impl TransitionCounts {
    /// No observation yet, for `pairs` valid pairs.
    pub fn new(pairs: usize) -> Self {
        Self {
            visits: vec![0; pairs],
            next: vec![Vec::new(); pairs],
        }
    }

    /// Counts one transition of pair `p` to `s_next`: O(successors of p).
    /// Returns N(s, a) after the update.
    pub fn record(&mut self, p: usize, s_next: usize) -> u64 {
        let t = s_next as u32;
        let row = &mut self.next[p];
        match row.iter_mut().find(|(u, _)| *u == t) {
            Some((_, n)) => *n += 1,
            None => row.push((t, 1)),
        }
        self.visits[p] += 1;
        self.visits[p]
    }

    /// N(s, a) per pair.
    pub fn visits(&self) -> &[u64] {
        &self.visits
    }

    /// (s′, N(s, a, s′)) of pair `p`.
    pub fn successors(&self, p: usize) -> &[(u32, u64)] {
        &self.next[p]
    }

    /// Number of pairs.
    pub fn pairs(&self) -> usize {
        self.visits.len()
    }

    /// Stored (pair, successor) entries.
    pub fn entries(&self) -> usize {
        self.next.iter().map(Vec::len).sum()
    }

    /// Row p of P̂ = N(s, a, ·) / N(s, a), written into `out`.
    pub fn estimate_into(&self, p: usize, out: &mut Vec<(u32, f64)>) {
        out.clear();
        let n = self.visits[p] as f64;
        out.extend(self.next[p].iter().map(|&(t, c)| (t, c as f64 / n)));
        debug_assert!(
            out.is_empty() || (out.iter().map(|&(_, q)| q).sum::<f64>() - 1.0).abs() < 1e-9,
            "a row of P̂ must sum to 1"
        );
    }

    /// Checks counts restored from a snapshot against the model's pairs and
    /// states: successors in range and listed once, positive counts that
    /// add up to N(s, a).
    pub fn validate(&self, structure: &EnvModel) -> Result<()> {
        let bad = |what: String| Err(AlgoError::InvalidSnapshot(what));
        let pairs = structure.n_pairs();
        if self.visits.len() != pairs || self.next.len() != pairs {
            return bad(format!("transition counts do not have {pairs} pairs"));
        }
        for (p, (row, &n)) in self.next.iter().zip(&self.visits).enumerate() {
            let mut sum = 0u64;
            for (i, &(t, c)) in row.iter().enumerate() {
                if t as usize >= structure.states() || c == 0 {
                    return bad(format!("pair {p}: successor {t} with count {c}"));
                }
                if row[..i].iter().any(|&(u, _)| u == t) {
                    return bad(format!("pair {p} lists successor {t} twice"));
                }
                sum = sum.saturating_add(c);
            }
            if sum != n {
                return bad(format!("pair {p}: successor counts sum to {sum}, not {n}"));
            }
        }
        Ok(())
    }
}

/// A learned P̂ with its counts: the per-agent planning model of an agent
/// without a posted transition table (not shared between agents, unlike
/// the `Arc<PlanningModel>` of a known model).
#[derive(Debug, Clone)]
pub struct LearnedModel {
    params: ValidLearnedParams,
    counts: TransitionCounts,
    /// Valid pairs of the real states (the absorbing state's pair is extra).
    pairs: usize,
    /// Pairs seen at least m times.
    known: usize,
    /// P̂ (and s* under R-max), the basis and its caches.
    plan: PlanningModel,
    /// Scratch row of P̂.
    row: Vec<(u32, f64)>,
}

impl LearnedModel {
    /// A model with nothing known, for the states, actions and valid pairs
    /// of `structure` (whose own P is ignored) and its basis. R-max
    /// optimism needs the indicator basis: s* has no state features.
    pub fn new(structure: &PlanningModel, params: ValidLearnedParams) -> Result<Self> {
        let counts = TransitionCounts::new(structure.model().n_pairs());
        Self::from_counts(structure, params, counts)
    }

    /// A model whose P̂ is rebuilt from `counts` (a snapshot's).
    pub fn from_counts(
        structure: &PlanningModel,
        params: ValidLearnedParams,
        counts: TransitionCounts,
    ) -> Result<Self> {
        let model = structure.model();
        counts.validate(model)?;
        let absorbing = params.optimism == Optimism::Absorbing;
        if absorbing && !matches!(structure.basis(), Basis::Indicator) {
            return Err(AlgoError::InvalidParameter {
                name: "optimism",
                reason: "`absorbing` needs the indicator basis (the absorbing state has no \
                         features); use `stimulus` with a feature basis"
                    .into(),
            });
        }
        let plan = structure.with_model(EnvModel::unknown_of(model, absorbing)?)?;
        let mut learned = Self {
            params,
            pairs: model.n_pairs(),
            known: 0,
            plan,
            row: Vec::new(),
            counts,
        };
        for p in 0..learned.pairs {
            if learned.counts.visits[p] >= u64::from(params.known_after) {
                learned.known += 1;
                learned.write_row(p);
            }
        }
        Ok(learned)
    }

    /// Counts the transition of pair `p` to `s_next` and updates P̂'s row of
    /// `p` if it is known: O(successors of p). Returns true when P̂ changed.
    pub fn record(&mut self, p: usize, s_next: usize) -> bool {
        let before = self.counts.successors(p).len();
        let n = self.counts.record(p, s_next);
        let m = u64::from(self.params.known_after);
        if n < m {
            return false;
        }
        if n == m {
            self.known += 1;
        } else if before == 1 && self.counts.successors(p).len() == 1 {
            // A single successor with probability 1, as before.
            return false;
        }
        self.write_row(p);
        true
    }

    fn write_row(&mut self, p: usize) {
        self.counts.estimate_into(p, &mut self.row);
        self.plan.set_successors(p, &self.row);
    }

    /// The planning model: P̂ (plus s* under R-max) and the basis.
    pub fn planning_model(&self) -> &PlanningModel {
        &self.plan
    }

    /// The counts N(s, a, s′).
    pub fn counts(&self) -> &TransitionCounts {
        &self.counts
    }

    /// The parameters.
    pub fn params(&self) -> ValidLearnedParams {
        self.params
    }

    /// Pairs seen at least m times.
    pub fn known_pairs(&self) -> usize {
        self.known
    }

    /// How much of the model is known: known pairs / valid pairs.
    pub fn known_fraction(&self) -> f64 {
        self.known as f64 / self.pairs.max(1) as f64
    }

    /// True when pair `p` is known.
    pub fn is_known(&self, p: usize) -> bool {
        self.counts.visits[p] >= u64::from(self.params.known_after)
    }

    /// Valid pairs of the real states.
    pub fn pairs(&self) -> usize {
        self.pairs
    }

    /// True under R-max optimism: the planning model has the extra state s*.
    pub fn absorbing(&self) -> bool {
        self.params.optimism == Optimism::Absorbing
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_update_the_pairs_own_row_only() {
        let mut c = TransitionCounts::new(3);
        assert_eq!(c.record(1, 4), 1);
        assert_eq!(c.record(1, 2), 2);
        assert_eq!(c.record(1, 4), 3);
        assert_eq!(c.successors(1), &[(4, 2), (2, 1)]);
        assert_eq!(c.visits(), &[0, 3, 0]);
        assert!(c.successors(0).is_empty() && c.successors(2).is_empty());
        assert_eq!(c.entries(), 2);
        let mut row = Vec::new();
        c.estimate_into(1, &mut row);
        assert_eq!(row, vec![(4, 2.0 / 3.0), (2, 1.0 / 3.0)]);
        let sum: f64 = row.iter().map(|&(_, q)| q).sum();
        assert!((sum - 1.0).abs() < 1e-15);
    }

    #[test]
    fn parameters_are_checked_once() {
        let p = LearnedParams::default().check().expect("defaults");
        assert_eq!(p.known_after, 3);
        assert_eq!(p.optimism, Optimism::Absorbing);
        assert_eq!(p.to_params().check().expect("round trip"), p);
        for m in [0, MAX_KNOWN_AFTER + 1] {
            let e = LearnedParams {
                known_after: Some(m),
                ..Default::default()
            }
            .check()
            .expect_err("out of range");
            assert!(e.to_string().contains("`known_after`"), "{e}");
        }
        let p: LearnedParams =
            serde_json::from_str(r#"{"known_after":3,"optimism":"stimulus"}"#).expect("json");
        assert_eq!(p.check().expect("valid").optimism, Optimism::Stimulus);
    }

    fn hallway_structure() -> PlanningModel {
        PlanningModel::new(crate::model::hallway().model, Basis::Indicator)
    }

    fn check_rows(model: &EnvModel) {
        for p in 0..model.n_pairs() {
            let sum: f64 = model.successors(p).1.iter().sum();
            assert!((sum - 1.0).abs() < 1e-12, "row {p} sums to {sum}");
        }
    }

    #[test]
    fn p_hat_follows_the_counts_once_a_pair_is_known() {
        let structure = hallway_structure();
        let params = LearnedParams {
            known_after: Some(2),
            optimism: Some(Optimism::Stimulus),
        }
        .check()
        .expect("params");
        let mut l = LearnedModel::new(&structure, params).expect("learned");
        let p = structure.model().pair(10, 1).expect("right from 10");
        let plan = |l: &LearnedModel| l.planning_model().model().clone();
        // Unknown: P̂ loops on the state.
        assert_eq!(plan(&l).successors(p), (&[10u32][..], &[1.0][..]));
        assert!(!l.record(p, 11), "one visit of m = 2: still unknown");
        assert_eq!(plan(&l).successors(p).0, &[10]);
        assert_eq!(l.known_pairs(), 0);
        assert!(l.record(p, 10), "second visit: known");
        assert_eq!(plan(&l).successors(p), (&[11u32, 10][..], &[0.5, 0.5][..]));
        assert!(!plan(&l).is_deterministic());
        assert!(l.record(p, 11));
        let after = plan(&l);
        let (next, prob) = after.successors(p);
        assert_eq!(next, &[11, 10]);
        assert_eq!(prob, &[2.0 / 3.0, 1.0 / 3.0]);
        assert_eq!(l.known_pairs(), 1);
        assert!((l.known_fraction() - 1.0 / 148.0).abs() < 1e-15);
        // The neighbours' rows were not touched by the splice.
        assert_eq!(plan(&l).successors(p - 1).0, &[10], "left from 10: unknown");
        assert_eq!(plan(&l).successors(p + 1).0, &[10], "stay at 10: unknown");
        check_rows(l.planning_model().model());
        // Rebuilt from the counts, P̂ is the same.
        let back =
            LearnedModel::from_counts(&structure, params, l.counts().clone()).expect("from counts");
        assert_eq!(back.planning_model().model(), l.planning_model().model());
        assert_eq!(back.known_pairs(), 1);
    }

    #[test]
    fn absorbing_optimism_adds_one_state_and_needs_the_indicator_basis() {
        let structure = hallway_structure();
        let params = LearnedParams {
            known_after: Some(1),
            ..Default::default()
        }
        .check()
        .expect("params");
        let mut l = LearnedModel::new(&structure, params).expect("learned");
        let m = l.planning_model().model();
        assert_eq!((m.states(), m.n_pairs()), (51, 149));
        assert_eq!(m.successors(148).0, &[50], "s* loops on itself");
        assert!((0..148).all(|p| m.successors(p).0 == [50]));
        let p = structure.model().pair(3, 2).expect("stay");
        assert!(l.record(p, 3), "m = 1: known after one visit");
        assert!(!l.record(p, 3), "a deterministic row does not change again");
        assert_eq!(l.planning_model().model().successors(p).0, &[3]);
        assert!(l.planning_model().model().is_deterministic());
        check_rows(l.planning_model().model());
        let pvf = PlanningModel::new(
            crate::model::hallway().model,
            Basis::build(
                &crate::spec::BasisSpec::ProtoValue { k: 5 },
                structure.model(),
            )
            .expect("pvf"),
        );
        let e = LearnedModel::new(&pvf, params).expect_err("absorbing with PVF");
        assert!(e.to_string().contains("indicator basis"), "{e}");
        let stim = LearnedParams {
            optimism: Some(Optimism::Stimulus),
            ..Default::default()
        };
        LearnedModel::new(&pvf, stim.check().expect("params")).expect("stimulus with PVF");
    }

    #[test]
    fn corrupt_counts_are_refused() {
        let model = crate::model::hallway().model;
        let mut c = TransitionCounts::new(model.n_pairs());
        c.record(0, 1);
        c.validate(&model).expect("valid");
        let mut bad = c.clone();
        bad.visits[0] = 2;
        assert!(bad.validate(&model).is_err(), "sum mismatch");
        let mut bad = c.clone();
        bad.next[0][0].0 = 50;
        assert!(bad.validate(&model).is_err(), "successor out of range");
        assert!(TransitionCounts::new(3).validate(&model).is_err());
    }
}
