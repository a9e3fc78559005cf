//! The distribution of one lockstep tick's cost on the continuous
//! three-room (docs/algorithm.md §9.5), tick by tick, where criterion
//! (`benches/continuous.rs`) reports means over batches of ticks.
//!
//! ```text
//! cargo run --release -p mcapi-experiments --example continuous_tick -- [TICKS]
//! ```
//!
//! Runs the agent on 8 × 8 RBFs × 4 actions (the default basis of d = 2
//! before the grid planner; the sample store's default) for TICKS ticks (default 12,000), times each `step` of the last
//! quarter (the store is full by then), and prints the store's state every
//! 1000 ticks, then the median, 90th and 99th percentiles.

use mcapi_core::AgentParams;
use mcapi_core::continuous::{ContinuousAgent, ContinuousBasisSpec, ContinuousObservation};
use mcapi_experiments::continuous::{World, spec_of};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn main() -> anyhow::Result<()> {
    let ticks: usize = match std::env::args().nth(1) {
        Some(t) => t.parse()?,
        None => 12_000,
    };
    anyhow::ensure!(ticks >= 4, "TICKS must be at least 4");
    let world = World::three_room();
    let params = AgentParams {
        seed: Some(7),
        ..Default::default()
    }
    .check(world.stimuli().len(), 7)?;
    let mut spec = spec_of(&world);
    spec.basis = Some(ContinuousBasisSpec::Rbf {
        centres_per_dim: 8,
        width: None,
    });
    let mut agent = ContinuousAgent::new(spec.build()?, params);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut x = world.start(&mut rng);
    let mut action = agent
        .step(&ContinuousObservation {
            observation: &x,
            stimulus: None,
            action_taken: None,
        })?
        .action;
    let mut last = agent.stats();
    let mut times = Vec::with_capacity(ticks / 4 + 1);
    for t in 1..=ticks {
        x = world.step(&x, action, &mut rng);
        let xi = world.stimulus(&x, &mut rng);
        let start = std::time::Instant::now();
        action = agent
            .step(&ContinuousObservation {
                observation: &x,
                stimulus: Some(&xi),
                action_taken: None,
            })?
            .action;
        if t > ticks - ticks / 4 {
            times.push(start.elapsed().as_secs_f64() * 1e3);
        }
        if t % 1000 == 0 {
            let s = agent.stats();
            println!(
                "tick {t}: {} transitions stored, {} (cell, action) slots, {:.1} rank-one updates a tick, {} rebuilds",
                s.samples,
                s.slots,
                (s.updates - last.updates) as f64 / 1000.0,
                s.rebuilds - last.rebuilds
            );
            last = s;
        }
    }
    times.sort_by(f64::total_cmp);
    let at = |q: f64| times[((times.len() - 1) as f64 * q) as usize];
    println!(
        "one tick, the last {} ticks: median {:.3} ms, p90 {:.3} ms, p99 {:.3} ms",
        times.len(),
        at(0.5),
        at(0.9),
        at(0.99)
    );
    Ok(())
}
