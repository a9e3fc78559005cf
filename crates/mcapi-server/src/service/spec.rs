//! What clients send to create a session and what they get back: the
//! environment model in its forms (posted, preset, grid map, and a posted
//! or grid model whose transitions the agent learns, docs/algorithm.md §8),
//! the agent configuration, and the summaries returned.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use mcapi_core::continuous::{ContinuousModel, ContinuousSpec};
use mcapi_core::model::{GridMap, grid_preset, hallway, three_room};
use mcapi_core::spec::ModelSpec;
use mcapi_core::{BasisSpec, EnvModel, LearnedParams, ValidLearnedParams};

use super::agent_config::CURIOSITY_DIMENSION;
use super::error::ServiceError;
use super::limits::Limits;
use super::wire::GridLayout;

/// A model in one of its three forms, parsed.
#[derive(Debug, Clone, PartialEq)]
pub enum ModelInput {
    /// A named preset.
    Preset {
        /// `hallway` or `three_room`.
        name: String,
        /// Basis override.
        basis: Option<BasisSpec>,
    },
    /// An ASCII grid map with marked sources.
    Grid {
        /// Map rows.
        lines: Vec<String>,
        /// Mark → stimulus dimension.
        sources: BTreeMap<String, usize>,
        /// Names of the stimulus dimensions (default: the marks).
        stimuli: Option<Vec<String>>,
        /// Basis override.
        basis: Option<BasisSpec>,
        /// `"learn": true`: the agent learns P from its transitions instead
        /// of planning on the map's (docs/algorithm.md §8), with these
        /// parameters; `None` plans on the map.
        learn: Option<ValidLearnedParams>,
    },
    /// A full model.
    Spec(Box<ModelSpec>),
    /// A full model with `"transitions": "learn"`: states, actions and
    /// stimuli only; the agent learns P (docs/algorithm.md §8).
    Learned(Box<LearnedSpec>),
    /// A continuous observation space (docs/algorithm.md §9): observations
    /// are vectors, and transitions are always learned.
    Continuous(Box<ContinuousSpec>),
}

/// A full model whose transitions the agent learns (`"transitions":
/// "learn"`): every action is available in every state (a move into a
/// wall is a transition back to the same state, which the agent learns
/// like any other), and P is estimated from the observations
/// (docs/algorithm.md §8).
#[derive(Debug, Clone, PartialEq)]
pub struct LearnedSpec {
    /// Number of states |S|.
    pub states: usize,
    /// Optional display names of the states.
    pub state_names: Option<Vec<String>>,
    /// Action names.
    pub actions: Vec<String>,
    /// Names of the stimulus dimensions.
    pub stimuli: Vec<String>,
    /// Feature basis; the default depends on the model's size.
    pub basis: Option<BasisSpec>,
    /// m and the optimism rule, checked.
    pub learning: ValidLearnedParams,
}

/// The `"transitions": "learn"` marker of a learned full model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum LearnMarker {
    Learn,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct LearnedForm {
    states: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    state_names: Option<Vec<String>>,
    actions: Vec<String>,
    transitions: LearnMarker,
    stimuli: Vec<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    basis: Option<BasisSpec>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    learning: Option<LearnedParams>,
}

/// Checks learned-model parameters once (m in 1..=10⁶, the optimism rule),
/// naming the field in the error.
pub fn learned_params(
    field: &'static str,
    params: Option<LearnedParams>,
) -> Result<ValidLearnedParams, ServiceError> {
    params
        .unwrap_or_default()
        .check()
        .map_err(|e| ServiceError::algo_at(field, e))
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct PresetForm {
    preset: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    basis: Option<BasisSpec>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct GridForm {
    grid: Vec<String>,
    #[serde(default)]
    sources: BTreeMap<String, usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    stimuli: Option<Vec<String>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    basis: Option<BasisSpec>,
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    learn: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    learning: Option<LearnedParams>,
}

fn from_value<T: serde::de::DeserializeOwned>(value: Value) -> Result<T, ServiceError> {
    serde_json::from_value(value).map_err(|e| ServiceError::field("model", e))
}

impl ModelInput {
    /// Picks the form by its distinguishing key and parses it.
    pub fn parse(value: Value) -> Result<Self, ServiceError> {
        let Some(obj) = value.as_object() else {
            return Err(ServiceError::field("model", "must be a JSON object"));
        };
        // serde reads a struct from an array too; the API takes objects
        // only, on every transport (gRPC's `model_json` comes here as well).
        for key in ["basis", "learning", "observation_space", "samples"] {
            if obj.get(key).is_some_and(|v| !v.is_object() && !v.is_null()) {
                return Err(ServiceError::field(
                    match key {
                        "basis" => "model.basis",
                        "learning" => "model.learning",
                        "observation_space" => "model.observation_space",
                        _ => "model.samples",
                    },
                    "must be a JSON object",
                ));
            }
        }
        if obj.contains_key("observation_space") {
            if obj.contains_key("transitions") || obj.contains_key("next") {
                return Err(ServiceError::field(
                    "model.transitions",
                    "a continuous model's transitions are always learned from what the session observes; no table can be posted",
                ));
            }
            Ok(Self::Continuous(Box::new(from_value(value)?)))
        } else if obj.contains_key("preset") {
            let f: PresetForm = from_value(value)?;
            Ok(Self::Preset {
                name: f.preset,
                basis: f.basis,
            })
        } else if obj.contains_key("grid") {
            let f: GridForm = from_value(value)?;
            let learn = match (f.learn, f.learning) {
                (false, Some(_)) => {
                    return Err(ServiceError::field(
                        "model.learning",
                        "is only taken with `\"learn\": true`",
                    ));
                }
                (false, None) => None,
                (true, params) => Some(learned_params("model.learning", params)?),
            };
            Ok(Self::Grid {
                lines: f.grid,
                sources: f.sources,
                stimuli: f.stimuli,
                basis: f.basis,
                learn,
            })
        } else if obj.get("transitions").is_some_and(Value::is_string) {
            let f: LearnedForm = from_value(value)?;
            Ok(Self::Learned(Box::new(LearnedSpec {
                states: f.states,
                state_names: f.state_names,
                actions: f.actions,
                stimuli: f.stimuli,
                basis: f.basis,
                learning: learned_params("model.learning", f.learning)?,
            })))
        } else {
            Ok(Self::Spec(Box::new(from_value(value)?)))
        }
    }

    /// The model as the JSON the REST API takes (what a durable session
    /// record keeps): [`ModelInput::parse`] of it gives `self` back.
    pub fn to_json_text(&self) -> Result<String, ServiceError> {
        let text = match self {
            Self::Preset { name, basis } => serde_json::to_string(&PresetForm {
                preset: name.clone(),
                basis: basis.clone(),
            }),
            Self::Grid {
                lines,
                sources,
                stimuli,
                basis,
                learn,
            } => serde_json::to_string(&GridForm {
                grid: lines.clone(),
                sources: sources.clone(),
                stimuli: stimuli.clone(),
                basis: basis.clone(),
                learn: learn.is_some(),
                learning: learn.as_ref().map(ValidLearnedParams::to_params),
            }),
            Self::Spec(spec) => serde_json::to_string(spec),
            Self::Learned(spec) => serde_json::to_string(&spec.form()),
            Self::Continuous(spec) => serde_json::to_string(spec),
        };
        text.map_err(|e| ServiceError::Internal(format!("encoding a model: {e}")))
    }

    /// A key identifying the model and basis, for sharing built models: the
    /// SHA-256 of a canonical rendering, so a large posted model is not kept
    /// twice.
    pub fn cache_key(&self) -> String {
        use sha2::Digest;
        let text = match self {
            Self::Preset { name, basis } => format!("preset:{name}:{basis:?}"),
            Self::Grid {
                lines,
                sources,
                stimuli,
                basis,
                learn,
            } => format!("grid:{lines:?}:{sources:?}:{stimuli:?}:{basis:?}:{learn:?}"),
            Self::Spec(spec) => format!("spec:{}", serde_json::to_string(spec).unwrap_or_default()),
            Self::Learned(spec) => format!(
                "learned:{}",
                serde_json::to_string(&spec.form()).unwrap_or_default()
            ),
            Self::Continuous(spec) => format!(
                "continuous:{}",
                serde_json::to_string(spec).unwrap_or_default()
            ),
        };
        sha2::Sha256::digest(text.as_bytes())
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect()
    }

    /// Builds and validates the model and picks its basis; with
    /// `curious`, the model gains the curiosity dimension, last.
    pub fn build(
        &self,
        limits: &Limits,
        curious: bool,
    ) -> Result<(EnvModel, BasisSpec), ServiceError> {
        let (model, basis) = match self {
            Self::Preset { name, basis } => {
                limits.check_name("model.preset", name)?;
                let preset = match name.as_str() {
                    "hallway" => hallway(),
                    "three_room" => three_room(),
                    other => {
                        return Err(ServiceError::field(
                            "model.preset",
                            format!("unknown preset `{other}` (known: hallway, three_room)"),
                        ));
                    }
                };
                (preset.model, basis.clone())
            }
            Self::Grid {
                lines,
                sources,
                stimuli,
                basis,
                learn: _,
            } => {
                limits.check_grid(lines, sources, stimuli.as_deref())?;
                limits.check_grid_basis(lines, basis.as_ref())?;
                (
                    grid_model(lines, sources, stimuli.as_deref(), limits)?,
                    basis.clone(),
                )
            }
            Self::Spec(spec) => {
                limits.check_model_spec(spec)?;
                (EnvModel::from_spec(spec)?, spec.basis.clone())
            }
            Self::Learned(spec) => {
                limits.check_learned_spec(
                    spec.states,
                    &spec.actions,
                    &spec.stimuli,
                    spec.state_names.as_deref(),
                )?;
                if matches!(spec.basis, Some(BasisSpec::ProtoValue { .. })) {
                    return Err(ServiceError::field(
                        "model.basis",
                        "proto-value functions come from the transition graph, which a model \
                         that learns its transitions does not have; use `indicator` or `custom` \
                         (a grid map with `\"learn\": true` takes them: its map is the graph)",
                    ));
                }
                (spec.structure()?, spec.basis.clone())
            }
            // Built by `build_continuous`: it has no states to enumerate.
            Self::Continuous(_) => {
                return Err(ServiceError::Internal(
                    "a continuous model has no planning model of states".into(),
                ));
            }
        };
        let model = if curious {
            model.with_stimulus(CURIOSITY_DIMENSION).map_err(|e| {
                ServiceError::field(
                    "model.stimuli",
                    format!("{e}; the curiosity channel adds `{CURIOSITY_DIMENSION}`"),
                )
            })?
        } else {
            model
        };
        limits.check_model(&model)?;
        let basis = basis.unwrap_or_else(|| BasisSpec::default_for(&model));
        limits.check_basis(&model, &basis)?;
        Ok((model, basis))
    }
}

fn grid_model(
    lines: &[String],
    sources: &BTreeMap<String, usize>,
    stimuli: Option<&[String]>,
    limits: &Limits,
) -> Result<EnvModel, ServiceError> {
    let cells: usize = lines.iter().map(String::len).sum();
    if cells > limits.max_pairs {
        return Err(ServiceError::LimitExceeded(format!(
            "`model.grid` has {cells} cells; the limit is {} state-action pairs",
            limits.max_pairs
        )));
    }
    let grid = GridMap::parse(lines)?;
    if sources.is_empty() {
        return Err(ServiceError::field(
            "model.sources",
            "map at least one mark to a stimulus dimension",
        ));
    }
    let n = sources.values().max().map_or(0, |m| m + 1);
    let mut marks: Vec<Option<char>> = vec![None; n];
    for (mark, &dim) in sources {
        let mut chars = mark.chars();
        let (Some(c), None) = (chars.next(), chars.next()) else {
            return Err(ServiceError::field(
                "model.sources",
                format!("key `{mark}` must be one character"),
            ));
        };
        if grid.mark_state(c).is_none() {
            return Err(ServiceError::field(
                "model.sources",
                format!("the map has no cell marked `{c}`"),
            ));
        }
        if marks[dim].replace(c).is_some() {
            return Err(ServiceError::field(
                "model.sources",
                format!("dimension {dim} is given twice"),
            ));
        }
    }
    let names: Vec<String> = match stimuli {
        Some(names) if names.len() != n => {
            return Err(ServiceError::field(
                "model.stimuli",
                format!(
                    "has {} names, but `sources` uses {n} dimensions",
                    names.len()
                ),
            ));
        }
        Some(names) => names.to_vec(),
        None => marks
            .iter()
            .enumerate()
            .map(|(d, m)| m.map_or_else(|| format!("dim{d}"), |c| c.to_string()))
            .collect(),
    };
    // Validates the same way the presets are built.
    let text = lines.join("\n");
    let pairs: Vec<(char, &str)> = marks
        .iter()
        .zip(&names)
        .filter_map(|(m, name)| m.map(|c| (c, name.as_str())))
        .collect();
    if pairs.len() == n {
        return Ok(grid_preset(&text, &pairs)?.model);
    }
    // Some dimensions have no source on the map (e.g. delivered elsewhere).
    Ok(grid.model(names)?)
}

impl ModelInput {
    /// The map layout of a grid-form model or the `three_room` preset
    /// (`None` for other models, or a map that does not parse).
    pub fn layout(&self) -> Option<GridLayout> {
        let grid = match self {
            Self::Preset { name, .. } if name == "three_room" => {
                GridMap::from_text(mcapi_core::model::THREE_ROOM_MAP).ok()?
            }
            Self::Grid { lines, .. } => GridMap::parse(lines).ok()?,
            Self::Preset { .. } | Self::Spec(_) | Self::Learned(_) | Self::Continuous(_) => {
                return None;
            }
        };
        Some(GridLayout::of(&grid))
    }

    /// The parameters of a model whose transitions the agent learns
    /// (docs/algorithm.md §8); `None` for a model with posted transitions.
    pub fn learning(&self) -> Option<ValidLearnedParams> {
        match self {
            Self::Grid { learn, .. } => *learn,
            Self::Learned(spec) => Some(spec.learning),
            Self::Preset { .. } | Self::Spec(_) | Self::Continuous(_) => None,
        }
    }

    /// The continuous spec, if this is one.
    pub fn continuous(&self) -> Option<&ContinuousSpec> {
        match self {
            Self::Continuous(spec) => Some(spec),
            Self::Preset { .. } | Self::Grid { .. } | Self::Spec(_) | Self::Learned(_) => None,
        }
    }

    /// Checks and builds a continuous model (its sizes first, then its
    /// basis), naming the field at fault.
    pub fn build_continuous(spec: &ContinuousSpec) -> Result<ContinuousModel, ServiceError> {
        spec.build().map_err(|e| match e {
            // `invalid_model` and `invalid_basis`, as a model with numbered
            // states gets them; a parameter is named under `model`.
            e @ (mcapi_core::AlgoError::InvalidModel(_)
            | mcapi_core::AlgoError::InvalidBasis(_)) => e.into(),
            e => ServiceError::algo_at("model", e),
        })
    }
}

impl LearnedSpec {
    fn form(&self) -> LearnedForm {
        let Self {
            states,
            state_names,
            actions,
            stimuli,
            basis,
            learning,
        } = self;
        LearnedForm {
            states: *states,
            state_names: state_names.clone(),
            actions: actions.clone(),
            transitions: LearnMarker::Learn,
            stimuli: stimuli.clone(),
            basis: basis.clone(),
            learning: Some(learning.to_params()),
        }
    }

    /// The structure the agent learns on: every action available in every
    /// state. Its P (each pair back to its own state) is never planned on:
    /// the agent's P̂ replaces it (`Agent::new_learned`). Call after
    /// [`Limits::check_learned_spec`], which bounds states × actions.
    pub fn structure(&self) -> Result<EnvModel, ServiceError> {
        let n_actions = self.actions.len();
        let spec = ModelSpec {
            states: self.states,
            state_names: self.state_names.clone(),
            actions: self.actions.clone(),
            next: Some((0..self.states).map(|s| vec![Some(s); n_actions]).collect()),
            transitions: None,
            stimuli: self.stimuli.clone(),
            basis: None,
        };
        Ok(EnvModel::from_spec(&spec)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// A model parsed by a transport is stored as JSON and parsed again on
    /// recovery: the round trip must give it back exactly.
    #[test]
    fn json_text_parses_back_to_the_same_model() {
        let models = [
            json!({"preset": "hallway"}),
            json!({"preset": "three_room", "basis": {"kind": "proto_value", "k": 4}}),
            json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1}}),
            json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 1},
                   "stimuli": ["x", "y"], "basis": {"kind": "indicator"}}),
            json!({"states": 2, "state_names": ["l", "r"], "actions": ["go", "stay"],
                   "next": [[1, 0], [null, 1]], "stimuli": ["x"]}),
            json!({"states": 2, "actions": ["go"], "stimuli": ["x"],
                   "transitions": [{"state": 0, "action": "go", "next": [[1, 0.1], [0, 0.9]]},
                                   {"state": 1, "action": 0, "next": [[0, 1.0]]}],
                   "basis": {"kind": "custom", "state_features": [[0.1], [1e-300]]}}),
            json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1}, "learn": true}),
            json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1}, "learn": true,
                   "learning": {"known_after": 7, "optimism": "stimulus"}}),
            json!({"states": 3, "actions": ["l", "r"], "stimuli": ["x"], "transitions": "learn"}),
            json!({"states": 3, "state_names": ["a", "b", "c"], "actions": ["l", "r"],
                   "stimuli": ["x"], "transitions": "learn", "basis": {"kind": "indicator"},
                   "learning": {"known_after": 1}}),
        ];
        for value in models {
            let input = ModelInput::parse(value.clone()).expect("valid model");
            let text = input.to_json_text().expect("encodes");
            let back: Value = serde_json::from_str(&text).expect("JSON");
            assert_eq!(ModelInput::parse(back).expect("parses"), input, "{value}");
        }
    }

    /// A learned model's parameters are checked once, at parsing, and
    /// written back in full, so a recovered session learns with the
    /// parameters it was created with whatever the defaults become.
    #[test]
    fn learned_models_parse_with_checked_parameters() {
        let grid = ModelInput::parse(
            json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0}, "learn": true}),
        )
        .expect("grid");
        let l = grid.learning().expect("learns");
        assert_eq!(
            (l.known_after, l.optimism),
            (3, mcapi_core::Optimism::Absorbing)
        );
        let text = grid.to_json_text().expect("encodes");
        assert!(
            text.contains(r#""learning":{"known_after":3,"optimism":"absorbing"}"#),
            "{text}"
        );
        let known =
            ModelInput::parse(json!({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0}}))
                .expect("grid");
        assert!(known.learning().is_none());
        assert!(!known.to_json_text().expect("encodes").contains("learn"));
        assert_ne!(
            known.cache_key(),
            grid.cache_key(),
            "a learned grid is another model"
        );
        for (model, needle) in [
            (
                json!({"grid": ["#a#"], "sources": {"a": 0}, "learning": {"known_after": 2}}),
                "only taken with",
            ),
            (
                json!({"grid": ["#a#"], "sources": {"a": 0}, "learn": true,
                       "learning": {"known_after": 0}}),
                "`known_after` 0 is not in 1..=1000000",
            ),
            (
                json!({"states": 2, "actions": ["go"], "stimuli": ["x"], "transitions": "learn",
                       "learning": {"optimism": "hopeful"}}),
                "unknown variant `hopeful`",
            ),
            (
                json!({"states": 2, "actions": ["go"], "stimuli": ["x"], "transitions": "guess"}),
                "unknown variant `guess`, expected `learn`",
            ),
            (
                json!({"states": 2, "actions": ["go"], "stimuli": ["x"], "transitions": "learn",
                       "learning": [5, "stimulus"]}),
                "`model.learning`: must be a JSON object",
            ),
            (
                json!({"grid": ["#a#"], "sources": {"a": 0}, "learn": true, "learning": []}),
                "`model.learning`: must be a JSON object",
            ),
            (
                json!({"observation_space": [[0], [1]], "actions": ["a"], "stimuli": ["x"]}),
                "`model.observation_space`: must be a JSON object",
            ),
            (
                json!({"observation_space": {"low": [0], "high": [1]}, "actions": ["a"],
                       "stimuli": ["x"], "samples": [1, 2, 3, 4]}),
                "`model.samples`: must be a JSON object",
            ),
            (
                json!({"states": 2, "actions": ["go"], "stimuli": ["x"], "transitions": "learn",
                       "next": [[0], [1]]}),
                "unknown field `next`",
            ),
        ] {
            let e = ModelInput::parse(model.clone()).expect_err("invalid");
            assert!(e.to_string().contains(needle), "{model}: {e}");
        }
    }
}
