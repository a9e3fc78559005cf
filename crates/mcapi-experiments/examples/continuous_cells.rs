//! The continuous three-room seen through a grid: the discrete agent with
//! a learned model (docs/algorithm.md §8) on the cell of each observation,
//! a state aggregation. The measurement of docs/algorithm.md §9.6 that
//! asks how much of the continuous agent's shortfall is the features and
//! the planner, and how much the aggregation of a continuous world into
//! states.
//!
//! ```text
//! cargo run --release -p mcapi-experiments --example continuous_cells -- \
//!     --cells 26x11 --known-after 5 --gamma 0.88 --trials 4 --steps 20000 --seed 1
//! ```
//!
//! With `--nodes R`, the states are not a grid's cells but points the
//! agent observed: an observation farther than R from every node so far
//! becomes a node (at most W × H of them), and every observation is the
//! state of its nearest node. The states then follow where the robot can
//! be, not a grid laid over the walls.
//!
//! Prints one line a trial and the mean cumulative stimulus against the
//! discrete agent's on the map itself (computed on the same trials).

use std::sync::Arc;

use anyhow::{Context, bail};
use mcapi_core::{
    Agent, AgentParams, Basis, EnvModel, LearnedParams, Observation, Optimism, PlanningModel,
};
use mcapi_experiments::continuous::{ContinuousKind, ContinuousTrial, trial_metrics};
use mcapi_experiments::paper::trial_seeds;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

struct Options {
    cells: (usize, usize),
    nodes: Option<f64>,
    known_after: u32,
    gamma: f64,
    optimism: Optimism,
    trials: usize,
    steps: usize,
    seed: u64,
}

fn parse() -> anyhow::Result<Options> {
    let usage = "usage: continuous_cells [--cells WxH] [--known-after M] [--gamma G] \
                 [--nodes R] [--optimism absorbing|stimulus] [--trials N] [--steps N] \
                 [--seed N]";
    let mut o = Options {
        cells: (26, 11),
        nodes: None,
        known_after: 5,
        gamma: 0.88,
        optimism: Optimism::Absorbing,
        trials: 4,
        steps: 20_000,
        seed: 1,
    };
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut rest = args.iter();
    while let Some(flag) = rest.next() {
        let value = rest
            .next()
            .with_context(|| format!("{flag} needs a value; {usage}"))?;
        match flag.as_str() {
            "--cells" => {
                let (w, h) = value.split_once('x').context("--cells is WxH")?;
                o.cells = (w.parse().context("--cells")?, h.parse().context("--cells")?);
            }
            "--nodes" => o.nodes = Some(value.parse().context("--nodes")?),
            "--known-after" => o.known_after = value.parse().context("--known-after")?,
            "--gamma" => o.gamma = value.parse().context("--gamma")?,
            "--optimism" => o.optimism = serde_json::from_value(value.as_str().into())?,
            "--trials" => o.trials = value.parse().context("--trials")?,
            "--steps" => o.steps = value.parse().context("--steps")?,
            "--seed" => o.seed = value.parse().context("--seed")?,
            other => bail!("unknown flag {other:?}; {usage}"),
        }
    }
    let (w, h) = o.cells;
    anyhow::ensure!(
        (1..=512).contains(&w) && (1..=512).contains(&h),
        "--cells: 1..=512 each"
    );
    anyhow::ensure!(
        o.nodes.is_none_or(|r| r > 0.0 && r.is_finite()),
        "--nodes: a radius above 0"
    );
    anyhow::ensure!(
        o.trials > 0 && o.steps > 0,
        "--trials and --steps: at least 1"
    );
    Ok(o)
}

fn main() -> anyhow::Result<()> {
    let o = parse()?;
    let kind = ContinuousKind::ThreeRoom;
    let world = kind.world();
    let (w, h) = o.cells;
    let n = world.stimuli().len();
    let na = world.actions().len();
    // Every action valid in every cell; P is learned, so `next` is ignored.
    let next = (0..w * h).map(|s| vec![Some(s); na]).collect();
    let model = EnvModel::deterministic(next, world.actions(), world.stimuli())?;
    let ctx = Arc::new(PlanningModel::new(model, Basis::Indicator));
    let learned = LearnedParams {
        known_after: Some(o.known_after),
        optimism: Some(o.optimism),
    }
    .check()?;
    let trials = (0..o.trials)
        .into_par_iter()
        .map(|t| -> anyhow::Result<_> {
            let (world_seed, agent_seed) = trial_seeds(o.seed, t);
            let mut rng = ChaCha8Rng::seed_from_u64(world_seed);
            let params = AgentParams {
                gamma: Some(o.gamma),
                eta: Some(kind.gamma_eta().1),
                seed: Some(agent_seed),
                ..Default::default()
            }
            .check(n, agent_seed)?;
            let mut agent = Agent::new_learned(ctx.clone(), params, learned)?;
            let mut states = States::new(o.cells, o.nodes);
            let mut cell = |x: &[f64]| states.of(x);
            let mut x = world.start(&mut rng);
            let mut action = agent.step(&Observation::first(cell(&x)))?.action;
            let mut rec = ContinuousTrial {
                dims: n,
                d: 2,
                ..Default::default()
            };
            for _ in 0..o.steps {
                x = world.step(&x, action, &mut rng);
                let xi = world.stimulus(&x, &mut rng);
                let step = agent.step(&Observation::new(cell(&x), &xi))?;
                action = step.action;
                rec.points.extend_from_slice(&x);
                rec.stimulus.extend_from_slice(&xi);
                rec.abs_reward.push(step.reward);
                rec.drive.extend_from_slice(agent.drive().vector());
                rec.at_source
                    .push(world.source_at(&x).map_or(u8::MAX, |s| s as u8));
            }
            Ok(trial_metrics(&rec))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    for (t, m) in trials.iter().enumerate() {
        println!(
            "trial {t}: stimulus {:.0}, balance {:.2}, sources {} (all by tick {}), traversals {}",
            m["total_stimulus"],
            m["balance"],
            m["sources_found"],
            m["all_sources_found"],
            m["traversals"]
        );
    }
    let mean = trials.iter().map(|m| m["total_stimulus"]).sum::<f64>() / o.trials as f64;
    let reference =
        mcapi_experiments::continuous::discrete_reference_stimulus(o.trials, o.steps, o.seed)?;
    println!(
        "mean stimulus {mean:.0}; the discrete agent on the map {reference:.0}; ratio {:.3}",
        mean / reference
    );
    Ok(())
}

/// How an observation becomes a state: the cell of a `w × h` grid, or the
/// nearest of the nodes grown from the observations.
struct States {
    cells: (usize, usize),
    /// The nodes' radius, if the states are nodes.
    radius: Option<f64>,
    nodes: Vec<[f64; 2]>,
}

impl States {
    fn new(cells: (usize, usize), radius: Option<f64>) -> Self {
        Self {
            cells,
            radius,
            nodes: Vec::new(),
        }
    }

    fn of(&mut self, x: &[f64]) -> usize {
        let (w, h) = self.cells;
        let Some(radius) = self.radius else {
            let i = ((x[0] * w as f64) as usize).min(w - 1);
            let j = ((x[1] * h as f64) as usize).min(h - 1);
            return j * w + i;
        };
        let (mut best, mut nearest) = (f64::INFINITY, 0);
        for (i, n) in self.nodes.iter().enumerate() {
            let d = (n[0] - x[0]).hypot(n[1] - x[1]);
            if d < best {
                (best, nearest) = (d, i);
            }
        }
        if best > radius && self.nodes.len() < w * h {
            self.nodes.push([x[0], x[1]]);
            nearest = self.nodes.len() - 1;
        }
        nearest
    }
}
