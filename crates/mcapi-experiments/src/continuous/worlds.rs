//! The paper's two worlds in continuous form (docs/algorithm.md §9.6):
//! a point that moves by small noisy steps, and sources that are regions
//! of the box.
//!
//! - **Continuous hallway:** x ∈ [0, 1]; left, right, stay move by 0.02
//!   with Gaussian noise σ = 0.005, clipped to the box; food where
//!   x < 0.04, rest where x > 0.96.
//! - **Continuous three-room:** the three-room map scaled into [0, 1]²
//!   (each map cell is 1/26 wide and 1/11 tall; wall cells are solid, so
//!   their edges are the walls' segments and the gaps in them the doors);
//!   west, east, north, south move by 0.02 with noise σ = 0.005, and a move
//!   into a wall leaves the robot where it was; the sources a, b, c are
//!   discs of radius 0.04 around their cells' centres.
//!
//! A source delivers 6 + N(0, 2) on its own dimension, as the discrete
//! worlds do (docs/algorithm.md §6).

use rand::{Rng, RngExt};
use rand_distr::{Distribution, Normal};

use mcapi_core::model::{GridMap, three_room};

pub use crate::paper::{SOURCE_NOISE_SD, SOURCE_STIMULUS};

/// A move's length.
pub const STEP: f64 = 0.02;
/// σ of a move's Gaussian noise, per coordinate.
pub const STEP_NOISE: f64 = 0.005;
/// The hallway's food region is x < this, its rest region x > 1 − this.
pub const HALLWAY_SOURCE: f64 = 0.04;
/// Radius of a three-room source disc.
pub const DISC_RADIUS: f64 = 0.04;

/// A continuous world.
#[derive(Debug, Clone)]
pub enum World {
    /// The hallway.
    Hallway,
    /// The three-room maze.
    ThreeRoom(Maze),
}

/// The three-room map as solid cells and source discs.
#[derive(Debug, Clone)]
pub struct Maze {
    map: GridMap,
    /// Centres of the sources a, b, c, in stimulus order.
    pub sources: Vec<[f64; 2]>,
}

impl Maze {
    /// The map of Experiment 2 (the discrete preset's map and sources).
    pub fn three_room() -> Self {
        let preset = three_room();
        let map = preset
            .grid
            .unwrap_or_else(|| unreachable!("the three-room preset has a map"));
        let mut sources = preset.sources;
        sources.sort_by_key(|s| s.dim);
        let centre = |state: usize| {
            let (r, c) = map.cell_of(state);
            [
                (c as f64 + 0.5) / map.cols() as f64,
                (r as f64 + 0.5) / map.rows() as f64,
            ]
        };
        let sources = sources.iter().map(|s| centre(s.state)).collect();
        Self { map, sources }
    }

    /// Whether (x, y) lies in a wall cell (or outside the map).
    pub fn blocked(&self, p: [f64; 2]) -> bool {
        let c = (p[0] * self.map.cols() as f64).floor();
        let r = (p[1] * self.map.rows() as f64).floor();
        if c < 0.0 || r < 0.0 {
            return true;
        }
        self.map.state_at(r as usize, c as usize).is_none()
    }

    /// A uniformly random free point.
    pub fn random_free(&self, rng: &mut impl Rng) -> [f64; 2] {
        loop {
            let p = [rng.random::<f64>(), rng.random::<f64>()];
            if !self.blocked(p) {
                return p;
            }
        }
    }
}

/// A navigator that knows the maze: the reference for how much stimulus
/// following the drive can collect on the continuous layout when the way
/// to every source is known (docs/algorithm.md §9.6).
///
/// It keeps the agent's drive D (the same MCA rule) and heads for the
/// source i with the largest discounted reward γ^{T_i} |D_i|, T_i the
/// moves to its disc (0 inside it): the choice MCA-PI's planner makes
/// with a perfect model, up to the drive's own change on the way. It moves
/// down a geodesic distance field to that source's disc, computed once by
/// breadth-first search over a grid of `NAV_RES`² points in free space;
/// inside the disc it moves towards the disc's centre, so it stays while
/// D still points there. It learns nothing: what it collects is set by the
/// layout, the move length, γ and the drive alone.
#[derive(Debug, Clone)]
pub struct Navigator {
    maze: Maze,
    /// Per source, the number of grid moves from each grid point to the
    /// disc (`u32::MAX`: in a wall or cut off).
    dist: Vec<Vec<u32>>,
}

/// Grid points per unit length of the navigator's distance field (a
/// move of [`STEP`] crosses two).
pub const NAV_RES: usize = 100;

impl Navigator {
    /// The distance fields of the maze's sources.
    pub fn new(maze: &Maze) -> Self {
        let r = NAV_RES;
        let centre = |i: usize| (i as f64 + 0.5) / r as f64;
        let free: Vec<bool> = (0..r * r)
            .map(|k| !maze.blocked([centre(k % r), centre(k / r)]))
            .collect();
        let dist = maze
            .sources
            .iter()
            .map(|c| {
                let mut dist = vec![u32::MAX; r * r];
                let mut queue = std::collections::VecDeque::new();
                for k in 0..r * r {
                    let (dx, dy) = (centre(k % r) - c[0], centre(k / r) - c[1]);
                    if free[k] && dx * dx + dy * dy <= DISC_RADIUS * DISC_RADIUS {
                        dist[k] = 0;
                        queue.push_back(k);
                    }
                }
                while let Some(k) = queue.pop_front() {
                    let (x, y) = (k % r, k / r);
                    let next = [
                        (x > 0).then(|| k - 1),
                        (x + 1 < r).then(|| k + 1),
                        (y > 0).then(|| k - r),
                        (y + 1 < r).then(|| k + r),
                    ];
                    for n in next.into_iter().flatten() {
                        if free[n] && dist[n] == u32::MAX {
                            dist[n] = dist[k] + 1;
                            queue.push_back(n);
                        }
                    }
                }
                dist
            })
            .collect();
        Self {
            maze: maze.clone(),
            dist,
        }
    }

    /// The distance field's value at `p`.
    fn distance(&self, source: usize, p: [f64; 2]) -> u32 {
        let cell = |v: f64| ((v * NAV_RES as f64).floor().max(0.0) as usize).min(NAV_RES - 1);
        self.dist[source][cell(p[1]) * NAV_RES + cell(p[0])]
    }

    /// The source to head for from `x` with drive `d`: the largest
    /// γ^{T_i} |d_i| (the first when tied).
    pub fn heading(&self, x: &[f64], d: &[f64], gamma: f64) -> usize {
        let p = [x[0], x[1]];
        let per_move = STEP * NAV_RES as f64;
        let mut best = (0, f64::NEG_INFINITY);
        for (i, di) in d.iter().enumerate().take(self.dist.len()) {
            let grid = self.distance(i, p);
            if grid == u32::MAX {
                continue;
            }
            let moves = (f64::from(grid) / per_move).ceil();
            let value = gamma.powf(moves) * di.abs();
            if value > best.1 {
                best = (i, value);
            }
        }
        best.0
    }

    /// The move towards `source` from `x`: nearer the disc's centre when
    /// inside the disc, else down the distance field (ties to the first
    /// action; a move into a wall is never chosen while another is open).
    pub fn act(&self, x: &[f64], source: usize) -> usize {
        let c = self.maze.sources[source];
        let inside = {
            let (dx, dy) = (x[0] - c[0], x[1] - c[1]);
            dx * dx + dy * dy <= DISC_RADIUS * DISC_RADIUS
        };
        let mut best = (0, f64::INFINITY);
        for (a, (dx, dy)) in MOVES.iter().enumerate() {
            let p = [x[0] + dx, x[1] + dy];
            if self.maze.blocked(p) {
                continue;
            }
            let cost = if inside {
                (p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)
            } else {
                f64::from(self.distance(source, p))
            };
            if cost < best.1 {
                best = (a, cost);
            }
        }
        best.0
    }
}

/// The three-room's moves: west, east, north, south.
const MOVES: [(f64, f64); 4] = [(-STEP, 0.0), (STEP, 0.0), (0.0, -STEP), (0.0, STEP)];

impl World {
    /// The continuous hallway.
    pub fn hallway() -> Self {
        Self::Hallway
    }

    /// The continuous three-room maze.
    pub fn three_room() -> Self {
        Self::ThreeRoom(Maze::three_room())
    }

    /// Observation dimension.
    pub fn dim(&self) -> usize {
        match self {
            Self::Hallway => 1,
            Self::ThreeRoom(_) => 2,
        }
    }

    /// Action names.
    pub fn actions(&self) -> Vec<String> {
        let names: &[&str] = match self {
            Self::Hallway => &["left", "right", "stay"],
            Self::ThreeRoom(_) => &["west", "east", "north", "south"],
        };
        names.iter().map(|s| s.to_string()).collect()
    }

    /// Stimulus names.
    pub fn stimuli(&self) -> Vec<String> {
        let names: &[&str] = match self {
            Self::Hallway => &["food", "rest"],
            Self::ThreeRoom(_) => &["a", "b", "c"],
        };
        names.iter().map(|s| s.to_string()).collect()
    }

    /// A uniformly random start point.
    pub fn start(&self, rng: &mut impl Rng) -> Vec<f64> {
        match self {
            Self::Hallway => vec![rng.random::<f64>()],
            Self::ThreeRoom(maze) => maze.random_free(rng).to_vec(),
        }
    }

    /// The point after action `a` from `x`.
    pub fn step(&self, x: &[f64], a: usize, rng: &mut impl Rng) -> Vec<f64> {
        let noise = Normal::new(0.0, STEP_NOISE).unwrap_or_else(|_| unreachable!("σ > 0"));
        match self {
            Self::Hallway => {
                let dx = [-STEP, STEP, 0.0][a.min(2)];
                vec![(x[0] + dx + noise.sample(rng)).clamp(0.0, 1.0)]
            }
            Self::ThreeRoom(maze) => {
                let (dx, dy) = MOVES[a.min(3)];
                let next = [x[0] + dx + noise.sample(rng), x[1] + dy + noise.sample(rng)];
                if maze.blocked(next) {
                    x.to_vec()
                } else {
                    next.to_vec()
                }
            }
        }
    }

    /// Which source, if any, the point is in.
    pub fn source_at(&self, x: &[f64]) -> Option<usize> {
        match self {
            Self::Hallway if x[0] < HALLWAY_SOURCE => Some(0),
            Self::Hallway if x[0] > 1.0 - HALLWAY_SOURCE => Some(1),
            Self::Hallway => None,
            Self::ThreeRoom(maze) => maze.sources.iter().position(|c| {
                let (dx, dy) = (x[0] - c[0], x[1] - c[1]);
                dx * dx + dy * dy <= DISC_RADIUS * DISC_RADIUS
            }),
        }
    }

    /// ξ at a point: 6 + N(0, 2) on its source's dimension, 0 elsewhere.
    pub fn stimulus(&self, x: &[f64], rng: &mut impl Rng) -> Vec<f64> {
        let n = self.stimuli().len();
        let mut xi = vec![0.0; n];
        if let Some(i) = self.source_at(x) {
            let noise = Normal::new(0.0, SOURCE_NOISE_SD).unwrap_or_else(|_| unreachable!("σ > 0"));
            xi[i] = SOURCE_STIMULUS + noise.sample(rng);
        }
        xi
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn the_maze_has_three_sources_in_free_space_and_solid_walls() {
        let maze = Maze::three_room();
        assert_eq!(maze.sources.len(), 3);
        for s in &maze.sources {
            assert!(!maze.blocked(*s));
        }
        assert!(maze.blocked([0.0, 0.0]) && maze.blocked([0.5, 0.99]));
        // The wall between rooms 1 and 2 (column 8) outside its door (row 3).
        assert!(maze.blocked([8.5 / 26.0, 5.5 / 11.0]));
        assert!(!maze.blocked([8.5 / 26.0, 3.5 / 11.0]));
    }

    #[test]
    fn the_navigator_reaches_every_source_from_a_random_point() {
        let world = World::three_room();
        let World::ThreeRoom(maze) = &world else {
            unreachable!()
        };
        let nav = Navigator::new(maze);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for source in 0..3 {
            let mut x = world.start(&mut rng);
            let arrived = (0..2000).any(|_| {
                x = world.step(&x, nav.act(&x, source), &mut rng);
                world.source_at(&x) == Some(source)
            });
            assert!(arrived, "source {source} not reached from {x:?}");
        }
    }

    #[test]
    fn moves_stay_in_free_space() {
        let world = World::three_room();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut x = world.start(&mut rng);
        for t in 0..5000 {
            x = world.step(&x, t % 4, &mut rng);
            if let World::ThreeRoom(maze) = &world {
                assert!(!maze.blocked([x[0], x[1]]));
            }
        }
    }
}
