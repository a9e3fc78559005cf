//! The paper's experiments (docs/algorithm.md §6) over the pure core: the
//! hallway (Exp. 1), the three-room maze (Exp. 2) and the curiosity room
//! (Exp. 3, §7), with their baselines, metrics, per-trial CSV series,
//! `summary.json` and figures.
//!
//! An experiment is a list of configurations run for the same trials: trial
//! `i` of every configuration uses the same world seed (the same start state
//! and source noise stream) and the same agent seed, so configurations are
//! compared on common random numbers. Trials run in parallel (rayon) with a
//! progress bar on stderr.

pub mod continuous;
pub mod curiosity;
pub mod dominance;
pub mod metrics;
pub mod paper;
pub mod plots;
pub mod run;

pub use paper::{Experiment, ExperimentKind};
pub use run::{RunOptions, run_experiment};
