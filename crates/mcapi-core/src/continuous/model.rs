//! The continuous model form (docs/sessions.md, "Continuous worlds"): an
//! observation space, named actions and stimuli, a basis, and how the
//! sample store is cut. Transitions are always learned; no table can be
//! posted for a continuous space.

use serde::{Deserialize, Serialize};

use super::basis::{ContinuousBasisSpec, FeatureMap, MAX_STATE_FEATURES};
use super::space::{MAX_DIM, ObservationSpace, OutOfBounds};
use crate::error::{AlgoError, Result};

/// Most actions of a continuous world.
pub const MAX_ACTIONS: usize = 64;
/// Most stored transitions.
pub const MAX_SAMPLES: u32 = 16_384;
/// Most transitions kept per (cell, action).
pub const MAX_PER_CELL: u32 = 64;
/// Most cells per dimension of the sample grid.
pub const MAX_CELLS_PER_DIM: u32 = 1024;
/// Largest `known_after`.
pub const MAX_KNOWN_AFTER: u32 = 1000;
/// Default stored transitions.
pub const DEFAULT_MAX_SAMPLES: u32 = 2048;
/// Default transitions per (cell, action).
pub const DEFAULT_PER_CELL: u32 = 2;
/// Default visits after which a (cell, action) pair is known.
pub const DEFAULT_KNOWN_AFTER: u32 = 1;

/// How the sample store is cut, as a client sends it; every field optional.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SampleParams {
    /// Cells per dimension of the grid that counts visits (default by d:
    /// 50 for d = 1, 25 for d = 2, then ⌊4096^(1/d)⌋, at least 2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cells_per_dim: Option<u32>,
    /// Transitions kept per (cell, action).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub per_cell: Option<u32>,
    /// Transitions kept in all.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max: Option<u32>,
    /// Visits after which a (cell, action) pair is known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub known_after: Option<u32>,
}

/// Checked sample-store parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ValidSampleParams {
    /// Cells per dimension.
    pub cells_per_dim: u32,
    /// Transitions per (cell, action).
    pub per_cell: u32,
    /// Transitions in all.
    pub max: u32,
    /// Visits to be known.
    pub known_after: u32,
}

/// The default cells per dimension of a d-dimensional space.
pub fn default_cells_per_dim(d: usize) -> u32 {
    match d {
        1 => 50,
        2 => 25,
        _ => ((MAX_STATE_FEATURES as f64).powf(1.0 / d as f64).floor() as u32).max(2),
    }
}

impl SampleParams {
    /// Checks each field against its bound.
    pub fn check(&self, d: usize) -> Result<ValidSampleParams> {
        let field = |name: &'static str, v: Option<u32>, default: u32, lo: u32, hi: u32| {
            let v = v.unwrap_or(default);
            if (lo..=hi).contains(&v) {
                Ok(v)
            } else {
                Err(AlgoError::InvalidParameter {
                    name,
                    reason: format!("{v} is not in {lo}..={hi}"),
                })
            }
        };
        Ok(ValidSampleParams {
            cells_per_dim: field(
                "samples.cells_per_dim",
                self.cells_per_dim,
                default_cells_per_dim(d),
                1,
                MAX_CELLS_PER_DIM,
            )?,
            per_cell: field(
                "samples.per_cell",
                self.per_cell,
                DEFAULT_PER_CELL,
                1,
                MAX_PER_CELL,
            )?,
            max: field("samples.max", self.max, DEFAULT_MAX_SAMPLES, 1, MAX_SAMPLES)?,
            known_after: field(
                "samples.known_after",
                self.known_after,
                DEFAULT_KNOWN_AFTER,
                1,
                MAX_KNOWN_AFTER,
            )?,
        })
    }
}

/// A continuous world, as a client posts it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContinuousSpec {
    /// The box observations live in.
    pub observation_space: ObservationSpace,
    /// Action names, 1..=[`MAX_ACTIONS`].
    pub actions: Vec<String>,
    /// Stimulus names.
    pub stimuli: Vec<String>,
    /// The basis (default by dimension, [`ContinuousBasisSpec::default_for`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub basis: Option<ContinuousBasisSpec>,
    /// What an observation outside the box does.
    #[serde(default)]
    pub out_of_bounds: OutOfBounds,
    /// How the sample store is cut.
    #[serde(default)]
    pub samples: SampleParams,
}

/// A checked continuous world with its basis built.
#[derive(Debug, Clone, PartialEq)]
pub struct ContinuousModel {
    /// The posted spec, with the effective basis and sample parameters filled in.
    pub spec: ContinuousSpec,
    /// The built basis.
    pub features: FeatureMap,
    /// The checked sample parameters.
    pub samples: ValidSampleParams,
}

impl ContinuousSpec {
    /// Checks every field (sizes first) and builds the basis.
    pub fn build(&self) -> Result<ContinuousModel> {
        self.observation_space.check()?;
        let d = self.observation_space.dim();
        debug_assert!(d <= MAX_DIM);
        let na = self.actions.len();
        if na == 0 || na > MAX_ACTIONS {
            return Err(AlgoError::InvalidModel(format!(
                "a continuous world has 1..={MAX_ACTIONS} actions, not {na}"
            )));
        }
        crate::model::check_names("actions", &self.actions)?;
        crate::model::check_names("stimuli", &self.stimuli)?;
        let basis = self
            .basis
            .clone()
            .unwrap_or_else(|| ContinuousBasisSpec::default_for(d, na));
        let features = basis.build(d, na)?;
        let samples = self.samples.check(d)?;
        let spec = Self {
            basis: Some(basis),
            samples: SampleParams {
                cells_per_dim: Some(samples.cells_per_dim),
                per_cell: Some(samples.per_cell),
                max: Some(samples.max),
                known_after: Some(samples.known_after),
            },
            ..self.clone()
        };
        Ok(ContinuousModel {
            spec,
            features,
            samples,
        })
    }
}

impl ContinuousModel {
    /// d.
    pub fn dim(&self) -> usize {
        self.spec.observation_space.dim()
    }

    /// |A|.
    pub fn n_actions(&self) -> usize {
        self.spec.actions.len()
    }

    /// n.
    pub fn n_stimuli(&self) -> usize {
        self.spec.stimuli.len()
    }
}
