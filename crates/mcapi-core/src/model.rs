//! The environment model: finite states, named actions, the valid state-action
//! pairs and the known transition model P(s'|s,a) (docs/algorithm.md §1).
//!
//! Only **valid pairs** exist: an action that would leave the chain or walk into
//! a wall is simply absent. Every per-pair quantity of the algorithm (Φ, Ξ, R,
//! Q) has one row per valid pair, indexed `0..n_pairs()`; pairs are numbered in
//! state-major, action-minor order, so the pairs of state `s` are the contiguous
//! range [`EnvModel::pairs_of`]. Transitions are stored sparsely (CSR over
//! pairs), which serves deterministic and stochastic models alike.

use std::collections::HashSet;
use std::ops::Range;

use serde::{Deserialize, Serialize};

use super::error::{AlgoError, Result};
use super::spec::{ActionRef, ModelSpec, TransitionSpec};

/// Probabilities of one pair must sum to 1 within this tolerance (docs/sessions.md, "The model").
pub const PROBABILITY_TOLERANCE: f64 = 1e-9;

const NONE: u32 = u32::MAX;

/// A validated environment model with valid-pair indexing and sparse P.
#[derive(Debug, Clone, PartialEq)]
pub struct EnvModel {
    states: usize,
    actions: Vec<String>,
    stimuli: Vec<String>,
    state_names: Option<Vec<String>>,
    /// `pair_start[s]..pair_start[s+1]` are the pairs of state s.
    pair_start: Vec<u32>,
    pair_state: Vec<u32>,
    pair_action: Vec<u32>,
    /// Dense `states * actions` table of pair indices, `NONE` if unavailable.
    pair_lookup: Vec<u32>,
    /// `succ_start[p]..succ_start[p+1]` index `succ_state` / `succ_prob`.
    succ_start: Vec<u32>,
    succ_state: Vec<u32>,
    succ_prob: Vec<f64>,
    deterministic: bool,
}

fn invalid(msg: impl Into<String>) -> AlgoError {
    AlgoError::InvalidModel(msg.into())
}

/// Names of one kind: at least one, none blank, none twice.
pub(crate) fn check_names(kind: &str, names: &[String]) -> Result<()> {
    if names.is_empty() {
        return Err(invalid(format!("`{kind}` must not be empty")));
    }
    let mut seen = HashSet::with_capacity(names.len());
    for (i, name) in names.iter().enumerate() {
        if name.trim().is_empty() {
            return Err(invalid(format!("`{kind}[{i}]` is an empty name")));
        }
        if !seen.insert(name.as_str()) {
            return Err(invalid(format!("`{kind}` names `{name}` twice")));
        }
    }
    Ok(())
}

impl EnvModel {
    /// Validates a posted model. Errors name the offending field and index.
    pub fn from_spec(spec: &ModelSpec) -> Result<Self> {
        let states = spec.states;
        if states == 0 {
            return Err(invalid("`states` must be at least 1"));
        }
        check_names("actions", &spec.actions)?;
        check_names("stimuli", &spec.stimuli)?;
        let n_actions = spec.actions.len();
        if states.saturating_mul(n_actions) >= NONE as usize {
            return Err(invalid("`states` x `actions` is too large"));
        }
        if let Some(names) = &spec.state_names
            && names.len() != states
        {
            return Err(invalid(format!(
                "`state_names` has {} entries, expected {states}",
                names.len()
            )));
        }
        // rows[s * A + a] = successors of (s, a), empty when unavailable.
        let mut rows: Vec<Vec<(usize, f64)>> = vec![Vec::new(); states * n_actions];
        match (&spec.next, &spec.transitions) {
            (Some(_), Some(_)) => {
                return Err(invalid("give either `next` or `transitions`, not both"));
            }
            (None, None) => {
                return Err(invalid("one of `next` or `transitions` is required"));
            }
            (Some(next), None) => {
                if next.len() != states {
                    return Err(invalid(format!(
                        "`next` has {} rows, expected one per state ({states})",
                        next.len()
                    )));
                }
                for (s, row) in next.iter().enumerate() {
                    if row.len() != n_actions {
                        return Err(invalid(format!(
                            "`next[{s}]` has {} entries, expected one per action ({n_actions})",
                            row.len()
                        )));
                    }
                    for (a, target) in row.iter().enumerate() {
                        if let Some(t) = *target {
                            if t >= states {
                                return Err(invalid(format!(
                                    "`next[{s}][{a}]` = {t} is out of range (states are 0..{states})"
                                )));
                            }
                            rows[s * n_actions + a].push((t, 1.0));
                        }
                    }
                }
            }
            (None, Some(transitions)) => {
                for (i, tr) in transitions.iter().enumerate() {
                    let s = tr.state;
                    if s >= states {
                        return Err(invalid(format!(
                            "`transitions[{i}].state` = {s} is out of range (states are 0..{states})"
                        )));
                    }
                    let a = match &tr.action {
                        ActionRef::Index(a) if *a < n_actions => *a,
                        ActionRef::Index(a) => {
                            return Err(invalid(format!(
                                "`transitions[{i}].action` = {a} is out of range (actions are 0..{n_actions})"
                            )));
                        }
                        ActionRef::Name(name) => {
                            spec.actions.iter().position(|x| x == name).ok_or_else(|| {
                                invalid(format!(
                                    "`transitions[{i}].action` = `{name}` is not one of `actions`"
                                ))
                            })?
                        }
                    };
                    let row = &mut rows[s * n_actions + a];
                    if !row.is_empty() {
                        return Err(invalid(format!(
                            "`transitions[{i}]` repeats state {s}, action `{}`",
                            spec.actions[a]
                        )));
                    }
                    if tr.next.is_empty() {
                        return Err(invalid(format!("`transitions[{i}].next` is empty")));
                    }
                    let mut sum = 0.0;
                    for (j, &(t, p)) in tr.next.iter().enumerate() {
                        if t >= states {
                            return Err(invalid(format!(
                                "`transitions[{i}].next[{j}]` state {t} is out of range (states are 0..{states})"
                            )));
                        }
                        if !p.is_finite() || p <= 0.0 || p > 1.0 {
                            return Err(invalid(format!(
                                "`transitions[{i}].next[{j}]` probability {p} is not in (0, 1]"
                            )));
                        }
                        if tr.next[..j].iter().any(|&(u, _)| u == t) {
                            return Err(invalid(format!(
                                "`transitions[{i}].next` lists state {t} twice"
                            )));
                        }
                        sum += p;
                    }
                    if (sum - 1.0).abs() > PROBABILITY_TOLERANCE {
                        return Err(invalid(format!(
                            "`transitions[{i}]` probabilities sum to {sum}, not 1 (state {s}, action `{}`)",
                            spec.actions[a]
                        )));
                    }
                    row.extend_from_slice(&tr.next);
                }
            }
        }
        Self::from_rows(
            states,
            spec.actions.clone(),
            spec.stimuli.clone(),
            spec.state_names.clone(),
            &rows,
        )
    }

    /// Builds the CSR structure from per-(s,a) successor lists (already
    /// checked), and refuses states without any available action.
    fn from_rows(
        states: usize,
        actions: Vec<String>,
        stimuli: Vec<String>,
        state_names: Option<Vec<String>>,
        rows: &[Vec<(usize, f64)>],
    ) -> Result<Self> {
        let n_actions = actions.len();
        let mut pair_start = Vec::with_capacity(states + 1);
        let mut pair_state = Vec::new();
        let mut pair_action = Vec::new();
        let mut pair_lookup = vec![NONE; states * n_actions];
        let mut succ_start = vec![0u32];
        let mut succ_state = Vec::new();
        let mut succ_prob = Vec::new();
        let mut deterministic = true;
        for s in 0..states {
            pair_start.push(pair_state.len() as u32);
            let before = pair_state.len();
            for a in 0..n_actions {
                let row = &rows[s * n_actions + a];
                if row.is_empty() {
                    continue;
                }
                pair_lookup[s * n_actions + a] = pair_state.len() as u32;
                pair_state.push(s as u32);
                pair_action.push(a as u32);
                deterministic &= row.len() == 1;
                for &(t, p) in row {
                    succ_state.push(t as u32);
                    succ_prob.push(p);
                }
                succ_start.push(succ_state.len() as u32);
            }
            if pair_state.len() == before {
                return Err(invalid(format!("state {s} has no available action")));
            }
        }
        pair_start.push(pair_state.len() as u32);
        if deterministic {
            // A single successor carries probability 1 (within tolerance); store it exactly.
            succ_prob.iter_mut().for_each(|p| *p = 1.0);
        }
        Ok(Self {
            states,
            actions,
            stimuli,
            state_names,
            pair_start,
            pair_state,
            pair_action,
            pair_lookup,
            succ_start,
            succ_state,
            succ_prob,
            deterministic,
        })
    }

    /// The same model with one more stimulus dimension, last (the curiosity
    /// dimension of docs/algorithm.md §7: no transition delivers it, a channel
    /// does). Refuses a name the model already has.
    pub fn with_stimulus(mut self, name: &str) -> Result<Self> {
        self.stimuli.push(name.to_string());
        check_names("stimuli", &self.stimuli)?;
        Ok(self)
    }

    /// Builds a deterministic model from `next[s][a]` (`None` = unavailable).
    pub fn deterministic(
        next: Vec<Vec<Option<usize>>>,
        actions: Vec<String>,
        stimuli: Vec<String>,
    ) -> Result<Self> {
        Self::from_spec(&ModelSpec {
            states: next.len(),
            state_names: None,
            actions,
            next: Some(next),
            transitions: None,
            stimuli,
            basis: None,
        })
    }

    /// The hallway of Experiment 1 (docs/algorithm.md §6): an `n`-state chain with
    /// actions left, right, stay; state 0 lacks left and state n-1 lacks right.
    pub fn chain(n: usize, stimuli: Vec<String>) -> Result<Self> {
        let next = (0..n)
            .map(|s| vec![s.checked_sub(1), (s + 1 < n).then_some(s + 1), Some(s)])
            .collect();
        Self::deterministic(next, names(&["left", "right", "stay"]), stimuli)
    }

    /// The starting point of a learned transition model P̂ (docs/algorithm.md §8): the
    /// states, actions and valid pairs of `structure` (its P is ignored),
    /// with every pair still unknown. An unknown pair moves to the absorbing
    /// optimistic state s* = |S| when `absorbing` (R-max style: s* is one
    /// extra state with a single self-looping pair, of action 0, numbered
    /// last, so the pairs of the real states keep their indices), and stays
    /// where it is otherwise. [`EnvModel::set_successors`] then writes the
    /// rows that the counts make known.
    pub fn unknown_of(structure: &EnvModel, absorbing: bool) -> Result<Self> {
        let states = structure.states + usize::from(absorbing);
        let n_actions = structure.n_actions();
        if states.saturating_mul(n_actions) >= NONE as usize {
            return Err(invalid("`states` x `actions` is too large"));
        }
        let mut rows: Vec<Vec<(usize, f64)>> = vec![Vec::new(); states * n_actions];
        for p in 0..structure.n_pairs() {
            let s = structure.pair_state(p);
            let target = if absorbing { structure.states } else { s };
            rows[s * n_actions + structure.pair_action(p)].push((target, 1.0));
        }
        if absorbing {
            rows[structure.states * n_actions].push((structure.states, 1.0));
        }
        let state_names = structure.state_names.as_ref().map(|names| {
            let mut names = names.clone();
            if absorbing {
                names.push("(unknown)".to_string());
            }
            names
        });
        Self::from_rows(
            states,
            structure.actions.clone(),
            structure.stimuli.clone(),
            state_names,
            &rows,
        )
    }

    /// Replaces the successors of pair `p` by `next` (states and
    /// probabilities, which must sum to 1): the update of one row of a
    /// learned P̂. It costs O(|next|) when the row keeps its length and one
    /// shift of the later rows (a memmove over the stored transitions) when
    /// it gains a successor, which happens at most once per distinct
    /// successor of the pair.
    pub fn set_successors(&mut self, p: usize, next: &[(u32, f64)]) {
        debug_assert!(!next.is_empty());
        debug_assert!(
            (next.iter().map(|&(_, q)| q).sum::<f64>() - 1.0).abs() <= PROBABILITY_TOLERANCE,
            "a row of P̂ must sum to 1"
        );
        debug_assert!(next.iter().all(|&(t, _)| (t as usize) < self.states));
        let (a, b) = (self.succ_start[p] as usize, self.succ_start[p + 1] as usize);
        let old_len = b - a;
        if old_len == next.len() {
            for ((st, pr), &(t, q)) in self.succ_state[a..b]
                .iter_mut()
                .zip(&mut self.succ_prob[a..b])
                .zip(next)
            {
                *st = t;
                *pr = q;
            }
        } else {
            self.succ_state.splice(a..b, next.iter().map(|&(t, _)| t));
            self.succ_prob.splice(a..b, next.iter().map(|&(_, q)| q));
            let grow = next.len() as i64 - old_len as i64;
            for start in &mut self.succ_start[p + 1..] {
                *start = (i64::from(*start) + grow) as u32;
            }
        }
        if next.len() > 1 {
            self.deterministic = false;
        } else if old_len > 1 {
            self.deterministic =
                (0..self.n_pairs()).all(|q| self.succ_start[q + 1] - self.succ_start[q] == 1);
        }
    }

    /// Number of states |S|.
    pub fn states(&self) -> usize {
        self.states
    }

    /// Action names.
    pub fn actions(&self) -> &[String] {
        &self.actions
    }

    /// Number of actions |A| (available or not).
    pub fn n_actions(&self) -> usize {
        self.actions.len()
    }

    /// Stimulus dimension names.
    pub fn stimuli(&self) -> &[String] {
        &self.stimuli
    }

    /// Number of stimulus dimensions n.
    pub fn n_stimuli(&self) -> usize {
        self.stimuli.len()
    }

    /// Optional state names.
    pub fn state_names(&self) -> Option<&[String]> {
        self.state_names.as_deref()
    }

    /// Number of valid pairs.
    pub fn n_pairs(&self) -> usize {
        self.pair_state.len()
    }

    /// Number of stored transitions (non-zero entries of P).
    pub fn n_transitions(&self) -> usize {
        self.succ_state.len()
    }

    /// True when every valid pair has exactly one successor.
    pub fn is_deterministic(&self) -> bool {
        self.deterministic
    }

    /// The contiguous range of pair indices belonging to state `s`.
    #[inline]
    pub fn pairs_of(&self, s: usize) -> Range<usize> {
        self.pair_start[s] as usize..self.pair_start[s + 1] as usize
    }

    /// State of pair `p`.
    #[inline]
    pub fn pair_state(&self, p: usize) -> usize {
        self.pair_state[p] as usize
    }

    /// Action index of pair `p`.
    #[inline]
    pub fn pair_action(&self, p: usize) -> usize {
        self.pair_action[p] as usize
    }

    /// Pair index of (s, a), or `None` when a is unavailable in s (or out of range).
    #[inline]
    pub fn pair(&self, s: usize, a: usize) -> Option<usize> {
        if s >= self.states || a >= self.actions.len() {
            return None;
        }
        let p = self.pair_lookup[s * self.actions.len() + a];
        (p != NONE).then_some(p as usize)
    }

    /// State of every pair, in pair order.
    pub fn pair_states(&self) -> &[u32] {
        &self.pair_state
    }

    /// Action index of every pair, in pair order.
    pub fn pair_actions(&self) -> &[u32] {
        &self.pair_action
    }

    /// Successor states and probabilities of pair `p`.
    #[inline]
    pub fn successors(&self, p: usize) -> (&[u32], &[f64]) {
        let r = self.succ_start[p] as usize..self.succ_start[p + 1] as usize;
        (&self.succ_state[r.clone()], &self.succ_prob[r])
    }

    /// The single successor of every pair, in pair order, in a
    /// deterministic model (each pair has exactly one successor, so the
    /// successor table is indexed by the pair itself).
    #[inline]
    pub fn next_states(&self) -> &[u32] {
        debug_assert!(self.deterministic);
        debug_assert_eq!(self.succ_state.len(), self.n_pairs());
        &self.succ_state
    }

    /// The single successor of pair `p` in a deterministic model.
    #[inline]
    pub fn next_state(&self, p: usize) -> usize {
        debug_assert!(self.deterministic);
        self.succ_state[self.succ_start[p] as usize] as usize
    }

    /// Draws s' ~ P(.|p) with a uniform number `u` in [0, 1).
    pub fn sample_next(&self, p: usize, u: f64) -> usize {
        let (next, prob) = self.successors(p);
        let mut acc = 0.0;
        for (&t, &q) in next.iter().zip(prob) {
            acc += q;
            if u < acc {
                return t as usize;
            }
        }
        // Rounding left `acc` a hair below 1: the last successor takes the rest.
        next[next.len() - 1] as usize
    }

    /// The model back in its posted form (deterministic models as `next`).
    pub fn to_spec(&self) -> ModelSpec {
        let n_actions = self.n_actions();
        if self.deterministic {
            let next = (0..self.states)
                .map(|s| {
                    (0..n_actions)
                        .map(|a| self.pair(s, a).map(|p| self.next_state(p)))
                        .collect()
                })
                .collect();
            return self.spec_with(Some(next), None);
        }
        let transitions = (0..self.n_pairs())
            .map(|p| {
                let (next, prob) = self.successors(p);
                TransitionSpec {
                    state: self.pair_state(p),
                    action: ActionRef::Index(self.pair_action(p)),
                    next: next
                        .iter()
                        .map(|&t| t as usize)
                        .zip(prob.iter().copied())
                        .collect(),
                }
            })
            .collect();
        self.spec_with(None, Some(transitions))
    }

    fn spec_with(
        &self,
        next: Option<Vec<Vec<Option<usize>>>>,
        transitions: Option<Vec<TransitionSpec>>,
    ) -> ModelSpec {
        ModelSpec {
            states: self.states,
            state_names: self.state_names.clone(),
            actions: self.actions.clone(),
            next,
            transitions,
            stimuli: self.stimuli.clone(),
            basis: None,
        }
    }
}

/// Converts string literals to owned names.
pub fn names(list: &[&str]) -> Vec<String> {
    list.iter().map(|s| s.to_string()).collect()
}

/// A parsed ASCII grid map: `#` is a wall, `.` a free cell, and any other
/// printable character a free cell carrying that mark (a stimulus source).
/// Free cells are numbered row-major; actions are left, right, north, south,
/// stay, and moves into walls or off the map are unavailable.
#[derive(Debug, Clone, PartialEq)]
pub struct GridMap {
    rows: usize,
    cols: usize,
    /// `cell_state[r * cols + c]`: state of a free cell, `None` for a wall.
    cell_state: Vec<Option<usize>>,
    /// `(row, col)` of each state.
    state_cell: Vec<(usize, usize)>,
    /// Marked cells in row-major order: `(mark, state)`.
    marks: Vec<(char, usize)>,
}

/// Action names of grid maps, in index order.
pub const GRID_ACTIONS: [&str; 5] = ["left", "right", "north", "south", "stay"];

impl GridMap {
    /// Parses map lines; blank trailing lines are ignored, rows must have equal width.
    pub fn parse<S: AsRef<str>>(lines: &[S]) -> Result<Self> {
        let lines: Vec<&str> = lines
            .iter()
            .map(|l| l.as_ref().trim_end_matches(['\r', '\n']))
            .collect();
        let rows = lines
            .iter()
            .rposition(|l| !l.trim().is_empty())
            .map_or(0, |i| i + 1);
        if rows == 0 {
            return Err(invalid("grid map is empty"));
        }
        let cols = lines[0].chars().count();
        // Rows are checked one by one below: reserve no more than the map
        // actually holds, whatever its first row claims.
        let cells: usize = lines[..rows].iter().map(|l| l.len()).sum();
        let mut cell_state = Vec::with_capacity(cells.min(rows.saturating_mul(cols)));
        let mut state_cell = Vec::new();
        let mut marks = Vec::new();
        for (r, line) in lines[..rows].iter().enumerate() {
            let width = line.chars().count();
            if width != cols {
                return Err(invalid(format!(
                    "grid row {r} has {width} columns, expected {cols} like row 0"
                )));
            }
            for (c, ch) in line.chars().enumerate() {
                match ch {
                    '#' => cell_state.push(None),
                    '.' => {
                        cell_state.push(Some(state_cell.len()));
                        state_cell.push((r, c));
                    }
                    ch if ch.is_ascii_graphic() => {
                        marks.push((ch, state_cell.len()));
                        cell_state.push(Some(state_cell.len()));
                        state_cell.push((r, c));
                    }
                    other => {
                        return Err(invalid(format!(
                            "grid row {r}, column {c}: unexpected character {other:?} (use `#`, `.` or a letter)"
                        )));
                    }
                }
            }
        }
        if state_cell.is_empty() {
            return Err(invalid("grid map has no free cell"));
        }
        Ok(Self {
            rows,
            cols,
            cell_state,
            state_cell,
            marks,
        })
    }

    /// Parses a map from text (one row per line).
    pub fn from_text(text: &str) -> Result<Self> {
        Self::parse(&text.lines().collect::<Vec<_>>())
    }

    /// Map height in cells.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Map width in cells.
    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Number of free cells (states).
    pub fn states(&self) -> usize {
        self.state_cell.len()
    }

    /// State of cell (row, col), `None` for walls and cells off the map.
    pub fn state_at(&self, row: usize, col: usize) -> Option<usize> {
        if row >= self.rows || col >= self.cols {
            return None;
        }
        self.cell_state[row * self.cols + col]
    }

    /// Cell (row, col) of a state.
    pub fn cell_of(&self, state: usize) -> (usize, usize) {
        self.state_cell[state]
    }

    /// Marked cells in row-major order.
    pub fn marks(&self) -> &[(char, usize)] {
        &self.marks
    }

    /// State of the (first) cell marked `mark`.
    pub fn mark_state(&self, mark: char) -> Option<usize> {
        self.marks.iter().find(|(m, _)| *m == mark).map(|&(_, s)| s)
    }

    /// The deterministic grid-world model with the five grid actions.
    pub fn model(&self, stimuli: Vec<String>) -> Result<EnvModel> {
        let next = self
            .state_cell
            .iter()
            .map(|&(r, c)| {
                let left = c.checked_sub(1).and_then(|c| self.state_at(r, c));
                let right = self.state_at(r, c + 1);
                let north = r.checked_sub(1).and_then(|r| self.state_at(r, c));
                let south = self.state_at(r + 1, c);
                let stay = self.state_at(r, c);
                vec![left, right, north, south, stay]
            })
            .collect();
        EnvModel::deterministic(next, names(&GRID_ACTIONS), stimuli)
    }
}

/// A stimulus source of a preset: the state where dimension `dim` is delivered.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Source {
    /// Stimulus dimension fed at this state.
    pub dim: usize,
    /// The state.
    pub state: usize,
}

/// A ready-made environment of the paper, with its stimulus sources.
#[derive(Debug, Clone)]
pub struct Preset {
    /// The model.
    pub model: EnvModel,
    /// The stimulus sources.
    pub sources: Vec<Source>,
    /// The grid map, for presets built from one.
    pub grid: Option<GridMap>,
}

/// The three-room map of Experiment 2 (`data/three_room.txt`).
pub const THREE_ROOM_MAP: &str = include_str!("../../../data/three_room.txt");

/// The curiosity room of Experiment 3 (`data/curiosity_room.txt`).
pub const CURIOSITY_ROOM_MAP: &str = include_str!("../../../data/curiosity_room.txt");

/// Hallway of Experiment 1: 50 states, food (dim 0) at 10, rest (dim 1) at 40.
pub fn hallway() -> Preset {
    // The chain is valid by construction.
    let model = EnvModel::chain(50, names(&["food", "rest"]))
        .unwrap_or_else(|e| unreachable!("hallway preset is valid: {e}"));
    Preset {
        model,
        sources: vec![Source { dim: 0, state: 10 }, Source { dim: 1, state: 40 }],
        grid: None,
    }
}

/// Builds a preset from a grid map whose marks `marks[i]` feed dimension i.
pub fn grid_preset(text: &str, marks: &[(char, &str)]) -> Result<Preset> {
    let grid = GridMap::from_text(text)?;
    let mut sources = Vec::with_capacity(marks.len());
    for (dim, &(mark, _)) in marks.iter().enumerate() {
        let state = grid
            .mark_state(mark)
            .ok_or_else(|| invalid(format!("grid map has no cell marked `{mark}`")))?;
        sources.push(Source { dim, state });
    }
    let stimuli = marks.iter().map(|&(_, name)| name.to_string()).collect();
    let model = grid.model(stimuli)?;
    Ok(Preset {
        model,
        sources,
        grid: Some(grid),
    })
}

/// Three-room maze of Experiment 2: sources `a`, `b`, `c` are dims 0, 1, 2.
pub fn three_room() -> Preset {
    grid_preset(THREE_ROOM_MAP, &[('a', "a"), ('b', "b"), ('c', "c")])
        .unwrap_or_else(|e| unreachable!("three-room preset is valid: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec_json(json: &str) -> ModelSpec {
        serde_json::from_str(json).expect("valid JSON spec")
    }

    fn err_of(json: &str) -> String {
        EnvModel::from_spec(&spec_json(json))
            .expect_err("model must be rejected")
            .to_string()
    }

    #[test]
    fn hallway_has_expected_pairs() {
        let h = hallway().model;
        assert_eq!(h.states(), 50);
        assert_eq!(h.n_pairs(), 50 * 3 - 2);
        assert!(h.is_deterministic());
        assert_eq!(h.pair(0, 0), None, "state 0 has no left");
        assert_eq!(h.pair(49, 1), None, "state 49 has no right");
        let p = h.pair(10, 1).expect("right from 10");
        assert_eq!(h.next_state(p), 11);
        assert_eq!(h.pairs_of(0), 0..2);
        assert_eq!(h.pair_action(0), 1);
    }

    #[test]
    fn three_room_has_200_cells_and_sources() {
        let p = three_room();
        assert_eq!(p.model.states(), 200);
        assert_eq!(p.sources.len(), 3);
        let g = p.grid.expect("grid preset");
        // `a` is on row 8, column 2 of the map.
        assert_eq!(g.cell_of(p.sources[0].state), (8, 2));
        // Every free cell can stay; doorways connect the rooms.
        for s in 0..200 {
            assert!(p.model.pair(s, 4).is_some());
        }
    }

    #[test]
    fn stochastic_model_round_trips() {
        let m = EnvModel::from_spec(&spec_json(
            r#"{"states":2,"actions":["go"],"stimuli":["x"],
                "transitions":[{"state":0,"action":"go","next":[[0,0.25],[1,0.75]]},
                               {"state":1,"action":0,"next":[[0,1.0]]}]}"#,
        ))
        .expect("valid");
        assert!(!m.is_deterministic());
        assert_eq!(m.successors(0).1, &[0.25, 0.75]);
        assert_eq!(m.sample_next(0, 0.2), 0);
        assert_eq!(m.sample_next(0, 0.3), 1);
        assert_eq!(EnvModel::from_spec(&m.to_spec()).expect("round trip"), m);
    }

    #[test]
    fn invalid_models_name_the_problem() {
        let cases = [
            (
                r#"{"states":2,"actions":["a"],"stimuli":["x"],"next":[[1],[2]]}"#,
                "`next[1][0]` = 2 is out of range",
            ),
            (
                r#"{"states":2,"actions":["a"],"stimuli":["x"],"next":[[1],[null]]}"#,
                "state 1 has no available action",
            ),
            (
                r#"{"states":2,"actions":["a"],"stimuli":["x"],"next":[[1]]}"#,
                "`next` has 1 rows",
            ),
            (
                r#"{"states":1,"actions":["a"],"stimuli":["x"],
                   "transitions":[{"state":0,"action":0,"next":[[0,0.5]]}]}"#,
                "probabilities sum to 0.5",
            ),
            (
                r#"{"states":1,"actions":["a"],"stimuli":["x"],
                   "transitions":[{"state":0,"action":"b","next":[[0,1.0]]}]}"#,
                "`b` is not one of `actions`",
            ),
            (
                r#"{"states":1,"actions":["a"],"stimuli":["x"],
                   "transitions":[{"state":3,"action":0,"next":[[0,1.0]]}]}"#,
                "`transitions[0].state` = 3 is out of range",
            ),
            (
                r#"{"states":1,"actions":["a"],"stimuli":["x"],
                   "transitions":[{"state":0,"action":0,"next":[[0,-1.0],[0,2.0]]}]}"#,
                "probability -1 is not in (0, 1]",
            ),
            (
                r#"{"states":1,"actions":["a","a"],"stimuli":["x"],"next":[[0,0]]}"#,
                "`actions` names `a` twice",
            ),
            (
                r#"{"states":1,"actions":["a"],"stimuli":[],"next":[[0]]}"#,
                "`stimuli` must not be empty",
            ),
            (
                r#"{"states":0,"actions":["a"],"stimuli":["x"],"next":[]}"#,
                "`states` must be at least 1",
            ),
            (
                r#"{"states":1,"actions":["a"],"stimuli":["x"]}"#,
                "one of `next` or `transitions` is required",
            ),
        ];
        for (json, expected) in cases {
            let msg = err_of(json);
            assert!(
                msg.contains(expected),
                "{msg:?} should contain {expected:?}"
            );
        }
    }

    #[test]
    fn grid_rejects_ragged_rows_and_bad_characters() {
        let e = GridMap::parse(&["###", "#.", "###"]).expect_err("ragged");
        assert!(e.to_string().contains("grid row 1 has 2 columns"), "{e}");
        let e = GridMap::parse(&["#\t#"]).expect_err("tab");
        assert!(e.to_string().contains("unexpected character"), "{e}");
        let e = GridMap::parse(&["###"]).expect_err("no free cell");
        assert!(e.to_string().contains("no free cell"), "{e}");
    }

    #[test]
    fn grid_moves_respect_walls() {
        let g = GridMap::parse(&["####", "#.a#", "####"]).expect("valid");
        let m = g.model(names(&["x"])).expect("model");
        assert_eq!(m.states(), 2);
        assert_eq!(g.marks(), &[('a', 1)]);
        assert_eq!(m.pair(0, 0), None, "wall on the left");
        let right = m.pair(0, 1).expect("right is free");
        assert_eq!(m.next_state(right), 1);
        assert_eq!(m.pair(0, 2), None, "wall to the north");
    }
}
