//! The paper experiments.
