//! The graph a PVF basis is built on, grown observation by observation,
//! and when the basis is rebuilt (docs/algorithm.md §9.2).
//!
//! **Nodes.** An observation becomes a node when it is farther than
//! δ = `nodes`^(−1/d) from every node (the spacing of a grid of `nodes`
//! points filling the box), until there are `nodes` of them: a greedy
//! δ-net of what the agent has seen, even whatever the agent dwells on.
//!
//! **Edges** ([`EDGES`]). With [`Edges::Transitions`] (the default), two
//! nodes are joined when the agent moved from a point nearest to one to a
//! point nearest to the other: the graph of observed transitions. A wall
//! thicker than δ is never crossed by such an edge (a point on one side
//! has a node of its own side within δ, nearer than any behind the wall),
//! and the trajectory is a walk on the graph, so every node is connected.
//! Each node keeps at most `neighbours` edges (later ones are dropped).
//! [`Edges::Nearest`] joins each node to its `neighbours` nearest nodes in
//! the box instead (Mahadevan & Maggioni's graph), which ignores walls.
//!
//! **Schedule.** The first build comes when [`FIRST_BUILD_NODES`] nodes
//! exist; then a rebuild whenever the nodes or the edges grew by
//! [`REBUILD_GROWTH`] since the last build, at least
//! [`MIN_TICKS_BETWEEN_BUILDS`] ticks after it. Both counts are bounded
//! (`nodes` nodes, `nodes × neighbours` edges), so there are at most about
//! log(nodes · neighbours) / log(1 + growth) builds in a session's life.
//! Everything depends only on the observations, in order: a replay
//! rebuilds at the same ticks with the same bits.

use serde::{Deserialize, Serialize};

use super::pvf::{Pvf, nearest, sq_dist};
use crate::error::Result;

/// Nodes the first build waits for.
pub const FIRST_BUILD_NODES: usize = 8;
/// Relative growth of the nodes or the edges that triggers a rebuild.
pub const REBUILD_GROWTH: f64 = 0.25;
/// Fewest ticks between two builds.
pub const MIN_TICKS_BETWEEN_BUILDS: u64 = 50;

/// How the graph's edges are chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Edges {
    /// Between the nodes nearest to consecutive observations.
    Transitions,
    /// Each node to its `neighbours` nearest nodes, symmetrised.
    Nearest,
}

/// The edge rule every PVF basis uses (measured: docs/algorithm.md §9.2).
pub const EDGES: Edges = Edges::Transitions;

/// The growing node set and edges, and the build schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PvfGraph {
    d: usize,
    max_nodes: usize,
    neighbours: usize,
    /// δ².
    delta2: f64,
    /// Row-major `n × d`.
    nodes: Vec<f64>,
    /// Each node's neighbours, ascending.
    adj: Vec<Vec<u32>>,
    edges: usize,
    /// The node nearest to the last observation.
    last: Option<u32>,
    built_nodes: usize,
    built_edges: usize,
    built_tick: Option<u64>,
    /// Builds so far.
    pub builds: u64,
}

impl PvfGraph {
    /// Whether a graph read from a snapshot is one of dimension `d`, and
    /// every index in it points inside it.
    pub fn fits(&self, d: usize) -> bool {
        let n = self.nodes.len() / d.max(1);
        self.d == d
            && self.nodes.len() == n * d
            && self.adj.len() == n
            && self.adj.iter().flatten().all(|&j| (j as usize) < n)
            && self.last.is_none_or(|j| (j as usize) < n)
    }

    /// An empty graph for the basis `pvf` describes.
    pub fn new(pvf: &Pvf) -> Self {
        let (d, max_nodes) = (pvf.dim(), pvf.max_nodes());
        let delta = (max_nodes as f64).powf(-1.0 / d as f64);
        Self {
            d,
            max_nodes,
            neighbours: pvf.neighbours(),
            delta2: delta * delta,
            nodes: Vec::new(),
            adj: Vec::new(),
            edges: 0,
            last: None,
            built_nodes: 0,
            built_edges: 0,
            built_tick: None,
            builds: 0,
        }
    }

    /// Nodes so far.
    pub fn nodes(&self) -> usize {
        self.adj.len()
    }

    /// Undirected edges so far.
    pub fn edges(&self) -> usize {
        self.edges
    }

    /// Takes the normalised observation s; `moved_from_last` says the
    /// agent moved to it from the previous one (a transition).
    /// O(n·d).
    pub fn observe(&mut self, s: &[f64], moved_from_last: bool) {
        let (mut j, e) = if self.nodes.is_empty() {
            (0, f64::INFINITY)
        } else {
            nearest(&self.nodes, self.d, s)
        };
        if e > self.delta2 && self.nodes() < self.max_nodes {
            self.nodes.extend_from_slice(&s[..self.d]);
            self.adj.push(Vec::new());
            j = self.nodes() - 1;
        }
        let j = j as u32;
        if moved_from_last
            && EDGES == Edges::Transitions
            && let Some(i) = self.last
        {
            self.link(i, j);
        }
        self.last = Some(j);
    }

    fn link(&mut self, i: u32, j: u32) {
        if i == j {
            return;
        }
        let cap = self.neighbours;
        let (a, b) = (&self.adj[i as usize], &self.adj[j as usize]);
        if a.len() >= cap || b.len() >= cap {
            return;
        }
        if let Err(p) = a.binary_search(&j) {
            self.adj[i as usize].insert(p, j);
            if let Err(q) = self.adj[j as usize].binary_search(&i) {
                self.adj[j as usize].insert(q, i);
            }
            self.edges += 1;
        }
    }

    /// Whether the basis is due for a (re)build at this tick.
    pub fn due(&self, tick: u64) -> bool {
        let n = self.nodes();
        match self.built_tick {
            None => n >= FIRST_BUILD_NODES,
            Some(t) => {
                let grew = |now: usize, then: usize| {
                    now > then && now as f64 >= then as f64 * (1.0 + REBUILD_GROWTH)
                };
                tick >= t + MIN_TICKS_BETWEEN_BUILDS
                    && (grew(n, self.built_nodes) || grew(self.edges, self.built_edges))
            }
        }
    }

    /// Builds the PVFs of the graph as it is (the basis `pvf` gives the
    /// sizes) and records the attempt at `tick`, so that a failed one is
    /// retried only when the graph has grown again.
    pub fn build(&mut self, pvf: &Pvf, tick: u64) -> Result<Pvf> {
        self.built_nodes = self.nodes();
        self.built_edges = self.edges;
        self.built_tick = Some(tick);
        let edges: Vec<(u32, u32)> = match EDGES {
            Edges::Transitions => self
                .adj
                .iter()
                .enumerate()
                .flat_map(|(i, a)| a.iter().map(move |&j| (i as u32, j)))
                .collect(),
            Edges::Nearest => self.nearest_edges(),
        };
        let built = pvf.build(&self.nodes, &edges)?;
        self.builds += 1;
        Ok(built)
    }

    /// Each node's `neighbours` nearest nodes (ties by index). O(n² d).
    fn nearest_edges(&self) -> Vec<(u32, u32)> {
        let n = self.nodes();
        let d = self.d;
        let mut out = Vec::with_capacity(n * self.neighbours);
        let mut dist: Vec<(f64, u32)> = Vec::with_capacity(n);
        for i in 0..n {
            let x = &self.nodes[i * d..(i + 1) * d];
            dist.clear();
            dist.extend(
                (0..n)
                    .filter(|&j| j != i)
                    .map(|j| (sq_dist(x, &self.nodes[j * d..(j + 1) * d]), j as u32)),
            );
            dist.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            out.extend(
                dist.iter()
                    .take(self.neighbours)
                    .map(|&(_, j)| (i as u32, j)),
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nodes_are_a_bounded_delta_net_and_edges_follow_the_moves() {
        let pvf = Pvf::empty(1, 4, 10, 3);
        let mut g = PvfGraph::new(&pvf);
        // δ = 0.1: a walk from 0 to 1 in steps of 0.01 makes about 10 nodes.
        for i in 0..=100 {
            g.observe(&[i as f64 / 100.0], i > 0);
        }
        assert_eq!(g.nodes(), 10, "bounded by `nodes`");
        assert_eq!(g.edges(), 9, "a chain");
        assert!(g.due(0));
        let built = g.build(&pvf, 0).expect("build");
        assert_eq!(built.nodes(), 10);
        assert!(!g.due(1000), "nothing grew");
        // A jump without a transition adds no edge.
        g.observe(&[0.0], false);
        assert_eq!(g.edges(), 9);
    }
}
