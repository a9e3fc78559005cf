//! The estimation error ε (§7 step 5) and the learning-progress stimulus of
//! Eq. 7.

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

use super::params::ValidCuriosityParams;

/// The last τ ROC errors; ε is their mean (§7 step 5). Starts filled with
/// `initial_error` (1.0, ours) and counts the errors actually pushed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorWindow {
    errors: VecDeque<f64>,
    samples: u64,
}

impl ErrorWindow {
    /// τ entries of `fill`, no samples yet.
    pub fn new(tau: usize, fill: f64) -> Self {
        Self {
            errors: std::iter::repeat_n(fill, tau.max(1)).collect(),
            samples: 0,
        }
    }

    /// Pushes one error (dropping the oldest) and returns the new mean.
    pub fn push(&mut self, error: f64) -> f64 {
        self.errors.pop_front();
        self.errors.push_back(error);
        self.samples += 1;
        self.mean()
    }

    /// ε: the mean of the window (recomputed, so no rounding drift).
    pub fn mean(&self) -> f64 {
        self.errors.iter().sum::<f64>() / self.errors.len() as f64
    }

    /// Errors pushed so far.
    pub fn samples(&self) -> u64 {
        self.samples
    }
}

/// Eq. 7: ξ_cur = Clip(g·(ε_{n−L} − ε_n)/L, 0, clip), the learning progress
/// over the last L learned samples, scaled by the gain g. Always in
/// [0, clip]: a progress that is not a number (errors that overflowed to
/// ∞ on both sides) counts as none (our guard, not the paper's).
pub fn curiosity_stimulus(eps_lagged: f64, eps_now: f64, params: &ValidCuriosityParams) -> f64 {
    let progress = params.gain * (eps_lagged - eps_now) / params.lag as f64;
    if progress.is_nan() {
        return 0.0;
    }
    progress.clamp(0.0, params.clip)
}

/// A learning module's ε (step 5) and the lag history Eq. 7 needs. Both
/// start filled with `initial_error` (ours: a fresh module then earns
/// curiosity from its first sample).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LearningProgress {
    pub(super) window: ErrorWindow,
    /// ε_{n−L} … ε_{n−1}.
    lagged: VecDeque<f64>,
}

impl LearningProgress {
    /// A fresh window of τ and lag history of L, both `initial_error`.
    pub fn new(params: &ValidCuriosityParams) -> Self {
        Self {
            window: ErrorWindow::new(params.tau, params.initial_error),
            lagged: std::iter::repeat_n(params.initial_error, params.lag).collect(),
        }
    }

    /// Pushes the ROC error of learned sample n; returns (ε_n, ξ_cur).
    pub fn push(&mut self, error: f64, params: &ValidCuriosityParams) -> (f64, f64) {
        let epsilon = self.window.push(error);
        let lagged = self.lagged.pop_front().unwrap_or(params.initial_error);
        self.lagged.push_back(epsilon);
        (epsilon, curiosity_stimulus(lagged, epsilon, params))
    }

    /// ε: the mean of the last τ errors.
    pub fn epsilon(&self) -> f64 {
        self.window.mean()
    }
}
