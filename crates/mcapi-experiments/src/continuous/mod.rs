//! The paper's experiments in continuous form (docs/algorithm.md §9.6):
//! `mcapi experiment continuous-hallway` and `continuous-three-room`.
//!
//! Each trial runs the continuous MCA-PI agent and a random walk on the
//! same world seed (start point, move noise, source noise). Metrics are
//! the discrete experiments' (cumulative |r|, cumulative stimulus per
//! source, balance = min/max of it, when every source was first found)
//! plus the number of source-to-source traversals (arrivals at a source
//! other than the last one visited). The three-room also runs the
//! discrete agent of Experiment 2 on the same layout for the same trials,
//! as the reference for the cumulative stimulus.

pub mod figures;
pub mod worlds;

use std::collections::BTreeMap;

use anyhow::Context;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use mcapi_core::continuous::{
    ContinuousAgent, ContinuousBasisSpec, ContinuousObservation, ContinuousSpec, ObservationSpace,
    SampleParams,
};
use mcapi_core::{AgentParams, Drive};

use super::metrics::{Stat, summarise};
use super::paper::{Experiment, ExperimentKind, trial_seeds};
use super::run::{RunOptions, run_trials, trial_csv};
pub use worlds::World;

/// Which continuous experiment.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ContinuousKind {
    /// The hallway, x ∈ [0, 1].
    Hallway,
    /// The three-room maze in [0, 1]².
    ThreeRoom,
}

impl ContinuousKind {
    /// The experiment's name in `summary.json`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Hallway => "continuous-hallway",
            Self::ThreeRoom => "continuous-three-room",
        }
    }

    /// The world.
    pub fn world(self) -> World {
        match self {
            Self::Hallway => World::hallway(),
            Self::ThreeRoom => World::three_room(),
        }
    }

    /// γ, η of the discrete experiment of the same layout.
    pub fn gamma_eta(self) -> (f64, f64) {
        let exp = Experiment::new(match self {
            Self::Hallway => ExperimentKind::Hallway,
            Self::ThreeRoom => ExperimentKind::ThreeRoom,
        });
        (exp.gamma, exp.eta)
    }

    /// Default ticks per trial.
    pub fn default_steps(self) -> usize {
        match self {
            Self::Hallway => 5000,
            Self::ThreeRoom => 20_000,
        }
    }
}

/// How a trial chooses actions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Driver {
    /// The continuous MCA-PI agent.
    McaPi,
    /// A uniformly random action every tick.
    RandomWalk,
    /// The three-room's [`worlds::Navigator`]: the map known, heading for
    /// the source of the largest discounted drive.
    Navigator,
}

/// What one trial produced, tick by tick.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ContinuousTrial {
    /// The point after each tick, row-major ticks × d.
    pub points: Vec<f64>,
    /// The stimulus received at each tick, row-major ticks × n.
    pub stimulus: Vec<f64>,
    /// |r| of Eq. 3 at each tick.
    pub abs_reward: Vec<f64>,
    /// D after each tick, row-major ticks × n.
    pub drive: Vec<f64>,
    /// Stimulus dimensions.
    pub dims: usize,
    /// Observation dimensions.
    pub d: usize,
    /// Source index at each tick (`u8::MAX`: none).
    pub at_source: Vec<u8>,
}

/// The continuous world's model as a client would post it.
pub fn spec_of(world: &World) -> ContinuousSpec {
    let d = world.dim();
    ContinuousSpec {
        observation_space: ObservationSpace {
            low: vec![0.0; d],
            high: vec![1.0; d],
        },
        actions: world.actions(),
        stimuli: world.stimuli(),
        basis: None,
        out_of_bounds: Default::default(),
        samples: Default::default(),
    }
}

/// Runs one trial of `steps` ticks.
pub fn run_trial(
    kind: ContinuousKind,
    spec: &ContinuousSpec,
    driver: Driver,
    seed: u64,
    trial: usize,
    steps: usize,
) -> anyhow::Result<ContinuousTrial> {
    let world = kind.world();
    let (world_seed, agent_seed) = trial_seeds(seed, trial);
    let mut rng = ChaCha8Rng::seed_from_u64(world_seed);
    let mut policy_rng = ChaCha8Rng::seed_from_u64(agent_seed);
    let (gamma, eta) = kind.gamma_eta();
    let n = world.stimuli().len();
    let params = AgentParams {
        gamma: Some(gamma),
        eta: Some(eta),
        seed: Some(agent_seed),
        ..Default::default()
    }
    .check(n, agent_seed)?;
    let mut agent = match driver {
        Driver::McaPi => Some(ContinuousAgent::new(spec.build()?, params.clone())),
        Driver::RandomWalk | Driver::Navigator => None,
    };
    let navigator = match (&world, driver) {
        (World::ThreeRoom(maze), Driver::Navigator) => Some(worlds::Navigator::new(maze)),
        (_, Driver::Navigator) => anyhow::bail!("the navigator needs the three-room's map"),
        _ => None,
    };
    // The random walk and the navigator keep the same drive bookkeeping,
    // for |r| (and the navigator for its heading).
    let mut drive = Drive::new(
        &params.priorities,
        eta,
        &mut ChaCha8Rng::seed_from_u64(agent_seed),
    );
    let na = world.actions().len();
    let mut rec = ContinuousTrial {
        dims: n,
        d: world.dim(),
        ..Default::default()
    };
    let mut x = world.start(&mut rng);
    let mut action = match &mut agent {
        Some(agent) => {
            agent
                .step(&ContinuousObservation {
                    observation: &x,
                    stimulus: None,
                    action_taken: None,
                })?
                .action
        }
        None => match &navigator {
            Some(nav) => nav.act(&x, nav.heading(&x, drive.vector(), gamma)),
            None => policy_rng.random_range(0..na),
        },
    };
    for _ in 0..steps {
        x = world.step(&x, action, &mut rng);
        let xi = world.stimulus(&x, &mut rng);
        let (next, reward, d) = match &mut agent {
            Some(agent) => {
                let step = agent.step(&ContinuousObservation {
                    observation: &x,
                    stimulus: Some(&xi),
                    action_taken: None,
                })?;
                (step.action, step.reward, agent.drive().vector().to_vec())
            }
            None => {
                let r = drive.update(&xi).abs();
                let next = match &navigator {
                    Some(nav) => nav.act(&x, nav.heading(&x, drive.vector(), gamma)),
                    None => policy_rng.random_range(0..na),
                };
                (next, r, drive.vector().to_vec())
            }
        };
        rec.points.extend_from_slice(&x);
        rec.stimulus.extend_from_slice(&xi);
        rec.abs_reward.push(reward);
        rec.drive.extend_from_slice(&d);
        rec.at_source
            .push(world.source_at(&x).map_or(u8::MAX, |s| s as u8));
        action = next;
    }
    Ok(rec)
}

/// The metrics of one trial.
pub fn trial_metrics(rec: &ContinuousTrial) -> BTreeMap<String, f64> {
    let steps = rec.abs_reward.len();
    let mut m = BTreeMap::new();
    m.insert("cumulative_abs_reward".into(), rec.abs_reward.iter().sum());
    let mut cum = vec![0.0; rec.dims];
    for row in rec.stimulus.chunks_exact(rec.dims.max(1)) {
        cum.iter_mut().zip(row).for_each(|(c, x)| *c += x);
    }
    let hi = cum.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let lo = cum.iter().copied().fold(f64::INFINITY, f64::min);
    m.insert(
        "balance".into(),
        if hi > 0.0 { (lo / hi).max(0.0) } else { 0.0 },
    );
    m.insert("total_stimulus".into(), cum.iter().sum());
    let mut first = vec![None; rec.dims];
    let mut last = None;
    let mut traversals = 0u64;
    for (t, &s) in rec.at_source.iter().enumerate() {
        if s == u8::MAX {
            continue;
        }
        let s = s as usize;
        if first.get(s).is_some_and(|f: &Option<usize>| f.is_none()) {
            first[s] = Some(t + 1);
        }
        if last.is_some_and(|l| l != s) {
            traversals += 1;
        }
        last = Some(s);
    }
    m.insert("traversals".into(), traversals as f64);
    let never = (steps + 1) as f64;
    let all = first
        .iter()
        .try_fold(0usize, |acc, f| f.map(|t| acc.max(t)))
        .map_or(never, |t| t as f64);
    m.insert("all_sources_found".into(), all);
    m.insert(
        "sources_found".into(),
        first.iter().filter(|f| f.is_some()).count() as f64,
    );
    m
}

/// `summary.json` of a continuous experiment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContinuousSummary {
    /// `continuous-hallway` or `continuous-three-room`.
    pub experiment: String,
    /// Trials.
    pub trials: usize,
    /// Ticks per trial.
    pub steps: usize,
    /// Base seed.
    pub seed: u64,
    /// The effective model the agent ran with.
    pub model: ContinuousSpec,
    /// `{config: {metric: Stat}}`: `mca_pi`, `random_walk`, and for the
    /// three-room `discrete_mca_pi` (Experiment 2's agent, indicator
    /// basis, on the same layout and trials) and `map_navigator` (a
    /// driver that knows the map, [`worlds::Navigator`]).
    pub configs: BTreeMap<String, BTreeMap<String, Stat>>,
    /// Ratios of means: `traversals_vs_random_walk` and (three-room)
    /// `stimulus_vs_discrete` and `navigator_vs_discrete`.
    pub ratios: BTreeMap<String, f64>,
}

/// Everything a continuous experiment produced.
#[derive(Debug)]
pub struct ContinuousOutput {
    /// `summary.json`'s content.
    pub summary: ContinuousSummary,
    /// Files written.
    pub files: Vec<std::path::PathBuf>,
}

/// Runs the continuous agent and the random walk for `opts.trials`
/// trials in parallel (and the discrete reference for the three-room),
/// writes `summary.json`, the per-trial CSV series and the figures.
pub fn run(kind: ContinuousKind, opts: &RunOptions) -> anyhow::Result<ContinuousOutput> {
    run_with_model(kind, opts, None, SampleParams::default())
}

/// [`run`] with the agent on `basis` (the world's default when `None`)
/// and the sample store cut as `samples` says.
pub fn run_with_model(
    kind: ContinuousKind,
    opts: &RunOptions,
    basis: Option<ContinuousBasisSpec>,
    samples: SampleParams,
) -> anyhow::Result<ContinuousOutput> {
    anyhow::ensure!(opts.trials > 0, "--trials must be at least 1");
    anyhow::ensure!(opts.steps > 0, "--steps must be at least 1");
    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("creating {}", opts.out.display()))?;
    let world = kind.world();
    let spec = ContinuousSpec {
        basis,
        samples,
        ..spec_of(&world)
    }
    .build()?
    .spec;
    let names: &[&'static str] = match kind {
        ContinuousKind::Hallway => &["mca_pi", "random_walk"],
        ContinuousKind::ThreeRoom => &["mca_pi", "random_walk", "map_navigator"],
    };
    let grouped = run_trials(opts, kind.name(), names, |c, t| {
        let driver = [Driver::McaPi, Driver::RandomWalk, Driver::Navigator][c];
        let rec = run_trial(kind, &spec, driver, opts.seed, t, opts.steps)
            .with_context(|| format!("{} trial {t}", names[c]))?;
        if opts.csv {
            write_csv(names[c], t, &rec, &opts.out)?;
        }
        Ok(rec)
    })?;
    let mut configs = BTreeMap::new();
    let mut means = BTreeMap::new();
    for (name, recs) in &grouped {
        let per_trial: Vec<_> = recs.iter().map(trial_metrics).collect();
        let stats = summarise(&per_trial);
        for key in ["traversals", "total_stimulus"] {
            if let Some(st) = stats.get(key) {
                means.insert((name.to_string(), key), st.mean);
            }
        }
        configs.insert(name.to_string(), stats);
    }
    if kind == ContinuousKind::ThreeRoom {
        let stats = discrete_reference(opts)?;
        if let Some(st) = stats.get("total_stimulus") {
            means.insert(("discrete_mca_pi".into(), "total_stimulus"), st.mean);
        }
        configs.insert("discrete_mca_pi".into(), stats);
    }
    let mut ratios = BTreeMap::new();
    let ratio = |a: (&str, &'static str), b: (&str, &'static str)| {
        let x = means.get(&(a.0.to_string(), a.1))?;
        let y = means.get(&(b.0.to_string(), b.1))?;
        (*y > 0.0).then(|| x / y)
    };
    if let Some(r) = ratio(("mca_pi", "traversals"), ("random_walk", "traversals")) {
        ratios.insert("traversals_vs_random_walk".into(), r);
    }
    if let Some(r) = ratio(
        ("mca_pi", "total_stimulus"),
        ("discrete_mca_pi", "total_stimulus"),
    ) {
        ratios.insert("stimulus_vs_discrete".into(), r);
    }
    if let Some(r) = ratio(
        ("map_navigator", "total_stimulus"),
        ("discrete_mca_pi", "total_stimulus"),
    ) {
        ratios.insert("navigator_vs_discrete".into(), r);
    }
    let summary = ContinuousSummary {
        experiment: kind.name().into(),
        trials: opts.trials,
        steps: opts.steps,
        seed: opts.seed,
        model: spec,
        configs,
        ratios,
    };
    let path = opts.out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&summary)? + "\n")
        .with_context(|| format!("writing {}", path.display()))?;
    let mut files = vec![path];
    if opts.figures {
        files.extend(figures::draw(
            kind.name(),
            &world.stimuli(),
            &grouped[0].1,
            &grouped[1].1,
            &opts.out,
        )?);
    }
    Ok(ContinuousOutput { summary, files })
}

/// Experiment 2's agent (indicator basis, known model) on the same
/// layout, trials and ticks: the reference for the cumulative stimulus.
fn discrete_reference(opts: &RunOptions) -> anyhow::Result<BTreeMap<String, Stat>> {
    let exp = Experiment::new(ExperimentKind::ThreeRoom);
    let ctxs = exp.planning_models()?;
    let c = exp
        .configs
        .iter()
        .position(|c| c.name == "indicator")
        .context("the indicator configuration")?;
    let sources: Vec<usize> = exp.preset.sources.iter().map(|s| s.state).collect();
    let per_trial = (0..opts.trials)
        .into_par_iter()
        .map(|t| {
            let rec = crate::paper::run_trial(
                &exp,
                &exp.configs[c],
                ctxs[c].as_ref(),
                opts.seed,
                t,
                opts.steps,
                false,
            )?;
            Ok(crate::metrics::trial_metrics(&rec, &sources))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let keep = [
        "total_stimulus",
        "balance",
        "cumulative_abs_reward",
        "all_sources_found",
    ];
    Ok(summarise(&per_trial)
        .into_iter()
        .filter(|(k, _)| keep.contains(&k.as_str()))
        .collect())
}

/// The mean cumulative stimulus of [`discrete_reference`] over `trials`
/// trials of `steps` ticks from `seed`.
pub fn discrete_reference_stimulus(trials: usize, steps: usize, seed: u64) -> anyhow::Result<f64> {
    let opts = RunOptions {
        trials,
        steps,
        seed,
        out: std::env::temp_dir(),
        csv: false,
        figures: false,
        progress: false,
    };
    discrete_reference(&opts)?
        .get("total_stimulus")
        .map(|s| s.mean)
        .context("the discrete agent's total stimulus")
}

/// `DIR/<config>/trial_<i>.csv`: tick, the point, the stimulus, |r|, D.
fn write_csv(
    config: &str,
    trial: usize,
    rec: &ContinuousTrial,
    out: &std::path::Path,
) -> anyhow::Result<()> {
    use std::io::Write;
    let (path, mut w) = trial_csv(out, config, trial)?;
    let axes: Vec<String> = (0..rec.d).map(|j| format!("x{j}")).collect();
    let stim: Vec<String> = (0..rec.dims).map(|j| format!("xi{j}")).collect();
    let drive: Vec<String> = (0..rec.dims).map(|j| format!("d{j}")).collect();
    writeln!(
        w,
        "tick,{},{},abs_r,{}",
        axes.join(","),
        stim.join(","),
        drive.join(",")
    )?;
    for t in 0..rec.abs_reward.len() {
        let row = |data: &[f64], width: usize| -> String {
            data[t * width..(t + 1) * width]
                .iter()
                .map(|v| format!("{v}"))
                .collect::<Vec<_>>()
                .join(",")
        };
        writeln!(
            w,
            "{},{},{},{},{}",
            t + 1,
            row(&rec.points, rec.d),
            row(&rec.stimulus, rec.dims),
            rec.abs_reward[t],
            row(&rec.drive, rec.dims)
        )?;
    }
    w.flush()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// The printed table of a summary.
pub fn results_table(summary: &ContinuousSummary) -> String {
    let mut out = String::from(
        "| config | cumulative abs reward | cumulative stimulus | balance | traversals | sources found | all found at |\n\
         |---|---|---|---|---|---|---|\n",
    );
    for (name, m) in &summary.configs {
        let cell = |k: &str| {
            m.get(k)
                .map_or("-".to_string(), |s| format!("{:.2} ± {:.2}", s.mean, s.sd))
        };
        out += &format!(
            "| {name} | {} | {} | {} | {} | {} | {} |\n",
            cell("cumulative_abs_reward"),
            cell("total_stimulus"),
            cell("balance"),
            cell("traversals"),
            cell("sources_found"),
            cell("all_sources_found"),
        );
    }
    for (k, v) in &summary.ratios {
        out += &format!("\n{k}: {v:.2}");
    }
    out + "\n"
}
