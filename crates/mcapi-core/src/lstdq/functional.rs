//! Engine 1: the indicator basis on a deterministic model. Q = R + γ P^π Q
//! is policy evaluation on a functional graph (each state has one
//! successor under π): every component is a cycle with trees hanging off
//! it, solved in O(|S|) by a closed form on the cycle and back-substitution
//! on the trees; then Q(s,a) = R(s,a) + γ V(s'). No matrix is formed.

use super::*;

#[derive(Debug, Clone, Default)]
pub(super) struct FunctionalGraph {
    /// V^π of the last evaluation (warm start of Gauss–Seidel when a
    /// learned P̂ stops being deterministic, [`Planner::model_changed`]).
    pub(super) v: Vec<f64>,
    /// The last walk over the graph, in one allocation: the successor of
    /// every state under its policy (the first |S| entries), then its order
    /// of solving: a state u < |S| is back-substituted, V(u) = r(u) +
    /// γ V(succ(u)); an entry |S| + L − 1 is followed by the L states
    /// c_0 … c_{L−1} of a cycle, solved in closed form. The order depends
    /// only on the successors, so an evaluation whose successors are the
    /// last walk's (π and P unchanged: most ticks) replays it without
    /// walking. Empty until the first evaluation.
    walk: Vec<u32>,
}

impl FunctionalGraph {
    /// The engine for `states` states, before any evaluation.
    pub(super) fn new(states: usize) -> Self {
        Self {
            v: vec![0.0; states],
            ..Self::default()
        }
    }

    /// The recorded walk (see the field).
    pub(super) fn walk(&self) -> &[u32] {
        &self.walk
    }

    /// Exact Q^π for a deterministic model and Φ = I (see module docs).
    ///
    /// The walk over the graph (marks, a path, cycles found) is done only
    /// when a state's successor under π changed since the last evaluation;
    /// otherwise its recorded order is replayed. Either way every V(s) is
    /// computed by the same operations on the same values, so the bits do
    /// not depend on whether the order was recorded or replayed.
    pub(super) fn evaluate(
        &mut self,
        model: &EnvModel,
        policy: &[u32],
        r: &[f64],
        gamma: f64,
        scratch: &mut Scratch,
    ) {
        let n = model.states();
        let next_states = model.next_states();
        debug_assert_eq!(policy.len(), n);
        debug_assert_eq!(scratch.q_next.len(), next_states.len());
        debug_assert_eq!(r.len(), next_states.len());
        let next = |&p: &u32| next_states[p as usize];
        let unchanged =
            self.walk.len() > n && self.walk[..n].iter().copied().eq(policy.iter().map(next));
        if !unchanged {
            self.walk.clear();
            self.walk.extend(policy.iter().map(next));
            self.record_walk(n, scratch);
        }
        let (succ, order) = self.walk.split_at(n);
        let v = &mut self.v;
        let reward = |s: usize| r[policy[s] as usize];
        // The value written last, kept in a register: a tree's path is
        // solved from its root outwards, so a state's successor is most
        // often the state solved just before it, and reading its value
        // back from `v` would wait for the store (the same bits either way).
        let mut last = (usize::MAX, 0.0);
        let mut i = 0;
        while let Some(&e) = order.get(i) {
            i += 1;
            let e = e as usize;
            if e < n {
                let next = succ[e] as usize;
                let v_next = if next == last.0 { last.1 } else { v[next] };
                let value = reward(e) + gamma * v_next;
                v[e] = value;
                last = (e, value);
                continue;
            }
            // A cycle c_0, c_1, ..., c_{L-1}:
            // V(c_0) = Σ_i γ^i r(c_i) / (1 − γ^L), summed backwards (Horner).
            let len = e - n + 1;
            let cycle = &order[i..i + len];
            i += len;
            let mut sum = 0.0;
            for &c in cycle.iter().rev() {
                sum = reward(c as usize) + gamma * sum;
            }
            let v0 = sum / (1.0 - gamma.powi(len as i32));
            v[cycle[0] as usize] = v0;
            let mut after = (cycle[0] as usize, v0);
            for &c in cycle[1..].iter().rev() {
                after = (c as usize, reward(c as usize) + gamma * after.1);
                v[c as usize] = after.1;
            }
            last = after;
        }
        let v: &[f64] = v;
        for ((qp, &rp), &next) in scratch.q_next.iter_mut().zip(r).zip(next_states) {
            *qp = rp + gamma * v[next as usize];
        }
    }

    /// Appends to `walk` (which holds the n successors) the order of
    /// solving their functional graph: from each state not yet solved,
    /// follow successors until a solved state or a cycle; the cycle first,
    /// then the path back to the start.
    fn record_walk(&mut self, n: usize, scratch: &mut Scratch) {
        const UNSEEN: u8 = 0;
        const ON_PATH: u8 = 1;
        const DONE: u8 = 2;
        let Scratch { mark, stack, .. } = scratch;
        mark.clear();
        mark.resize(n, UNSEEN);
        let walk = &mut self.walk;
        for start in 0..n {
            if mark[start] == DONE {
                continue;
            }
            stack.clear();
            let mut s = start;
            while mark[s] == UNSEEN {
                mark[s] = ON_PATH;
                stack.push(s as u32);
                s = walk[s] as usize;
            }
            if mark[s] == ON_PATH {
                // The walk closed a cycle c_0 = s, ..., c_{L-1} (the stack's tail).
                let pos = stack.iter().rposition(|&x| x as usize == s).unwrap_or(0);
                let cycle = &stack[pos..];
                walk.push((n + cycle.len() - 1) as u32);
                walk.extend_from_slice(cycle);
                for &c in cycle {
                    mark[c as usize] = DONE;
                }
                stack.truncate(pos);
            }
            // The rest of the path leads into solved states.
            while let Some(u) = stack.pop() {
                walk.push(u);
                mark[u as usize] = DONE;
            }
        }
    }
}
