//! The agent configuration of a session, defined once. The algorithm's
//! part is the core's [`AgentParams`] (checked into [`ValidParams`]); the
//! service adds the update mode, the history length and the curiosity
//! channel. [`SessionConfig`] is what a client sends (every field
//! optional), [`EffectiveConfig`] what a session runs with (every field
//! set, the seed drawn); every conversion between them, and to and from
//! the core's types, is here, each destructuring its source completely so
//! a new field does not compile until it is handled. The proto messages
//! convert in one place too, `crate::api::grpc::convert`.

use serde::{Deserialize, Serialize};

use mcapi_core::params::AGENT_PARAMS;
use mcapi_core::params::spec::{Default, Kind, Max, Param};
use mcapi_core::{AgentParams, CuriosityParams, StimulusRate, ValidParams};

/// How a session's reply relates to its policy update.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum UpdateMode {
    /// Reply after exactly one LSTDQ update (Algorithm 1 to the letter).
    #[default]
    Lockstep,
    /// Reply at once with the newest policy; the tick loop catches up.
    Async,
}

/// Default length of the history ring buffer.
pub const DEFAULT_HISTORY: usize = 256;

/// `update_mode`: how a session's reply relates to its policy update.
pub const UPDATE_MODE: Param = Param {
    name: "update_mode",
    kind: Kind::Choice(&["lockstep", "async"]),
    default: Default::Name("lockstep"),
    unit: "",
    doc: "`lockstep`: the reply follows exactly one policy update; `async`: the reply \
          comes at once and the tick loop updates behind it",
    see: "sessions.md#update-modes",
};

/// `history`: the recent ticks a session keeps.
pub const HISTORY: Param = Param {
    name: "history",
    kind: Kind::Integer {
        min: 0,
        max: Max::Limit {
            flag: "--max-history",
            hard: u64::MAX,
        },
    },
    default: Default::Integer(DEFAULT_HISTORY as u64),
    unit: "ticks",
    doc: "recent ticks kept for /history",
    see: "",
};

/// `curiosity`: a curiosity channel.
pub const CURIOSITY: Param = Param {
    name: "curiosity",
    kind: Kind::Object("CuriosityConfig"),
    default: Default::Absent,
    unit: "",
    doc: "a curiosity channel: the server appends a stimulus dimension `curiosity`, last, \
          and computes it from the raw `signal` of observations",
    see: "algorithm.md#7-curiosity-the-intmca-channel-sec-43-eqs-6-7",
};

/// The options a session adds to the core's agent parameters, in the
/// order of [`SessionConfig`]'s fields after them.
pub const SESSION_PARAMS: [Param; 3] = [UPDATE_MODE, HISTORY, CURIOSITY];

/// Every option of `agent` in a create request, in [`SessionConfig`]'s
/// order: the core's table, then the session's.
pub fn session_options() -> impl Iterator<Item = &'static Param> {
    AGENT_PARAMS.iter().chain(SESSION_PARAMS.iter())
}

/// Agent configuration of a session; every field is optional.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SessionConfig {
    /// MCA rate η (Eq. 1), 0 < η <= 0.5; default 0.01.
    pub eta: Option<f64>,
    /// Discount γ in [0, 1); default 0.95.
    pub gamma: Option<f64>,
    /// Priorities ρ in (0, 1], one per stimulus; default all 1.
    pub priorities: Option<Vec<f64>>,
    /// `"sample_mean"` (default) or a constant rate in (0, 1].
    #[schema(value_type = Option<Object>)]
    pub stimulus_rate: Option<StimulusRate>,
    /// σ of the optimistic initialisation of Ξ; default 0.3.
    pub optimistic_sd: Option<f64>,
    /// Ridge added to A only when singular; default 1e-6.
    pub ridge: Option<f64>,
    /// ε-greedy exploration; default 0.
    pub epsilon: Option<f64>,
    /// Seed of the session's RNG; drawn at random when absent and returned.
    pub seed: Option<u64>,
    /// `lockstep` (default) or `async`.
    pub update_mode: Option<UpdateMode>,
    /// Number of recent ticks kept for `/history`; default 256.
    pub history: Option<usize>,
    /// A curiosity channel (docs/algorithm.md §7): the server appends a stimulus
    /// dimension `curiosity`, last, and computes it from raw `signal`s.
    pub curiosity: Option<CuriosityConfig>,
}

/// Name of the stimulus dimension a curiosity channel adds.
pub const CURIOSITY_DIMENSION: &str = "curiosity";

/// A session's curiosity channel (docs/algorithm.md §7).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CuriosityConfig {
    /// Dimension m of the raw signal x(t) (2 for the paper's Eq. 6).
    pub signal_dim: usize,
    /// The channel's constants (§7); each defaults to the paper's or the
    /// reproduction's value (`g` = 800, `dt` = 0.08, δ = 0.3, ...).
    #[serde(default)]
    #[schema(value_type = Object)]
    pub params: CuriosityParams,
}

impl SessionConfig {
    /// The algorithm's part, for [`AgentParams::check`].
    pub fn params(&self) -> AgentParams {
        let Self {
            eta,
            gamma,
            priorities,
            stimulus_rate,
            optimistic_sd,
            ridge,
            epsilon,
            seed,
            update_mode: _,
            history: _,
            curiosity: _,
        } = self;
        AgentParams {
            eta: *eta,
            gamma: *gamma,
            priorities: priorities.clone(),
            stimulus_rate: *stimulus_rate,
            optimistic_sd: *optimistic_sd,
            ridge: *ridge,
            epsilon: *epsilon,
            seed: *seed,
        }
    }

    /// The effective configuration of a session whose algorithm's part
    /// checked into `params`: the service's part resolved to its defaults.
    pub fn effective(&self, params: &ValidParams) -> EffectiveConfig {
        let ValidParams {
            eta,
            gamma,
            priorities,
            stimulus_rate,
            optimistic_sd,
            ridge,
            epsilon,
            seed,
        } = params;
        EffectiveConfig {
            eta: *eta,
            gamma: *gamma,
            priorities: priorities.clone(),
            stimulus_rate: *stimulus_rate,
            optimistic_sd: *optimistic_sd,
            ridge: *ridge,
            epsilon: *epsilon,
            seed: *seed,
            update_mode: self.update_mode.unwrap_or_default(),
            history: self.history.unwrap_or(DEFAULT_HISTORY),
            curiosity: self.curiosity.clone(),
        }
    }
}

/// The request that builds a session with exactly this configuration again
/// (recovery rebuilds a stored session from its effective configuration).
impl From<&EffectiveConfig> for SessionConfig {
    fn from(c: &EffectiveConfig) -> Self {
        let EffectiveConfig {
            eta,
            gamma,
            priorities,
            stimulus_rate,
            optimistic_sd,
            ridge,
            epsilon,
            seed,
            update_mode,
            history,
            curiosity,
        } = c;
        Self {
            eta: Some(*eta),
            gamma: Some(*gamma),
            priorities: Some(priorities.clone()),
            stimulus_rate: Some(*stimulus_rate),
            optimistic_sd: Some(*optimistic_sd),
            ridge: Some(*ridge),
            epsilon: Some(*epsilon),
            seed: Some(*seed),
            update_mode: Some(*update_mode),
            history: Some(*history),
            curiosity: curiosity.clone(),
        }
    }
}

/// `$ref` to the stimulus-rate schema, which the OpenAPI document writes out
/// by hand (`crate::api::schemas`).
fn stimulus_rate_ref() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
    utoipa::openapi::Ref::from_schema_name("StimulusRate").into()
}

/// The effective configuration of a session, every field set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct EffectiveConfig {
    /// η.
    pub eta: f64,
    /// γ.
    pub gamma: f64,
    /// ρ.
    pub priorities: Vec<f64>,
    /// Ξ learning rate.
    #[schema(schema_with = stimulus_rate_ref)]
    pub stimulus_rate: StimulusRate,
    /// σ of Ξ's initialisation.
    pub optimistic_sd: f64,
    /// Ridge λ.
    pub ridge: f64,
    /// ε.
    pub epsilon: f64,
    /// The seed (drawn by the server when not given).
    pub seed: u64,
    /// Update mode.
    pub update_mode: UpdateMode,
    /// History length.
    pub history: usize,
    /// The curiosity channel, every parameter set; absent without one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curiosity: Option<CuriosityConfig>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// [`SessionConfig`] and [`EffectiveConfig`] have one field per entry
    /// of the tables, in their order.
    #[test]
    fn the_configs_have_one_field_per_table_entry() {
        let names: Vec<&str> = session_options().map(|p| p.name).collect();
        let config = SessionConfig {
            eta: Some(0.1),
            gamma: Some(0.5),
            priorities: Some(vec![1.0]),
            stimulus_rate: Some(StimulusRate::Constant(0.5)),
            optimistic_sd: Some(0.1),
            ridge: Some(1.0),
            epsilon: Some(0.0),
            seed: Some(1),
            update_mode: Some(UpdateMode::Async),
            history: Some(3),
            curiosity: Some(CuriosityConfig {
                signal_dim: 2,
                params: CuriosityParams::default(),
            }),
        };
        let mut keys: Vec<String> = serde_json::to_value(&config)
            .expect("serialises")
            .as_object()
            .expect("an object")
            .keys()
            .cloned()
            .collect();
        let mut sorted = names.clone();
        sorted.sort_unstable();
        keys.sort_unstable();
        assert_eq!(keys, sorted);
        let params = config.params().check(1, 0).expect("valid");
        let effective = serde_json::to_value(config.effective(&params)).expect("serialises");
        let mut keys: Vec<&String> = effective.as_object().expect("an object").keys().collect();
        keys.sort_unstable();
        assert_eq!(keys, sorted);
    }
}
