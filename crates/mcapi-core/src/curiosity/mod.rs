//! Curiosity: the intMCA channel (docs/algorithm.md §7; paper Sec. 4.3, Eqs. 6-7).
//!
//! A curiosity channel turns a raw signal x(t) ∈ Rᵐ, received only at signal
//! sources, into one extra stimulus dimension ξ_cur. Read in the order of §7:
//!
//! 1. [`SfaModule`] ([`sfa`]): incremental slow feature analysis (Kompella et al. 2012),
//!    §7 "A module" steps 1-3: quadratic expansion, exact running centring
//!    and whitening, backward differences, MCA on the differences, the slow
//!    feature y.
//! 2. [`Roc`] ([`roc`]): Robust Online Clustering of y (Guedalia, London, Werman 1999),
//!    step 4; its error e is the distance to the nearest centre.
//! 3. [`ErrorWindow`] and [`curiosity_stimulus`] ([`progress`]): the estimation error ε
//!    (step 5) and the learning-progress stimulus of Eq. 7.
//! 4. [`CuriosityChannel`] ([`channel`]): the active module and the library of frozen
//!    ones, with the freeze, explain and bind rules (ours, §7).
//! 5. [`Signals`] ([`signal`]): the book and music signals of Eq. 6 on per-source clocks.
//!
//! Everything here is synchronous and deterministic: the only randomness, a
//! module's initial feature direction w₀, comes from the channel's seed.
//!
//! The constants of all of them are [`CuriosityParams`] ([`params`]).

pub mod channel;
pub mod params;
pub mod progress;
pub mod roc;
pub mod sfa;
pub mod signal;

#[cfg(test)]
mod tests;

pub use channel::{ActiveModule, CuriosityChannel, CuriosityStep, FrozenModule};
pub use params::{
    CuriosityParams, MAX_CENTRES, MAX_LIBRARY, MAX_SIGNAL_DIM, MAX_SOURCES_LIMIT, MAX_WINDOW,
    ValidCuriosityParams,
};
pub use progress::{ErrorWindow, LearningProgress, curiosity_stimulus};
pub use roc::{Centre, Roc};
pub use sfa::{SfaModule, expand_quadratic, expanded_dim};
pub use signal::{Eq6Source, Signals};
