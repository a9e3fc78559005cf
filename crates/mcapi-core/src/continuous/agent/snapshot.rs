//! A continuous world's agent as a snapshot keeps it (docs/algorithm.md
//! §9.7): everything that changes as the agent learns, so that a restored
//! agent continues with the same bits as the one that wrote it.
//!
//! What a snapshot does not hold is what the session's record rebuilds or
//! what is a function of what it holds:
//!
//! - the model (the posted spec and the basis built from it) and the
//!   parameters; a PVF basis, rebuilt as its graph grows, is the exception
//!   and is kept;
//! - the features of the stored transitions and of the current
//!   observation: v is a function of the point and the basis, so it is
//!   recomputed, to the same bits, at restore (two N × k matrices are most
//!   of the agent's memory);
//! - the planner's per-tick scratch (the targets, the successor rewards and
//!   the switches), which every plan recomputes before it reads them.
//!
//! What it does hold is kept bit for bit: A⁻¹ and Ξ's inverses were built
//! by thousands of rank-one updates, and no recomputation would give their
//! bits back.

use serde::{Deserialize, Serialize};

use super::ContinuousAgent;
use crate::agent::RngState;
use crate::continuous::basis::{FeatureMap, Pvf, PvfGraph};
use crate::continuous::grid::GridPlanner;
use crate::continuous::model::ContinuousModel;
use crate::continuous::planner::SamplePlanner;
use crate::continuous::samples::SampleStore;
use crate::continuous::stimulus::{LinearStimulus, PROBES};
use crate::drive::Drive;
use crate::error::{AlgoError, Result};
use crate::params::ValidParams;

/// The state of a [`ContinuousAgent`]: [`ContinuousAgent::snapshot`] makes
/// one and [`ContinuousAgent::restore`] resumes it. An agent on a grid
/// (docs/algorithm.md §9.8) keeps other things than one on features, so
/// each has its own form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum ContinuousState {
    /// An agent on a feature basis.
    Features(Box<ContinuousSnapshot>),
    /// An agent on a grid.
    Grid(Box<GridSnapshot>),
}

impl From<ContinuousSnapshot> for ContinuousState {
    fn from(s: ContinuousSnapshot) -> Self {
        Self::Features(Box::new(s))
    }
}

impl From<GridSnapshot> for ContinuousState {
    fn from(s: GridSnapshot) -> Self {
        Self::Grid(Box::new(s))
    }
}

impl ContinuousState {
    /// The snapshot of an agent on a feature basis, if this is one.
    pub fn features(self) -> Option<ContinuousSnapshot> {
        match self {
            Self::Features(s) => Some(*s),
            Self::Grid(_) => None,
        }
    }
}

/// The state of an agent on a grid: the drive, the grid planner whole
/// (its kept transitions, Ξ's cells, π, and V and R as of its last plan,
/// which the next action reads), and the loop's counters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridSnapshot {
    rng: RngState,
    drive: Drive,
    grid: GridPlanner,
    /// The current normalised observation.
    s: Option<Vec<f64>>,
    advised: Option<usize>,
    tick: u64,
    clipped: u64,
    needs_plan: bool,
    policy_version: u64,
}

/// The state of an agent on a feature basis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContinuousSnapshot {
    rng: RngState,
    drive: Drive,
    xi: LinearStimulus,
    store: SampleStore,
    planner: SamplePlanner,
    known_next: Vec<u64>,
    /// The current normalised observation (its features are recomputed).
    s: Option<Vec<f64>>,
    advised: Option<usize>,
    tick: u64,
    clipped: u64,
    needs_plan: bool,
    policy_version: u64,
    /// u_a = W_a Λ D as of the last plan: the next observation's successor
    /// choice reads it before the next plan recomputes it.
    u: Vec<f64>,
    r_max: f64,
    probes: Vec<f64>,
    graph: Option<PvfGraph>,
    /// The PVF basis in use, if the basis is one (it changes as the graph
    /// grows; the other bases are the record's).
    pvf: Option<Pvf>,
}

/// A [`ContinuousState`] borrowed from a live agent
/// ([`ContinuousAgent::snapshot_ref`]): it serialises to the same bytes
/// as the owned snapshot (serde writes a reference, a slice and a `Box` as
/// what they point at, and the names are the owned types'), without
/// copying the agent's matrices first: A⁻¹ alone is 32 MiB at k|A| =
/// 2048, which encoding the owned snapshot holds twice.
#[derive(Debug, Serialize)]
#[serde(rename = "ContinuousState")]
pub enum ContinuousStateRef<'a> {
    /// [`ContinuousState::Features`].
    Features(ContinuousSnapshotRef<'a>),
    /// [`ContinuousState::Grid`].
    Grid(GridSnapshotRef<'a>),
}

/// [`GridSnapshot`] borrowed: the same fields, in the same order.
#[derive(Debug, Serialize)]
#[serde(rename = "GridSnapshot")]
pub struct GridSnapshotRef<'a> {
    rng: RngState,
    drive: &'a Drive,
    grid: &'a GridPlanner,
    s: Option<&'a [f64]>,
    advised: Option<usize>,
    tick: u64,
    clipped: u64,
    needs_plan: bool,
    policy_version: u64,
}

/// [`ContinuousSnapshot`] borrowed: the same fields, in the same order.
#[derive(Debug, Serialize)]
#[serde(rename = "ContinuousSnapshot")]
pub struct ContinuousSnapshotRef<'a> {
    rng: RngState,
    drive: &'a Drive,
    xi: &'a LinearStimulus,
    store: &'a SampleStore,
    planner: &'a SamplePlanner,
    known_next: &'a [u64],
    s: Option<&'a [f64]>,
    advised: Option<usize>,
    tick: u64,
    clipped: u64,
    needs_plan: bool,
    policy_version: u64,
    u: &'a [f64],
    r_max: f64,
    probes: &'a [f64],
    graph: Option<&'a PvfGraph>,
    pvf: Option<&'a Pvf>,
}

impl ContinuousAgent {
    /// The agent's state borrowed, for encoding: the bytes of
    /// [`Self::snapshot`]'s, with nothing copied (what a durable store
    /// writes; [`Self::snapshot`] is for keeping a state apart from the
    /// agent).
    pub fn snapshot_ref(&self) -> ContinuousStateRef<'_> {
        let s = self.s.as_ref().map(|(s, _)| s.as_slice());
        if let Some(grid) = &self.grid {
            return ContinuousStateRef::Grid(GridSnapshotRef {
                rng: RngState::of(&self.rng),
                drive: &self.drive,
                grid,
                s,
                advised: self.advised,
                tick: self.tick,
                clipped: self.clipped,
                needs_plan: self.needs_plan,
                policy_version: self.policy_version,
            });
        }
        ContinuousStateRef::Features(ContinuousSnapshotRef {
            rng: RngState::of(&self.rng),
            drive: &self.drive,
            xi: &self.xi,
            store: &self.store,
            planner: &self.planner,
            known_next: &self.known_next,
            s,
            advised: self.advised,
            tick: self.tick,
            clipped: self.clipped,
            needs_plan: self.needs_plan,
            policy_version: self.policy_version,
            u: &self.u,
            r_max: self.r_max,
            probes: &self.probes,
            graph: self.graph.as_ref(),
            pvf: match &self.model.features {
                FeatureMap::Pvf(p) => Some(p),
                _ => None,
            },
        })
    }

    /// The agent's state, copied: kept apart from the agent, and what a
    /// stored snapshot decodes to. A durable store encodes
    /// [`Self::snapshot_ref`] instead (the same bytes, nothing copied).
    pub fn snapshot(&self) -> ContinuousState {
        if let Some(grid) = &self.grid {
            return ContinuousState::Grid(Box::new(GridSnapshot {
                rng: RngState::of(&self.rng),
                drive: self.drive.clone(),
                grid: (**grid).clone(),
                s: self.s.as_ref().map(|(s, _)| s.clone()),
                advised: self.advised,
                tick: self.tick,
                clipped: self.clipped,
                needs_plan: self.needs_plan,
                policy_version: self.policy_version,
            }));
        }
        ContinuousState::Features(Box::new(ContinuousSnapshot {
            rng: RngState::of(&self.rng),
            drive: self.drive.clone(),
            xi: self.xi.clone(),
            store: self.store.clone(),
            planner: self.planner.clone(),
            known_next: self.known_next.clone(),
            s: self.s.as_ref().map(|(s, _)| s.clone()),
            advised: self.advised,
            tick: self.tick,
            clipped: self.clipped,
            needs_plan: self.needs_plan,
            policy_version: self.policy_version,
            u: self.u.clone(),
            r_max: self.r_max,
            probes: self.probes.clone(),
            graph: self.graph.clone(),
            pvf: match &self.model.features {
                FeatureMap::Pvf(p) => Some(p.clone()),
                _ => None,
            },
        }))
    }

    /// Resumes a snapshot on the model and parameters of the session that
    /// wrote it. A snapshot that does not fit them (its shapes, or a basis
    /// of another kind) is refused, never half restored.
    pub fn restore(
        model: ContinuousModel,
        params: ValidParams,
        state: impl Into<ContinuousState>,
    ) -> Result<Self> {
        match (state.into(), &model.features) {
            (ContinuousState::Grid(snap), FeatureMap::Grid(_)) => {
                Self::restore_grid(model, params, *snap)
            }
            (ContinuousState::Features(snap), map) if !matches!(map, FeatureMap::Grid(_)) => {
                Self::restore_features(model, params, *snap)
            }
            _ => Err(AlgoError::InvalidSnapshot(
                "its basis (a grid or features) does not fit the model".into(),
            )),
        }
    }

    fn restore_grid(
        model: ContinuousModel,
        params: ValidParams,
        snap: GridSnapshot,
    ) -> Result<Self> {
        let bad = |what: &str| Err(misfit(what));
        let (d, na, n) = (model.dim(), model.n_actions(), model.n_stimuli());
        let FeatureMap::Grid(shape) = model.features else {
            return bad("basis");
        };
        if !drive_fits(&snap.drive, n) {
            return bad("drive");
        }
        if !snap.grid.fits(&shape, na, n) {
            return bad("grid");
        }
        if snap
            .s
            .as_ref()
            .is_some_and(|s| s.len() != d || !s.iter().all(|x| (0.0..=1.0).contains(x)))
            || snap.advised.is_some_and(|a| a >= na)
        {
            return bad("observation");
        }
        let mut agent = Self::new(model, params);
        agent.rng = snap.rng.resume();
        agent.drive = snap.drive;
        agent.grid = Some(Box::new(snap.grid));
        agent.s = snap.s.map(|s| (s, Vec::new()));
        agent.advised = snap.advised;
        agent.tick = snap.tick;
        agent.clipped = snap.clipped;
        agent.needs_plan = snap.needs_plan;
        agent.policy_version = snap.policy_version;
        Ok(agent)
    }

    fn restore_features(
        mut model: ContinuousModel,
        params: ValidParams,
        snap: ContinuousSnapshot,
    ) -> Result<Self> {
        let bad = |what: &str| Err(misfit(what));
        let (d, k, na, n) = (
            model.dim(),
            model.features.len(),
            model.n_actions(),
            model.n_stimuli(),
        );
        match (&mut model.features, snap.pvf, &snap.graph) {
            (FeatureMap::Pvf(current), Some(pvf), Some(graph)) => {
                if !pvf.fits(d, k) || !graph.fits(d) {
                    return bad("PVF basis");
                }
                *current = pvf;
            }
            (FeatureMap::Pvf(_), _, _) => return bad("basis (a PVF basis without its graph)"),
            (_, None, None) => {}
            (_, _, _) => return bad("basis (a PVF basis, the model has another)"),
        }
        let len = snap.store.len();
        if !drive_fits(&snap.drive, n) {
            return bad("drive");
        }
        if !snap.xi.fits(na, k, n) {
            return bad("stimulus function");
        }
        if !snap.store.fits(d, k, na, n) {
            return bad("sample store");
        }
        if !snap.planner.fits(k, na, len) || snap.known_next.len() != len {
            return bad("planner");
        }
        if snap.s.as_ref().is_some_and(|s| s.len() != d)
            || snap.advised.is_some_and(|a| a >= na)
            || snap.u.len() != na * k
            || snap.probes.len() != PROBES * k
        {
            return bad("observation or reward weights");
        }
        let mut store = snap.store;
        let map = &model.features;
        store.restore_features(|s, out| map.features_into(s, out));
        let s = snap.s.map(|s| {
            let mut v = vec![0.0; k];
            map.features_into(&s, &mut v);
            (s, v)
        });
        let mut agent = Self::new(model, params);
        agent.rng = snap.rng.resume();
        agent.drive = snap.drive;
        agent.xi = snap.xi;
        agent.store = store;
        agent.planner = snap.planner;
        agent.known_next = snap.known_next;
        agent.s = s;
        agent.advised = snap.advised;
        agent.tick = snap.tick;
        agent.clipped = snap.clipped;
        agent.needs_plan = snap.needs_plan;
        agent.policy_version = snap.policy_version;
        agent.u = snap.u;
        agent.r_max = snap.r_max;
        agent.probes = snap.probes;
        agent.graph = snap.graph;
        Ok(agent)
    }
}

/// The refusal of a snapshot whose `what` does not fit the model.
fn misfit(what: &str) -> AlgoError {
    AlgoError::InvalidSnapshot(format!("its {what} does not fit the model"))
}

/// A drive of n finite components and unit length.
fn drive_fits(drive: &Drive, n: usize) -> bool {
    drive.vector().len() == n
        && drive.inv_rho().len() == n
        && drive.vector().iter().all(|x| x.is_finite())
        && (crate::drive::norm(drive.vector()) - 1.0).abs() <= 1e-6
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::AgentParams;
    use crate::continuous::{
        ContinuousBasisSpec, ContinuousObservation, ContinuousSpec, ObservationSpace, OutOfBounds,
    };

    fn spec(basis: Option<ContinuousBasisSpec>) -> ContinuousSpec {
        ContinuousSpec {
            observation_space: ObservationSpace {
                low: vec![-1.0, 0.0],
                high: vec![1.0, 10.0],
            },
            actions: vec!["a".into(), "b".into(), "c".into()],
            stimuli: vec!["food".into(), "rest".into()],
            // None: the RBFs that were the default of d = 2 before the grid.
            basis: basis.or(Some(ContinuousBasisSpec::Rbf {
                centres_per_dim: 10,
                width: None,
            })),
            out_of_bounds: OutOfBounds::Clip,
            samples: Default::default(),
        }
    }

    fn params(seed: u64) -> ValidParams {
        AgentParams {
            seed: Some(seed),
            ..Default::default()
        }
        .check(2, seed)
        .expect("params")
    }

    fn pvf() -> Option<ContinuousBasisSpec> {
        Some(ContinuousBasisSpec::Pvf {
            k: 12,
            nodes: Some(2048),
            neighbours: None,
        })
    }

    /// A deterministic little world: the action moves the point; food at
    /// one end, rest at the other.
    struct World {
        x: Vec<f64>,
        t: usize,
    }

    impl World {
        fn new() -> Self {
            Self {
                x: vec![0.0, 5.0],
                t: 0,
            }
        }

        fn next(&mut self, a: usize) -> [f64; 2] {
            let t = self.t;
            self.t += 1;
            self.x[0] = (self.x[0] + [-0.1, 0.1, 0.0][a] + 0.01 * ((t * 7 % 5) as f64 - 2.0))
                .clamp(-1.2, 1.2);
            self.x[1] = (self.x[1] + 0.3 * ((t % 3) as f64 - 1.0)).clamp(0.0, 10.0);
            [
                if self.x[0] < -0.8 { 6.0 } else { 0.0 },
                if self.x[0] > 0.8 { 6.0 } else { 0.0 },
            ]
        }
    }

    /// `ticks` observations (the first of a fresh agent without a
    /// stimulus), planned every third one as a server's async mode may;
    /// each step's bits out.
    fn run(agent: &mut ContinuousAgent, world: &mut World, ticks: usize) -> Vec<(usize, u64, u64)> {
        let mut out = Vec::new();
        for _ in 0..ticks {
            let a = agent.advised_action().unwrap_or(0);
            let xi = (agent.tick() > 0 || agent.advised_action().is_some()).then(|| world.next(a));
            let observed = agent
                .observe(&ContinuousObservation {
                    observation: &world.x,
                    stimulus: xi.as_ref().map(|x| x.as_slice()),
                    action_taken: None,
                })
                .expect("observe");
            if world.t % 3 == 0 {
                agent.plan();
            }
            let (action, value) = agent.act().expect("act");
            out.push((action, value.to_bits(), observed.reward.to_bits()));
        }
        out
    }

    /// The agent's snapshot as a store gives it back (scratch buffers
    /// empty).
    fn stored(agent: &ContinuousAgent) -> ContinuousState {
        let bytes = postcard::to_allocvec(&agent.snapshot()).expect("encode");
        let borrowed = postcard::to_allocvec(&agent.snapshot_ref()).expect("encode");
        assert!(
            bytes == borrowed,
            "the borrowed snapshot encodes to other bytes than the owned one"
        );
        postcard::from_bytes(&bytes).expect("decode")
    }

    /// Runs an agent `before` observations, restores its snapshot and runs
    /// both 600 more.
    fn round_trip(basis: Option<ContinuousBasisSpec>, before: usize) {
        let is_pvf = matches!(basis, Some(ContinuousBasisSpec::Pvf { .. }));
        let is_grid = matches!(basis, Some(ContinuousBasisSpec::Grid { .. }));
        let model = spec(basis).build().expect("model");
        let mut a = ContinuousAgent::new(model.clone(), params(5));
        let mut world = World::new();
        run(&mut a, &mut world, before);
        // Observed and not yet planned: the restored agent plans first.
        assert!(
            a.needs_plan(),
            "the snapshot is taken between observe and plan"
        );
        let builds = a.stats().basis_builds;
        let snap = stored(&a);
        let mut b = ContinuousAgent::restore(model, params(5), snap.clone()).expect("restore");
        assert_eq!(stored(&b), snap);
        let mut twin = World {
            x: world.x.clone(),
            t: world.t,
        };
        let (ra, rb) = (run(&mut a, &mut world, 600), run(&mut b, &mut twin, 600));
        assert_eq!(ra, rb, "the restored agent continues with the same bits");
        assert_eq!(a.stats(), b.stats());
        assert_eq!(stored(&a), stored(&b));
        if is_pvf {
            assert!(
                builds >= 1 && a.stats().basis_builds > builds,
                "PVF builds: {builds} before the snapshot, {} in all",
                a.stats().basis_builds
            );
        }
        if is_grid {
            assert!(a.stats().slots > 0, "{:?}", a.stats());
        } else {
            // Past a rebuild of A⁻¹ from the samples, after the restore.
            assert!(a.stats().rebuilds >= 1, "{:?}", a.stats());
        }
    }

    #[test]
    fn a_restored_agent_continues_bit_for_bit() {
        round_trip(None, 602);
    }

    /// A PVF basis is part of the snapshot: restored past several rebuilds,
    /// and rebuilt again after the restore at the same ticks.
    #[test]
    fn a_restored_pvf_agent_continues_bit_for_bit_across_rebuilds() {
        round_trip(pvf(), 152);
    }

    /// A grid agent's snapshot holds its planner whole (kept moves, Ξ's
    /// cells, π, V and R of its last plan).
    #[test]
    fn a_restored_grid_agent_continues_bit_for_bit() {
        round_trip(grid(), 401);
    }

    #[test]
    fn a_grid_snapshot_fits_only_a_grid_of_its_shape() {
        let model = spec(grid()).build().expect("model");
        let mut a = ContinuousAgent::new(model.clone(), params(5));
        run(&mut a, &mut World::new(), 50);
        let snap = a.snapshot();
        assert!(matches!(snap, ContinuousState::Grid(_)));
        let other = spec(Some(ContinuousBasisSpec::Grid {
            cells_per_dim: 8,
            neighbours: None,
            reach: None,
        }));
        let err = ContinuousAgent::restore(other.build().expect("model"), params(5), snap.clone());
        assert!(matches!(err, Err(AlgoError::InvalidSnapshot(_))), "{err:?}");
        let err =
            ContinuousAgent::restore(spec(None).build().expect("model"), params(5), snap.clone());
        assert!(matches!(err, Err(AlgoError::InvalidSnapshot(_))), "{err:?}");
        let mut bad = snap.clone();
        if let ContinuousState::Grid(g) = &mut bad {
            g.advised = Some(3);
        }
        let err = ContinuousAgent::restore(model.clone(), params(5), bad);
        assert!(matches!(err, Err(AlgoError::InvalidSnapshot(_))), "{err:?}");
        assert!(ContinuousAgent::restore(model, params(5), snap).is_ok());
    }

    fn grid() -> Option<ContinuousBasisSpec> {
        Some(ContinuousBasisSpec::Grid {
            cells_per_dim: 12,
            neighbours: Some(3),
            reach: Some(2.5),
        })
    }

    #[test]
    fn a_snapshot_that_does_not_fit_the_model_is_refused() {
        let model = spec(None).build().expect("model");
        let mut a = ContinuousAgent::new(model.clone(), params(5));
        run(&mut a, &mut World::new(), 50);
        let snap = a.snapshot().features().expect("a feature basis");
        // Another basis (Fourier order 2: other k).
        let mut other = spec(None);
        other.basis = Some(ContinuousBasisSpec::Fourier {
            order: 2,
            max_coupling: None,
        });
        let err = ContinuousAgent::restore(other.build().expect("model"), params(5), snap.clone());
        assert!(matches!(err, Err(AlgoError::InvalidSnapshot(_))), "{err:?}");
        // A PVF model and a snapshot without a graph.
        let err =
            ContinuousAgent::restore(spec(pvf()).build().expect("model"), params(5), snap.clone());
        assert!(matches!(err, Err(AlgoError::InvalidSnapshot(_))), "{err:?}");
        // An advised action out of range.
        let mut bad = snap.clone();
        bad.advised = Some(3);
        let err = ContinuousAgent::restore(model.clone(), params(5), bad);
        assert!(matches!(err, Err(AlgoError::InvalidSnapshot(_))), "{err:?}");
        // A stored transition without its knownness flags.
        let mut bad = snap.clone();
        bad.known_next.pop();
        let err = ContinuousAgent::restore(model.clone(), params(5), bad);
        assert!(matches!(err, Err(AlgoError::InvalidSnapshot(_))), "{err:?}");
        assert!(ContinuousAgent::restore(model, params(5), snap).is_ok());
    }
}
