//! What clients send to create a session and what they get back: the
//! environment model in its three forms (posted, preset, grid map), the
//! agent configuration, and the summaries returned.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use mcapi_core::model::{GridMap, grid_preset, hallway, three_room};
use mcapi_core::spec::ModelSpec;
use mcapi_core::{AgentParams, BasisSpec, CuriosityParams, EnvModel, StimulusRate};

use super::error::ServiceError;
use super::limits::Limits;

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
    /// A curiosity channel (ALGORITHM.md §7): the server appends a stimulus
    /// dimension `curiosity`, last, and computes it from raw `signal`s.
    pub curiosity: Option<CuriosityConfig>,
}

/// Name of the stimulus dimension a curiosity channel adds.
pub const CURIOSITY_DIMENSION: &str = "curiosity";

/// A session's curiosity channel (ALGORITHM.md §7).
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
    /// The algorithm's part.
    pub fn params(&self) -> AgentParams {
        AgentParams {
            eta: self.eta,
            gamma: self.gamma,
            priorities: self.priorities.clone(),
            stimulus_rate: self.stimulus_rate,
            optimistic_sd: self.optimistic_sd,
            ridge: self.ridge,
            epsilon: self.epsilon,
            seed: self.seed,
        }
    }
}

/// A request to create a session.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateSession {
    /// An environment model, `{"preset": "hallway" | "three_room"}`, or
    /// `{"grid": [...], "sources": {"a": 0, ...}}`.
    #[schema(value_type = Object)]
    pub model: Value,
    /// Agent configuration.
    #[serde(default)]
    pub agent: SessionConfig,
}

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

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PresetForm {
    preset: String,
    #[serde(default)]
    basis: Option<BasisSpec>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GridForm {
    grid: Vec<String>,
    #[serde(default)]
    sources: BTreeMap<String, usize>,
    #[serde(default)]
    stimuli: Option<Vec<String>>,
    #[serde(default)]
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

/// The basis of a session: its kind and, for feature bases, k per action.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct BasisSummary {
    /// `indicator`, `proto_value` or `custom`.
    pub kind: String,
    /// State features per action block (0 for `indicator`).
    pub k: usize,
}

impl BasisSummary {
    /// Summarises a basis choice.
    pub fn of(spec: &BasisSpec) -> Self {
        let (kind, k) = match spec {
            BasisSpec::Indicator => ("indicator", 0),
            BasisSpec::ProtoValue { k } => ("proto_value", *k),
            BasisSpec::Custom { state_features } => {
                ("custom", state_features.first().map_or(0, Vec::len))
            }
        };
        Self {
            kind: kind.into(),
            k,
        }
    }
}

/// What a session's model looks like, returned at creation and by `get`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ModelSummary {
    /// Number of states.
    pub states: usize,
    /// Action names.
    pub actions: Vec<String>,
    /// Stimulus names.
    pub stimuli: Vec<String>,
    /// Valid state-action pairs.
    pub pairs: usize,
    /// Stored transitions.
    pub transitions: usize,
    /// Whether every pair has one successor.
    pub deterministic: bool,
    /// The basis in use.
    pub basis: BasisSummary,
    /// Number of features.
    pub features: usize,
    /// Where each state lies on the map, for grid models (grid form and the
    /// `three_room` preset); absent for other models.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layout: Option<GridLayout>,
}

/// The map of a grid model: its size, the cell of each state and the marked
/// cells (the stimulus sources), for drawing values over the map.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct GridLayout {
    /// Map height in cells.
    pub rows: usize,
    /// Map width in cells.
    pub cols: usize,
    /// `[row, col]` of each state, indexed by state.
    pub cells: Vec<[usize; 2]>,
    /// Marked cells in row-major order: the mark and its state.
    pub marks: Vec<GridMark>,
}

/// A marked cell of a grid map.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct GridMark {
    /// The mark character.
    pub mark: String,
    /// The state of the marked cell.
    pub state: usize,
}

impl GridLayout {
    /// The layout of a parsed map.
    pub fn of(grid: &GridMap) -> Self {
        Self {
            rows: grid.rows(),
            cols: grid.cols(),
            cells: (0..grid.states())
                .map(|s| {
                    let (r, c) = grid.cell_of(s);
                    [r, c]
                })
                .collect(),
            marks: grid
                .marks()
                .iter()
                .map(|&(mark, state)| GridMark {
                    mark: mark.to_string(),
                    state,
                })
                .collect(),
        }
    }
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
