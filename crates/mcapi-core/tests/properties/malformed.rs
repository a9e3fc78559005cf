//! Property 6: malformed models are rejected (EnvModel::from_spec).

use super::*;

/// Injects one defect into a valid spec; returns the fragments the error
/// message must contain.
pub(crate) fn inject_defect(
    rng: &mut ChaCha8Rng,
    raw: &RawModel,
    spec: &mut ModelSpec,
    defect: usize,
) -> Vec<String> {
    let states = raw.states;
    let beyond = states + rng.random_range(0..5);
    if let Some(next) = spec.next.as_mut() {
        match defect % 4 {
            0 => {
                // A successor out of range.
                let s = rng.random_range(0..states);
                let a = raw.available(s)[rng.random_range(0..raw.available(s).len())];
                next[s][a] = Some(beyond);
                vec![format!(
                    "`next[{s}][{a}]` = {beyond} is out of range (states are 0..{states})"
                )]
            }
            1 => {
                // A state with no available action.
                let s = rng.random_range(0..states);
                next[s].iter_mut().for_each(|x| *x = None);
                vec![format!("state {s} has no available action")]
            }
            2 => {
                // A row of the wrong length.
                let s = rng.random_range(0..states);
                if rng.random_bool(0.5) {
                    next[s].push(Some(0));
                } else {
                    next[s].pop();
                }
                let len = next[s].len();
                vec![format!(
                    "`next[{s}]` has {len} entries, expected one per action ({})",
                    raw.actions
                )]
            }
            _ => {
                // The wrong number of rows.
                if rng.random_bool(0.5) {
                    next.push(vec![None; raw.actions]);
                } else {
                    next.pop();
                }
                vec![format!(
                    "`next` has {} rows, expected one per state ({states})",
                    next.len()
                )]
            }
        }
    } else {
        let list = spec
            .transitions
            .as_mut()
            .unwrap_or_else(|| unreachable!("one encoding is set"));
        let i = rng.random_range(0..list.len());
        let j = rng.random_range(0..list[i].next.len());
        match defect % 5 {
            0 => {
                list[i].state = beyond;
                vec![format!(
                    "`transitions[{i}].state` = {beyond} is out of range (states are 0..{states})"
                )]
            }
            1 => {
                list[i].next[j].0 = beyond;
                vec![format!(
                    "`transitions[{i}].next[{j}]` state {beyond} is out of range"
                )]
            }
            2 => {
                // Probabilities that do not sum to 1: too little, or an extra successor.
                let tr = &mut list[i];
                let unlisted = (0..states).find(|t| tr.next.iter().all(|&(u, _)| u != *t));
                match unlisted {
                    Some(t) if rng.random_bool(0.5) => {
                        tr.next.push((t, rng.random_range(0.001..=1.0)))
                    }
                    _ => {
                        let f = rng.random_range(0.0..0.999);
                        tr.next
                            .iter_mut()
                            .for_each(|(_, p)| *p = (*p * f).max(1e-3 * *p));
                    }
                }
                let sum: f64 = tr.next.iter().map(|&(_, p)| p).sum();
                vec![format!(
                    "`transitions[{i}]` probabilities sum to {sum}, not 1"
                )]
            }
            3 => {
                // A probability outside (0, 1]: negative, zero, above 1 or NaN.
                let p = match rng.random_range(0..4) {
                    0 => -rng.random_range(1e-9..=1.0),
                    1 => 0.0,
                    2 => 1.0 + rng.random_range(1e-6..=1.0),
                    _ => f64::NAN,
                };
                list[i].next[j].1 = p;
                vec![format!(
                    "`transitions[{i}].next[{j}]` probability {p} is not in (0, 1]"
                )]
            }
            _ => {
                // A state with no available action: drop all its transitions.
                let s = list[i].state;
                list.retain(|tr| tr.state != s);
                vec![format!("state {s} has no available action")]
            }
        }
    }
}

pub(crate) fn malformed_case(
    seed: u64,
    states: usize,
    actions: usize,
    stochastic: bool,
    defect: usize,
) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let raw = RawModel::random(&mut rng, states, actions, stochastic, 0.6);
    let mut spec = raw.spec(&mut rng, 2);
    prop_assert!(
        EnvModel::from_spec(&spec).is_ok(),
        "the undamaged spec must be valid"
    );
    let fragments = inject_defect(&mut rng, &raw, &mut spec, defect);
    match EnvModel::from_spec(&spec) {
        Ok(_) => {
            return Err(fail(format!(
                "accepted a spec with a defect ({fragments:?}): {spec:?}"
            )));
        }
        Err(e) => {
            prop_assert!(
                matches!(e, AlgoError::InvalidModel(_)),
                "wrong error kind: {:?}",
                e
            );
            let msg = e.to_string();
            for fragment in &fragments {
                prop_assert!(
                    msg.contains(fragment.as_str()),
                    "{:?} should contain {:?}",
                    msg,
                    fragment
                );
            }
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(config(256))]

    /// A valid random spec is accepted; with one injected defect it is
    /// refused as an invalid model whose message names field, index and value.
    #[test]
    fn malformed_models_are_rejected(
        seed in any::<u64>(),
        states in 1usize..=6,
        actions in 1usize..=3,
        stochastic in any::<bool>(),
        defect in 0usize..20,
    ) {
        malformed_case(seed, states, actions, stochastic, defect)?;
    }
}
