//! Size limits of the server: every request beyond one is refused with a
//! clear error before any large allocation.

use serde::{Deserialize, Serialize};

use crate::algo::model::ModelSpec;
use crate::algo::{BasisSpec, EnvModel};

use super::error::ServiceError;

/// Caps on what clients may ask of the server.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Limits {
    /// Sessions held at once.
    pub max_sessions: usize,
    /// States × actions of one model.
    pub max_pairs: usize,
    /// Stored transitions of one model.
    pub max_transitions: usize,
    /// Features of a basis (k·|A|).
    pub max_features: usize,
    /// States of a model using proto-value functions (eigendecomposition is O(|S|³)).
    pub max_pvf_states: usize,
    /// Stimulus dimensions.
    pub max_stimuli: usize,
    /// Request body size in bytes.
    pub max_body_bytes: usize,
    /// Observations in one batch.
    pub max_batch: usize,
    /// History entries per session.
    pub max_history: usize,
    /// Buffered messages per gRPC stream.
    pub stream_buffer: usize,
    /// Jobs waiting for the tick loop.
    pub queue: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_sessions: 250_000,
            max_pairs: 200_000,
            max_transitions: 2_000_000,
            max_features: 1024,
            max_pvf_states: 2000,
            max_stimuli: 64,
            max_body_bytes: 16 << 20,
            max_batch: 10_000,
            max_history: 100_000,
            stream_buffer: 64,
            queue: 1 << 20,
        }
    }
}

impl Limits {
    /// No limit at all (recovering sessions created under looser limits).
    pub fn unlimited() -> Self {
        Self {
            max_sessions: usize::MAX,
            max_pairs: usize::MAX,
            max_transitions: usize::MAX,
            max_features: usize::MAX,
            max_pvf_states: usize::MAX,
            max_stimuli: usize::MAX,
            max_body_bytes: usize::MAX,
            max_batch: usize::MAX,
            max_history: usize::MAX,
            stream_buffer: usize::MAX,
            queue: usize::MAX,
        }
    }
}

fn exceeded(what: &str, got: usize, limit: usize) -> ServiceError {
    ServiceError::LimitExceeded(format!("{what} is {got}; the limit is {limit}"))
}

impl Limits {
    /// Checks a posted model before it is built.
    pub fn check_model_spec(&self, spec: &ModelSpec) -> Result<(), ServiceError> {
        let pairs = spec.states.saturating_mul(spec.actions.len());
        if pairs > self.max_pairs {
            return Err(exceeded("`model` states x actions", pairs, self.max_pairs));
        }
        if let Some(t) = &spec.transitions {
            let n: usize = t.iter().map(|t| t.next.len()).sum();
            if n > self.max_transitions {
                return Err(exceeded(
                    "`model.transitions` count",
                    n,
                    self.max_transitions,
                ));
            }
        }
        if spec.stimuli.len() > self.max_stimuli {
            return Err(exceeded(
                "`model.stimuli` length",
                spec.stimuli.len(),
                self.max_stimuli,
            ));
        }
        Ok(())
    }

    /// Checks a built model.
    pub fn check_model(&self, model: &EnvModel) -> Result<(), ServiceError> {
        let pairs = model.states() * model.n_actions();
        if pairs > self.max_pairs {
            return Err(exceeded("`model` states x actions", pairs, self.max_pairs));
        }
        if model.n_transitions() > self.max_transitions {
            return Err(exceeded(
                "`model` transitions",
                model.n_transitions(),
                self.max_transitions,
            ));
        }
        if model.n_stimuli() > self.max_stimuli {
            return Err(exceeded(
                "`model.stimuli` length",
                model.n_stimuli(),
                self.max_stimuli,
            ));
        }
        Ok(())
    }

    /// Checks a basis choice for a model before it is built.
    pub fn check_basis(&self, model: &EnvModel, basis: &BasisSpec) -> Result<(), ServiceError> {
        let k = match basis {
            BasisSpec::Indicator => return Ok(()),
            BasisSpec::ProtoValue { k } => {
                if model.states() > self.max_pvf_states {
                    return Err(exceeded(
                        "`model` states for a proto_value basis",
                        model.states(),
                        self.max_pvf_states,
                    ));
                }
                *k
            }
            BasisSpec::Custom { state_features } => state_features.first().map_or(0, Vec::len),
        };
        let features = k.saturating_mul(model.n_actions());
        if features > self.max_features {
            return Err(exceeded(
                "`model.basis` features (k x actions)",
                features,
                self.max_features,
            ));
        }
        Ok(())
    }
}
