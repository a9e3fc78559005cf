//! The grid planner (docs/algorithm.md §9.8): MCA-PI on a continuous
//! space through a grid of cells over the normalised box, with a
//! transition model learned locally from the agent's own moves.
//!
//! - **Transitions.** Each (cell, action) keeps the displacements s′ − s
//!   of the `neighbours` observed transitions with that action whose start
//!   is nearest the cell's centre, within a reach. Its successor is the
//!   cell of the centre moved by their mean displacement. A transition
//!   that did not move (a push into a wall) reaches only 1.5 cells, one
//!   that moved `reach` cells (default 3.5), so a blocked move teaches the
//!   cells along the wall and one free move teaches the open space around
//!   it. When most of its kept transitions did not move, the pair stays in
//!   its cell (a majority, so that the noise that blocks some moves along
//!   a wall does not make a free move look blocked). A transition that
//!   starts inside a cell counts as the nearest possible for that cell,
//!   newest first, so what the agent just saw where it stands outweighs
//!   what it saw elsewhere.
//! - **Knownness and optimism.** A pair with no transition within reach is
//!   unknown and worth Q_opt = R_max / (1 − γ) (R-max, as §8 and §9.4).
//! - **Ξ (line 5).** The stimulus of a cell is the mean of what was
//!   received on arriving in it; a cell never entered takes the stimulus
//!   last received within one cell of its centre; one nowhere near a
//!   received stimulus keeps the optimistic prior N(0, σ²) of §3. The
//!   reward of a pair (line 8) is that of its successor cell,
//!   R(c, a) = |Ξ(succ(c, a)) · ΛD|.
//! - **Planning (line 9).** The model is deterministic, so the policy's
//!   graph is functional (one successor per cell): one exact evaluation
//!   of V^π along it, as LSTDQ with the indicator basis of the cells
//!   would give, and one greedy improvement of every cell, each tick.
//!
//! Everything is a function of the observations and of the prior's draws,
//! in a fixed order, so a replay gives the same bits.

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use super::space::MAX_DIM;

/// Most cells of a grid (cells_per_dim^d): as many as a basis has features
/// (`MAX_STATE_FEATURES`, checked where the basis is defined).
pub const MAX_GRID_CELLS: usize = 4096;
/// Cells per dimension of the default grid (d ≤ 2), where they fit.
pub const DEFAULT_GRID_CELLS_PER_DIM: usize = 64;
/// Most (cell, action) pairs of a grid.
pub const MAX_GRID_PAIRS: usize = 16_384;
/// Most transitions kept per (cell, action).
pub const MAX_GRID_NEIGHBOURS: u32 = 16;
/// Default transitions kept per (cell, action).
pub const DEFAULT_GRID_NEIGHBOURS: u32 = 5;
/// Default reach of a transition that moved, in cells.
pub const DEFAULT_GRID_REACH: f64 = 3.5;
/// Largest reach, in cells.
pub const MAX_GRID_REACH: f64 = 8.0;
/// Reach of a transition that did not move, in cells.
pub const BLOCKED_REACH: f64 = 1.5;
/// A transition moved less than this in every coordinate, in cells, did
/// not move.
pub const BLOCKED_MOVE: f64 = 0.25;
/// Reach of a received stimulus over cells never entered, in cells.
pub const STIMULUS_REACH: f64 = 1.0;

/// Actions within this relative distance of the best Q are tied
/// (docs/algorithm.md §2.6).
const TIE: f64 = 1e-10;

/// No successor: the pair is unknown.
const UNKNOWN: u32 = u32::MAX;

/// The shape of a grid planner, checked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridShape {
    /// The space's dimension.
    pub d: usize,
    /// Cells per dimension.
    pub cells_per_dim: usize,
    /// Transitions kept per (cell, action).
    pub neighbours: usize,
    /// How far a move teaches, in cells.
    pub reach: f64,
}

impl GridShape {
    /// cells_per_dim^d.
    pub fn cells(&self) -> usize {
        self.cells_per_dim.pow(self.d as u32)
    }
}

/// The grid planner of one agent.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridPlanner {
    d: usize,
    /// Cells per dimension.
    res: usize,
    actions: usize,
    stimuli: usize,
    /// Transitions kept per pair.
    neighbours: usize,
    /// Reach of a transition that moved, in normalised units.
    reach: f64,
    gamma: f64,
    /// Per pair, `neighbours` slots of (distance, Δ₁..Δ_d), nearest first;
    /// an empty slot has distance +∞.
    slots: Vec<f64>,
    /// Per pair, the successor cell ([`UNKNOWN`]: no transition in reach).
    succ: Vec<u32>,
    /// Per cell, the sum of the stimuli received on arriving, and how many.
    stimulus_sum: Vec<f64>,
    arrivals: Vec<u32>,
    /// Per cell never entered, the stimulus last received nearest it
    /// within [`STIMULUS_REACH`], and that distance (+∞: none).
    near: Vec<f64>,
    near_distance: Vec<f64>,
    /// Ξ's prior per cell.
    prior: Vec<f64>,
    /// π per cell.
    policy: Vec<u8>,
    /// V^π per cell, as of the last plan.
    v: Vec<f64>,
    /// |Ξ(c) · ΛD| per cell, as of the last plan.
    reward: Vec<f64>,
    r_max: f64,
    /// Pairs with a successor.
    known: usize,
    /// Slots holding a transition.
    kept: usize,
    /// Scratch of the evaluation: 1 on the walk, 2 done.
    #[serde(skip)]
    mark: Vec<u8>,
    #[serde(skip)]
    walk: Vec<u32>,
}

/// Counters of a grid planner.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GridStats {
    /// Transitions kept.
    pub kept: usize,
    /// (cell, action) pairs with a successor.
    pub known: usize,
}

impl GridPlanner {
    /// A grid of `res`^d cells (checked by the caller against
    /// [`MAX_GRID_CELLS`] and [`MAX_GRID_PAIRS`]), Ξ's prior drawn from
    /// `rng`, N(0, `prior_sd`²) per cell and stimulus, cell by cell.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        d: usize,
        res: usize,
        actions: usize,
        stimuli: usize,
        neighbours: usize,
        reach_cells: f64,
        gamma: f64,
        prior_sd: f64,
        rng: &mut impl Rng,
    ) -> Self {
        let cells = res.pow(d as u32);
        debug_assert!(cells <= MAX_GRID_CELLS && cells * actions <= MAX_GRID_PAIRS);
        debug_assert!(actions <= u8::MAX as usize + 1);
        let prior = (0..cells * stimuli)
            .map(|_| {
                let z: f64 = StandardNormal.sample(rng);
                prior_sd * z
            })
            .collect();
        Self {
            d,
            res,
            actions,
            stimuli,
            neighbours,
            reach: reach_cells / res as f64,
            gamma,
            slots: vec![f64::INFINITY; cells * actions * neighbours * (1 + d)],
            succ: vec![UNKNOWN; cells * actions],
            stimulus_sum: vec![0.0; cells * stimuli],
            arrivals: vec![0; cells],
            near: vec![0.0; cells * stimuli],
            near_distance: vec![f64::INFINITY; cells],
            prior,
            policy: vec![0; cells],
            v: vec![0.0; cells],
            reward: vec![0.0; cells],
            r_max: 0.0,
            known: 0,
            kept: 0,
            mark: Vec::new(),
            walk: Vec::new(),
        }
    }

    /// Whether the planner fits a grid of this shape with these actions
    /// and stimuli (a snapshot's check).
    pub fn fits(&self, shape: &GridShape, actions: usize, stimuli: usize) -> bool {
        let (d, res) = (shape.d, shape.cells_per_dim);
        let cells = res.checked_pow(d as u32).unwrap_or(usize::MAX);
        let pairs = cells.saturating_mul(actions);
        self.d == d
            && self.res == res
            && self.neighbours == shape.neighbours
            && self.reach.to_bits() == (shape.reach / res as f64).to_bits()
            && self.actions == actions
            && self.stimuli == stimuli
            && cells <= MAX_GRID_CELLS
            && pairs <= MAX_GRID_PAIRS
            && self.slots.len() == pairs * self.neighbours * (1 + d)
            && self.succ.len() == pairs
            && self
                .succ
                .iter()
                .all(|&s| s == UNKNOWN || (s as usize) < cells)
            && self.policy.iter().all(|&a| (a as usize) < actions)
            && [&self.stimulus_sum, &self.near, &self.prior]
                .iter()
                .all(|v| v.len() == cells * stimuli)
            && [&self.near_distance, &self.v, &self.reward]
                .iter()
                .all(|v| v.len() == cells)
            && self.arrivals.len() == cells
            && self.policy.len() == cells
            && self.r_max.is_finite()
            && self.v.iter().chain(&self.reward).all(|x| x.is_finite())
    }

    /// Number of cells.
    pub fn cells(&self) -> usize {
        self.arrivals.len()
    }

    /// Counters.
    pub fn stats(&self) -> GridStats {
        GridStats {
            kept: self.kept,
            known: self.known,
        }
    }

    /// The cell of a normalised point.
    pub fn cell_of(&self, s: &[f64]) -> usize {
        let mut cell = 0;
        for &x in s.iter().rev() {
            let i = ((x * self.res as f64).floor().max(0.0) as usize).min(self.res - 1);
            cell = cell * self.res + i;
        }
        cell
    }

    /// Writes the centre of `cell` into `out`.
    fn centre_into(&self, mut cell: usize, out: &mut [f64]) {
        for x in out.iter_mut() {
            *x = ((cell % self.res) as f64 + 0.5) / self.res as f64;
            cell /= self.res;
        }
    }

    /// Calls `f(cell, distance)` for every cell whose centre lies within
    /// `radius` of `p`, in increasing cell order.
    fn for_cells_near(&mut self, p: &[f64], radius: f64, mut f: impl FnMut(&mut Self, usize, f64)) {
        let res = self.res as f64;
        let top = self.res - 1;
        let (mut lo, mut hi) = ([0usize; MAX_DIM], [0usize; MAX_DIM]);
        for (j, &x) in p.iter().enumerate() {
            lo[j] = (((x - radius) * res).floor().max(0.0) as usize).min(top);
            hi[j] = (((x + radius) * res).floor().max(0.0) as usize).min(top);
        }
        let mut idx = lo;
        loop {
            let mut cell = 0;
            let mut dist2 = 0.0;
            for j in (0..self.d).rev() {
                cell = cell * self.res + idx[j];
                let centre = (idx[j] as f64 + 0.5) / res;
                dist2 += (centre - p[j]) * (centre - p[j]);
            }
            let dist = dist2.sqrt();
            if dist <= radius {
                f(self, cell, dist);
            }
            // The next index, dimension 0 fastest.
            let mut j = 0;
            loop {
                if j == self.d {
                    return;
                }
                if idx[j] < hi[j] {
                    idx[j] += 1;
                    break;
                }
                idx[j] = lo[j];
                j += 1;
            }
        }
    }

    /// Line 5 and the model: the transition (s, a, s′) with stimulus ξ
    /// received at s′ (all points normalised).
    pub fn observe(&mut self, s: &[f64], a: usize, s_next: &[f64], xi: &[f64]) {
        let d = self.d;
        let cell_width = 1.0 / self.res as f64;
        let mut delta = [0.0f64; MAX_DIM];
        let delta = &mut delta[..d];
        for ((m, y), x) in delta.iter_mut().zip(s_next).zip(s) {
            *m = y - x;
        }
        let delta = &*delta;
        let moved = delta.iter().any(|x| x.abs() >= BLOCKED_MOVE * cell_width);
        let radius = if moved {
            self.reach
        } else {
            BLOCKED_REACH * cell_width
        };
        let own = 0.5 * (d as f64).sqrt() * cell_width;
        self.for_cells_near(s, radius, |g, cell, dist| {
            let dist = if dist <= own { 0.0 } else { dist };
            g.keep(cell * g.actions + a, dist, delta);
        });
        // Ξ: the arrival cell, and the cells never entered near s′.
        let arrived = self.cell_of(s_next);
        let n = self.stimuli;
        self.arrivals[arrived] += 1;
        for (sum, x) in self.stimulus_sum[arrived * n..(arrived + 1) * n]
            .iter_mut()
            .zip(xi)
        {
            *sum += x;
        }
        self.for_cells_near(s_next, STIMULUS_REACH * cell_width, |g, cell, dist| {
            if dist <= g.near_distance[cell] {
                g.near_distance[cell] = dist;
                g.near[cell * n..(cell + 1) * n].copy_from_slice(xi);
            }
        });
    }

    /// Keeps a transition of displacement `delta` at `dist` from pair
    /// `pair`'s cell centre among its nearest, then re-derives the pair's
    /// successor.
    fn keep(&mut self, pair: usize, dist: f64, delta: &[f64]) {
        let (k, w) = (self.neighbours, 1 + self.d);
        let slots = &mut self.slots[pair * k * w..(pair + 1) * k * w];
        let Some(pos) = (0..k).find(|&i| dist <= slots[i * w]) else {
            return;
        };
        if slots[(k - 1) * w].is_infinite() {
            self.kept += 1;
        }
        slots[pos * w..].rotate_right(w);
        slots[pos * w] = dist;
        slots[pos * w + 1..(pos + 1) * w].copy_from_slice(delta);
        let cell = pair / self.actions;
        let cell_width = 1.0 / self.res as f64;
        let still = |slot: &[f64]| {
            slot[1..]
                .iter()
                .all(|x| x.abs() < BLOCKED_MOVE * cell_width)
        };
        let mut mean = [0.0f64; MAX_DIM];
        let (mut moved, mut blocked) = (0u32, 0u32);
        for slot in slots.chunks_exact(w).take_while(|slot| slot[0].is_finite()) {
            if still(slot) {
                blocked += 1;
            } else {
                mean.iter_mut().zip(&slot[1..]).for_each(|(m, x)| *m += x);
                moved += 1;
            }
        }
        let next = if blocked > moved {
            cell
        } else {
            let mut target = [0.0f64; MAX_DIM];
            let target = &mut target[..self.d];
            self.centre_into(cell, target);
            for (t, m) in target.iter_mut().zip(&mean) {
                *t = (*t + m / f64::from(moved)).clamp(0.0, 1.0);
            }
            self.cell_of(target)
        };
        if self.succ[pair] == UNKNOWN {
            self.known += 1;
        }
        self.succ[pair] = next as u32;
    }

    /// Line 8: R of every cell for the drive `scaled` = Λ D, and R_max.
    /// Ξ of a cell is the mean of its arrivals, else the nearest received
    /// stimulus, else the prior.
    pub fn rewards(&mut self, scaled: &[f64]) {
        let n = self.stimuli;
        let mut r_max: f64 = 0.0;
        for cell in 0..self.cells() {
            let at = cell * n..(cell + 1) * n;
            let dot: f64 = if self.arrivals[cell] > 0 {
                let count = f64::from(self.arrivals[cell]);
                self.stimulus_sum[at]
                    .iter()
                    .zip(scaled)
                    .map(|(x, l)| x / count * l)
                    .sum()
            } else if self.near_distance[cell].is_finite() {
                self.near[at].iter().zip(scaled).map(|(x, l)| x * l).sum()
            } else {
                self.prior[at].iter().zip(scaled).map(|(x, l)| x * l).sum()
            };
            self.reward[cell] = dot.abs();
            r_max = r_max.max(dot.abs());
        }
        self.r_max = r_max;
    }

    /// Q_opt of an unknown pair: R_max for ever.
    fn q_opt(&self) -> f64 {
        self.r_max / (1.0 - self.gamma)
    }

    /// Q(cell, a) as the agent acts on it.
    pub fn q(&self, cell: usize, a: usize) -> f64 {
        match self.succ[cell * self.actions + a] {
            UNKNOWN => self.q_opt(),
            next => self.reward[next as usize] + self.gamma * self.v[next as usize],
        }
    }

    /// Lines 8-9: R for the drive `scaled` = Λ D, one exact evaluation of
    /// V^π on the functional graph of π, one greedy improvement of every
    /// cell (ties keep π).
    pub fn plan(&mut self, scaled: &[f64]) {
        self.rewards(scaled);
        self.evaluate();
        for cell in 0..self.cells() {
            let current = self.policy[cell] as usize;
            let mut best = (current, self.q(cell, current));
            for a in 0..self.actions {
                let q = self.q(cell, a);
                if q > best.1 + TIE * (1.0 + best.1.abs()) {
                    best = (a, q);
                }
            }
            self.policy[cell] = best.0 as u8;
        }
        debug_assert!(self.v.iter().all(|v| v.is_finite()));
    }

    /// V^π(c) = R(c, π(c)) + γ V^π(succ(c, π(c))), or Q_opt where that
    /// pair is unknown: each walk of π's successors ends at a cell already
    /// valued, at an unknown pair, or in a cycle, which is solved in
    /// closed form; then the walk is valued backwards.
    fn evaluate(&mut self) {
        let cells = self.cells();
        let g = self.gamma;
        let q_opt = self.q_opt();
        let mut mark = std::mem::take(&mut self.mark);
        let mut walk = std::mem::take(&mut self.walk);
        mark.clear();
        mark.resize(cells, 0);
        let next_of = |s: &Self, c: usize| s.succ[c * s.actions + s.policy[c] as usize];
        for start in 0..cells {
            let mut c = start;
            walk.clear();
            while mark[c] == 0 {
                let next = next_of(self, c);
                if next == UNKNOWN {
                    self.v[c] = q_opt;
                    mark[c] = 2;
                    break;
                }
                mark[c] = 1;
                walk.push(c as u32);
                c = next as usize;
            }
            if mark[c] == 1 {
                // A cycle: from c's place on the walk to its end.
                let from = walk.iter().rposition(|&x| x as usize == c).unwrap_or(0);
                let (mut sum, mut discount) = (0.0, 1.0);
                for &x in &walk[from..] {
                    sum += discount * self.reward[next_of(self, x as usize) as usize];
                    discount *= g;
                }
                self.v[c] = sum / (1.0 - discount);
                mark[c] = 2;
                for i in (from + 1..walk.len()).rev() {
                    let x = walk[i] as usize;
                    let next = next_of(self, x) as usize;
                    self.v[x] = self.reward[next] + g * self.v[next];
                    mark[x] = 2;
                }
                walk.truncate(from);
            }
            while let Some(x) = walk.pop() {
                let x = x as usize;
                let next = next_of(self, x) as usize;
                self.v[x] = self.reward[next] + g * self.v[next];
                mark[x] = 2;
            }
        }
        self.mark = mark;
        self.walk = walk;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn planner(d: usize, res: usize, actions: usize) -> GridPlanner {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        GridPlanner::new(d, res, actions, 1, 5, 3.5, 0.9, 0.3, &mut rng)
    }

    #[test]
    fn cells_and_centres_agree() {
        let g = planner(2, 10, 4);
        let mut centre = vec![0.0; 2];
        for cell in 0..g.cells() {
            g.centre_into(cell, &mut centre);
            assert_eq!(g.cell_of(&centre), cell);
        }
        assert_eq!(g.cell_of(&[0.0, 0.0]), 0);
        assert_eq!(g.cell_of(&[1.0, 1.0]), 99);
        assert_eq!(g.cell_of(&[0.95, 0.05]), 9);
    }

    #[test]
    fn one_free_move_teaches_the_cells_around_it() {
        let mut g = planner(2, 10, 4);
        g.observe(&[0.55, 0.55], 1, &[0.65, 0.55], &[0.0]);
        // The start's own cell and its neighbours within 3.5 cells move east.
        let own = g.cell_of(&[0.55, 0.55]);
        assert_eq!(g.succ[own * 4 + 1] as usize, g.cell_of(&[0.65, 0.55]));
        let near = g.cell_of(&[0.35, 0.55]);
        assert_eq!(g.succ[near * 4 + 1] as usize, g.cell_of(&[0.45, 0.55]));
        // Other actions and far cells stay unknown.
        assert_eq!(g.succ[own * 4], UNKNOWN);
        assert_eq!(g.succ[g.cell_of(&[0.05, 0.95]) * 4 + 1], UNKNOWN);
    }

    #[test]
    fn blocked_moves_override_free_moves_where_they_outnumber_them() {
        let mut g = planner(2, 10, 4);
        g.observe(&[0.25, 0.55], 1, &[0.35, 0.55], &[0.0]);
        let wall = g.cell_of(&[0.55, 0.55]);
        assert_ne!(g.succ[wall * 4 + 1] as usize, wall, "generalised: moves");
        // One push that did not move is outvoted by the move that did
        // (noise near a wall blocks some moves that mostly pass) ...
        g.observe(&[0.57, 0.53], 1, &[0.57, 0.53], &[0.0]);
        assert_ne!(g.succ[wall * 4 + 1] as usize, wall);
        // ... a second one is not.
        g.observe(&[0.56, 0.54], 1, &[0.56, 0.54], &[0.0]);
        assert_eq!(
            g.succ[wall * 4 + 1] as usize,
            wall,
            "blocked where it was pushed"
        );
        // Two cells away the free move is still the nearest.
        let open = g.cell_of(&[0.35, 0.55]);
        assert_ne!(g.succ[open * 4 + 1] as usize, open);
    }

    #[test]
    fn the_value_of_a_cycle_is_its_discounted_reward() {
        // Two cells; each move teaches both (reach 1.75 of the box): east
        // leads into cell 1 or stays there, west into cell 0 or stays.
        // A stimulus of 1 on arriving in cell 1, none in cell 0.
        let mut g = planner(1, 2, 2);
        g.observe(&[0.25], 1, &[0.75], &[1.0]);
        g.observe(&[0.75], 0, &[0.25], &[0.0]);
        assert_eq!(g.succ, vec![0, 1, 0, 1]);
        g.plan(&[1.0]);
        g.plan(&[1.0]);
        let gamma: f64 = 0.9;
        // π: east everywhere; V(1) is a cycle of one cell, 1 / (1 − γ).
        assert_eq!(g.policy, vec![1, 1]);
        let v1 = 1.0 / (1.0 - gamma);
        assert!((g.v[1] - v1).abs() < 1e-12, "{} vs {v1}", g.v[1]);
        assert!((g.q(0, 1) - (1.0 + gamma * v1)).abs() < 1e-12);
        assert!((g.q(1, 0) - gamma * g.v[0]).abs() < 1e-12);
        assert!((g.v[0] - (1.0 + gamma * v1)).abs() < 1e-12);
    }

    #[test]
    fn a_two_cell_cycle_is_solved_in_closed_form() {
        let mut g = planner(1, 2, 2);
        g.observe(&[0.25], 1, &[0.75], &[1.0]);
        g.observe(&[0.75], 0, &[0.25], &[0.0]);
        // π swaps the cells: 0 → 1 (reward 1) → 0 (reward 0) → ...
        g.policy = vec![1, 0];
        g.rewards(&[1.0]);
        g.evaluate();
        let gamma: f64 = 0.9;
        let v0 = 1.0 / (1.0 - gamma * gamma);
        assert!((g.v[0] - v0).abs() < 1e-12, "{} vs {v0}", g.v[0]);
        assert!((g.v[1] - gamma * v0).abs() < 1e-12);
    }

    #[test]
    fn unknown_pairs_are_optimistic_and_the_policy_heads_for_them() {
        let mut g = planner(1, 10, 2);
        // Moving right is known from every cell; left nowhere.
        for i in 0..9 {
            let x = (i as f64 + 0.5) / 10.0;
            g.observe(&[x], 1, &[x + 0.1], &[0.0]);
        }
        g.plan(&[1.0]);
        assert!(g.r_max > 0.0);
        for cell in 0..10 {
            assert!((g.q(cell, 0) - g.q_opt()).abs() < 1e-12);
        }
    }

    #[test]
    fn a_replay_gives_the_same_bits() {
        let run = || {
            let mut g = planner(2, 8, 4);
            let mut rng = ChaCha8Rng::seed_from_u64(9);
            let mut x: Vec<f64> = vec![0.5, 0.5];
            for t in 0..500 {
                let a = rng.random_range(0..4);
                let step: (f64, f64) = [(-0.1, 0.0), (0.1, 0.0), (0.0, -0.1), (0.0, 0.1)][a];
                let y = vec![
                    (x[0] + step.0 + 0.01 * rng.random::<f64>()).clamp(0.0, 1.0),
                    (x[1] + step.1).clamp(0.0, 1.0),
                ];
                let xi = [if t % 7 == 0 { 5.0 } else { 0.0 }];
                g.observe(&x, a, &y, &xi);
                g.plan(&[1.0]);
                x = y;
            }
            g
        };
        assert_eq!(run(), run());
    }
}
