//! Property 3: indicator-basis LSTDQ is exact policy evaluation (§5).

use super::*;

pub(crate) fn indicator_case(
    seed: u64,
    states: usize,
    actions: usize,
    stochastic: bool,
    gamma: f64,
) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let raw = RawModel::random(&mut rng, states, actions, stochastic, 0.7);
    let model = raw.model(&mut rng, 1)?;
    let idx = raw.pair_index();
    for (s, row) in idx.iter().enumerate() {
        for (a, &p) in row.iter().enumerate() {
            prop_assert_eq!(model.pair(s, a), p, "pair numbering of ({}, {})", s, a);
        }
    }
    prop_assert_eq!(model.n_pairs(), raw.n_pairs());
    prop_assert_eq!(model.is_deterministic(), !stochastic || states < 2);
    let pi = raw.random_policy(&mut rng);
    let r = random_rewards(&mut rng, raw.n_pairs());
    let ctx = PlanningModel::new(model, Basis::Indicator);
    let before = policy_pairs(&idx, &pi);
    let mut planner = Planner::new(&ctx, before.clone());
    let out = planner
        .update(&ctx, &r, gamma, 1e-6, &mut rng)
        .map_err(|e| fail(format!("update failed: {e}")))?;
    let want = raw.dense_q(&idx, &pi, &r, gamma)?;
    assert_close(planner.q(), &want, 1e-8, "Q")?;
    // Fig. 2d: the first error is ‖Q − 0‖₂.
    let q_norm = norm(planner.q());
    prop_assert!((out.lstdq_error - q_norm).abs() <= 1e-12 * (1.0 + q_norm));
    check_greedy(
        ctx.model(),
        &before,
        planner.policy(),
        planner.q(),
        out.policy_changes,
    )
}

proptest! {
    #![proptest_config(config(128))]

    /// Deterministic models (functional-graph engine): Q = (I − γP^π)⁻¹R.
    #[test]
    fn indicator_lstdq_is_exact_on_deterministic_models(
        seed in any::<u64>(), states in 1usize..=12, actions in 1usize..=4, gamma in 0.0f64..0.99,
    ) {
        indicator_case(seed, states, actions, false, gamma)?;
    }

    /// Stochastic models (Gauss–Seidel engine): Q = (I − γP^π)⁻¹R.
    #[test]
    fn indicator_lstdq_is_exact_on_stochastic_models(
        seed in any::<u64>(), states in 1usize..=12, actions in 1usize..=4, gamma in 0.0f64..0.99,
    ) {
        indicator_case(seed, states, actions, true, gamma)?;
    }
}
