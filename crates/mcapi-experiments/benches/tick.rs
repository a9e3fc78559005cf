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
//! Run: `cargo bench --bench tick`.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use mcapi_core::model::hallway;
use mcapi_core::{
    Agent, AgentParams, Basis, BasisSpec, CuriosityParams, CuriousAgent, CuriousObservation,
    Eq6Source, Observation, PlanningModel, Signals,
};
use mcapi_experiments::paper::Simulation;
use mcapi_experiments::{Experiment, ExperimentKind};

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

criterion_group!(benches, bench_tick, bench_curiosity);
criterion_main!(benches);
