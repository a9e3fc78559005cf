//! The world of experiment 3: the curiosity room (`data/curiosity_room.txt`)
//! with its food, rest, book and music cells, and what one trial in it
//! records. The runner ([`super`]) fills it; the figures
//! ([`crate::plots`]) read it.

use mcapi_core::model::{CURIOSITY_ROOM_MAP, GridMap};
use mcapi_core::{AlgoError, Eq6Source};

use crate::paper::TrialRecord;

/// Stimulus dimensions of the EM+IM agent; the EM-only agent has the first two.
pub const STIMULI: [&str; 3] = ["food", "rest", "curiosity"];

/// The curiosity room: its map and the states of F, R, K and M.
#[derive(Debug, Clone)]
pub struct Room {
    /// The map.
    pub grid: GridMap,
    /// F (food, dimension 0).
    pub food: usize,
    /// R (rest, dimension 1).
    pub rest: usize,
    /// K (book signal, source 0).
    pub book: usize,
    /// M (music signal, source 1).
    pub music: usize,
}

impl Room {
    /// `data/curiosity_room.txt`.
    pub fn new() -> Result<Self, AlgoError> {
        let grid = GridMap::from_text(CURIOSITY_ROOM_MAP)?;
        let mark = |c: char| {
            grid.mark_state(c)
                .ok_or_else(|| AlgoError::InvalidModel(format!("no cell marked `{c}`")))
        };
        Ok(Self {
            food: mark('F')?,
            rest: mark('R')?,
            book: mark('K')?,
            music: mark('M')?,
            grid,
        })
    }

    /// Food, rest, book, music: the "sources" of the generic metrics
    /// (`fraction_at_source_<i>`, `all_sources_found`).
    pub fn sources(&self) -> [usize; 4] {
        [self.food, self.rest, self.book, self.music]
    }

    /// The signal source at state `s`, if any.
    pub fn signal_at(&self, s: usize) -> Option<Eq6Source> {
        if s == self.book {
            Some(Eq6Source::Book)
        } else if s == self.music {
            Some(Eq6Source::Music)
        } else {
            None
        }
    }
}

/// One trial: the generic record (3 stimulus dimensions for both
/// configurations; the EM-only agent's curiosity column is identically 0)
/// and the curiosity channel's history.
#[derive(Debug, Clone, Default)]
pub struct CuriosityRecord {
    /// States, actions, D (padded with 0 for EM-only), |r|, ξ, LSTDQ error.
    pub base: TrialRecord,
    /// ε of the active module after each tick (empty for EM-only).
    pub epsilon: Vec<f64>,
    /// (tick, source) of every module freeze.
    pub freezes: Vec<(u64, usize)>,
    /// Per frozen module at the end: its source and its window means on the
    /// book and on the music (None where it has fewer than τ samples).
    pub explain: Vec<(usize, [Option<f64>; 2])>,
    /// Per frozen module at the end: |correlation| of its slow feature with
    /// its source's hidden slow feature (sin t, resp. sin(2t + π/3)).
    pub feature_correlation: Vec<f64>,
    /// Ticks with condition (3) in force (D\[cur\] held at 0).
    pub suppressed_ticks: u64,
}
