//! The cost of one lockstep tick of the continuous agent (docs/algorithm.md
//! §9.5): Ξ's RLS step, D, the transition stored, R over the stored
//! transitions, one LSTDQ evaluation, one greedy improvement of every
//! stored successor, the next action.
//!
//! Each iteration is a real tick of an agent living in its world, after
//! a warm-up long enough to fill the sample store:
//! - `hallway_d1`: the continuous hallway on 64 RBFs × 3 actions;
//! - `three_room_d2`: the continuous three-room on 8 × 8 RBFs × 4 actions
//!   (the default bases of d = 1 and 2 before the grid planner);
//! - `hallway_d1_grid`, `three_room_d2_grid`: the same worlds on their
//!   default, the grid planner (docs/algorithm.md §9.8: 64 cells per
//!   dimension, one exact evaluation and improvement over every cell);
//! - `three_room_d2_pvf`: the same on 75 PVFs × 4 actions (the basis is
//!   rebuilt as its graph grows; `rebuild` below times one rebuild alone);
//! - `box_d8`: a point in [0, 1]^8 moved by 16 actions (each axis, either
//!   way), sources in a corner and at the centre; default basis (for 16
//!   actions: Fourier of order 2, uncoupled, 17 features a block).
//!
//! - `snapshot_1936_owned`, `snapshot_1936_borrowed`: encoding the
//!   snapshot of an agent on 22 × 22 RBFs × 4 actions (k|A| = 1936, an
//!   A⁻¹ of 30 MiB) as a durable store did before, a copy of the agent
//!   encoded into a growing buffer, and as it does now, the agent borrowed
//!   ([`ContinuousAgent::snapshot_ref`]) and encoded into a buffer sized
//!   by a counting pass first.
//!
//! Run: `cargo bench --bench continuous`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use mcapi_core::AgentParams;
use mcapi_core::continuous::{
    ContinuousAgent, ContinuousBasisSpec, ContinuousObservation, ContinuousSpec, ObservationSpace,
};
use mcapi_experiments::continuous::{World, spec_of};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

#[path = "support/encode.rs"]
mod encode;

/// Ticks before measuring; few when `cargo test --all-targets` runs the
/// bench once as a test (a debug build), so `make test` stays quick.
const WARM_UP_TICKS: usize = if cfg!(debug_assertions) { 100 } else { 3000 };

/// A world to step: the experiments' worlds or the 8-dimensional box.
enum Bench {
    World(World),
    /// A world on a basis other than its default.
    WorldOn(World, ContinuousBasisSpec),
    Box8,
}

impl Bench {
    fn spec(&self) -> ContinuousSpec {
        match self {
            Self::World(w) => spec_of(w),
            Self::WorldOn(w, basis) => ContinuousSpec {
                basis: Some(basis.clone()),
                ..spec_of(w)
            },
            Self::Box8 => ContinuousSpec {
                observation_space: ObservationSpace {
                    low: vec![0.0; 8],
                    high: vec![1.0; 8],
                },
                actions: (0..16).map(|i| format!("a{i}")).collect(),
                stimuli: vec!["corner".into(), "centre".into()],
                basis: None,
                out_of_bounds: Default::default(),
                samples: Default::default(),
            },
        }
    }

    fn start(&self, rng: &mut ChaCha8Rng) -> Vec<f64> {
        match self {
            Self::World(w) | Self::WorldOn(w, _) => w.start(rng),
            Self::Box8 => (0..8).map(|_| rng.random::<f64>()).collect(),
        }
    }

    fn step(&self, x: &[f64], a: usize, rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<f64>) {
        match self {
            Self::World(w) | Self::WorldOn(w, _) => {
                let next = w.step(x, a, rng);
                let xi = w.stimulus(&next, rng);
                (next, xi)
            }
            Self::Box8 => {
                let noise = Normal::new(0.0, 0.005).expect("σ > 0");
                let mut next = x.to_vec();
                let sign = if a % 2 == 0 { -1.0 } else { 1.0 };
                next[a / 2] += sign * 0.05;
                for v in next.iter_mut() {
                    *v = (*v + noise.sample(rng)).clamp(0.0, 1.0);
                }
                let corner = next.iter().all(|v| *v < 0.2);
                let centre = next.iter().all(|v| (v - 0.5).abs() < 0.2);
                (
                    next,
                    vec![
                        if corner { 6.0 } else { 0.0 },
                        if centre { 6.0 } else { 0.0 },
                    ],
                )
            }
        }
    }
}

struct Running {
    bench: Bench,
    agent: ContinuousAgent,
    rng: ChaCha8Rng,
    x: Vec<f64>,
    action: usize,
}

impl Running {
    fn new(bench: Bench) -> Self {
        let spec = bench.spec();
        let n = spec.stimuli.len();
        let params = AgentParams {
            seed: Some(7),
            ..Default::default()
        }
        .check(n, 7)
        .expect("params");
        let mut agent = ContinuousAgent::new(spec.build().expect("model"), params);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let x = bench.start(&mut rng);
        let action = agent
            .step(&ContinuousObservation {
                observation: &x,
                stimulus: None,
                action_taken: None,
            })
            .expect("first step")
            .action;
        let mut run = Self {
            bench,
            agent,
            rng,
            x,
            action,
        };
        for _ in 0..WARM_UP_TICKS {
            run.tick();
        }
        run
    }

    fn tick(&mut self) -> usize {
        let (x, xi) = self.bench.step(&self.x, self.action, &mut self.rng);
        self.x = x;
        let step = self
            .agent
            .step(&ContinuousObservation {
                observation: &self.x,
                stimulus: Some(&xi),
                action_taken: None,
            })
            .expect("tick");
        self.action = step.action;
        step.action
    }
}

fn bench_continuous(c: &mut Criterion) {
    let mut group = c.benchmark_group("continuous");
    for (name, bench) in [
        ("hallway_d1", Bench::WorldOn(World::hallway(), rbf(64))),
        ("three_room_d2", Bench::WorldOn(World::three_room(), rbf(8))),
        ("hallway_d1_grid", Bench::World(World::hallway())),
        ("three_room_d2_grid", Bench::World(World::three_room())),
        (
            "three_room_d2_pvf",
            Bench::WorldOn(World::three_room(), pvf()),
        ),
        ("box_d8", Bench::Box8),
    ] {
        let mut run = Running::new(bench);
        group.bench_function(name, |b| b.iter(|| black_box(run.tick())));
    }
    // One basis rebuild alone: a copy of the warmed-up agent whose graph
    // has just grown is planned once, against a copy that is not due.
    let run = Running::new(Bench::WorldOn(World::three_room(), pvf()));
    group.bench_function("three_room_d2_pvf_rebuild", |b| {
        b.iter_batched(
            || run.agent.clone(),
            |mut agent| black_box(agent.force_basis_rebuild()),
            criterion::BatchSize::LargeInput,
        )
    });
    group.finish();
    bench_snapshot(c);
}

/// Ticks of the agent whose snapshot is encoded: its A⁻¹ is dense from the
/// start, so the size hardly depends on them.
const SNAPSHOT_TICKS: usize = if cfg!(debug_assertions) { 3 } else { 40 };

fn bench_snapshot(c: &mut Criterion) {
    let spec = ContinuousSpec {
        basis: Some(rbf(22)),
        ..spec_of(&World::three_room())
    };
    let params = AgentParams {
        seed: Some(7),
        ..Default::default()
    }
    .check(spec.stimuli.len(), 7)
    .expect("params");
    let mut agent = ContinuousAgent::new(spec.build().expect("model"), params);
    let world = World::three_room();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut x = world.start(&mut rng);
    let mut stimulus = None;
    for _ in 0..SNAPSHOT_TICKS {
        let step = agent
            .step(&ContinuousObservation {
                observation: &x,
                stimulus: stimulus.as_deref(),
                action_taken: None,
            })
            .expect("tick");
        x = world.step(&x, step.action, &mut rng);
        stimulus = Some(world.stimulus(&x, &mut rng));
    }
    let owned = |agent: &ContinuousAgent| encode::growing(&agent.snapshot());
    let borrowed = |agent: &ContinuousAgent| encode::sized(&agent.snapshot_ref());
    assert!(owned(&agent) == borrowed(&agent), "the same bytes");
    let mut group = c.benchmark_group("continuous");
    group.sample_size(20);
    group.bench_function("snapshot_1936_owned", |b| {
        b.iter(|| black_box(owned(&agent)))
    });
    group.bench_function("snapshot_1936_borrowed", |b| {
        b.iter(|| black_box(borrowed(&agent)))
    });
    group.finish();
}

/// Normalised RBFs, `c` centres per dimension.
fn rbf(c: u32) -> ContinuousBasisSpec {
    ContinuousBasisSpec::Rbf {
        centres_per_dim: c,
        width: None,
    }
}

/// 75 PVFs × 4 actions: 300 state-action features, as the default aims at.
fn pvf() -> ContinuousBasisSpec {
    ContinuousBasisSpec::Pvf {
        k: 75,
        nodes: None,
        neighbours: None,
    }
}

criterion_group!(benches, bench_continuous);
criterion_main!(benches);
