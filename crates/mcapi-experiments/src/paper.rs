//! The worlds and configurations of Experiments 1 and 2 (docs/algorithm.md §6),
//! and the simulation of one trial.

use std::sync::Arc;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use mcapi_core::model::{Preset, hallway, three_room};
use mcapi_core::{
    Agent, AgentParams, AlgoError, Basis, BasisSpec, Drive, EnvModel, LearnedParams, Observation,
    PlanningModel, Step, ValidLearnedParams, ValidParams,
};

use super::dominance::DominanceTracker;

/// The learned-model parameters, for the CLI.
pub use mcapi_core::{LearnedParams as LearnedModelParams, Optimism};

/// Magnitude of a source's stimulus on its own dimension.
pub const SOURCE_STIMULUS: f64 = 6.0;

/// Standard deviation of the source noise. docs/algorithm.md writes N(0, 2); we
/// read the 2 as the standard deviation, as §6 writes N(0, σ) for the
/// Brownian step. With it η‖ξ‖² exceeds 1 − η on some visits, so Eq. 1 flips
/// a component's sign now and then, as §2.4 says it does.
pub const SOURCE_NOISE_SD: f64 = 2.0;

/// σ of the Brownian baseline: E|round(N(0, σ))| ≈ 4 states per tick.
pub fn brownian_sigma() -> f64 {
    4.0 * (std::f64::consts::PI / 2.0).sqrt()
}

/// Ticks a drive must have dominated before a figure snapshot is taken.
pub const SNAPSHOT_DELAY: u64 = 25;

/// Snapshots are taken in the last three quarters of a trial, once Ξ has
/// learned where the sources are (the early value maps show the optimistic
/// initialisation rather than the drives).
pub const SNAPSHOT_FROM_FRACTION: f64 = 0.25;

/// Which experiment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ExperimentKind {
    /// Experiment 1: the 50-state hallway with food and rest.
    Hallway,
    /// Experiment 2: the three-room maze with sources a, b, c.
    ThreeRoom,
}

/// How a configuration chooses its actions.
#[derive(Debug, Clone, PartialEq)]
pub enum Controller {
    /// MCA-PI with a basis and optional ε-greedy exploration.
    McaPi {
        /// Feature basis.
        basis: BasisSpec,
        /// Exploration ε.
        epsilon: f64,
        /// `Some`: the agent learns P̂ from its own transitions instead of
        /// planning on the world's P (docs/algorithm.md §8).
        learned: Option<ValidLearnedParams>,
    },
    /// Brownian exploration on a chain: step = round(N(0, σ)), clipped.
    Brownian {
        /// σ of the step.
        sigma: f64,
    },
    /// A uniformly random valid action every tick.
    RandomWalk,
}

/// One named configuration of an experiment.
#[derive(Debug, Clone)]
pub struct Config {
    /// Name used in `summary.json` (e.g. `mca_pi`).
    pub name: &'static str,
    /// Action selection.
    pub controller: Controller,
}

/// An experiment: a world, its parameters and its configurations.
#[derive(Debug, Clone)]
pub struct Experiment {
    /// Which one.
    pub kind: ExperimentKind,
    /// The world: model, sources, map.
    pub preset: Preset,
    /// Discount γ.
    pub gamma: f64,
    /// MCA rate η.
    pub eta: f64,
    /// The configurations, in report order.
    pub configs: Vec<Config>,
    /// Default ticks per trial.
    pub default_steps: usize,
    /// Slip probability p of the world (0: the paper's deterministic world).
    pub slip: f64,
}

/// Which transition model the MCA-PI agents of an experiment plan on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum ModelChoice {
    /// The world's P, known to the agent (the paper).
    #[default]
    Known,
    /// P̂ learned from the agent's own transitions, reported against the
    /// known model on the same seeds (docs/algorithm.md §8).
    Learned,
}

/// Variations of an experiment beyond the paper's (`mcapi experiment` flags).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Variant {
    /// Known or learned model.
    pub model: ModelChoice,
    /// Slip probability p in [0, 1): with probability p a move goes to the
    /// result of a uniformly random available action of the state instead.
    pub slip: f64,
    /// Parameters of the learned model.
    pub learned: LearnedParams,
}

/// Largest slip probability accepted.
pub const MAX_SLIP: f64 = 0.9;

/// The slippery version of a deterministic model: P(·|s, a) = (1 − p)
/// δ(next(s, a)) + p · mean over the available a′ of δ(next(s, a′)), so with
/// probability p the move goes to a random neighbour of s (or stays, when
/// staying is available). The simulator samples it; a known-model agent
/// plans on it.
pub fn slippery(model: &EnvModel, p: f64) -> Result<EnvModel, AlgoError> {
    if !(0.0..=MAX_SLIP).contains(&p) {
        return Err(AlgoError::InvalidParameter {
            name: "slip",
            reason: format!("{p} is not in [0, {MAX_SLIP}]"),
        });
    }
    if !model.is_deterministic() {
        return Err(AlgoError::InvalidModel(
            "only a deterministic world can be made slippery".into(),
        ));
    }
    let mut spec = model.to_spec();
    let next = spec.next.take().unwrap_or_default();
    let mut transitions = Vec::with_capacity(model.n_pairs());
    for (s, row) in next.iter().enumerate() {
        let moves: Vec<usize> = row.iter().flatten().copied().collect();
        let share = p / moves.len() as f64;
        for (a, target) in row.iter().enumerate() {
            let Some(target) = *target else { continue };
            let mut out: Vec<(usize, f64)> = vec![(target, 1.0 - p)];
            for &t in &moves {
                match out.iter_mut().find(|(u, _)| *u == t) {
                    Some((_, q)) => *q += share,
                    None => out.push((t, share)),
                }
            }
            out.retain(|&(_, q)| q > 0.0);
            transitions.push(mcapi_core::TransitionSpec {
                state: s,
                action: mcapi_core::ActionRef::Index(a),
                next: out,
            });
        }
    }
    spec.transitions = Some(transitions);
    EnvModel::from_spec(&spec)
}

impl Experiment {
    /// The paper's configuration of an experiment.
    pub fn new(kind: ExperimentKind) -> Self {
        match kind {
            ExperimentKind::Hallway => Self {
                kind,
                preset: hallway(),
                gamma: 0.95,
                eta: 0.01,
                configs: vec![
                    Config {
                        name: "mca_pi",
                        controller: Controller::McaPi {
                            basis: BasisSpec::Indicator,
                            epsilon: 0.0,
                            learned: None,
                        },
                    },
                    Config {
                        name: "brownian",
                        controller: Controller::Brownian {
                            sigma: brownian_sigma(),
                        },
                    },
                ],
                default_steps: 5000,
                slip: 0.0,
            },
            ExperimentKind::ThreeRoom => Self {
                kind,
                preset: three_room(),
                gamma: 0.85,
                eta: 0.01,
                configs: vec![
                    Config {
                        name: "indicator",
                        controller: Controller::McaPi {
                            basis: BasisSpec::Indicator,
                            epsilon: 0.0,
                            learned: None,
                        },
                    },
                    Config {
                        name: "pvf30",
                        controller: Controller::McaPi {
                            basis: BasisSpec::ProtoValue { k: 30 },
                            epsilon: 0.0,
                            learned: None,
                        },
                    },
                    Config {
                        name: "pvf30_eps0.3",
                        controller: Controller::McaPi {
                            basis: BasisSpec::ProtoValue { k: 30 },
                            epsilon: 0.3,
                            learned: None,
                        },
                    },
                    Config {
                        name: "random_walk",
                        controller: Controller::RandomWalk,
                    },
                ],
                default_steps: 10_000,
                slip: 0.0,
            },
        }
    }

    /// The experiment with a variant: `--model learned` replaces the
    /// configurations by the known-model MCA-PI (indicator basis), its
    /// learned twin `<name>_learned` and the baseline; `--slip p` makes the
    /// world slippery for every configuration.
    pub fn with_variant(kind: ExperimentKind, variant: &Variant) -> Result<Self, AlgoError> {
        let mut exp = Self::new(kind);
        // Any slip but exactly 0 goes through `slippery`, which refuses
        // negative, NaN and too-large values.
        if variant.slip != 0.0 {
            exp.preset.model = slippery(&exp.preset.model, variant.slip)?;
            exp.slip = variant.slip;
        }
        if variant.model == ModelChoice::Learned {
            let learned = variant.learned.check()?;
            let (known, learned_name, baseline) = match kind {
                ExperimentKind::Hallway => ("mca_pi", "mca_pi_learned", "brownian"),
                ExperimentKind::ThreeRoom => ("indicator", "indicator_learned", "random_walk"),
            };
            let find = |name: &str| exp.configs.iter().find(|c| c.name == name).cloned();
            let (Some(known), Some(baseline)) = (find(known), find(baseline)) else {
                return Err(AlgoError::Numerical(
                    "experiment without its configs".into(),
                ));
            };
            let mut twin = known.clone();
            twin.name = learned_name;
            if let Controller::McaPi { learned: l, .. } = &mut twin.controller {
                *l = Some(learned);
            }
            exp.configs = vec![known, twin, baseline];
        }
        Ok(exp)
    }

    /// Name used in files and `summary.json`.
    pub fn name(&self) -> &'static str {
        match self.kind {
            ExperimentKind::Hallway => "hallway",
            ExperimentKind::ThreeRoom => "three-room",
        }
    }

    /// Number of stimulus dimensions.
    pub fn dims(&self) -> usize {
        self.preset.model.n_stimuli()
    }

    /// Builds the shared planning models, one per distinct basis.
    pub fn planning_models(&self) -> Result<Vec<Option<Arc<PlanningModel>>>, AlgoError> {
        let mut built: Vec<(BasisSpec, Arc<PlanningModel>)> = Vec::new();
        self.configs
            .iter()
            .map(|c| match &c.controller {
                Controller::McaPi { basis, .. } => {
                    if let Some((_, ctx)) = built.iter().find(|(b, _)| b == basis) {
                        return Ok(Some(Arc::clone(ctx)));
                    }
                    let model = self.preset.model.clone();
                    let b = Basis::build(basis, &model)?;
                    let ctx = Arc::new(PlanningModel::new(model, b));
                    built.push((basis.clone(), Arc::clone(&ctx)));
                    Ok(Some(ctx))
                }
                _ => Ok(None),
            })
            .collect()
    }
}

/// Value function and greedy policy at one instant (for Fig. 3e-g).
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    /// Tick of the snapshot.
    pub tick: u64,
    /// The dominant drive component at that tick.
    pub dominant: usize,
    /// V(s) per state.
    pub values: Vec<f64>,
    /// Greedy action index per state.
    pub actions: Vec<usize>,
    /// Where the agent was.
    pub state: usize,
}

/// Everything recorded in one trial, one entry per tick 1..=steps.
#[derive(Debug, Clone, Default)]
pub struct TrialRecord {
    /// Stimulus dimensions n.
    pub dims: usize,
    /// State at tick 0.
    pub start: usize,
    /// D₀, the drive before the first tick.
    pub initial_drive: Vec<f64>,
    /// s_t after each tick.
    pub states: Vec<u32>,
    /// The action taken at each tick (for Brownian: the signed displacement).
    pub actions: Vec<i32>,
    /// D after each tick, row-major ticks × n.
    pub drive: Vec<f64>,
    /// |r| of each tick.
    pub abs_reward: Vec<f64>,
    /// ξ received at each tick, ticks × n.
    pub stimulus: Vec<f64>,
    /// ‖Q_t − Q_{t+1}‖ of each tick (0 for controllers that do not plan).
    pub lstdq_error: Vec<f64>,
    /// V(source state) after each tick, ticks × sources.
    pub source_values: Vec<f64>,
    /// Value/policy snapshots when each drive first dominated.
    pub snapshots: Vec<Snapshot>,
    /// Fraction of LSTDQ updates that reused the factorisation.
    pub reuse_fraction: f64,
    /// Fraction of valid pairs the agent's model knows after each tick (1
    /// for a known model and for controllers that do not plan).
    pub known: Vec<f32>,
}

impl TrialRecord {
    /// Number of ticks recorded.
    pub fn steps(&self) -> usize {
        self.abs_reward.len()
    }

    /// D at tick index `t` (0-based: tick t+1).
    pub fn drive_at(&self, t: usize) -> &[f64] {
        &self.drive[t * self.dims..(t + 1) * self.dims]
    }
}

/// Seeds of trial `trial`: (world, agent). Mixing with SplitMix64 constants
/// keeps neighbouring trials' streams unrelated.
pub fn trial_seeds(seed: u64, trial: usize) -> (u64, u64) {
    let base = seed ^ (trial as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let mix = |mut z: u64| {
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    (mix(base), mix(base ^ 0xD1B5_4A32_D192_ED03))
}

/// The world side of a trial: sources with noisy stimuli.
struct World<'a> {
    preset: &'a Preset,
    noise: Normal<f64>,
    rng: ChaCha8Rng,
}

impl<'a> World<'a> {
    fn new(preset: &'a Preset, seed: u64) -> Result<Self, AlgoError> {
        let noise = Normal::new(0.0, SOURCE_NOISE_SD)
            .map_err(|e| AlgoError::Numerical(format!("noise distribution: {e}")))?;
        Ok(Self {
            preset,
            noise,
            rng: ChaCha8Rng::seed_from_u64(seed),
        })
    }

    /// ξ at state `s`: SOURCE_STIMULUS + noise on the source's own
    /// dimension, exactly 0 elsewhere (docs/algorithm.md §6).
    fn stimulus(&mut self, s: usize, xi: &mut [f64]) {
        xi.fill(0.0);
        for src in &self.preset.sources {
            if src.state == s {
                xi[src.dim] = SOURCE_STIMULUS + self.noise.sample(&mut self.rng);
            }
        }
    }
}

/// Runs one trial of `config` for `steps` ticks.
///
/// `record_snapshots` asks for the value/policy snapshots of Fig. 3(e-g).
pub fn run_trial(
    exp: &Experiment,
    config: &Config,
    ctx: Option<&Arc<PlanningModel>>,
    seed: u64,
    trial: usize,
    steps: usize,
    record_snapshots: bool,
) -> Result<TrialRecord, AlgoError> {
    let (world_seed, agent_seed) = trial_seeds(seed, trial);
    let model = &exp.preset.model;
    let n = model.n_stimuli();
    let mut world = World::new(&exp.preset, world_seed)?;
    let start = world.rng.random_range(0..model.states());
    let n_src = exp.preset.sources.len();
    let mut rec = TrialRecord {
        dims: n,
        start,
        initial_drive: Vec::new(),
        states: Vec::with_capacity(steps),
        actions: Vec::with_capacity(steps),
        drive: Vec::with_capacity(steps * n),
        abs_reward: Vec::with_capacity(steps),
        stimulus: Vec::with_capacity(steps * n),
        lstdq_error: Vec::with_capacity(steps),
        source_values: Vec::with_capacity(steps * n_src),
        snapshots: Vec::new(),
        reuse_fraction: 0.0,
        known: Vec::with_capacity(steps),
    };
    let mut xi = vec![0.0; n];
    let params = AgentParams {
        eta: Some(exp.eta),
        gamma: Some(exp.gamma),
        seed: Some(agent_seed),
        epsilon: match config.controller {
            Controller::McaPi { epsilon, .. } => Some(epsilon),
            _ => None,
        },
        ..Default::default()
    }
    .check(n, agent_seed)?;
    match &config.controller {
        Controller::McaPi { learned, .. } => {
            let ctx =
                ctx.ok_or_else(|| AlgoError::Numerical("MCA-PI needs a planning model".into()))?;
            let mut sim = Simulation::with_world(world, start, Arc::clone(ctx), params, *learned)?;
            let mut tracker = DominanceTracker::new(sim.agent.drive().vector());
            rec.initial_drive = sim.agent.drive().vector().to_vec();
            for _ in 0..steps {
                let (action, step) = sim.tick()?;
                let agent = &sim.agent;
                rec.push(
                    sim.state,
                    action as i32,
                    agent.drive().vector(),
                    step.reward,
                    &sim.xi,
                );
                rec.lstdq_error
                    .push(step.plan.map_or(0.0, |p| p.lstdq_error));
                for src in &exp.preset.sources {
                    rec.source_values.push(agent.planner().value(src.state));
                }
                rec.known.push(agent.known_fraction() as f32);
                tracker.observe(agent.drive().vector());
                let dom = tracker.current();
                if record_snapshots
                    && step.tick as f64 >= SNAPSHOT_FROM_FRACTION * steps as f64
                    && tracker.held() >= SNAPSHOT_DELAY
                    && !rec.snapshots.iter().any(|s| s.dominant == dom)
                {
                    rec.snapshots.push(Snapshot {
                        tick: step.tick,
                        dominant: dom,
                        values: (0..model.states())
                            .map(|s| agent.planner().value(s))
                            .collect(),
                        actions: (0..model.states())
                            .map(|s| agent.greedy_action(s))
                            .collect(),
                        state: sim.state,
                    });
                }
            }
            let stats = sim.agent.planner().stats();
            rec.reuse_fraction = stats.reuses as f64 / stats.updates.max(1) as f64;
        }
        Controller::Brownian { sigma } => {
            let mut rng = ChaCha8Rng::seed_from_u64(agent_seed);
            let mut drive = Drive::new(&params.priorities, params.eta, &mut rng);
            rec.initial_drive = drive.vector().to_vec();
            let step_dist = Normal::new(0.0, *sigma)
                .map_err(|e| AlgoError::Numerical(format!("Brownian step: {e}")))?;
            let last = model.states() as i64 - 1;
            let mut state = start as i64;
            for _ in 0..steps {
                let step = step_dist.sample(&mut rng).round() as i64;
                let next = (state + step).clamp(0, last);
                let moved = next - state;
                state = next;
                world.stimulus(state as usize, &mut xi);
                let r = drive.update(&xi).abs();
                rec.push(state as usize, moved as i32, drive.vector(), r, &xi);
                rec.known.push(1.0);
                rec.lstdq_error.push(0.0);
                rec.source_values.extend(std::iter::repeat_n(0.0, n_src));
            }
        }
        Controller::RandomWalk => {
            let mut rng = ChaCha8Rng::seed_from_u64(agent_seed);
            let mut drive = Drive::new(&params.priorities, params.eta, &mut rng);
            rec.initial_drive = drive.vector().to_vec();
            let mut state = start;
            for _ in 0..steps {
                let pair = rng.random_range(model.pairs_of(state));
                let action = model.pair_action(pair);
                state = model.sample_next(pair, world.rng.random());
                world.stimulus(state, &mut xi);
                let r = drive.update(&xi).abs();
                rec.push(state, action as i32, drive.vector(), r, &xi);
                rec.known.push(1.0);
                rec.lstdq_error.push(0.0);
                rec.source_values.extend(std::iter::repeat_n(0.0, n_src));
            }
        }
    }
    Ok(rec)
}

/// An MCA-PI agent living in an experiment's world: the loop of a trial,
/// also driven tick by tick by the benchmarks.
pub struct Simulation<'a> {
    world: World<'a>,
    agent: Agent,
    /// The agent's current state.
    state: usize,
    /// The action the agent advised for `state`.
    action: usize,
    /// The stimulus of the last tick.
    xi: Vec<f64>,
}

impl<'a> Simulation<'a> {
    /// A fresh agent with seed `params.seed` at a random start of the world
    /// seeded `world_seed` (the same start as trial runs with that seed).
    pub fn new(
        exp: &'a Experiment,
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        world_seed: u64,
    ) -> Result<Self, AlgoError> {
        let mut world = World::new(&exp.preset, world_seed)?;
        let start = world.rng.random_range(0..exp.preset.model.states());
        Self::with_world(world, start, ctx, params, None)
    }

    /// Like [`Simulation::new`], for an agent that learns P̂ (docs/algorithm.md §8).
    pub fn new_learned(
        exp: &'a Experiment,
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        learned: ValidLearnedParams,
        world_seed: u64,
    ) -> Result<Self, AlgoError> {
        let mut world = World::new(&exp.preset, world_seed)?;
        let start = world.rng.random_range(0..exp.preset.model.states());
        Self::with_world(world, start, ctx, params, Some(learned))
    }

    fn with_world(
        world: World<'a>,
        start: usize,
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        learned: Option<ValidLearnedParams>,
    ) -> Result<Self, AlgoError> {
        let mut agent = match learned {
            None => Agent::new(ctx, params),
            Some(l) => Agent::new_learned(ctx, params, l)?,
        };
        let action = agent.step(&Observation::first(start))?.action;
        let n = world.preset.model.n_stimuli();
        Ok(Self {
            world,
            agent,
            state: start,
            action,
            xi: vec![0.0; n],
        })
    }

    /// One tick: the world applies the advised action and delivers ξ, the
    /// agent steps (Algorithm 1). Returns the action taken and the step.
    pub fn tick(&mut self) -> Result<(usize, Step), AlgoError> {
        let model = &self.world.preset.model;
        let taken = self.action;
        let pair = model
            .pair(self.state, taken)
            .ok_or_else(|| AlgoError::Numerical("agent chose an unavailable action".into()))?;
        let u: f64 = self.world.rng.random();
        self.state = model.sample_next(pair, u);
        self.world.stimulus(self.state, &mut self.xi);
        let step = self.agent.step(&Observation::new(self.state, &self.xi))?;
        self.action = step.action;
        Ok((taken, step))
    }

    /// The agent.
    pub fn agent(&self) -> &Agent {
        &self.agent
    }

    /// The agent's current state.
    pub fn state(&self) -> usize {
        self.state
    }
}

impl TrialRecord {
    fn push(&mut self, state: usize, action: i32, drive: &[f64], abs_reward: f64, xi: &[f64]) {
        self.states.push(state as u32);
        self.actions.push(action);
        self.drive.extend_from_slice(drive);
        self.abs_reward.push(abs_reward);
        self.stimulus.extend_from_slice(xi);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::trial_metrics;

    fn learned_variant(kind: ExperimentKind, slip: f64) -> Experiment {
        Experiment::with_variant(
            kind,
            &Variant {
                model: ModelChoice::Learned,
                slip,
                learned: LearnedParams::default(),
            },
        )
        .expect("variant")
    }

    #[test]
    fn a_learned_agent_finds_both_hallway_sources() {
        let exp = learned_variant(ExperimentKind::Hallway, 0.0);
        let names: Vec<&str> = exp.configs.iter().map(|c| c.name).collect();
        assert_eq!(names, ["mca_pi", "mca_pi_learned", "brownian"]);
        let ctxs = exp.planning_models().expect("models");
        let sources: Vec<usize> = exp.preset.sources.iter().map(|s| s.state).collect();
        for trial in 0..3 {
            let rec = run_trial(
                &exp,
                &exp.configs[1],
                ctxs[1].as_ref(),
                7,
                trial,
                1500,
                false,
            )
            .expect("trial");
            let m = trial_metrics(&rec, &sources);
            assert!(m["all_sources_found"] <= 1500.0, "trial {trial}: {m:?}");
            assert!(
                m["balance"] > 0.5,
                "trial {trial}: balance {}",
                m["balance"]
            );
            assert_eq!(m["model_known"], 1.0, "trial {trial}: the hallway is small");
            assert!(rec.known[0] < 0.1, "almost nothing is known at first");
        }
    }

    #[test]
    fn the_slippery_world_moves_with_probability_p_to_a_random_neighbour() {
        let model = hallway().model;
        let slip = slippery(&model, 0.3).expect("slippery");
        assert_eq!(slip.n_pairs(), model.n_pairs());
        // (10, right): 0.7 to 11, and 0.1 each to 9, 11, 10.
        let p = slip.pair(10, 1).expect("right");
        let (next, prob) = slip.successors(p);
        let mut row: Vec<(u32, f64)> = next.iter().copied().zip(prob.iter().copied()).collect();
        row.sort_by_key(|&(t, _)| t);
        let expected = [(9, 0.1), (10, 0.1), (11, 0.8)];
        for ((t, q), (u, r)) in row.iter().zip(expected) {
            assert_eq!(*t, u);
            assert!((q - r).abs() < 1e-12, "{t}: {q} vs {r}");
        }
        assert!(slippery(&model, 0.95).is_err());
        for bad in [-0.1, f64::NAN] {
            let variant = Variant {
                slip: bad,
                ..Default::default()
            };
            let e = Experiment::with_variant(ExperimentKind::ThreeRoom, &variant)
                .expect_err("bad slip");
            assert!(e.to_string().contains("`slip`"), "{e}");
        }
        let exp = learned_variant(ExperimentKind::ThreeRoom, 0.2);
        assert!(!exp.preset.model.is_deterministic());
        assert_eq!(exp.slip, 0.2);
    }
}
