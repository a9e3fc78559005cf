//! What clients send to create a session and what they get back: the
//! environment model in its three forms (posted, preset, grid map), the
//! agent configuration, and the summaries returned.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use mcapi_core::model::{GridMap, grid_preset, hallway, three_room};
use mcapi_core::spec::ModelSpec;
use mcapi_core::{BasisSpec, EnvModel};

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
    },
    /// A full model.
    Spec(Box<ModelSpec>),
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
        if obj.contains_key("preset") {
            let f: PresetForm = from_value(value)?;
            Ok(Self::Preset {
                name: f.preset,
                basis: f.basis,
            })
        } else if obj.contains_key("grid") {
            let f: GridForm = from_value(value)?;
            Ok(Self::Grid {
                lines: f.grid,
                sources: f.sources,
                stimuli: f.stimuli,
                basis: f.basis,
            })
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
            } => serde_json::to_string(&GridForm {
                grid: lines.clone(),
                sources: sources.clone(),
                stimuli: stimuli.clone(),
                basis: basis.clone(),
            }),
            Self::Spec(spec) => serde_json::to_string(spec),
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
            } => format!("grid:{lines:?}:{sources:?}:{stimuli:?}:{basis:?}"),
            Self::Spec(spec) => format!("spec:{}", serde_json::to_string(spec).unwrap_or_default()),
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
            } => {
                limits.check_grid(lines, sources, stimuli.as_deref())?;
                (
                    grid_model(lines, sources, stimuli.as_deref(), limits)?,
                    basis.clone(),
                )
            }
            Self::Spec(spec) => {
                limits.check_model_spec(spec)?;
                (EnvModel::from_spec(spec)?, spec.basis.clone())
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
            Self::Preset { .. } | Self::Spec(_) => return None,
        };
        Some(GridLayout::of(&grid))
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
        ];
        for value in models {
            let input = ModelInput::parse(value.clone()).expect("valid model");
            let text = input.to_json_text().expect("encodes");
            let back: Value = serde_json::from_str(&text).expect("JSON");
            assert_eq!(ModelInput::parse(back).expect("parses"), input, "{value}");
        }
    }
}
