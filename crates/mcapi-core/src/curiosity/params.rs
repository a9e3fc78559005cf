//! The curiosity channel's constants (docs/algorithm.md §7), checked once:
//! [`CuriosityParams::check`] gives the [`ValidCuriosityParams`] that every
//! other part of the channel accepts.

use std::ops::Deref;

use serde::{Deserialize, Serialize};

use crate::error::AlgoError;

/// Every constant of the curiosity channel (docs/algorithm.md §7). [`Default`]
/// gives the paper's values and, where the paper is silent, the values of the
/// reproduction that §7 records; those are marked **(ours)**.
///
/// Check once with [`CuriosityParams::check`]; the channel accepts only
/// [`ValidCuriosityParams`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CuriosityParams {
    /// N_max, the most centres ROC keeps (paper: 3). At least 2, since the
    /// rule merges a pair.
    pub max_centres: usize,
    /// β, the smallest step a ROC centre moves by towards a sample it wins
    /// (paper: 0.01); the step is max(1/c, β) for a centre of weight c.
    pub beta: f64,
    /// τ, the number of recent ROC errors whose mean is the estimation
    /// error ε (paper: 20).
    pub tau: usize,
    /// The lag L of Eq. 7: ξ_cur compares ε_n with ε_{n−L} and divides by L
    /// (paper: 20).
    pub lag: usize,
    /// η_c, the MCA rate of the slow-feature direction w **(ours: 0.03)**.
    /// CCSA's 0.01 learns too slowly for the agent's visits to K and M.
    pub eta_c: f64,
    /// g, the gain of Eq. 7 **(ours: 800)**. The paper gives none. With
    /// ROC errors of order 1 and τ = L = 20, the raw progress
    /// (ε_{n−L} − ε_n)/L is of order 10⁻³-10⁻², so g·(…) = 40·(ε_{n−L} − ε_n)
    /// reaches the clip only when ε fell by 0.3 within 20 samples: a fresh
    /// module's first ~20-30 samples sit at the clip, later learning-progress
    /// bumps are 2-8, on the scale of the extrinsic stimuli (6 ± noise), so
    /// curiosity competes with food and rest in the drive without swamping
    /// them. A much smaller g leaves ξ_cur too weak for the agent to return
    /// to a signal source.
    pub gain: f64,
    /// Upper clip of ξ_cur in Eq. 7 (paper: Clip(·, 0, 12)).
    pub clip: f64,
    /// δ: a module whose ε stays below δ is frozen (paper: 0.3).
    pub delta: f64,
    /// Freeze after this many consecutive learned samples with ε < δ
    /// **(ours: 100; 50 freezes half-learned features)**.
    pub freeze_after: u32,
    /// A frozen module explains a source when the mean of its window of
    /// errors on that source is below this **(ours: 0.3, = δ)**.
    pub explain_below: f64,
    /// ... and it has seen at least this many samples of the source
    /// **(ours: 20, = τ)**.
    pub explain_min_samples: u64,
    /// Signal clock: a source's own time advances by dt per delivered sample,
    /// starting at t = 0 **(ours: 0.08)**. Used by [`Signals`]. The paper
    /// gives no time step. The signals of Eq. 6 mix a slow part (period 2π,
    /// resp. π) with cos 11t; dt = 0.08 samples the slow part finely (about
    /// 79 samples per period of sin t, so a learned feature changes by less
    /// than 0.12 per sample and its ROC error stays well under δ) while the
    /// fast part advances 0.88 rad per sample, so it looks fast to the
    /// learner. The reproduction found dt in [0.075, 0.088] works; 0.1 and
    /// 0.072 alias the fast part so that one module wrongly explains the
    /// other signal.
    pub dt: f64,
    /// Whitening floor, relative part: eigenvalues of the covariance are
    /// floored at `floor_rel`·λ_max + `floor_abs` (§7 step 2: 1e-3).
    pub floor_rel: f64,
    /// Whitening floor, absolute part (§7 step 2: 1e-8).
    pub floor_abs: f64,
    /// A fresh module's error window and lag history start filled with this
    /// value **(ours: 1.0; starting at 0 gives no first curiosity and the
    /// agent never returns)**. The same fill is used for a frozen module's
    /// window on a source it has not yet seen.
    pub initial_error: f64,
    /// Sources are numbered `0..max_sources`; a bound on the library's
    /// per-source state (our limit, default 64).
    pub max_sources: usize,
}

impl Default for CuriosityParams {
    fn default() -> Self {
        Self {
            max_centres: 3,
            beta: 0.01,
            tau: 20,
            lag: 20,
            eta_c: 0.03,
            gain: 800.0,
            clip: 12.0,
            delta: 0.3,
            freeze_after: 100,
            explain_below: 0.3,
            explain_min_samples: 20,
            dt: 0.08,
            floor_rel: 1e-3,
            floor_abs: 1e-8,
            initial_error: 1.0,
            max_sources: 64,
        }
    }
}

/// Curiosity parameters that passed [`CuriosityParams::check`].
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ValidCuriosityParams(CuriosityParams);

impl ValidCuriosityParams {
    /// Wraps parameters that passed [`CuriosityParams::check`] (which
    /// checks them against the table of `crate::params`).
    pub(crate) fn checked(params: CuriosityParams) -> Self {
        Self(params)
    }
}

impl Deref for ValidCuriosityParams {
    type Target = CuriosityParams;

    fn deref(&self) -> &CuriosityParams {
        &self.0
    }
}

/// Largest accepted signal dimension m: the expansion has d = m(m+3)/2
/// entries and each learned sample costs an O(d³) eigendecomposition.
pub const MAX_SIGNAL_DIM: usize = 64;

/// Largest accepted `max_sources`.
pub const MAX_SOURCES_LIMIT: usize = 1 << 16;

/// Largest accepted `tau` and `lag` (our limit): the error window and the
/// lag history are allocated at these lengths for every module.
pub const MAX_WINDOW: usize = 100_000;

/// Largest accepted `max_centres` (our limit): ROC's merge step is
/// quadratic in the number of centres.
pub const MAX_CENTRES: usize = 1024;

/// Most frozen modules a channel keeps (our limit; the paper's library is
/// unbounded). Once the library is full the active module goes on learning
/// instead of freezing, so memory and the per-sample cost of judging stay
/// bounded whatever the signal does.
pub const MAX_LIBRARY: usize = 64;

pub(super) fn bad(name: &'static str, reason: impl Into<String>) -> AlgoError {
    AlgoError::InvalidParameter {
        name,
        reason: reason.into(),
    }
}
