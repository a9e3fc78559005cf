//! MCA-PI on continuous observations (docs/algorithm.md §9): worlds whose
//! states are points of a box [low, high]^d, as robots sense them, with
//! the transitions learned from what the agent sees.
//!
//! Read in the order of a tick: [`space`] (the box and normalisation),
//! [`basis`] (features over it), [`stimulus`] (Ξ as a linear model,
//! line 5), [`samples`] (the transitions kept), [`planner`] (LSTDQ on
//! them, line 9) and [`agent`] (the loop). [`model`] is the form a client
//! posts.

pub mod agent;
pub mod basis;
mod dot;
pub mod grid;
pub mod model;
pub mod planner;
pub mod samples;
pub mod space;
pub mod stimulus;

pub use agent::{
    ContinuousAgent, ContinuousObservation, ContinuousObserved, ContinuousSnapshot,
    ContinuousSnapshotRef, ContinuousState, ContinuousStateRef, ContinuousStats, ContinuousStep,
    GridSnapshot, GridSnapshotRef,
};
pub use basis::{ContinuousBasisSpec, FeatureMap};
pub use grid::GridShape;
pub use model::{ContinuousModel, ContinuousSpec, SampleParams, ValidSampleParams};
pub use space::{ObservationSpace, OutOfBounds};
