//! Rebuilding a PVF basis mid-session (docs/algorithm.md §9.2): when the
//! graph has grown enough ([`super::PvfGraph::due`]), at the start of a
//! plan, everything that lives in feature space moves to the new basis
//! consistently before the plan evaluates:
//!
//! - v and v′ of every stored transition, and v at the probe points and at
//!   the current observation, are recomputed;
//! - Ξ is refitted on the stored transitions (each with its weight in
//!   visits and its mean stimulus) towards a fresh prior, drawn from the
//!   session's seed on a ChaCha stream of its own per build, so the
//!   agent's action draws are untouched;
//! - the planner keeps its successor policy π and rebuilds A⁻¹ from the
//!   new features (the ridge follows the new E‖v‖²); Q is not carried as
//!   numbers but re-evaluated: the plan that follows runs its LSTDQ
//!   evaluation of π on the new basis with the refitted Ξ, as every tick
//!   does.
//!
//! Everything is a function of the seed and the observations in order.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::{ContinuousAgent, PLANNER_RIDGE};
use crate::continuous::basis::FeatureMap;
use crate::continuous::stimulus::{LinearStimulus, mean_sq_norm, probe_features};

impl ContinuousAgent {
    /// Rebuilds the basis if its graph says so (a PVF basis only).
    pub(super) fn maybe_rebuild_basis(&mut self) {
        if self.graph.as_ref().is_some_and(|g| g.due(self.tick)) {
            self.rebuild_basis();
        }
    }

    /// Rebuilds a PVF basis now, off its schedule, and tells whether it
    /// did: for benchmarks of the rebuild alone (a session never calls it;
    /// its rebuilds come from the schedule only).
    #[doc(hidden)]
    pub fn force_basis_rebuild(&mut self) -> bool {
        self.rebuild_basis()
    }

    fn rebuild_basis(&mut self) -> bool {
        let Some(graph) = &mut self.graph else {
            return false;
        };
        let FeatureMap::Pvf(old) = &self.model.features else {
            return false;
        };
        // A failed eigensolve keeps the old basis until the graph grows again.
        let Ok(built) = graph.build(old, self.tick) else {
            return false;
        };
        let stream = graph.builds;
        let d = self.model.dim();
        self.model.features = FeatureMap::Pvf(built);
        let map = &self.model.features;
        self.store.refeature(|s, out| map.features_into(s, out));
        self.probes = probe_features(map, d);
        let typical = mean_sq_norm(map, d);
        let mut rng = ChaCha8Rng::seed_from_u64(self.params.seed);
        rng.set_stream(stream);
        self.xi = LinearStimulus::fitted(
            self.model.n_actions(),
            map.len(),
            self.model.n_stimuli(),
            self.params.optimistic_sd,
            typical,
            &mut rng,
            &self.store,
        );
        self.planner.rebase(PLANNER_RIDGE * typical);
        if let Some((s, v)) = &mut self.s {
            map.features_into(s, v);
        }
        true
    }
}
