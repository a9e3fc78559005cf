//! Agent parameters, checked once (`AgentParams::check -> ValidParams`) so
//! that the algorithm only ever sees valid values. Each parameter's name,
//! range, default and doc are declared once, in [`table`]; the check reads
//! them from there. Defaults follow docs/algorithm.md §2-§6.

mod curiosity;
pub mod spec;
pub mod table;

use serde::{Deserialize, Serialize};

use super::error::Result;
pub use spec::{Bound, Kind, Max, Param};
pub use table::{AGENT_PARAMS, CURIOSITY_PARAMS};

/// How the stimulus function Ξ learns (Algorithm 1, line 5).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum StimulusRate {
    /// A constant rate η_stim in (0, 1].
    Constant(f64),
    /// The named rule, currently only `"sample_mean"` (η_stim = 1/n(s,a)).
    Named(StimulusRateName),
}

/// Named stimulus-rate rules.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StimulusRateName {
    /// η_stim = 1/n(s,a): Ξ is the sample mean of what each pair delivered.
    SampleMean,
}

impl Default for StimulusRate {
    fn default() -> Self {
        Self::Named(StimulusRateName::SampleMean)
    }
}

/// Default MCA learning rate η (docs/algorithm.md §6).
pub const DEFAULT_ETA: f64 = real_default(table::ETA);
/// Default discount γ (the hallway's).
pub const DEFAULT_GAMMA: f64 = real_default(table::GAMMA);
/// Default σ of the optimistic initialisation of Ξ (docs/algorithm.md §3).
pub const DEFAULT_OPTIMISTIC_SD: f64 = real_default(table::OPTIMISTIC_SD);
/// Default ridge λ, added only when A is singular (docs/algorithm.md §2.6).
pub const DEFAULT_RIDGE: f64 = real_default(table::RIDGE);

const fn real_default(p: Param) -> f64 {
    match p.default {
        spec::Default::Real(x) => x,
        _ => f64::NAN,
    }
}

/// The agent's parameters as Rust fields, in the order of
/// [`table::AGENT_PARAMS`]: the one list from which the core's
/// [`AgentParams`] and [`ValidParams`] and the server's session
/// configurations are generated. `agent_params!(m)` calls the macro `m`
/// with the list (`/// doc` then `name: Type,` per parameter).
#[macro_export]
macro_rules! agent_params {
    ($then:ident) => {
        $then! {
            /// MCA learning rate η (Eq. 1), 0 < η <= 0.5.
            eta: f64,
            /// Discount γ in [0, 1).
            gamma: f64,
            /// Priorities ρ in [1e-6, 1], one per stimulus dimension; Λ = diag(1/ρ).
            priorities: Vec<f64>,
            /// Learning rate of Ξ (Algorithm 1, line 5).
            stimulus_rate: $crate::StimulusRate,
            /// σ of the optimistic initialisation Ξ ~ N(0, σ²).
            optimistic_sd: f64,
            /// Ridge λ added to A only when A is singular.
            ridge: f64,
            /// ε of ε-greedy exploration (our addition; default 0, off).
            epsilon: f64,
            /// Seed of the agent's ChaCha RNG; drawn at random when absent.
            seed: u64,
        }
    };
}

/// [`AgentParams`] (every field optional, as a client sends it),
/// [`ValidParams`] (every field checked) and the way back.
macro_rules! param_structs {
    ($($(#[doc = $doc:literal])* $name:ident: $ty:ty,)*) => {
        /// Agent configuration as a client sends it; every field is optional.
        #[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
        #[serde(deny_unknown_fields)]
        pub struct AgentParams {
            $(
                $(#[doc = $doc])*
                #[serde(default, skip_serializing_if = "Option::is_none")]
                pub $name: Option<$ty>,
            )*
        }

        /// Checked parameters; only [`AgentParams::check`] makes them.
        #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
        pub struct ValidParams {
            $(
                $(#[doc = $doc])*
                pub $name: $ty,
            )*
        }

        impl ValidParams {
            /// Back to the optional form, every field set (the effective
            /// configuration).
            #[allow(clippy::clone_on_copy)]
            pub fn to_params(&self) -> AgentParams {
                AgentParams {
                    $($name: Some(self.$name.clone()),)*
                }
            }
        }
    };
}

agent_params!(param_structs);

impl AgentParams {
    /// Validates against a model with `n_stimuli` stimulus dimensions, each
    /// field against its entry of [`table`] (η ≤ 0.5 is the first half of
    /// condition (1), docs/algorithm.md §4). `fallback_seed` is used when
    /// no seed was given.
    pub fn check(&self, n_stimuli: usize, fallback_seed: u64) -> Result<ValidParams> {
        let Self {
            eta,
            gamma,
            priorities,
            stimulus_rate,
            optimistic_sd,
            ridge,
            epsilon,
            seed,
        } = self;
        // In the table's order, so the first bad field is the one named.
        let eta = table::ETA.real(*eta)?;
        let gamma = table::GAMMA.real(*gamma)?;
        let priorities = table::PRIORITIES.per_stimulus(priorities.as_deref(), n_stimuli)?;
        let stimulus_rate = stimulus_rate.unwrap_or_default();
        if let StimulusRate::Constant(c) = stimulus_rate {
            table::STIMULUS_RATE.real(Some(c))?;
        }
        Ok(ValidParams {
            eta,
            gamma,
            priorities,
            stimulus_rate,
            optimistic_sd: table::OPTIMISTIC_SD.real(*optimistic_sd)?,
            ridge: table::RIDGE.real(*ridge)?,
            epsilon: table::EPSILON.real(*epsilon)?,
            seed: seed.unwrap_or(fallback_seed),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_papers() {
        let p = AgentParams::default().check(2, 7).expect("defaults valid");
        assert_eq!(p.eta, 0.01);
        assert_eq!(p.gamma, 0.95);
        assert_eq!(p.priorities, vec![1.0, 1.0]);
        assert_eq!(p.seed, 7);
        assert_eq!(p.epsilon, 0.0);
        assert_eq!(p.to_params().check(2, 99).expect("round trip"), p);
    }

    #[test]
    fn out_of_range_values_are_named() {
        let cases: [(AgentParams, &str); 7] = [
            (
                AgentParams {
                    eta: Some(0.6),
                    ..Default::default()
                },
                "`eta`",
            ),
            (
                AgentParams {
                    eta: Some(f64::NAN),
                    ..Default::default()
                },
                "`eta`: must be a finite",
            ),
            (
                AgentParams {
                    gamma: Some(1.0),
                    ..Default::default()
                },
                "`gamma`",
            ),
            (
                AgentParams {
                    priorities: Some(vec![1.0]),
                    ..Default::default()
                },
                "has 1 entries",
            ),
            (
                AgentParams {
                    priorities: Some(vec![1.0, 0.0]),
                    ..Default::default()
                },
                "entry 1 = 0",
            ),
            (
                AgentParams {
                    stimulus_rate: Some(StimulusRate::Constant(2.0)),
                    ..Default::default()
                },
                "`stimulus_rate`",
            ),
            (
                AgentParams {
                    epsilon: Some(-0.1),
                    ..Default::default()
                },
                "`epsilon`",
            ),
        ];
        for (params, expected) in cases {
            let msg = params.check(2, 0).expect_err("invalid").to_string();
            assert!(
                msg.contains(expected),
                "{msg:?} should contain {expected:?}"
            );
        }
    }

    /// Values the arithmetic cannot carry (Λ = diag(1/ρ) or the optimistic
    /// draw of Ξ overflowing, a ridge too small to ever regularise) are
    /// refused by the check, naming the field, not by the first plan.
    #[test]
    fn values_the_arithmetic_cannot_carry_are_refused() {
        let cases = [
            (
                AgentParams {
                    priorities: Some(vec![5e-324, 1.0]),
                    ..Default::default()
                },
                "`priorities`",
            ),
            (
                AgentParams {
                    priorities: Some(vec![1e-200, 1.0]),
                    ..Default::default()
                },
                "`priorities`",
            ),
            (
                AgentParams {
                    optimistic_sd: Some(1e308),
                    ..Default::default()
                },
                "`optimistic_sd`",
            ),
            (
                AgentParams {
                    ridge: Some(5e-324),
                    ..Default::default()
                },
                "`ridge`",
            ),
            (
                AgentParams {
                    ridge: Some(1e308),
                    ..Default::default()
                },
                "`ridge`",
            ),
        ];
        for (params, expected) in cases {
            let msg = params.check(2, 0).expect_err("refused").to_string();
            assert!(msg.contains(expected), "{msg:?} should name {expected}");
        }
        let edges = AgentParams {
            priorities: Some(vec![table::MIN_PRIORITY, 1.0]),
            optimistic_sd: Some(crate::error::MAX_STIMULUS),
            ridge: Some(1e-12),
            ..Default::default()
        };
        edges.check(2, 0).expect("the ends of the ranges are valid");
    }

    #[test]
    fn the_table_names_every_field_in_order() {
        // One example value per entry of the table: the fields must take
        // them (unknown fields are refused), check them and give them back.
        let request: serde_json::Map<String, serde_json::Value> = AGENT_PARAMS
            .iter()
            .map(|p| (p.name.to_owned(), p.example()))
            .collect();
        let params: AgentParams =
            serde_json::from_value(request.into()).expect("every entry is a field");
        let full = params
            .check(1, 0)
            .expect("the examples are valid")
            .to_params();
        let json = serde_json::to_value(&full).expect("serialises");
        let keys: Vec<&str> = json
            .as_object()
            .expect("an object")
            .keys()
            .map(String::as_str)
            .collect();
        let mut names: Vec<&str> = AGENT_PARAMS.iter().map(|p| p.name).collect();
        names.sort_unstable();
        // serde_json's map is sorted.
        assert_eq!(keys, names);
    }

    #[test]
    fn stimulus_rate_parses_both_forms() {
        let p: AgentParams =
            serde_json::from_str(r#"{"stimulus_rate":"sample_mean"}"#).expect("named");
        assert_eq!(p.stimulus_rate, Some(StimulusRate::default()));
        let p: AgentParams = serde_json::from_str(r#"{"stimulus_rate":0.1}"#).expect("constant");
        assert_eq!(p.stimulus_rate, Some(StimulusRate::Constant(0.1)));
    }
}
