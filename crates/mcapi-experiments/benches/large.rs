//! Large worlds (docs/algorithm.md §5, the sparse solver): open square grid maps of about 1,000,
//! 10,000 and 100,000 states (32², 100², 316²; five actions, two stimulus
//! sources in opposite corners), with the indicator basis.
//!
//! - `large/build/*`: from the map's text to an agent ready for its first
//!   observation (grid parsing, the model, the basis, the planning model and
//!   the agent's initial Ξ, D and π₀), what `POST /v1/sessions` pays.
//! - `large/tick/*`: one lockstep tick (Ξ, D and R updates, one policy
//!   evaluation and improvement, the next action) of an agent walking its
//!   world, after a warm-up.
//! - `large/build_pvf30/*`, `large/tick_pvf30/*`: the same with 30
//!   proto-value functions (150 features). Above 800 states they come from
//!   the sparse eigensolver (docs/algorithm.md §5); `dense_pvf30/1k` is the
//!   dense eigensolver at 1,024 states, for comparison. The 100k build takes
//!   tens of seconds per sample: `-- 'large/(build|tick)_pvf30/(1k|10k)'`
//!   skips it.
//! - `large/tick_pvf30_eps0.3/*`: the PVF tick of an ε-greedy agent
//!   (ε = 0.3), whose policy keeps changing.
//! - `large/tick_slip/*`: one tick on the slippery grid (slip 0.2, so P is
//!   stochastic: Gauss–Seidel on the indicator basis), after a short
//!   warm-up.
//! - `large/snapshot_{owned,borrowed}/{known,learned}_100k`: encoding the
//!   snapshot of an agent on the 100k grid (its known model, or the one it
//!   learns, counts included) as a durable store writes it (postcard, a
//!   record-version byte first), from a copy of the agent (`snapshot`,
//!   `learned_snapshot`) or from the agent borrowed (`snapshot_ref`,
//!   `learned_snapshot_ref`, into a buffer sized first, as the server's
//!   `durable::encode` does). The session's lock is held for this time.
//!
//! Run: `cargo bench -p mcapi-experiments --bench large`.

use std::hint::black_box;
use std::sync::Arc;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use mcapi_core::basis::{StateGraph, sparse_pvfs};
use mcapi_core::model::GridMap;
use mcapi_core::{
    Agent, AgentParams, Basis, BasisSpec, EnvModel, LearnedParams, Observation, PlanningModel,
};
use mcapi_experiments::paper::slippery;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[path = "support/encode.rs"]
mod encode;

const WARM_UP_TICKS: usize = 300;

/// An open `side` × `side` grid with sources `F` and `W` in opposite corners.
fn open_grid(side: usize) -> String {
    let mut rows: Vec<Vec<u8>> = vec![vec![b'.'; side]; side];
    rows[1][1] = b'F';
    rows[side - 2][side - 2] = b'W';
    let mut text = String::with_capacity(side * (side + 1));
    for row in rows {
        text.push_str(std::str::from_utf8(&row).expect("ascii"));
        text.push('\n');
    }
    text
}

/// A fresh agent on the map, as the server builds one; `slip` > 0 makes
/// the world slippery (stochastic P).
fn agent(text: &str, basis: &BasisSpec, slip: f64) -> (Agent, [usize; 2]) {
    agent_eps(text, basis, slip, 0.0)
}

/// [`agent`] with ε-greedy exploration.
fn agent_eps(text: &str, basis: &BasisSpec, slip: f64, epsilon: f64) -> (Agent, [usize; 2]) {
    let grid = GridMap::from_text(text).expect("grid");
    let sources = [
        grid.mark_state('F').expect("F"),
        grid.mark_state('W').expect("W"),
    ];
    let mut model = grid
        .model(vec!["food".into(), "water".into()])
        .expect("model");
    if slip > 0.0 {
        model = slippery(&model, slip).expect("slippery");
    }
    (agent_on(model, basis, epsilon), sources)
}

fn agent_on(model: EnvModel, basis: &BasisSpec, epsilon: f64) -> Agent {
    let basis = Basis::build(basis, &model).expect("basis");
    let ctx = Arc::new(PlanningModel::new(model, basis));
    let params = AgentParams {
        seed: Some(7),
        epsilon: Some(epsilon),
        ..Default::default()
    }
    .check(2, 0)
    .expect("params");
    Agent::new(ctx, params)
}

/// An agent and where it stands, walking its grid (sampling P when it is
/// stochastic).
struct Walk {
    agent: Agent,
    sources: [usize; 2],
    state: usize,
    started: bool,
    rng: ChaCha8Rng,
}

impl Walk {
    fn new((agent, sources): (Agent, [usize; 2])) -> Self {
        let state = agent.planning_model().model().states() / 2;
        Self {
            agent,
            sources,
            state,
            started: false,
            rng: ChaCha8Rng::seed_from_u64(11),
        }
    }

    fn warm_up(mut self, ticks: usize) -> Self {
        for _ in 0..ticks {
            self.tick();
        }
        self
    }

    fn tick(&mut self) {
        let stimulus = match self.state {
            s if s == self.sources[0] => [6.0, 0.0],
            s if s == self.sources[1] => [0.0, 6.0],
            _ => [0.0, 0.0],
        };
        let step = self
            .agent
            .step(&Observation {
                state: self.state,
                stimulus: self.started.then_some(&stimulus[..]),
                action_taken: None,
            })
            .expect("tick");
        self.started = true;
        let model = self.agent.planning_model().model();
        let pair = model.pair(self.state, step.action).expect("advised pair");
        let (next, p) = model.successors(pair);
        let mut u: f64 = self.rng.random();
        self.state = next[next.len() - 1] as usize;
        for (&t, &q) in next.iter().zip(p) {
            if u < q {
                self.state = t as usize;
                break;
            }
            u -= q;
        }
    }
}

const PVF30: BasisSpec = BasisSpec::ProtoValue { k: 30 };

fn bench_large(c: &mut Criterion) {
    let sizes = [("1k", 32), ("10k", 100), ("100k", 316)];
    let mut group = c.benchmark_group("large");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(5));
    for (name, side) in sizes {
        let text = open_grid(side);
        group.bench_function(BenchmarkId::new("build", name), |b| {
            b.iter(|| black_box(agent(&text, &BasisSpec::Indicator, 0.0)));
        });
        let mut walk = Walk::new(agent(&text, &BasisSpec::Indicator, 0.0)).warm_up(WARM_UP_TICKS);
        group.bench_function(BenchmarkId::new("tick", name), |b| b.iter(|| walk.tick()));
        group.bench_function(BenchmarkId::new("build_pvf30", name), |b| {
            b.iter(|| black_box(agent(&text, &PVF30, 0.0)));
        });
        let mut walk = Walk::new(agent(&text, &PVF30, 0.0)).warm_up(WARM_UP_TICKS);
        group.bench_function(BenchmarkId::new("tick_pvf30", name), |b| {
            b.iter(|| walk.tick())
        });
        // The greedy PVF agent soon stops moving (docs/algorithm.md §6), so
        // its ticks reuse A's factorisation; with ε = 0.3 it keeps moving
        // and its policy keeps changing (rank-one updates and rebuilds).
        let mut walk = Walk::new(agent_eps(&text, &PVF30, 0.0, 0.3)).warm_up(WARM_UP_TICKS);
        group.bench_function(BenchmarkId::new("tick_pvf30_eps0.3", name), |b| {
            b.iter(|| walk.tick())
        });
        let mut walk = Walk::new(agent(&text, &BasisSpec::Indicator, 0.2)).warm_up(20);
        group.bench_function(BenchmarkId::new("tick_slip", name), |b| {
            b.iter(|| walk.tick())
        });
    }
    let text = open_grid(32);
    let model = GridMap::from_text(&text)
        .expect("grid")
        .model(vec!["food".into(), "water".into()])
        .expect("model");
    // The dense eigensolver on the 1k grid (what `build_pvf30/1k` paid
    // before the sparse one), and the sparse one alone.
    group.bench_function(BenchmarkId::new("dense_pvf30", "1k"), |b| {
        b.iter(|| black_box(StateGraph::of(&model).dense_laplacian().symmetric_eigen()));
    });
    group.bench_function(BenchmarkId::new("sparse_pvf30", "1k"), |b| {
        b.iter(|| black_box(sparse_pvfs(&StateGraph::of(&model), 30).expect("pvfs")));
    });
    group.finish();
}

fn bench_snapshots(c: &mut Criterion) {
    let text = open_grid(316);
    let known = Walk::new(agent(&text, &BasisSpec::Indicator, 0.0)).warm_up(WARM_UP_TICKS);
    let (plain, sources) = agent(&text, &BasisSpec::Indicator, 0.0);
    let ctx = Arc::clone(plain.planning_model());
    let learned = Agent::new_learned(
        ctx,
        plain.params().clone(),
        LearnedParams::default().check().expect("learned params"),
    )
    .expect("learned agent");
    let learned = Walk::new((learned, sources)).warm_up(WARM_UP_TICKS);
    let (known, learned) = (&known.agent, &learned.agent);
    assert!(encode::growing(&known.snapshot()) == encode::sized(&known.snapshot_ref()));
    let owned = || learned.learned_snapshot().expect("learned");
    let borrowed = || learned.learned_snapshot_ref().expect("learned");
    assert!(
        encode::growing(&owned()) == encode::sized(&borrowed()),
        "the same bytes"
    );
    let mut group = c.benchmark_group("large");
    group.sample_size(20);
    group.bench_function(BenchmarkId::new("snapshot_owned", "known_100k"), |b| {
        b.iter(|| black_box(encode::growing(&known.snapshot())))
    });
    group.bench_function(BenchmarkId::new("snapshot_borrowed", "known_100k"), |b| {
        b.iter(|| black_box(encode::sized(&known.snapshot_ref())))
    });
    group.bench_function(BenchmarkId::new("snapshot_owned", "learned_100k"), |b| {
        b.iter(|| black_box(encode::growing(&owned())))
    });
    group.bench_function(BenchmarkId::new("snapshot_borrowed", "learned_100k"), |b| {
        b.iter(|| black_box(encode::sized(&borrowed())))
    });
    group.finish();
}

criterion_group!(benches, bench_snapshots, bench_large);
criterion_main!(benches);
