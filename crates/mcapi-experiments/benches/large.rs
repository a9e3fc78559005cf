//! Large worlds (issue 17, item 3): open square grid maps of about 1,000,
//! 10,000 and 100,000 states (32², 100², 316²; five actions, two stimulus
//! sources in opposite corners), with the indicator basis.
//!
//! - `large/build/*`: from the map's text to an agent ready for its first
//!   observation (grid parsing, the model, the basis, the planning model and
//!   the agent's initial Ξ, D and π₀), what `POST /v1/sessions` pays.
//! - `large/tick/*`: one lockstep tick (Ξ, D and R updates, one policy
//!   evaluation and improvement, the next action) of an agent walking its
//!   world, after a warm-up.
//! - `large/build_pvf30/1k`: the dense proto-value basis at 1,024 states, for
//!   comparison (the dense eigensolver is O(|S|³), which is why the server
//!   caps proto-value models at `max_pvf_states`).
//!
//! Run: `cargo bench -p mcapi-experiments --bench large`.

use std::hint::black_box;
use std::sync::Arc;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use mcapi_core::model::GridMap;
use mcapi_core::{Agent, AgentParams, Basis, BasisSpec, Observation, PlanningModel};

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

/// A fresh agent on the map, as the server builds one.
fn agent(text: &str, basis: &BasisSpec) -> (Agent, [usize; 2]) {
    let grid = GridMap::from_text(text).expect("grid");
    let sources = [
        grid.mark_state('F').expect("F"),
        grid.mark_state('W').expect("W"),
    ];
    let model = grid
        .model(vec!["food".into(), "water".into()])
        .expect("model");
    let basis = Basis::build(basis, &model).expect("basis");
    let ctx = Arc::new(PlanningModel::new(model, basis));
    let params = AgentParams {
        seed: Some(7),
        ..Default::default()
    }
    .check(2, 0)
    .expect("params");
    (Agent::new(ctx, params), sources)
}

/// An agent and where it stands, walking its grid.
struct Walk {
    agent: Agent,
    sources: [usize; 2],
    state: usize,
    started: bool,
}

impl Walk {
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
        self.state = model.next_state(pair);
    }
}

fn bench_large(c: &mut Criterion) {
    let sizes = [("1k", 32), ("10k", 100), ("100k", 316)];
    let mut group = c.benchmark_group("large");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(5));
    for (name, side) in sizes {
        let text = open_grid(side);
        group.bench_function(BenchmarkId::new("build", name), |b| {
            b.iter(|| black_box(agent(&text, &BasisSpec::Indicator)));
        });
        let (agent, sources) = agent(&text, &BasisSpec::Indicator);
        let start = agent.planning_model().model().states() / 2;
        let mut walk = Walk {
            agent,
            sources,
            state: start,
            started: false,
        };
        for _ in 0..WARM_UP_TICKS {
            walk.tick();
        }
        group.bench_function(BenchmarkId::new("tick", name), |b| b.iter(|| walk.tick()));
    }
    let text = open_grid(32);
    group.bench_function(BenchmarkId::new("build_pvf30", "1k"), |b| {
        b.iter(|| black_box(agent(&text, &BasisSpec::ProtoValue { k: 30 })));
    });
    group.finish();
}

criterion_group!(benches, bench_large);
criterion_main!(benches);
