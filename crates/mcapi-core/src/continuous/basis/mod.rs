//! Feature bases over the normalised box [0, 1]^d (docs/algorithm.md
//! §9.2): state features v(s) ∈ R^k, lifted to state-action features by
//! one block per action, φ(s, a) = e_a ⊗ v(s), as the discrete bases are
//! (docs/algorithm.md §5).
//!
//! - [`fourier`]: cos(π c·s) for integer c, coupled terms limited
//!   (Konidaris, Osentoski & Thomas, AAAI 2011);
//! - [`rbf`]: normalised Gaussians on a grid of centres;
//! - [`tiles`]: tile coding, hashed into a bounded table (Sutton & Barto
//!   §9.5.4);
//! - [`pvf`]: proto-value functions of the graph of observed transitions,
//!   extended by Nyström (Mahadevan & Maggioni, JMLR 2007), rebuilt as the
//!   graph grows ([`pvf_graph`]).
//!
//! Every size is bounded before anything is allocated: a spec's feature
//! count is computed in closed form and checked against
//! [`MAX_STATE_FEATURES`] first.

pub mod fourier;
pub mod pvf;
pub mod pvf_graph;
pub mod rbf;
pub mod tiles;

use serde::{Deserialize, Serialize};

use crate::error::{AlgoError, Result};

use super::grid::{
    DEFAULT_GRID_CELLS_PER_DIM, DEFAULT_GRID_NEIGHBOURS, DEFAULT_GRID_REACH, GridShape,
    MAX_GRID_CELLS, MAX_GRID_NEIGHBOURS, MAX_GRID_PAIRS, MAX_GRID_REACH,
};

pub use fourier::Fourier;
pub use pvf::Pvf;
pub use pvf_graph::PvfGraph;
pub use rbf::Rbf;
pub use tiles::Tiles;

/// Largest number of state features k of a continuous basis.
pub const MAX_STATE_FEATURES: usize = 4096;
// A grid has at most as many cells as a basis has features.
const _: () = assert!(MAX_GRID_CELLS == MAX_STATE_FEATURES);

/// Largest number of state-action features k·|A|: the planner keeps a
/// dense inverse of (k|A|)² numbers (32 MiB at this bound).
pub const MAX_PAIR_FEATURES: usize = 2048;

/// The state-action features a default basis aims at.
pub const DEFAULT_PAIR_FEATURES: usize = 300;

/// Largest Fourier order.
pub const MAX_ORDER: u32 = 64;
/// Largest number of RBF centres per dimension.
pub const MAX_CENTRES_PER_DIM: u32 = 64;
/// Largest number of tilings.
pub const MAX_TILINGS: u32 = 64;
/// Largest number of tiles per dimension of one tiling.
pub const MAX_TILES_PER_DIM: u32 = 1024;
/// Largest number of PVFs k (Ξ's refit at a rebuild costs O(|A| k³)).
pub const MAX_PVF_K: u32 = 256;
/// Largest node set of a PVF graph (an eigenproblem of this size at a
/// rebuild, and O(nodes · d) per feature evaluation).
pub const MAX_PVF_NODES: u32 = 2048;
/// Default node set of a PVF graph.
pub const DEFAULT_PVF_NODES: u32 = 800;
/// Largest number of edges per PVF graph node.
pub const MAX_PVF_NEIGHBOURS: u32 = 64;
/// Default edges per PVF graph node.
pub const DEFAULT_PVF_NEIGHBOURS: u32 = 16;

/// A basis as a client names it (`{"kind": "fourier", "order": 5}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ContinuousBasisSpec {
    /// cos(π c·s) for every integer c ∈ {0..order}^d with at most
    /// `max_coupling` non-zero entries (default: all of them, d).
    Fourier {
        /// Highest frequency per dimension.
        order: u32,
        /// Most dimensions a term couples.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        max_coupling: Option<u32>,
    },
    /// Normalised Gaussians on a grid of `centres_per_dim`^d centres,
    /// σ = `width` × the grid spacing (default 1).
    Rbf {
        /// Centres per dimension (at least 2).
        centres_per_dim: u32,
        /// σ in grid spacings.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        width: Option<f64>,
    },
    /// `tilings` offset grids of `tiles_per_dim`^d tiles, hashed into
    /// `table` features (default: the exact count when it fits in
    /// [`MAX_STATE_FEATURES`], else that bound).
    Tiles {
        /// Number of tilings (active features per point).
        tilings: u32,
        /// Tiles per dimension of one tiling.
        tiles_per_dim: u32,
        /// Size of the hashed table.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        table: Option<u32>,
    },
    /// The `k` smoothest proto-value functions of a graph over at most
    /// `nodes` subsampled observations (default [`DEFAULT_PVF_NODES`]),
    /// joined where the agent was seen to move, each node with at most
    /// `neighbours` edges (default [`DEFAULT_PVF_NEIGHBOURS`]); extended
    /// to any point by Nyström and rebuilt as the graph grows.
    Pvf {
        /// Number of PVFs (features per action).
        k: u32,
        /// Most graph nodes.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        nodes: Option<u32>,
        /// Most edges per node.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        neighbours: Option<u32>,
    },
    /// No features: a grid of `cells_per_dim`^d cells over the box,
    /// planned on exactly with a transition model learned from the
    /// `neighbours` nearest moves of each cell and action (default
    /// [`DEFAULT_GRID_NEIGHBOURS`]) within `reach` cells (default
    /// [`DEFAULT_GRID_REACH`]); docs/algorithm.md §9.8.
    Grid {
        /// Cells per dimension (at least 2).
        cells_per_dim: u32,
        /// Transitions kept per (cell, action).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        neighbours: Option<u32>,
        /// How far a move teaches, in cells.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        reach: Option<f64>,
    },
}

impl ContinuousBasisSpec {
    /// The default basis of a d-dimensional space with `actions` actions:
    /// for d ≤ 2, a grid of up to 64 cells per dimension (the most that
    /// fit [`MAX_GRID_CELLS`] and [`MAX_GRID_PAIRS`]; docs/algorithm.md
    /// §9.8 has the measurements), or normalised RBFs where fewer than 16
    /// cells per dimension would fit; above that, a Fourier basis,
    /// couplings limited to pairs, then to none, sized so that k·|A| stays
    /// near 300; where even the uncoupled Fourier basis of order 1 does
    /// not fit, hashed tiles that do.
    pub fn default_for(d: usize, actions: usize) -> Self {
        let actions = actions.max(1);
        let budget = (DEFAULT_PAIR_FEATURES / actions).max(8);
        if (1..=2).contains(&d) {
            let fits = |c: usize| {
                let cells = c.pow(d as u32);
                cells <= MAX_GRID_CELLS && cells * actions <= MAX_GRID_PAIRS
            };
            if let Some(c) = (16..=DEFAULT_GRID_CELLS_PER_DIM).rev().find(|&c| fits(c)) {
                return Self::Grid {
                    cells_per_dim: c as u32,
                    neighbours: None,
                    reach: None,
                };
            }
        }
        match d {
            0 | 1 => Self::Rbf {
                centres_per_dim: budget.min(MAX_CENTRES_PER_DIM as usize) as u32,
                width: None,
            },
            2 => {
                let c = ((budget as f64).sqrt().floor() as u32).clamp(2, MAX_CENTRES_PER_DIM);
                Self::Rbf {
                    centres_per_dim: c,
                    width: None,
                }
            }
            _ => {
                for coupling in [2, 1] {
                    let fits =
                        |order| fourier::count(d, order, coupling).is_some_and(|k| k <= budget);
                    if fits(1) {
                        let order = (1..=MAX_ORDER).take_while(|&o| fits(o)).last().unwrap_or(1);
                        return Self::Fourier {
                            order,
                            max_coupling: Some(coupling),
                        };
                    }
                }
                if fourier::count(d, 1, 1).is_some_and(|k| k * actions <= MAX_PAIR_FEATURES) {
                    return Self::Fourier {
                        order: 1,
                        max_coupling: Some(1),
                    };
                }
                let table = (MAX_PAIR_FEATURES / actions).max(8) as u32;
                Self::Tiles {
                    tilings: 8.min(table),
                    tiles_per_dim: 4,
                    table: Some(table),
                }
            }
        }
    }

    /// Checks the spec against a d-dimensional space and builds the map.
    pub fn build(&self, d: usize, actions: usize) -> Result<FeatureMap> {
        let map = match *self {
            Self::Fourier {
                order,
                max_coupling,
            } => {
                if !(1..=MAX_ORDER).contains(&order) {
                    return Err(bad(format!(
                        "fourier `order` {order} is not in 1..={MAX_ORDER}"
                    )));
                }
                let coupling = max_coupling.unwrap_or(d as u32);
                if coupling == 0 || coupling as usize > d {
                    return Err(bad(format!(
                        "fourier `max_coupling` {coupling} is not in 1..={d} (the space's dimension)"
                    )));
                }
                let k = fourier::count(d, order, coupling)
                    .filter(|&k| k <= MAX_STATE_FEATURES)
                    .ok_or_else(|| {
                        too_many(format!("fourier order {order} couplings {coupling}"))
                    })?;
                check_pairs(k, actions)?;
                FeatureMap::Fourier(Fourier::new(d, order, coupling))
            }
            Self::Rbf {
                centres_per_dim,
                width,
            } => {
                if !(2..=MAX_CENTRES_PER_DIM).contains(&centres_per_dim) {
                    return Err(bad(format!(
                        "rbf `centres_per_dim` {centres_per_dim} is not in 2..={MAX_CENTRES_PER_DIM}"
                    )));
                }
                let width = width.unwrap_or(1.0);
                if !(width.is_finite() && (0.05..=10.0).contains(&width)) {
                    return Err(bad(format!("rbf `width` {width} is not in 0.05..=10")));
                }
                let k = pow_bounded(centres_per_dim as usize, d)
                    .ok_or_else(|| too_many(format!("rbf {centres_per_dim}^{d} centres")))?;
                check_pairs(k, actions)?;
                FeatureMap::Rbf(Rbf::new(d, centres_per_dim as usize, width))
            }
            Self::Tiles {
                tilings,
                tiles_per_dim,
                table,
            } => {
                if !(1..=MAX_TILINGS).contains(&tilings) {
                    return Err(bad(format!(
                        "tiles `tilings` {tilings} is not in 1..={MAX_TILINGS}"
                    )));
                }
                if !(1..=MAX_TILES_PER_DIM).contains(&tiles_per_dim) {
                    return Err(bad(format!(
                        "tiles `tiles_per_dim` {tiles_per_dim} is not in 1..={MAX_TILES_PER_DIM}"
                    )));
                }
                // Each tiling has tiles_per_dim + 1 tiles per dimension (it is offset).
                let exact = pow_bounded(tiles_per_dim as usize + 1, d)
                    .and_then(|per| per.checked_mul(tilings as usize));
                let size = match table {
                    Some(t) if t as usize > MAX_STATE_FEATURES || t < tilings => {
                        return Err(bad(format!(
                            "tiles `table` {t} is not in {tilings}..={MAX_STATE_FEATURES}"
                        )));
                    }
                    Some(t) => t as usize,
                    None => exact.map_or(MAX_STATE_FEATURES, |e| e.min(MAX_STATE_FEATURES)),
                };
                check_pairs(size, actions)?;
                FeatureMap::Tiles(Tiles::new(
                    d,
                    tilings as usize,
                    tiles_per_dim as usize,
                    size,
                    exact == Some(size),
                ))
            }
            Self::Pvf {
                k,
                nodes,
                neighbours,
            } => {
                let nodes = nodes.unwrap_or(DEFAULT_PVF_NODES);
                if !(2..=MAX_PVF_NODES).contains(&nodes) {
                    return Err(bad(format!(
                        "pvf `nodes` {nodes} is not in 2..={MAX_PVF_NODES}"
                    )));
                }
                let most = MAX_PVF_K.min(nodes);
                if !(1..=most).contains(&k) {
                    return Err(bad(format!(
                        "pvf `k` {k} is not in 1..={most} (at most {MAX_PVF_K} and at most `nodes`)"
                    )));
                }
                let neighbours = neighbours.unwrap_or(DEFAULT_PVF_NEIGHBOURS);
                if !(1..=MAX_PVF_NEIGHBOURS).contains(&neighbours) {
                    return Err(bad(format!(
                        "pvf `neighbours` {neighbours} is not in 1..={MAX_PVF_NEIGHBOURS}"
                    )));
                }
                check_pairs(k as usize, actions)?;
                FeatureMap::Pvf(Pvf::empty(
                    d,
                    k as usize,
                    nodes as usize,
                    neighbours as usize,
                ))
            }
            Self::Grid {
                cells_per_dim,
                neighbours,
                reach,
            } => {
                let res = cells_per_dim as usize;
                let cells = (2..=MAX_GRID_CELLS)
                    .contains(&res)
                    .then(|| {
                        (0..d).try_fold(1usize, |acc, _| {
                            acc.checked_mul(res).filter(|&c| c <= MAX_GRID_CELLS)
                        })
                    })
                    .flatten()
                    .ok_or_else(|| {
                        bad(format!(
                            "grid `cells_per_dim` {cells_per_dim} is not in 2.. with \
                             cells_per_dim^{d} at most {MAX_GRID_CELLS} cells"
                        ))
                    })?;
                if cells.saturating_mul(actions) > MAX_GRID_PAIRS {
                    return Err(bad(format!(
                        "a grid of {cells} cells × {actions} actions exceeds \
                         {MAX_GRID_PAIRS} (cell, action) pairs"
                    )));
                }
                let neighbours = neighbours.unwrap_or(DEFAULT_GRID_NEIGHBOURS);
                if !(1..=MAX_GRID_NEIGHBOURS).contains(&neighbours) {
                    return Err(bad(format!(
                        "grid `neighbours` {neighbours} is not in 1..={MAX_GRID_NEIGHBOURS}"
                    )));
                }
                let reach = reach.unwrap_or(DEFAULT_GRID_REACH);
                if !(reach.is_finite() && (1.0..=MAX_GRID_REACH).contains(&reach)) {
                    return Err(bad(format!(
                        "grid `reach` {reach} is not in 1..={MAX_GRID_REACH} (cells)"
                    )));
                }
                FeatureMap::Grid(GridShape {
                    d,
                    cells_per_dim: res,
                    neighbours: neighbours as usize,
                    reach,
                })
            }
        };
        Ok(map)
    }
}

/// A built basis: v(s) for any s ∈ [0, 1]^d.
#[derive(Debug, Clone, PartialEq)]
pub enum FeatureMap {
    /// A Fourier basis.
    Fourier(Fourier),
    /// Normalised RBFs.
    Rbf(Rbf),
    /// Tile coding.
    Tiles(Tiles),
    /// Proto-value functions of the observed graph.
    Pvf(Pvf),
    /// No features: the agent plans on a grid (docs/algorithm.md §9.8).
    Grid(GridShape),
}

impl FeatureMap {
    /// k, the number of state features.
    pub fn len(&self) -> usize {
        match self {
            Self::Fourier(b) => b.len(),
            Self::Rbf(b) => b.len(),
            Self::Tiles(b) => b.len(),
            Self::Pvf(b) => b.len(),
            Self::Grid(_) => 0,
        }
    }

    /// Only for a grid, which plans without features.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Writes v(s) into `out` (length k).
    pub fn features_into(&self, s: &[f64], out: &mut [f64]) {
        debug_assert_eq!(out.len(), self.len());
        match self {
            Self::Fourier(b) => b.features_into(s, out),
            Self::Rbf(b) => b.features_into(s, out),
            Self::Tiles(b) => b.features_into(s, out),
            Self::Pvf(b) => b.features_into(s, out),
            Self::Grid(_) => {}
        }
        debug_assert!(out.iter().all(|v| v.is_finite()));
    }

    /// Floating-point operations of one evaluation, for the cost model.
    pub fn eval_cost(&self) -> usize {
        match self {
            Self::Fourier(b) => b.len() * (b.dim() + 8),
            Self::Rbf(b) => b.len() * 2 + b.dim() * b.centres() * 16,
            Self::Tiles(b) => b.len() + b.tilings() * b.dim() * 4,
            Self::Pvf(b) => b.eval_cost(),
            Self::Grid(_) => 0,
        }
    }
}

/// b^e, or None beyond [`MAX_STATE_FEATURES`].
fn pow_bounded(b: usize, e: usize) -> Option<usize> {
    let mut acc = 1usize;
    for _ in 0..e {
        acc = acc.checked_mul(b).filter(|&v| v <= MAX_STATE_FEATURES)?;
    }
    Some(acc)
}

fn check_pairs(k: usize, actions: usize) -> Result<()> {
    match k.checked_mul(actions) {
        Some(p) if p <= MAX_PAIR_FEATURES => Ok(()),
        _ => Err(bad(format!(
            "{k} state features × {actions} actions exceeds {MAX_PAIR_FEATURES} state-action features"
        ))),
    }
}

fn too_many(what: String) -> AlgoError {
    bad(format!("{what} exceeds {MAX_STATE_FEATURES} features"))
}

fn bad(msg: String) -> AlgoError {
    AlgoError::InvalidBasis(msg)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(d: usize, per: usize) -> Vec<Vec<f64>> {
        let mut pts = vec![Vec::new()];
        for _ in 0..d {
            pts = pts
                .into_iter()
                .flat_map(|p| {
                    (0..per).map(move |i| {
                        let mut q = p.clone();
                        q.push(i as f64 / (per - 1) as f64);
                        q
                    })
                })
                .collect();
        }
        pts
    }

    #[test]
    fn every_basis_is_finite_and_sized_as_declared() {
        let specs = [
            ContinuousBasisSpec::Fourier {
                order: 3,
                max_coupling: None,
            },
            ContinuousBasisSpec::Fourier {
                order: 4,
                max_coupling: Some(1),
            },
            ContinuousBasisSpec::Rbf {
                centres_per_dim: 5,
                width: None,
            },
            ContinuousBasisSpec::Tiles {
                tilings: 4,
                tiles_per_dim: 6,
                table: None,
            },
            ContinuousBasisSpec::Tiles {
                tilings: 8,
                tiles_per_dim: 10,
                table: Some(64),
            },
            ContinuousBasisSpec::Pvf {
                k: 20,
                nodes: None,
                neighbours: None,
            },
        ];
        for spec in &specs {
            let map = spec.build(2, 3).expect("a valid basis");
            let mut out = vec![0.0; map.len()];
            for p in grid(2, 7) {
                map.features_into(&p, &mut out);
                assert!(out.iter().all(|v| v.is_finite()), "{spec:?} at {p:?}");
                assert!(
                    out.iter().any(|v| *v != 0.0),
                    "{spec:?} at {p:?} is all zero"
                );
            }
        }
    }

    #[test]
    fn absurd_sizes_are_refused_before_allocation() {
        let absurd = [
            ContinuousBasisSpec::Fourier {
                order: u32::MAX,
                max_coupling: None,
            },
            ContinuousBasisSpec::Fourier {
                order: 10,
                max_coupling: Some(64),
            },
            ContinuousBasisSpec::Fourier {
                order: 0,
                max_coupling: None,
            },
            ContinuousBasisSpec::Rbf {
                centres_per_dim: u32::MAX,
                width: None,
            },
            ContinuousBasisSpec::Rbf {
                centres_per_dim: 64,
                width: None,
            },
            ContinuousBasisSpec::Rbf {
                centres_per_dim: 4,
                width: Some(f64::NAN),
            },
            ContinuousBasisSpec::Tiles {
                tilings: u32::MAX,
                tiles_per_dim: 4,
                table: None,
            },
            ContinuousBasisSpec::Tiles {
                tilings: 4,
                tiles_per_dim: u32::MAX,
                table: None,
            },
            ContinuousBasisSpec::Tiles {
                tilings: 4,
                tiles_per_dim: 4,
                table: Some(u32::MAX),
            },
            ContinuousBasisSpec::Pvf {
                k: u32::MAX,
                nodes: None,
                neighbours: None,
            },
            ContinuousBasisSpec::Pvf {
                k: 0,
                nodes: None,
                neighbours: None,
            },
            ContinuousBasisSpec::Pvf {
                k: 10,
                nodes: Some(u32::MAX),
                neighbours: None,
            },
            ContinuousBasisSpec::Pvf {
                k: 10,
                nodes: Some(5),
                neighbours: None,
            },
            ContinuousBasisSpec::Pvf {
                k: 10,
                nodes: Some(0),
                neighbours: None,
            },
            ContinuousBasisSpec::Pvf {
                k: 10,
                nodes: None,
                neighbours: Some(0),
            },
            ContinuousBasisSpec::Pvf {
                k: 10,
                nodes: None,
                neighbours: Some(u32::MAX),
            },
        ];
        for spec in &absurd {
            assert!(spec.build(8, 4).is_err(), "{spec:?} was accepted");
        }
        // 200 PVFs × 16 actions exceed the state-action bound.
        let pvf = ContinuousBasisSpec::Pvf {
            k: 200,
            nodes: None,
            neighbours: None,
        };
        let e = pvf.build(2, 16).expect_err("too many pairs");
        assert!(e.to_string().contains("exceeds 2048"), "{e}");
        let e = ContinuousBasisSpec::Pvf {
            k: 300,
            nodes: None,
            neighbours: None,
        }
        .build(2, 1)
        .expect_err("k above its bound");
        assert!(
            e.to_string().contains("pvf `k` 300 is not in 1..=256"),
            "{e}"
        );
        // A 64-dimensional Fourier basis of order 1 with full coupling has 2^64 terms.
        assert!(
            ContinuousBasisSpec::Fourier {
                order: 1,
                max_coupling: None
            }
            .build(64, 2)
            .is_err()
        );
    }

    #[test]
    fn defaults_fit_the_bounds_for_every_dimension() {
        for d in 1..=crate::continuous::space::MAX_DIM {
            for actions in [2, 4, 6, 16] {
                let spec = ContinuousBasisSpec::default_for(d, actions);
                let map = spec
                    .build(d, actions)
                    .unwrap_or_else(|e| panic!("d={d}: {e}"));
                assert!(map.len() * actions <= MAX_PAIR_FEATURES);
            }
        }
    }
}
