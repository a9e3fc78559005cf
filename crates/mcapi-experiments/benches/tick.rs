//! The cost of one full MCA-PI tick (Ξ, D, R update, one LSTDQ evaluation,
//! greedy improvement, next action) in the paper's worlds.
//!
//! Each iteration is a real tick of an agent living in its world: the world
//! moves the agent and delivers the stimulus, the agent steps. Agents are
//! warmed up first so the policy is in its steady regime (drives switching,
//! factorisation reused on some ticks and updated on others).
//!
//! The `curiosity` group prices the intMCA channel (docs/algorithm.md §7): a
//! curious agent standing at a signal source, learning a book sample every
//! tick (freezing disabled, so every tick pays for slow-feature learning),
//! against the plain agent on the same observations.
//!
//! The `lstdq` group prices one full feature-basis evaluation (b = ΦᵀR,
//! w = A⁻¹b, Q = Φw, the LSTDQ error and the greedy scan) on its own: the
//! warmed-up 30-PVF maze agent's planner, fed its own R and a copy nudged in
//! one entry in turn, so R changes on every update and the evaluation is
//! never skipped (the greedy agent of `tick/three_room_pvf30` has stopped
//! moving, so its R, and with it Q, stays the same bit for bit from tick to
//! tick and the planner skips the evaluation).
//!
//! Run: `cargo bench --bench tick`.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use mcapi_core::model::hallway;
use mcapi_core::{
    Agent, AgentParams, Basis, BasisSpec, CuriosityParams, CuriousAgent, CuriousObservation,
    Eq6Source, Observation, Planner, PlanningModel, Signals,
};
use mcapi_experiments::paper::Simulation;
use mcapi_experiments::{Experiment, ExperimentKind};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const WARM_UP_TICKS: usize = 2000;

fn simulation<'a>(exp: &'a Experiment, basis: &BasisSpec, epsilon: f64) -> Simulation<'a> {
    let model = exp.preset.model.clone();
    let basis = Basis::build(basis, &model).expect("basis");
    let ctx = Arc::new(PlanningModel::new(model, basis));
    let params = AgentParams {
        eta: Some(exp.eta),
        gamma: Some(exp.gamma),
        epsilon: Some(epsilon),
        seed: Some(7),
        ..Default::default()
    }
    .check(exp.dims(), 7)
    .expect("params");
    let mut sim = Simulation::new(exp, ctx, params, 11).expect("simulation");
    for _ in 0..WARM_UP_TICKS {
        sim.tick().expect("warm-up tick");
    }
    sim
}

fn bench_tick(c: &mut Criterion) {
    let hallway = Experiment::new(ExperimentKind::Hallway);
    let maze = Experiment::new(ExperimentKind::ThreeRoom);
    let setups: [(&str, &Experiment, BasisSpec, f64); 4] = [
        ("hallway_indicator", &hallway, BasisSpec::Indicator, 0.0),
        ("three_room_indicator", &maze, BasisSpec::Indicator, 0.0),
        (
            "three_room_pvf30",
            &maze,
            BasisSpec::ProtoValue { k: 30 },
            0.0,
        ),
        (
            "three_room_pvf30_eps0.3",
            &maze,
            BasisSpec::ProtoValue { k: 30 },
            0.3,
        ),
    ];
    let mut group = c.benchmark_group("tick");
    for (name, exp, basis, epsilon) in setups {
        let mut sim = simulation(exp, &basis, epsilon);
        group.bench_function(name, |b| b.iter(|| black_box(sim.tick().expect("tick"))));
    }
    // The hallway tick again, with 10,000 agents stepped in turn as a
    // server's group step touches them: when an agent's turn comes, none
    // of its state is in any cache any more (10,000 agents of about 9 KiB
    // are beyond L3), so this is the tick when its memory comes from DRAM.
    let model = hallway.preset.model.clone();
    let basis = Basis::build(&BasisSpec::Indicator, &model).expect("basis");
    let ctx = Arc::new(PlanningModel::new(model, basis));
    // `cargo test --all-targets` runs each bench once, unoptimised: a few
    // agents then (the bench measures only when run with `--bench`).
    let measuring = std::env::args().any(|a| a == "--bench");
    let agents = if measuring { MANY_AGENTS } else { 16 };
    let mut many: Vec<Simulation<'_>> = (0..agents as u64)
        .map(|i| {
            let params = AgentParams {
                eta: Some(hallway.eta),
                gamma: Some(hallway.gamma),
                seed: Some(i),
                ..Default::default()
            }
            .check(hallway.dims(), i)
            .expect("params");
            let mut sim =
                Simulation::new(&hallway, Arc::clone(&ctx), params, i).expect("simulation");
            for _ in 0..MANY_WARM_UP_TICKS {
                sim.tick().expect("warm-up tick");
            }
            sim
        })
        .collect();
    let mut turn = 0;
    group.bench_function("hallway_indicator_10000_agents", |b| {
        b.iter(|| {
            turn = (turn + 1) % many.len();
            black_box(many[turn].tick().expect("tick"))
        })
    });
    // The same, with the next agent's tables prefetched before each tick,
    // as a group step does.
    group.bench_function("hallway_indicator_10000_agents_prefetched", |b| {
        b.iter(|| {
            turn = (turn + 1) % many.len();
            mcapi_core::prefetch::value(&many[(turn + 2) % many.len()]);
            many[(turn + 1) % many.len()].agent().prefetch();
            black_box(many[turn].tick().expect("tick"))
        })
    });
    group.finish();
}

/// Agents of `tick/hallway_indicator_10000_agents`, and their warm-up.
const MANY_AGENTS: usize = 10_000;
const MANY_WARM_UP_TICKS: usize = 200;

fn bench_evaluation(c: &mut Criterion) {
    let maze = Experiment::new(ExperimentKind::ThreeRoom);
    let sim = simulation(&maze, &BasisSpec::ProtoValue { k: 30 }, 0.0);
    let agent = sim.agent();
    let ctx = Arc::clone(agent.planning_model());
    let mut planner = Planner::new(&ctx, agent.planner().policy().to_vec());
    let r = agent.rewards().to_vec();
    let mut nudged = r.clone();
    nudged[0] *= 1.0 + 1e-9;
    let inputs = [r, nudged];
    let (gamma, ridge) = (agent.params().gamma, agent.params().ridge);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut t = 0usize;
    let mut update = move || {
        t += 1;
        planner
            .update(&ctx, &inputs[t % 2], gamma, ridge, &mut rng)
            .expect("update")
    };
    for _ in 0..10 {
        update();
    }
    let mut group = c.benchmark_group("lstdq");
    group.bench_function("three_room_pvf30_evaluation", |b| {
        b.iter(|| black_box(update()))
    });
    group.finish();
}

/// The hallway's state where the signal is delivered.
const SOURCE: usize = 25;
const STAY: usize = 2;

fn bench_curiosity(c: &mut Criterion) {
    let params = |n| {
        AgentParams {
            seed: Some(7),
            ..Default::default()
        }
        .check(n, 7)
        .expect("params")
    };
    let plain_model = hallway().model;
    let curious_model = plain_model
        .clone()
        .with_stimulus("curiosity")
        .expect("curiosity dimension");
    let never_freeze = CuriosityParams {
        freeze_after: u32::MAX,
        ..CuriosityParams::default()
    }
    .check()
    .expect("curiosity params");
    let mut curious = CuriousAgent::new(
        Arc::new(PlanningModel::new(curious_model, Basis::Indicator)),
        params(3),
        never_freeze,
        2,
    )
    .expect("curious agent");
    let mut plain = Agent::new(
        Arc::new(PlanningModel::new(plain_model, Basis::Indicator)),
        params(2),
    );
    curious
        .step(&CuriousObservation::first(SOURCE))
        .expect("first");
    plain.step(&Observation::first(SOURCE)).expect("first");
    let mut signals = Signals::new(0.08);
    let extrinsic = [0.0, 0.0];
    let mut curious_tick = move || {
        let x = signals.next(Eq6Source::Book);
        let obs = CuriousObservation {
            action_taken: Some(STAY),
            ..CuriousObservation::new(SOURCE, &extrinsic, Some((0, &x)))
        };
        curious.step(&obs).expect("curious tick")
    };
    let mut plain_tick = move || {
        let obs = Observation {
            action_taken: Some(STAY),
            ..Observation::new(SOURCE, &extrinsic)
        };
        plain.step(&obs).expect("plain tick")
    };
    for _ in 0..WARM_UP_TICKS {
        curious_tick();
        plain_tick();
    }
    let mut group = c.benchmark_group("curiosity");
    group.bench_function("hallway_plain_tick", |b| b.iter(|| black_box(plain_tick())));
    group.bench_function("hallway_curious_tick_learning", |b| {
        b.iter(|| black_box(curious_tick()))
    });
    group.finish();
}

criterion_group!(benches, bench_tick, bench_evaluation, bench_curiosity);
criterion_main!(benches);
