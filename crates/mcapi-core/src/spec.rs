//! The environment model and its feature basis as a client posts them
//! (docs/sessions.md, "The model"): plain data, checked by
//! [`EnvModel::from_spec`](super::model::EnvModel::from_spec) and
//! [`Basis::build`](super::basis::Basis::build). The posted JSON is a
//! wire format: these derives must not change what they accept or print.

use serde::{Deserialize, Serialize};

/// An action as named in a posted transition: its index or its name.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum ActionRef {
    /// Index into `actions`.
    Index(usize),
    /// One of the names in `actions`.
    Name(String),
}

/// One row of the sparse stochastic encoding: the successors of a pair.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransitionSpec {
    /// Source state s.
    pub state: usize,
    /// Action a, by index or name.
    pub action: ActionRef,
    /// `[[s', p], ...]` with p in (0, 1] summing to 1.
    pub next: Vec<(usize, f64)>,
}

/// An environment model as a client posts it (docs/sessions.md, "The model").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelSpec {
    /// Number of states |S|; states are `0..states`.
    pub states: usize,
    /// Optional display names of the states.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state_names: Option<Vec<String>>,
    /// Action names, e.g. `["left", "right", "stay"]`.
    pub actions: Vec<String>,
    /// Deterministic encoding: `next[s][a] = s'`, `null` where unavailable.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub next: Option<Vec<Vec<Option<usize>>>>,
    /// Stochastic sparse encoding; a pair not listed is unavailable.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transitions: Option<Vec<TransitionSpec>>,
    /// Names of the n stimulus dimensions.
    pub stimuli: Vec<String>,
    /// Feature basis; the default depends on the model's size.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub basis: Option<BasisSpec>,
}

/// A basis as a client names it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum BasisSpec {
    /// Φ = I over valid pairs.
    Indicator,
    /// The k smoothest proto-value functions.
    ProtoValue {
        /// Number of eigenvectors per action block.
        k: usize,
    },
    /// `state_features[s]` is v(s), the same length k for every state.
    Custom {
        /// One row of k features per state.
        state_features: Vec<Vec<f64>>,
    },
}
