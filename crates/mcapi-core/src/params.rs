//! Agent parameters, checked once (`AgentParams::check -> ValidParams`) so
//! that the algorithm only ever sees valid values. Defaults follow
//! docs/algorithm.md §2-§6.

use serde::{Deserialize, Serialize};

use super::error::{AlgoError, Result};

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
pub const DEFAULT_ETA: f64 = 0.01;
/// Default discount γ (the hallway's).
pub const DEFAULT_GAMMA: f64 = 0.95;
/// Default σ of the optimistic initialisation of Ξ (docs/algorithm.md §3).
pub const DEFAULT_OPTIMISTIC_SD: f64 = 0.3;
/// Default ridge λ, added only when A is singular (docs/algorithm.md §2.6).
pub const DEFAULT_RIDGE: f64 = 1e-6;

/// Agent configuration as a client sends it; every field is optional.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct AgentParams {
    /// MCA learning rate η (Eq. 1), 0 < η <= 0.5.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eta: Option<f64>,
    /// Discount γ in [0, 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gamma: Option<f64>,
    /// Priorities ρ in (0, 1]^n; Λ = diag(1/ρ). Default all ones.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub priorities: Option<Vec<f64>>,
    /// Learning rate of Ξ.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stimulus_rate: Option<StimulusRate>,
    /// σ of the optimistic initialisation Ξ ~ N(0, σ²).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub optimistic_sd: Option<f64>,
    /// Ridge λ added to A only when A is singular.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ridge: Option<f64>,
    /// ε of ε-greedy exploration (our addition; default 0, off).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub epsilon: Option<f64>,
    /// Seed of the agent's ChaCha RNG; drawn at random when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

/// Checked parameters; only [`AgentParams::check`] makes them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ValidParams {
    /// η.
    pub eta: f64,
    /// γ.
    pub gamma: f64,
    /// ρ, one per stimulus dimension.
    pub priorities: Vec<f64>,
    /// Ξ learning rate.
    pub stimulus_rate: StimulusRate,
    /// σ of Ξ's initialisation.
    pub optimistic_sd: f64,
    /// Ridge λ.
    pub ridge: f64,
    /// Exploration ε.
    pub epsilon: f64,
    /// RNG seed.
    pub seed: u64,
}

fn bad(name: &'static str, reason: impl Into<String>) -> AlgoError {
    AlgoError::InvalidParameter {
        name,
        reason: reason.into(),
    }
}

fn finite(name: &'static str, x: f64) -> Result<f64> {
    if x.is_finite() {
        Ok(x)
    } else {
        Err(bad(name, "must be a finite number"))
    }
}

impl AgentParams {
    /// Validates against a model with `n_stimuli` stimulus dimensions.
    /// `fallback_seed` is used when no seed was given.
    pub fn check(&self, n_stimuli: usize, fallback_seed: u64) -> Result<ValidParams> {
        let eta = finite("eta", self.eta.unwrap_or(DEFAULT_ETA))?;
        // Condition (1), first half (docs/algorithm.md §4).
        if !(eta > 0.0 && eta <= 0.5) {
            return Err(bad(
                "eta",
                format!("{eta} is not in (0, 0.5] (condition (1))"),
            ));
        }
        let gamma = finite("gamma", self.gamma.unwrap_or(DEFAULT_GAMMA))?;
        if !(0.0..1.0).contains(&gamma) {
            return Err(bad("gamma", format!("{gamma} is not in [0, 1)")));
        }
        let priorities = match &self.priorities {
            None => vec![1.0; n_stimuli],
            Some(rho) => {
                if rho.len() != n_stimuli {
                    return Err(bad(
                        "priorities",
                        format!(
                            "has {} entries, expected one per stimulus ({n_stimuli})",
                            rho.len()
                        ),
                    ));
                }
                for (i, &r) in rho.iter().enumerate() {
                    if !(r.is_finite() && r > 0.0 && r <= 1.0) {
                        return Err(bad(
                            "priorities",
                            format!("entry {i} = {r} is not in (0, 1]"),
                        ));
                    }
                }
                rho.clone()
            }
        };
        let stimulus_rate = self.stimulus_rate.unwrap_or_default();
        if let StimulusRate::Constant(c) = stimulus_rate
            && !(c.is_finite() && c > 0.0 && c <= 1.0)
        {
            return Err(bad("stimulus_rate", format!("{c} is not in (0, 1]")));
        }
        let optimistic_sd = finite(
            "optimistic_sd",
            self.optimistic_sd.unwrap_or(DEFAULT_OPTIMISTIC_SD),
        )?;
        if optimistic_sd < 0.0 {
            return Err(bad("optimistic_sd", format!("{optimistic_sd} is negative")));
        }
        let ridge = finite("ridge", self.ridge.unwrap_or(DEFAULT_RIDGE))?;
        if ridge <= 0.0 {
            return Err(bad("ridge", format!("{ridge} must be positive")));
        }
        let epsilon = finite("epsilon", self.epsilon.unwrap_or(0.0))?;
        if !(0.0..=1.0).contains(&epsilon) {
            return Err(bad("epsilon", format!("{epsilon} is not in [0, 1]")));
        }
        Ok(ValidParams {
            eta,
            gamma,
            priorities,
            stimulus_rate,
            optimistic_sd,
            ridge,
            epsilon,
            seed: self.seed.unwrap_or(fallback_seed),
        })
    }
}

impl ValidParams {
    /// Back to the optional form, every field set (the effective configuration).
    pub fn to_params(&self) -> AgentParams {
        AgentParams {
            eta: Some(self.eta),
            gamma: Some(self.gamma),
            priorities: Some(self.priorities.clone()),
            stimulus_rate: Some(self.stimulus_rate),
            optimistic_sd: Some(self.optimistic_sd),
            ridge: Some(self.ridge),
            epsilon: Some(self.epsilon),
            seed: Some(self.seed),
        }
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

    #[test]
    fn stimulus_rate_parses_both_forms() {
        let p: AgentParams =
            serde_json::from_str(r#"{"stimulus_rate":"sample_mean"}"#).expect("named");
        assert_eq!(p.stimulus_rate, Some(StimulusRate::default()));
        let p: AgentParams = serde_json::from_str(r#"{"stimulus_rate":0.1}"#).expect("constant");
        assert_eq!(p.stimulus_rate, Some(StimulusRate::Constant(0.1)));
    }
}
