//! Unit tests of the three engines and the kernels.

use super::kernels::*;
use super::*;
use crate::model::{hallway, names};
use crate::spec::BasisSpec;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn first_action_policy(model: &EnvModel) -> Vec<u32> {
    (0..model.states())
        .map(|s| model.pairs_of(s).start as u32)
        .collect()
}

/// The axpy-form kernels the blocked ones replaced (commit 15aa12d):
/// b gains R(s,a) v(s) pair by pair, w and Q are sums of columns four at
/// a time. The blocked kernels must give the same bits.
fn reference_kernel(
    model: &EnvModel,
    f: &StateFeatures,
    a_inv: &[f64],
    r: &[f64],
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    fn combine(out: &mut [f64], cols: &[f64], c: &[f64]) {
        let n = out.len();
        out.fill(0.0);
        let mut quads = cols.chunks_exact(4 * n).zip(c.chunks_exact(4));
        for (block, c4) in &mut quads {
            for (i, o) in out.iter_mut().enumerate() {
                *o += (c4[0] * block[i] + c4[1] * block[n + i])
                    + (c4[2] * block[2 * n + i] + c4[3] * block[3 * n + i]);
            }
        }
        let done = c.len() / 4 * 4;
        for (&cj, col) in c[done..].iter().zip(cols[done * n..].chunks_exact(n)) {
            for (o, v) in out.iter_mut().zip(col) {
                *o += cj * v;
            }
        }
    }
    let (k, n) = (f.k(), model.states());
    let big_k = k * model.n_actions();
    let mut b = vec![0.0; big_k];
    for (p, &rp) in r.iter().enumerate() {
        let (s, a) = (model.pair_state(p), model.pair_action(p));
        for (bj, vj) in b[a * k..(a + 1) * k].iter_mut().zip(f.row(s)) {
            *bj += rp * vj;
        }
    }
    let mut w = vec![0.0; big_k];
    combine(&mut w, a_inv, &b);
    let mut v_cols = vec![0.0; n * k];
    for s in 0..n {
        for (j, &x) in f.row(s).iter().enumerate() {
            v_cols[j * n + s] = x;
        }
    }
    let mut q_states = vec![0.0; n * model.n_actions()];
    for (col, wa) in q_states.chunks_exact_mut(n).zip(w.chunks_exact(k)) {
        combine(col, &v_cols, wa);
    }
    let q = (0..model.n_pairs())
        .map(|p| q_states[model.pair_action(p) * n + model.pair_state(p)])
        .collect();
    (b, w, q)
}

#[test]
fn blocked_kernels_match_the_axpy_reference_bit_for_bit() {
    let model = hallway().model;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut normal = || rng.random::<f64>() * 2.0 - 1.0;
    let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    for k in [1, 3, 4, 5, 7, 8, 9, 16, 17, 30, 33, 41, 50] {
        let rows: Vec<Vec<f64>> = (0..50)
            .map(|_| (0..k).map(|_| normal()).collect())
            .collect();
        let basis = Basis::build(
            &BasisSpec::Custom {
                state_features: rows,
            },
            &model,
        )
        .expect("basis");
        let ctx = PlanningModel::new(model.clone(), basis);
        let (f, cache) = (
            ctx.state_features().expect("features"),
            ctx.features.as_ref().expect("cache"),
        );
        let big_k = 3 * k;
        let a_inv: Vec<f64> = (0..big_k * big_k).map(|_| normal()).collect();
        let r: Vec<f64> = (0..model.n_pairs()).map(|_| normal().abs()).collect();
        let (mut b, mut w, mut q) = (vec![0.0; big_k], vec![0.0; big_k], vec![0.0; 148]);
        let mut q_states = vec![0.0; 150];
        feature_kernel(
            FeatureKernel {
                pair_state: model.pair_states(),
                pair_action: model.pair_actions(),
                rows_padded: &cache.rows_padded,
                kp: cache.kp,
                v_cols: &cache.v_cols,
                k,
                a_inv: &a_inv,
                r: &r,
            },
            FeatureScratch {
                b_wide: &mut vec![0.0; 3 * cache.kp],
                b: &mut b,
                w: &mut w,
                q_states: &mut q_states,
            },
            &mut q,
        );
        let (b_ref, w_ref, q_ref) = reference_kernel(&model, f, &a_inv, &r);
        assert_eq!(bits(&b), bits(&b_ref), "b, k = {k}");
        assert_eq!(bits(&w), bits(&w_ref), "w, k = {k}");
        assert_eq!(bits(&q), bits(&q_ref), "Q, k = {k}");
        let mut x = vec![0.0; big_k];
        mat_vec(&a_inv, &b_ref, &mut x);
        assert_eq!(bits(&x), bits(&w_ref), "A⁻¹u, k = {k}");
    }
}

#[test]
fn an_evaluation_with_nothing_changed_is_skipped_without_changing_results() {
    let model = hallway().model;
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let rows: Vec<Vec<f64>> = (0..50)
        .map(|_| (0..6).map(|_| rng.random::<f64>() - 0.5).collect())
        .collect();
    let basis = Basis::build(
        &BasisSpec::Custom {
            state_features: rows,
        },
        &model,
    )
    .expect("basis");
    let ctx = PlanningModel::new(model.clone(), basis);
    let mut r: Vec<f64> = (0..model.n_pairs()).map(|_| rng.random::<f64>()).collect();
    let mut memo = Planner::new(&ctx, first_action_policy(&model));
    let mut full = memo.clone();
    let mut skipped = 0;
    for t in 0..60 {
        if t == 30 {
            r[7] += 0.25;
        }
        // `full` evaluates every time, `memo` may skip.
        if let Engine::Features(fe) = &mut full.engine {
            fe.evaluated = false;
        }
        if let Engine::Features(fe) = &memo.engine {
            skipped +=
                usize::from(fe.evaluated && !fe.stale && fe.pending.is_empty() && fe.r_last == r);
        }
        let mut rng_full = rng.clone();
        let a = memo.update(&ctx, &r, 0.9, 1e-6, &mut rng).expect("memo");
        let b = full
            .update(&ctx, &r, 0.9, 1e-6, &mut rng_full)
            .expect("full");
        assert_eq!(a, b, "tick {t}");
        assert_eq!(memo.policy(), full.policy(), "tick {t}");
        let bits = |p: &Planner| p.q().iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&memo), bits(&full), "tick {t}");
        assert_eq!(memo.stats(), full.stats(), "tick {t}");
    }
    assert!(skipped > 40, "only {skipped} evaluations skipped");
}

#[test]
fn a_changed_row_of_p_updates_m_and_the_plan() {
    let model = hallway().model;
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let rows: Vec<Vec<f64>> = (0..50)
        .map(|_| (0..4).map(|_| rng.random::<f64>() - 0.5).collect())
        .collect();
    let spec = BasisSpec::Custom {
        state_features: rows,
    };
    let basis = Basis::build(&spec, &model).expect("basis");
    let mut ctx = PlanningModel::new(model.clone(), basis.clone());
    let r: Vec<f64> = (0..model.n_pairs()).map(|_| rng.random::<f64>()).collect();
    let mut planner = Planner::new(&ctx, first_action_policy(&model));
    planner.update(&ctx, &r, 0.9, 1e-6, &mut rng).expect("plan");
    // Pair (20, right) becomes slippery: 0.7 to 21, 0.3 stays.
    let p = model.pair(20, 1).expect("right");
    ctx.set_successors(p, &[(21, 0.7), (20, 0.3)]);
    planner.model_changed(&ctx);
    let fresh = PlanningModel::new(ctx.model().clone(), basis);
    let (m, m_ref) = (
        &ctx.features.as_ref().expect("cache").m,
        &fresh.features.as_ref().expect("cache").m,
    );
    assert!((m - m_ref).amax() < 1e-12, "M kept in step with P");
    let mut reference = Planner::new(&fresh, planner.policy().to_vec());
    let mut rng_ref = rng.clone();
    planner.update(&ctx, &r, 0.9, 1e-6, &mut rng).expect("plan");
    reference
        .update(&fresh, &r, 0.9, 1e-6, &mut rng_ref)
        .expect("reference plan");
    for (a, b) in planner.q().iter().zip(reference.q()) {
        assert!((a - b).abs() < 1e-9, "{a} vs {b}");
    }
    // The functional-graph engine moves to Gauss–Seidel.
    let mut ind = PlanningModel::new(model.clone(), Basis::Indicator);
    let mut fg = Planner::new(&ind, first_action_policy(&model));
    fg.update(&ind, &r, 0.9, 1e-6, &mut rng).expect("plan");
    ind.set_successors(p, &[(21, 0.7), (20, 0.3)]);
    fg.model_changed(&ind);
    assert!(matches!(fg.engine, Engine::GaussSeidel { .. }));
    fg.update(&ind, &r, 0.9, 1e-6, &mut rng)
        .expect("stochastic plan");
}

#[test]
fn two_state_cycle_by_hand() {
    // 0 -go-> 1 -go-> 0, R = (1, 0), γ = 0.5: V0 = 1/(1−0.25) = 4/3, V1 = 0.5 V0.
    let model = EnvModel::deterministic(
        vec![vec![Some(1)], vec![Some(0)]],
        names(&["go"]),
        names(&["x"]),
    )
    .expect("model");
    let ctx = PlanningModel::new(model, Basis::Indicator);
    let mut planner = Planner::new(&ctx, vec![0, 1]);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let out = planner
        .update(&ctx, &[1.0, 0.0], 0.5, 1e-6, &mut rng)
        .expect("plan");
    assert!((planner.q()[0] - 4.0 / 3.0).abs() < 1e-15);
    assert!((planner.q()[1] - 2.0 / 3.0).abs() < 1e-15);
    assert!((out.lstdq_error - (16.0f64 / 9.0 + 4.0 / 9.0).sqrt()).abs() < 1e-12);
}

#[test]
fn hallway_policy_walks_to_the_reward() {
    let model = hallway().model;
    let ctx = PlanningModel::new(model.clone(), Basis::Indicator);
    let mut planner = Planner::new(&ctx, first_action_policy(&model));
    // Reward only for staying at 10.
    let mut r = vec![0.0; model.n_pairs()];
    r[model.pair(10, 2).expect("stay")] = 1.0;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    for _ in 0..60 {
        planner
            .update(&ctx, &r, 0.95, 1e-6, &mut rng)
            .expect("plan");
    }
    for s in 0..50 {
        let a = model.pair_action(planner.chosen_pair(s));
        let expected = match s.cmp(&10) {
            std::cmp::Ordering::Less => 1,
            std::cmp::Ordering::Equal => 2,
            std::cmp::Ordering::Greater => 0,
        };
        assert_eq!(a, expected, "state {s}");
    }
    assert!((planner.value(10) - 20.0).abs() < 1e-9, "V(10) = 1/(1-γ)");
}

#[test]
fn ties_keep_the_previous_action() {
    let model = hallway().model;
    let ctx = PlanningModel::new(model.clone(), Basis::Indicator);
    let policy: Vec<u32> = (0..50).map(|s| model.pairs_of(s).end as u32 - 1).collect();
    let mut planner = Planner::new(&ctx, policy.clone());
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let out = planner
        .update(&ctx, &vec![0.0; model.n_pairs()], 0.9, 1e-6, &mut rng)
        .expect("plan");
    assert_eq!(out.policy_changes, 0);
    assert_eq!(planner.policy(), &policy[..]);
}

#[test]
fn feature_engine_matches_indicator_when_features_are_complete() {
    // With one-hot state features the block basis spans all pairs, so
    // LSTDQ is exact and must agree with the indicator engine.
    let model = hallway().model;
    let eye: Vec<Vec<f64>> = (0..50)
        .map(|s| (0..50).map(|j| f64::from(u8::from(s == j))).collect())
        .collect();
    let basis = Basis::build(
        &BasisSpec::Custom {
            state_features: eye,
        },
        &model,
    )
    .expect("basis");
    let feat = PlanningModel::new(model.clone(), basis);
    let ind = PlanningModel::new(model.clone(), Basis::Indicator);
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let r: Vec<f64> = (0..model.n_pairs())
        .map(|p| ((p * 37) % 11) as f64 / 10.0)
        .collect();
    let mut pf = Planner::new(&feat, first_action_policy(&model));
    let mut pi = Planner::new(&ind, first_action_policy(&model));
    for _ in 0..30 {
        let mut rng_f = rng.clone();
        pf.update(&feat, &r, 0.9, 1e-6, &mut rng_f)
            .expect("feature plan");
        pi.update(&ind, &r, 0.9, 1e-6, &mut rng)
            .expect("indicator plan");
        for (a, b) in pf.q().iter().zip(pi.q()) {
            assert!((a - b).abs() < 1e-8, "{a} vs {b}");
        }
        assert_eq!(pf.policy(), pi.policy());
    }
    assert!(pf.stats().rank_one_updates > 0, "{:?}", pf.stats());
}

/// The functional-graph engine replays its recorded order while the
/// successors stay the same and walks again when they change; either way
/// V and Q have the bits of a walk from scratch.
#[test]
fn functional_graph_replays_its_order_with_the_bits_of_a_fresh_walk() {
    let states = 40;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let succ: Vec<Vec<Option<usize>>> = (0..states)
        .map(|_| (0..3).map(|_| Some(rng.random_range(0..states))).collect())
        .collect();
    let model =
        EnvModel::deterministic(succ, names(&["a", "b", "c"]), names(&["x"])).expect("model");
    let pairs = model.n_pairs();
    let mut kept = functional::FunctionalGraph::new(states);
    let mut policy = first_action_policy(&model);
    let mut walks = 0;
    for t in 0..60 {
        // Every third evaluation under a changed policy (a few states).
        if t % 3 == 0 {
            for _ in 0..1 + t % 4 {
                let s = rng.random_range(0..states);
                let range = model.pairs_of(s);
                policy[s] = rng.random_range(range.start..range.end) as u32;
            }
            walks += 1;
        }
        let r: Vec<f64> = (0..pairs).map(|_| rng.random::<f64>() - 0.3).collect();
        let mut scratch = Scratch::take(pairs);
        kept.evaluate(&model, &policy, &r, 0.9, &mut scratch);
        let q_kept: Vec<u64> = scratch.q_next.iter().map(|x| x.to_bits()).collect();
        let mut fresh = functional::FunctionalGraph::new(states);
        fresh.evaluate(&model, &policy, &r, 0.9, &mut scratch);
        let q_fresh: Vec<u64> = scratch.q_next.iter().map(|x| x.to_bits()).collect();
        scratch.put_back();
        assert_eq!(q_kept, q_fresh, "evaluation {t}");
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&kept.v), bits(&fresh.v), "evaluation {t}");
    }
    assert!(walks > 10 && walks < 60, "both paths taken");
}
