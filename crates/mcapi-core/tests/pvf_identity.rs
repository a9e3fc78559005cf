//! Bit-for-bit pins of the feature engine (docs/algorithm.md §5, engine 3)
//! on the three-room maze with 30 proto-value functions (150 features).
//!
//! The feature kernels (b = ΦᵀR, w = A⁻¹b, Q = Φw of §2.6) are tuned for
//! speed under one rule: every CPU and every version of the kernels must
//! produce the same bits, so a seed gives the same trajectory everywhere.
//! These tests run a few hundred ticks of an agent in the maze (the world of
//! Experiment 2: a noisy stimulus of 6 at each source, 0 elsewhere) and
//! compare a hash of everything the agent reported per tick (action, |r|,
//! LSTDQ error, policy changes), the final D and Q, and the planner's work
//! counters to values recorded from the reference kernels (commit 15aa12d).
//! The greedy run covers the rebuild and reuse paths, the ε = 0.3 run the
//! Sherman–Morrison path as well.

use std::sync::Arc;

use mcapi_core::lstdq::PlannerStats;
use mcapi_core::model::three_room;
use mcapi_core::{Agent, AgentParams, Basis, BasisSpec, Observation, PlanningModel};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// What a run is pinned by.
#[derive(Debug, PartialEq, Eq)]
struct Pins {
    /// FNV-1a over (action, |r| bits, LSTDQ error bits, policy changes) of every tick.
    trace: u64,
    /// The bits of D at the end.
    drive: Vec<u64>,
    /// FNV-1a over the bits of Q at the end.
    q: u64,
    /// Q of the first three pairs, as bits.
    q_head: [u64; 3],
    /// The planner's counters.
    stats: PlannerStats,
}

fn fnv(h: &mut u64, x: u64) {
    for byte in x.to_le_bytes() {
        *h ^= u64::from(byte);
        *h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
}

const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;

/// `ticks` ticks of a 30-PVF agent (γ = 0.85, η = 0.01, seed 7) in the
/// three-room maze, world seed 11.
fn run(epsilon: f64, ticks: usize) -> Pins {
    let preset = three_room();
    let model = preset.model.clone();
    let basis = Basis::build(&BasisSpec::ProtoValue { k: 30 }, &model).expect("basis");
    let ctx = Arc::new(PlanningModel::new(model.clone(), basis));
    let params = AgentParams {
        eta: Some(0.01),
        gamma: Some(0.85),
        epsilon: Some(epsilon),
        seed: Some(7),
        ..Default::default()
    }
    .check(model.n_stimuli(), 7)
    .expect("params");
    let mut agent = Agent::new(ctx, params);
    let mut world = ChaCha8Rng::seed_from_u64(11);
    let mut state = preset.sources[0].state;
    let mut action = agent
        .step(&Observation::first(state))
        .expect("first")
        .action;
    let mut xi = vec![0.0; model.n_stimuli()];
    let mut trace = FNV_OFFSET;
    for _ in 0..ticks {
        let pair = model.pair(state, action).expect("advised action is valid");
        state = model.sample_next(pair, world.random());
        xi.fill(0.0);
        for src in preset.sources.iter().filter(|src| src.state == state) {
            let noise: f64 = StandardNormal.sample(&mut world);
            xi[src.dim] = 6.0 + 2.0 * noise;
        }
        let step = agent.step(&Observation::new(state, &xi)).expect("tick");
        action = step.action;
        let plan = step.plan.expect("every tick after the first plans");
        fnv(&mut trace, action as u64);
        fnv(&mut trace, step.reward.to_bits());
        fnv(&mut trace, plan.lstdq_error.to_bits());
        fnv(&mut trace, plan.policy_changes as u64);
    }
    let q_all = agent.planner().q();
    let mut q = FNV_OFFSET;
    for x in q_all {
        fnv(&mut q, x.to_bits());
    }
    Pins {
        trace,
        drive: agent.drive().vector().iter().map(|x| x.to_bits()).collect(),
        q,
        q_head: [q_all[0].to_bits(), q_all[1].to_bits(), q_all[2].to_bits()],
        stats: agent.planner().stats(),
    }
}

#[test]
fn greedy_pvf30_three_room_is_bit_identical_to_the_reference() {
    let got = run(0.0, 400);
    let want = Pins {
        trace: 5_542_520_890_004_742_212,
        drive: vec![
            4_592_938_826_116_988_315,
            4_606_124_547_282_374_419,
            4_601_885_766_019_014_222,
        ],
        q: 13_715_599_468_907_808_741,
        q_head: [
            4_610_032_493_630_043_378,
            4_610_263_924_327_556_584,
            4_609_929_968_488_967_189,
        ],
        stats: PlannerStats {
            updates: 400,
            reuses: 393,
            factorisations: 3,
            rank_one_updates: 59,
            ridge_used: 0,
        },
    };
    assert_eq!(got, want);
}

#[test]
fn epsilon_pvf30_three_room_is_bit_identical_to_the_reference() {
    let got = run(0.3, 400);
    let want = Pins {
        trace: 9_000_995_518_732_218_000,
        drive: vec![
            4_563_528_142_978_113_617,
            4_606_177_474_877_875_233,
            4_601_940_456_807_544_064,
        ],
        q: 3_734_495_785_756_090_340,
        q_head: [
            4_609_897_454_854_907_296,
            4_610_211_403_776_102_687,
            4_609_644_812_235_092_534,
        ],
        stats: PlannerStats {
            updates: 400,
            reuses: 199,
            factorisations: 8,
            rank_one_updates: 1081,
            ridge_used: 0,
        },
    };
    assert_eq!(got, want);
}
