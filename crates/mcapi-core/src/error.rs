//! The one error type of the algorithm core.
//!
//! Every variant is a mistake in what a caller supplied (a model, a parameter,
//! an observation) except [`AlgoError::Numerical`], which reports a numerical
//! breakdown the core could not recover from. Messages name the offending field
//! so that the server can pass them to clients verbatim.

use thiserror::Error;

/// Errors raised by the pure MCA-PI core.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum AlgoError {
    /// The environment model is malformed; the message says where.
    #[error("invalid model: {0}")]
    InvalidModel(String),

    /// A stored agent state does not fit its model and parameters.
    #[error("invalid agent snapshot: {0}")]
    InvalidSnapshot(String),

    /// A parameter is outside its allowed range.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter {
        /// The parameter's name as it appears in the agent configuration.
        name: &'static str,
        /// Why the value was refused.
        reason: String,
    },

    /// The basis cannot be built for this model.
    #[error("invalid basis: {0}")]
    InvalidBasis(String),

    /// An observation names a state outside `0..states`.
    #[error("state {state} is out of range (the model has {states} states)")]
    StateOutOfRange {
        /// The state the caller sent.
        state: usize,
        /// Number of states in the model.
        states: usize,
    },

    /// An observation names an action index outside `0..actions`.
    #[error("action {action} is out of range (the model has {actions} actions)")]
    ActionOutOfRange {
        /// The action index the caller sent.
        action: usize,
        /// Number of actions in the model.
        actions: usize,
    },

    /// The action reported as taken is not available in the previous state.
    #[error("action `{action}` is not available in state {state}")]
    ActionNotAvailable {
        /// Previous state.
        state: usize,
        /// Name of the action.
        action: String,
    },

    /// A stimulus vector has the wrong number of components.
    #[error("stimulus has {got} components, expected {expected}")]
    StimulusLength {
        /// Components received.
        got: usize,
        /// Stimulus dimensions of the session.
        expected: usize,
    },

    /// The extrinsic stimulus of a curious agent has the wrong number of
    /// components (ξ_cur, its last dimension, comes from the signal).
    #[error(
        "stimulus has {got} components; this agent takes the {expected} extrinsic ones (the last dimension, curiosity, is computed from the signal)"
    )]
    ExtrinsicStimulusLength {
        /// Components received.
        got: usize,
        /// Extrinsic stimulus dimensions.
        expected: usize,
    },

    /// A number supplied by the caller is NaN or infinite.
    #[error("`{field}` contains a non-finite number")]
    NonFinite {
        /// Which input held the number.
        field: &'static str,
    },

    /// A stimulus component is beyond [`MAX_STIMULUS`] in magnitude.
    #[error("`stimulus[{index}]` = {value:e} exceeds the limit of ±{limit:e}")]
    StimulusTooLarge {
        /// Component index.
        index: usize,
        /// The value sent.
        value: f64,
        /// The limit.
        limit: f64,
    },

    /// The first observation of an agent must carry only a state.
    #[error("the first observation carries only a state; `{field}` must be omitted")]
    FirstObservation {
        /// Field that must not be present.
        field: &'static str,
    },

    /// An observation of a continuous world is malformed (wrong dimension,
    /// a non-finite coordinate, outside a box that refuses it); the message
    /// says which.
    #[error("{0}")]
    InvalidObservation(String),

    /// A later observation lacks its stimulus.
    #[error("`stimulus` is required on every observation after the first")]
    MissingStimulus,

    /// The numerics broke down (a singular system even after regularisation,
    /// or a non-finite intermediate). Not a caller's mistake.
    #[error("numerical failure: {0}")]
    Numerical(String),

    /// A build was stopped before it finished: its deadline passed or its
    /// caller went away ([`crate::basis::BuildBudget`]). Nothing was built.
    #[error("build stopped: {0}")]
    BuildStopped(String),
}

/// Largest accepted magnitude of a stimulus component. Beyond about 1e154
/// ‖Λξ‖² overflows f64; the limit keeps every downstream quantity (D's
/// norm, the second moment, Q and its differences) comfortably finite.
pub const MAX_STIMULUS: f64 = 1e12;

/// Checks a stimulus vector sent with an observation: `expected`
/// components, each finite and within ±[`MAX_STIMULUS`].
pub fn check_stimulus(xi: &[f64], expected: usize) -> Result<()> {
    if xi.len() != expected {
        return Err(AlgoError::StimulusLength {
            got: xi.len(),
            expected,
        });
    }
    if xi.iter().any(|x| !x.is_finite()) {
        return Err(AlgoError::NonFinite { field: "stimulus" });
    }
    if let Some((index, &value)) = xi.iter().enumerate().find(|(_, x)| x.abs() > MAX_STIMULUS) {
        return Err(AlgoError::StimulusTooLarge {
            index,
            value,
            limit: MAX_STIMULUS,
        });
    }
    Ok(())
}

/// Shorthand for results of the core.
pub type Result<T, E = AlgoError> = std::result::Result<T, E>;
