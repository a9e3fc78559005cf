//! Known issues of the core, found while writing these properties. Each is
//! phrased so that any reasonable fix (refuse the input, report an error,
//! or compute the right value) makes it pass; those still open are ignored
//! so that the suite stays green (run with `--ignored` to see them fail).

use super::*;

/// One finite but huge stimulus (‖Λξ‖² overflows f64) must not break the
/// session: it is either refused up front, or later ordinary ticks still
/// plan, with a finite λ₁ estimate. Before the fix: `Drive::update` left D
/// unchanged (its norm overflowed), the running second moment became inf
/// then NaN for good (condition (1) then read as violated forever), and
/// every later plan failed with "LSTDQ produced a non-finite Q" because
/// ‖Q_t − Q_{t+1}‖² overflowed although Q itself was finite. Now stimuli
/// beyond ±1e12 are refused.
#[test]
fn huge_finite_stimulus_does_not_break_the_session() {
    let model = EnvModel::chain(5, vec!["food".into(), "rest".into()]).expect("chain");
    let params = AgentParams {
        seed: Some(1),
        ..AgentParams::default()
    }
    .check(2, 0)
    .expect("params");
    let mut agent = Agent::new(
        Arc::new(PlanningModel::new(model, Basis::Indicator)),
        params,
    );
    agent
        .step(&Observation::first(2))
        .expect("first observation");
    let huge = agent.step(&Observation::new(2, &[1e200, 0.0]));
    if huge.is_err() && agent.tick() == 0 {
        return; // refused up front, nothing learned: fine
    }
    for t in 0..3 {
        let step = agent.step(&Observation::new(2, &[1.0, 0.0]));
        assert!(
            step.is_ok(),
            "ordinary tick {t} after a huge stimulus: {step:?}"
        );
    }
    assert!(
        agent.drive().lambda1_estimate().is_finite(),
        "λ₁ estimate is not finite"
    );
}

/// Stochastic models with γ close to 1 (γ ∈ [0, 1) is accepted): the
/// Gauss–Seidel engine used to stop at its sweep cap and silently return an
/// unconverged Q (relative error about 5e-5 at γ = 0.9999 on 3 states).
/// Either the result is exact or the update reports an error.
#[test]
fn stochastic_evaluation_near_gamma_one_is_exact_or_an_error() {
    for seed in 0..20 {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let raw = RawModel::random(&mut rng, 3, 1, true, 1.0);
        let model = raw.model(&mut rng, 1).expect("model");
        let idx = raw.pair_index();
        let pi = raw.random_policy(&mut rng);
        let r = random_rewards(&mut rng, raw.n_pairs());
        let gamma = 0.9999;
        let ctx = PlanningModel::new(model, Basis::Indicator);
        let mut planner = Planner::new(&ctx, policy_pairs(&idx, &pi));
        if planner.update(&ctx, &r, gamma, 1e-6, &mut rng).is_ok() {
            let want = raw.dense_q(&idx, &pi, &r, gamma).expect("dense solve");
            let scale = 1.0 + want.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            for (g, w) in planner.q().iter().zip(&want) {
                assert!(
                    (g - w).abs() <= 1e-8 * scale,
                    "seed {seed}: Q = {g}, dense {w}"
                );
            }
        }
    }
}

/// The λ₁ estimate behind condition (1) was a power iteration started from
/// (1, …, 1)/√n and capped at 200 steps; when the second moment's top
/// eigenvector was orthogonal to that start it missed λ₁. Stimuli that always
/// have the form (a, −a) give C = a²[[1, −1], [−1, 1]], λ₁ = 2a², but the
/// estimate was 0, so `condition_holds()` said true although η λ₁ = 0.8 ≥ 0.5.
/// (When the top eigenvector is merely nearly orthogonal to the start and λ₂
/// is close to λ₁, the capped iteration stops short: about 0.7% low on a
/// random 9-sample stream with λ₂/λ₁ = 0.989.) It is now a symmetric
/// eigendecomposition, exact and cheap for small n.
#[test]
fn lambda1_estimate_sees_an_antisymmetric_stimulus() {
    let mut drive = Drive::from_parts(vec![0.6, 0.8], &[1.0, 1.0], 0.4);
    for _ in 0..10 {
        drive.update(&[1.0, -1.0]);
    }
    let est = drive.lambda1_estimate();
    assert!((est - 2.0).abs() < 1e-9, "λ₁ estimate {est}, expected 2");
    assert!(
        !drive.condition_holds(),
        "η λ₁ = 0.8 violates condition (1)"
    );
}
