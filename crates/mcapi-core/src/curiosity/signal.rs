//! The book and music signals of Eq. 6 (experiment 3), each on its own
//! clock: the raw input a curiosity channel learns from.

use serde::{Deserialize, Serialize};

use super::params::ValidCuriosityParams;

/// The two signal sources of experiment 3 (Eq. 6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Eq6Source {
    /// K: x1 = sin t + cos²(11t), x2 = cos 11t; slow feature sin t.
    Book,
    /// M: x1 = sin(2t + π/3) − cos²(11t), x2 = cos 11t; slow feature
    /// sin(2t + π/3).
    Music,
}

impl Eq6Source {
    /// Both sources, in index order.
    pub const ALL: [Self; 2] = [Self::Book, Self::Music];

    /// The source index used with [`CuriosityChannel::observe`]: book 0,
    /// music 1.
    pub fn index(self) -> usize {
        match self {
            Self::Book => 0,
            Self::Music => 1,
        }
    }

    /// The slow feature the source hides: sin t, resp. sin(2t + π/3).
    pub fn slow_feature(self, t: f64) -> f64 {
        match self {
            Self::Book => t.sin(),
            Self::Music => (2.0 * t + std::f64::consts::FRAC_PI_3).sin(),
        }
    }
}

/// Per-source signal clocks (§7 "Signals", ours): each source's own t starts
/// at 0 and advances by dt per delivered sample.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Signals {
    dt: f64,
    /// Samples delivered per source (book, music); t = k·dt, exactly.
    delivered: [u64; 2],
}

impl Signals {
    /// Eq. 6 at time t.
    pub fn eq6(source: Eq6Source, t: f64) -> [f64; 2] {
        let fast = (11.0 * t).cos();
        let fast_sq = fast * fast;
        let x1 = match source {
            Eq6Source::Book => t.sin() + fast_sq,
            Eq6Source::Music => (2.0 * t + std::f64::consts::FRAC_PI_3).sin() - fast_sq,
        };
        [x1, fast]
    }

    /// Both clocks at 0, advancing by `dt` (the parameters' dt).
    pub fn new(dt: f64) -> Self {
        Self {
            dt,
            delivered: [0; 2],
        }
    }

    /// Clocks with the dt of checked parameters.
    pub fn with_params(params: &ValidCuriosityParams) -> Self {
        Self::new(params.dt)
    }

    /// The time of the source's next sample.
    pub fn time(&self, source: Eq6Source) -> f64 {
        self.delivered[source.index()] as f64 * self.dt
    }

    /// Delivers the source's next sample and advances its clock.
    pub fn next(&mut self, source: Eq6Source) -> [f64; 2] {
        let x = Self::eq6(source, self.time(source));
        self.delivered[source.index()] += 1;
        x
    }
}
