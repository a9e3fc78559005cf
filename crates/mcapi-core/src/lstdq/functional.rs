//! Engine 1: the indicator basis on a deterministic model. Q = R + γ P^π Q
//! is policy evaluation on a functional graph (each state has one
//! successor under π): every component is a cycle with trees hanging off
//! it, solved in O(|S|) by a closed form on the cycle and back-substitution
//! on the trees; then Q(s,a) = R(s,a) + γ V(s'). No matrix is formed.

use super::*;

#[derive(Debug, Clone)]
pub(super) struct FunctionalGraph {
    /// V^π of the last evaluation (warm start of Gauss–Seidel when a
    /// learned P̂ stops being deterministic, [`Planner::model_changed`]).
    pub(super) v: Vec<f64>,
}

impl FunctionalGraph {
    /// Exact Q^π for a deterministic model and Φ = I (see module docs).
    pub(super) fn evaluate(
        &mut self,
        model: &EnvModel,
        policy: &[u32],
        r: &[f64],
        gamma: f64,
        scratch: &mut Scratch,
    ) {
        pub(super) const UNSEEN: u8 = 0;
        pub(super) const ON_PATH: u8 = 1;
        pub(super) const DONE: u8 = 2;
        let n = model.states();
        let next = |s: usize| model.next_state(policy[s] as usize);
        let reward = |s: usize| r[policy[s] as usize];
        let Scratch {
            q_next: q,
            mark,
            stack,
            ..
        } = scratch;
        mark.clear();
        mark.resize(n, UNSEEN);
        let v = &mut self.v;
        for start in 0..n {
            if mark[start] == DONE {
                continue;
            }
            stack.clear();
            let mut s = start;
            while mark[s] == UNSEEN {
                mark[s] = ON_PATH;
                stack.push(s as u32);
                s = next(s);
            }
            if mark[s] == ON_PATH {
                // The walk closed a cycle c_0 = s, c_1, ..., c_{L-1} (the stack's tail):
                // V(c_0) = Σ_i γ^i r(c_i) / (1 − γ^L), summed backwards (Horner).
                let pos = stack.iter().rposition(|&x| x as usize == s).unwrap_or(0);
                let cycle = &stack[pos..];
                let len = cycle.len();
                let mut sum = 0.0;
                for &c in cycle.iter().rev() {
                    sum = reward(c as usize) + gamma * sum;
                }
                let v0 = sum / (1.0 - gamma.powi(len as i32));
                v[s] = v0;
                mark[s] = DONE;
                let mut after = v0;
                for &c in cycle[1..].iter().rev() {
                    let c = c as usize;
                    after = reward(c) + gamma * after;
                    v[c] = after;
                    mark[c] = DONE;
                }
                stack.truncate(pos);
            }
            // The rest of the path leads into solved states: back-substitute.
            while let Some(u) = stack.pop() {
                let u = u as usize;
                v[u] = reward(u) + gamma * v[next(u)];
                mark[u] = DONE;
            }
        }
        for (p, qp) in q.iter_mut().enumerate() {
            *qp = r[p] + gamma * v[model.next_state(p)];
        }
    }
}
