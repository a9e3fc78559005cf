//! # mcapi-core
//!
//! The pure MCA-PI core: synchronous, no I/O, no async (Kompella,
//! Kazerounian, Schmidhuber, "An Anti-Hebbian Learning Rule to Represent
//! Drive Motivations for Reinforcement Learning", SAB 2014).
//!
//! An agent receives n kinds of stimulus. Its drive D is a unit vector
//! updated by Peng's anti-Hebbian Minor Component Analysis rule, so it points
//! at the stimuli received least recently; the reward of a state-action pair
//! is how well its learned stimulus function Ξ matches D; with the known
//! transition model the agent re-plans every tick by model-based LSTDQ.
//!
//! Read in the order of Algorithm 1: [`model`] (the environment), [`basis`]
//! (features), [`stimulus`] (Ξ and R, line 5 and line 8), [`drive`] (D,
//! Eqs. 1-3), [`lstdq`] (line 9) and [`agent`] (the loop). [`continuous`]
//! is the same loop on observation vectors instead of state numbers.

pub mod agent;
pub mod basis;
pub mod continuous;
pub mod curiosity;
pub mod curious_agent;
pub mod drive;
pub mod error;
pub mod learned;
pub mod lstdq;
pub mod model;
pub mod params;
pub mod prefetch;
pub mod spec;
pub mod stimulus;

pub use agent::{
    Agent, AgentSnapshot, AgentSnapshotRef, LearnedSnapshot, LearnedSnapshotRef, Observation,
    ObserveOutcome, RngState, Step,
};
pub use basis::{Basis, BuildBudget};
pub use curiosity::{
    CuriosityChannel, CuriosityParams, CuriosityStep, Eq6Source, Signals, ValidCuriosityParams,
};
pub use curious_agent::{
    CuriousAgent, CuriousObservation, CuriousObserved, CuriousSnapshot, CuriousStep,
};
pub use drive::Drive;
pub use error::AlgoError;
pub use learned::{LearnedModel, LearnedParams, Optimism, TransitionCounts, ValidLearnedParams};
pub use lstdq::{PlanOutcome, Planner, PlanningModel};
pub use model::{EnvModel, GridMap, Preset, Source};
pub use params::{AgentParams, StimulusRate, ValidParams};
pub use spec::{ActionRef, BasisSpec, ModelSpec, TransitionSpec};
