//! The agent configuration of a session, defined once. The algorithm's
//! part is the core's [`AgentParams`] (checked into [`ValidParams`]); the
//! service adds the update mode, the history length and the curiosity
//! channel. [`SessionConfig`] is what a client sends (every field
//! optional), [`EffectiveConfig`] what a session runs with (every field
//! set, the seed drawn). Both, and every conversion between them and to and
//! from the core's types, are generated from the core's one list of agent
//! parameters ([`mcapi_core::agent_params`]), so a parameter added there
//! needs no edit here. The proto messages convert in one place,
//! `crate::api::grpc::convert`, which destructures them completely so that
//! a new field does not compile until it is handled.

use serde::{Deserialize, Serialize};

use mcapi_core::params::AGENT_PARAMS;
use mcapi_core::params::spec::{Default as ParamDefault, Kind, Max, Param};
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
    default: ParamDefault::Name("lockstep"),
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
    default: ParamDefault::Integer(DEFAULT_HISTORY as u64),
    unit: "ticks",
    doc: "recent ticks kept for /history",
    see: "",
};

/// `curiosity`: a curiosity channel.
pub const CURIOSITY: Param = Param {
    name: "curiosity",
    kind: Kind::Object("CuriosityConfig"),
    default: ParamDefault::Absent,
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

/// The schema of an agent parameter's field in the derived OpenAPI
/// schemas: the type's own, or a `$ref` for the types the document writes
/// out by hand (`crate::api::schemas`).
trait FieldSchema {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema>;
}

impl FieldSchema for f64 {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        <f64 as utoipa::PartialSchema>::schema()
    }
}

impl FieldSchema for u64 {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        <u64 as utoipa::PartialSchema>::schema()
    }
}

impl FieldSchema for Vec<f64> {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        <Vec<f64> as utoipa::PartialSchema>::schema()
    }
}

impl FieldSchema for StimulusRate {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        utoipa::openapi::Ref::from_schema_name("StimulusRate").into()
    }
}

/// [`SessionConfig`], [`EffectiveConfig`] and every conversion between them
/// and the core's types, from the core's list of agent parameters
/// ([`mcapi_core::agent_params`]) and the session's own three options: a
/// parameter added to the core's list is a field of both, converted, with
/// no edit here.
macro_rules! session_configs {
    ($($(#[doc = $doc:literal])* $name:ident: $ty:ty,)*) => {
        /// Agent configuration of a session; every field is optional.
        #[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, utoipa::ToSchema)]
        #[serde(deny_unknown_fields)]
        pub struct SessionConfig {
            $(
                $(#[doc = $doc])*
                #[schema(schema_with = <$ty as FieldSchema>::schema)]
                pub $name: Option<$ty>,
            )*
            /// `lockstep` (default) or `async`.
            pub update_mode: Option<UpdateMode>,
            /// Number of recent ticks kept for `/history`; default 256.
            pub history: Option<usize>,
            /// A curiosity channel (docs/algorithm.md §7): the server appends
            /// a stimulus dimension `curiosity`, last, and computes it from
            /// raw `signal`s.
            pub curiosity: Option<CuriosityConfig>,
        }

        /// The effective configuration of a session, every field set.
        #[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
        pub struct EffectiveConfig {
            $(
                $(#[doc = $doc])*
                #[schema(schema_with = <$ty as FieldSchema>::schema)]
                pub $name: $ty,
            )*
            /// Update mode.
            pub update_mode: UpdateMode,
            /// History length.
            pub history: usize,
            /// The curiosity channel, every parameter set; absent without one.
            #[serde(default, skip_serializing_if = "Option::is_none")]
            pub curiosity: Option<CuriosityConfig>,
        }

        impl SessionConfig {
            /// The algorithm's part, for [`AgentParams::check`].
            pub fn params(&self) -> AgentParams {
                AgentParams {
                    $($name: self.$name.clone(),)*
                }
            }

            /// The effective configuration of a session whose algorithm's
            /// part checked into `params`: the service's part resolved to
            /// its defaults.
            #[allow(clippy::clone_on_copy)]
            pub fn effective(&self, params: &ValidParams) -> EffectiveConfig {
                EffectiveConfig {
                    $($name: params.$name.clone(),)*
                    update_mode: self.update_mode.unwrap_or_default(),
                    history: self.history.unwrap_or(DEFAULT_HISTORY),
                    curiosity: self.curiosity.clone(),
                }
            }
        }

        /// The request that builds a session with exactly this configuration
        /// again (recovery rebuilds a stored session from its effective
        /// configuration).
        impl From<&EffectiveConfig> for SessionConfig {
            #[allow(clippy::clone_on_copy)]
            fn from(c: &EffectiveConfig) -> Self {
                Self {
                    $($name: Some(c.$name.clone()),)*
                    update_mode: Some(c.update_mode),
                    history: Some(c.history),
                    curiosity: c.curiosity.clone(),
                }
            }
        }
    };
}

mcapi_core::agent_params!(session_configs);

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

#[cfg(test)]
mod tests {
    use super::*;

    /// [`SessionConfig`] and [`EffectiveConfig`] have one field per entry
    /// of the tables, in their order.
    #[test]
    fn the_configs_have_one_field_per_table_entry() {
        let names: Vec<&str> = session_options().map(|p| p.name).collect();
        // One example value per entry of the tables: the fields must take
        // them (unknown fields are refused) and give them back.
        let mut request: serde_json::Map<String, serde_json::Value> = session_options()
            .map(|p| (p.name.to_owned(), p.example()))
            .collect();
        request.insert("curiosity".into(), serde_json::json!({"signal_dim": 2}));
        let config: SessionConfig =
            serde_json::from_value(request.into()).expect("every entry is a field");
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
