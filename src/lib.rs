//! # mcapi
//!
//! Hosts motivated reinforcement-learning agents: MCA-PI (Kompella,
//! Kazerounian, Schmidhuber, "An Anti-Hebbian Learning Rule to Represent
//! Drive Motivations for Reinforcement Learning", SAB 2014).
//!
//! An agent receives n kinds of stimulus. Its drive D is a unit vector
//! updated by Peng's anti-Hebbian Minor Component Analysis rule, so it points
//! at the stimuli received least recently; the reward of a state-action pair
//! is how well its learned stimulus function Ξ matches D; with the known
//! transition model the agent re-plans every tick by model-based LSTDQ.
//!
//! Modules:
//! - [`algo`]: the pure, synchronous algorithm core (Algorithm 1, Eqs. 1-3;
//!   the curiosity channel and the curious agent, Eqs. 6-7).
//! - [`experiments`]: the paper's experiments, metrics and figures.
//! - [`service`]: the session layer both transports call (sessions, tick loop, limits).

pub mod algo;
pub mod api;
pub mod config;
pub mod experiments;
pub mod loadgen;
pub mod server;
pub mod service;
pub mod store;
pub mod telemetry;
