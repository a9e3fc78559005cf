//! Property 7: agents are deterministic given the seed, and never produce NaN.

use super::*;

#[derive(Debug, Clone)]
pub(crate) struct AgentCase {
    pub(crate) seed: u64,
    pub(crate) states: usize,
    pub(crate) actions: usize,
    pub(crate) n_stimuli: usize,
    pub(crate) stochastic: bool,
    pub(crate) basis: usize,
    pub(crate) eta: f64,
    pub(crate) gamma: f64,
    pub(crate) epsilon: f64,
    pub(crate) constant_rate: Option<f64>,
    pub(crate) ticks: usize,
}

pub(crate) fn agent_case() -> impl Strategy<Value = AgentCase> {
    (
        (
            any::<u64>(),
            2usize..=12,
            1usize..=4,
            1usize..=3,
            any::<bool>(),
            0usize..3,
        ),
        (
            prop_oneof![1e-3f64..=0.5, Just(0.5)],
            0.0f64..0.99,
            prop_oneof![Just(0.0), 0.0f64..=1.0],
            prop::option::of(0.01f64..=1.0),
            1usize..=60,
        ),
    )
        .prop_map(
            |(
                (seed, states, actions, n_stimuli, stochastic, basis),
                (eta, gamma, epsilon, constant_rate, ticks),
            )| {
                AgentCase {
                    seed,
                    states,
                    actions,
                    n_stimuli,
                    stochastic,
                    basis,
                    eta,
                    gamma,
                    epsilon,
                    constant_rate,
                    ticks,
                }
            },
        )
}

pub(crate) fn build_agent(
    case: &AgentCase,
    spec: &ModelSpec,
    basis: &BasisSpec,
    rho: &[f64],
) -> TestResult<Agent> {
    let model = EnvModel::from_spec(spec).map_err(|e| fail(format!("model refused: {e}")))?;
    let basis = Basis::build(basis, &model).map_err(|e| fail(format!("basis refused: {e}")))?;
    let params = AgentParams {
        eta: Some(case.eta),
        gamma: Some(case.gamma),
        priorities: Some(rho.to_vec()),
        stimulus_rate: case.constant_rate.map(StimulusRate::Constant),
        epsilon: Some(case.epsilon),
        seed: Some(case.seed),
        ..AgentParams::default()
    }
    .check(case.n_stimuli, 0)
    .map_err(|e| fail(format!("params refused: {e}")))?;
    Ok(Agent::new(
        Arc::new(PlanningModel::new(model, basis)),
        params,
    ))
}

/// Everything observable about an agent's numeric state, bit for bit.
pub(crate) fn fingerprint(agent: &Agent) -> (Vec<u64>, Vec<u64>, Vec<u32>, Vec<u64>) {
    let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    (
        bits(agent.drive().vector()),
        bits(agent.planner().q()),
        agent.planner().policy().to_vec(),
        bits(agent.rewards()),
    )
}

pub(crate) fn check_finite(agent: &Agent, t: usize) -> TestResult {
    let d = agent.drive().vector();
    prop_assert!(d.iter().all(|x| x.is_finite()), "tick {}: D = {:?}", t, d);
    prop_assert!(
        (norm(d) - 1.0).abs() < 1e-12,
        "tick {}: ‖D‖ = {}",
        t,
        norm(d)
    );
    let q = agent.planner().q();
    prop_assert!(
        q.iter().all(|x| x.is_finite()),
        "tick {}: Q has a non-finite entry",
        t
    );
    prop_assert!(
        agent.rewards().iter().all(|x| x.is_finite() && *x >= 0.0),
        "tick {}: R",
        t
    );
    prop_assert!(
        agent.stimulus().table().iter().all(|x| x.is_finite()),
        "tick {}: Ξ",
        t
    );
    Ok(())
}

pub(crate) fn agent_determinism_case(case: AgentCase) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(case.seed ^ 0x9e37_79b9_7f4a_7c15);
    let raw = RawModel::random(&mut rng, case.states, case.actions, case.stochastic, 0.7);
    let spec = raw.spec(&mut rng, case.n_stimuli);
    let basis = match case.basis {
        0 => BasisSpec::Indicator,
        1 => BasisSpec::ProtoValue {
            k: rng.random_range(1..=case.states),
        },
        _ => {
            let k = rng.random_range(1..=3);
            BasisSpec::Custom {
                state_features: (0..case.states)
                    .map(|_| (0..k).map(|_| gaussian(&mut rng)).collect())
                    .collect(),
            }
        }
    };
    let rho: Vec<f64> = (0..case.n_stimuli)
        .map(|_| rng.random_range(0.1..=1.0))
        .collect();
    let mut a = build_agent(&case, &spec, &basis, &rho)?;
    let mut b = build_agent(&case, &spec, &basis, &rho)?;
    prop_assert_eq!(fingerprint(&a), fingerprint(&b));
    let clone_at = rng.random_range(0..=case.ticks);
    let mut c: Option<Agent> = None;

    let mut prev = rng.random_range(0..case.states);
    let first_a = a
        .step(&Observation::first(prev))
        .map_err(|e| fail(format!("first step: {e}")))?;
    let first_b = b
        .step(&Observation::first(prev))
        .map_err(|e| fail(format!("first step: {e}")))?;
    prop_assert_eq!(first_a, first_b);
    for t in 0..case.ticks {
        if t == clone_at {
            c = Some(a.clone());
        }
        let state = rng.random_range(0..case.states);
        let xi: Vec<f64> = (0..case.n_stimuli)
            .map(|_| {
                if rng.random_bool(0.5) {
                    0.0
                } else {
                    2.0 * gaussian(&mut rng)
                }
            })
            .collect();
        let action_taken = rng.random_bool(0.2).then(|| {
            let avail = raw.available(prev);
            avail[rng.random_range(0..avail.len())]
        });
        let obs = Observation {
            state,
            stimulus: Some(&xi),
            action_taken,
        };
        let sa = a.step(&obs).map_err(|e| fail(format!("tick {t}: {e}")))?;
        let sb = b.step(&obs).map_err(|e| fail(format!("tick {t}: {e}")))?;
        prop_assert_eq!(sa, sb, "tick {}", t);
        prop_assert_eq!(sa.reward.to_bits(), sb.reward.to_bits());
        prop_assert!(
            sa.reward.is_finite() && sa.reward >= 0.0,
            "tick {}: |r| = {}",
            t,
            sa.reward
        );
        prop_assert!(
            sa.action < case.actions && raw.rows[state][sa.action].is_some(),
            "tick {}: action {} unavailable in {}",
            t,
            sa.action,
            state
        );
        prop_assert_eq!(fingerprint(&a), fingerprint(&b), "tick {}", t);
        if let Some(c) = c.as_mut() {
            let sc = c
                .step(&obs)
                .map_err(|e| fail(format!("clone, tick {t}: {e}")))?;
            prop_assert_eq!(sa, sc, "clone, tick {}", t);
            prop_assert_eq!(fingerprint(&a), fingerprint(c), "clone, tick {}", t);
        }
        check_finite(&a, t)?;
        prev = state;
    }
    prop_assert_eq!(a.tick(), case.ticks as u64);
    Ok(())
}

proptest! {
    #![proptest_config(config(64))]

    /// Two agents with the same seed, fed the same observations (random
    /// states, stimuli with exact zeros, sometimes a reported action_taken),
    /// give identical steps and bit-identical D, Q, π and R; so does a clone
    /// taken midway. D, Q, R and Ξ stay finite, with ‖D‖ = 1.
    #[test]
    fn agents_are_deterministic_and_finite(case in agent_case()) {
        agent_determinism_case(case)?;
    }
}
