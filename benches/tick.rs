//! The cost of one full MCA-PI tick (Ξ, D, R update, one LSTDQ evaluation,
//! greedy improvement, next action) in the paper's worlds.
//!
//! Each iteration is a real tick of an agent living in its world: the world
//! moves the agent and delivers the stimulus, the agent steps. Agents are
//! warmed up first so the policy is in its steady regime (drives switching,
//! factorisation reused on some ticks and updated on others).
//!
//! Run: `cargo bench --bench tick`.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use mcapi::algo::{AgentParams, Basis, BasisSpec, PlanningModel};
use mcapi::experiments::paper::Simulation;
use mcapi::experiments::{Experiment, ExperimentKind};

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

criterion_group!(benches, bench_tick);
criterion_main!(benches);
