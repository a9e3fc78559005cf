//! Engine 2: the indicator basis on a stochastic model. (I − γ P_π) V =
//! R_π over states by Gauss–Seidel sweeps warm-started from the previous V,
//! with a dense LU solve as the exact fallback when γ is so close to 1 that
//! the sweeps do not converge.

use super::*;

/// Exact Q^π for a stochastic model and Φ = I (see module docs).
pub(super) fn gauss_seidel(
    model: &EnvModel,
    policy: &[u32],
    r: &[f64],
    gamma: f64,
    v: &mut [f64],
    q: &mut [f64],
) -> Result<()> {
    let expect = |p: usize, v: &[f64]| -> f64 {
        let (next, prob) = model.successors(p);
        next.iter()
            .zip(prob)
            .map(|(&t, &w)| w * v[t as usize])
            .sum()
    };
    let bound = if gamma > 0.0 {
        gamma / (1.0 - gamma)
    } else {
        0.0
    };
    let mut converged = false;
    for _ in 0..MAX_SWEEPS {
        let mut delta: f64 = 0.0;
        let mut scale: f64 = 0.0;
        for s in 0..model.states() {
            let p = policy[s] as usize;
            let new = r[p] + gamma * expect(p, v);
            delta = delta.max((new - v[s]).abs());
            scale = scale.max(new.abs());
            v[s] = new;
        }
        if bound * delta <= 1e-12 * (1.0 + scale) {
            converged = true;
            break;
        }
    }
    if !converged {
        // γ so close to 1 that the sweeps contract too slowly: solve
        // (I − γ P_π) V = R_π directly when the model is small enough.
        if model.states() > DENSE_FALLBACK_MAX_STATES {
            return Err(AlgoError::Numerical(format!(
                "policy evaluation did not converge in {MAX_SWEEPS} sweeps with gamma = {gamma}; use a smaller `gamma`"
            )));
        }
        dense_policy_values(model, policy, r, gamma, v)?;
    }
    for (p, qp) in q.iter_mut().enumerate() {
        *qp = r[p] + gamma * expect(p, v);
    }
    Ok(())
}

/// V = (I − γ P_π)⁻¹ R_π by dense LU (the exact fallback of [`gauss_seidel`]).
pub(super) fn dense_policy_values(
    model: &EnvModel,
    policy: &[u32],
    r: &[f64],
    gamma: f64,
    v: &mut [f64],
) -> Result<()> {
    let n = model.states();
    let mut m = DMatrix::<f64>::identity(n, n);
    let mut rhs = DVector::<f64>::zeros(n);
    for s in 0..n {
        let p = policy[s] as usize;
        rhs[s] = r[p];
        let (next, prob) = model.successors(p);
        for (&t, &w) in next.iter().zip(prob) {
            m[(s, t as usize)] -= gamma * w;
        }
    }
    let sol = m
        .lu()
        .solve(&rhs)
        .ok_or_else(|| AlgoError::Numerical("I − γP_π is singular".into()))?;
    v.copy_from_slice(sol.as_slice());
    Ok(())
}
